"""Rigid motions: rotation vectors in degrees about a centre, and their step-wise application.

Convention used everywhere (phantom truth, pose, FE boundary conditions):
``x_during = R (x_pre - centre) + centre + translation`` with
``R = Rotation.from_rotvec(radians(rotation_deg))``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def rotation_matrix(rotation_deg) -> np.ndarray:
    """3x3 rotation matrix of a rotation vector given in degrees."""
    return Rotation.from_rotvec(np.radians(np.asarray(rotation_deg, dtype=float))).as_matrix()


def apply_rigid(points_mm: np.ndarray, *, rotation_deg, centre_mm, translation_mm) -> np.ndarray:
    """Move ``points_mm`` (..., 3) by the rigid motion (rotation about ``centre_mm``, then translation)."""
    p = np.asarray(points_mm, dtype=float)
    c = np.asarray(centre_mm, dtype=float)
    R = rotation_matrix(rotation_deg)
    return (p - c) @ R.T + c + np.asarray(translation_mm, dtype=float)


def euler_xyz_deg(rotation_deg) -> np.ndarray:
    """Angles (deg) of rotations about the fixed x, then y, then z axis whose product is the rotation.

    ``R = Rz(c) @ Ry(b) @ Rx(a)``; the FE load schedule applies a, then b, then c, so the bone
    reaches exactly ``R`` after the three rotation steps.
    """
    return Rotation.from_rotvec(np.radians(np.asarray(rotation_deg, dtype=float))).as_euler("xyz", degrees=True)
