"""Pose stage end to end on digital phantoms: rendered scans -> segmentation stage -> pose.

Measures what the whole chain gives against the phantom truth, with the issue's tolerances on the
full rotation (about the leg axis too: the phantom's tibia is a rounded triangle, so a turn about
z moves its contour) and on the full translation vector. The three cases have no true shift along
the leg: a shift along z of a slowly tapering bone is below what the segmented contours resolve
(README, Stage 2), and the default 5-DOF fit does not estimate it.
"""

import numpy as np
import pytest

from deeptissue.imaging import Volume
from deeptissue.phantom import PhantomSpec, make_phantom
from deeptissue.pose import ACCURACY_TOLERANCES as TOL
from deeptissue.pose import estimate_pose, pose_errors
from deeptissue.segment import segment_volume

CASES = {
    "rat01-like": dict(seed=1, depth_mm=2.0, tilt_deg=(5.0, -3.0), bone_rotation_deg=(1.0, -0.5, 0.8),
                       bone_translation_mm=(0.05, -0.10, 0.0), snr=20),
    "tilt25x-shallow": dict(seed=4, depth_mm=1.0, tilt_deg=(25.0, 0.0), bone_rotation_deg=(3.0, 0.0, 0.0), snr=12),
    "tilt18-deep-norot": dict(seed=6, depth_mm=3.0, tilt_deg=(-18.0, -18.0), bone_translation_mm=(0.05, 0.05, 0.0),
                              snr=12),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_pose_from_segmented_phantom(name):
    ph = make_phantom(PhantomSpec(**CASES[name], supersample=4))
    pre, _ = segment_volume(Volume(ph.pre, ph.affine), state="pre")
    dur, _ = segment_volume(Volume(ph.during, ph.affine), state="during")
    pose, _ = estimate_pose(ph.during, ph.affine, pre, dur, animal=name)
    err = pose_errors(pose, ph.truth)
    for key in ("axis_error_deg", "tip_end_error_mm", "depth_error_mm", "bone_rotation_error_deg",
                "bone_translation_error_mm"):
        assert err[key] <= TOL[key], (key, err[key])
    if not np.any(ph.truth.bone_rotation_deg):
        # a zero rotation comes back close to zero (measured 0.08 deg, about z), not as a fit of noise
        assert np.linalg.norm(pose.bone_rotation_deg) <= 0.15
