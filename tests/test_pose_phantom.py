"""Pose stage on digital phantoms (deeptissue.phantom) against their exact truth.

The pose stage is measured on its own here: the contours are the phantom's exact truth contours
(resampled like the segmentation's; tibia and fibula), the volume is the rendered, noisy during scan.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deeptissue.bone_motion import fit_bone_motion
from deeptissue.phantom import PhantomSpec, make_phantom
from deeptissue.pose import ACCURACY_TOLERANCES as TOL
from deeptissue.pose import estimate_pose, pose_errors
from deeptissue.rigid import rotation_matrix

CASES = {
    "rat01-like": dict(
        seed=1,
        depth_mm=2.0,
        tilt_deg=(5.0, -3.0),
        bone_rotation_deg=(1.0, -0.5, 0.8),
        bone_translation_mm=(0.05, -0.10, 0.02),
        snr=20,
    ),
    "tilt25x-shallow": dict(
        seed=4,
        depth_mm=1.0,
        tilt_deg=(25.0, 0.0),
        bone_rotation_deg=(3.0, 0.0, 0.0),
        bone_translation_mm=(0.04, -0.03, 0.15),
        snr=12,
    ),
    "tilt18-deep-norot": dict(
        seed=6,
        depth_mm=3.0,
        tilt_deg=(-18.0, -18.0),
        bone_translation_mm=(0.05, 0.05, -0.12),
        snr=12,
    ),
    "tilt12-rat03-like": dict(
        seed=3,
        depth_mm=1.5,
        tilt_deg=(12.0, 4.0),
        bone_rotation_deg=(0.5, 1.2, -1.0),
        bone_translation_mm=(0.02, -0.06, -0.05),
        snr=12,
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_pose_on_phantom_within_the_accuracy_tolerances(name):
    ph = make_phantom(PhantomSpec(**CASES[name], supersample=4))
    pose, _ = estimate_pose(ph.during, ph.affine, ph.truth_pre, ph.truth_during, animal=name)
    truth = ph.truth
    err = pose_errors(pose, truth)
    for key in ("axis_error_deg", "tip_end_error_mm", "depth_error_mm", "bone_rotation_error_deg"):
        assert err[key] <= TOL[key], (key, err[key])
    assert err["tip_start_error_mm"] <= 0.1
    # the default fit uses the fibula (6 DOF) and recovers the full translation, along the leg too
    assert pose.extra["bone_dof"] == 6 and pose.extra["bone_fibula_slices"] == [20, 20]
    assert err["bone_translation_error_mm"] <= 0.005
    assert err["bone_rotation_error_deg"] <= 0.01
    # with exact contours the tapering, flaring, twisting tibia alone shows its shift along the leg
    # too: the 6-DOF fit on it recovers the full translation vector and the full rotation
    m = fit_bone_motion(ph.truth_pre.bone, ph.truth_during.bone, dof=6)
    R = rotation_matrix(m.motion.rotation_deg)
    t6 = m.motion.translation_mm + (R - np.eye(3)) @ (truth.bone_com_mm - m.motion.centre_mm)
    assert np.linalg.norm(t6 - truth.bone_translation_mm) <= TOL["bone_translation_error_mm"]
    rel = Rotation.from_matrix(R @ rotation_matrix(truth.bone_rotation_deg).T).magnitude()
    assert np.degrees(rel) <= TOL["bone_rotation_error_deg"]
    if not np.any(truth.bone_rotation_deg):
        assert np.linalg.norm(pose.bone_rotation_deg) <= 0.01  # zero comes back as zero
