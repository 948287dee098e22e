"""Pose stage end to end on digital phantoms: rendered scans -> segmentation stage -> pose.

Measures what the whole chain gives against the phantom truth. The tibia's turn about the leg
axis is not asserted to the issue's 0.3 deg: the segmented contours of the phantom's elliptic tibia
differ between pre and during by more than that turn moves them (see README, Stage 2).
"""

import numpy as np
import pytest

from deeptissue.imaging import Volume
from deeptissue.phantom import PhantomSpec, make_phantom
from deeptissue.pose import ACCURACY_TOLERANCES as TOL
from deeptissue.pose import estimate_pose, pose_errors
from deeptissue.rigid import rotation_matrix
from deeptissue.segment import segment_volume

CASES = {
    "rat01-like": dict(seed=1, depth_mm=2.0, tilt_deg=(5.0, -3.0), bone_rotation_deg=(1.0, -0.5, 0.8),
                       bone_translation_mm=(0.05, -0.10, 0.0), snr=20),
    "tilt25x-shallow": dict(seed=4, depth_mm=1.0, tilt_deg=(25.0, 0.0), bone_rotation_deg=(3.0, 0.0, 0.0), snr=12),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_pose_from_segmented_phantom(name):
    ph = make_phantom(PhantomSpec(**CASES[name], supersample=4))
    pre, _ = segment_volume(Volume(ph.pre, ph.affine), state="pre")
    dur, _ = segment_volume(Volume(ph.during, ph.affine), state="during")
    pose, _ = estimate_pose(ph.during, ph.affine, pre, dur, animal=name)
    err = pose_errors(pose, ph.truth)
    for key in ("axis_error_deg", "tip_end_error_mm", "depth_error_mm"):
        assert err[key] <= TOL[key], (key, err[key])
    # the turn about the x and y axes (the tilt of the tibia), and the shift across the leg
    assert np.linalg.norm(pose.bone_rotation_deg[:2] - ph.truth.bone_rotation_deg[:2]) <= TOL["bone_rotation_error_deg"]
    R = rotation_matrix(pose.bone_rotation_deg)
    t = pose.bone_translation_mm + (R - np.eye(3)) @ (ph.truth.bone_com_mm - pose.bone_com_mm)
    assert np.linalg.norm((t - ph.truth.bone_translation_mm)[:2]) <= TOL["bone_translation_error_mm"]
