"""Rigid motions: rotation vectors in degrees about a centre, and their step-wise application.

Convention used everywhere (phantom truth, pose, FE boundary conditions):
``x_during = R (x_pre - centre) + centre + translation`` with
``R = Rotation.from_rotvec(radians(rotation_deg))``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["BoneMotion", "apply_rigid", "euler_xyz_deg", "rotation_matrix"]


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
    return Rotation.from_rotvec(np.radians(np.asarray(rotation_deg, dtype=float))).as_euler(
        "xyz", degrees=True
    )


@dataclass(frozen=True)
class BoneMotion:
    """Rigid motion of the bone, pre -> during: ``x' = R (x - centre) + centre + translation``.

    The pose stage fits it (:func:`deeptissue.bone_motion.fit_bone_motion`) and the FE solve prescribes it on
    the bone facets (:func:`deeptissue.fem.solver.solve_indentation`). The default is no motion.

    Attributes
    ----------
    rotation_deg : tuple of 3 float
        Rotation vector [deg] (axis times angle), see :func:`rotation_matrix`.
    centre_mm : tuple of 3 float
        Centre of the rotation [mm]; the pose stage uses the tibia's pre-state centroid.
    translation_mm : tuple of 3 float
        Translation [mm] applied after the rotation.
    """

    rotation_deg: tuple = (0.0, 0.0, 0.0)
    centre_mm: tuple = (0.0, 0.0, 0.0)
    translation_mm: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        for name in ("rotation_deg", "centre_mm", "translation_mm"):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (3,):
                raise ValueError(
                    f"BoneMotion.{name}: expected 3 numbers, got {getattr(self, name)!r}"
                )
            object.__setattr__(self, name, tuple(float(x) for x in v))

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        """Points ``points_mm`` (..., 3) [mm] moved by this motion (:func:`apply_rigid`), same shape."""
        return apply_rigid(
            points_mm,
            rotation_deg=self.rotation_deg,
            centre_mm=self.centre_mm,
            translation_mm=self.translation_mm,
        )

    def undo(self, points_mm: np.ndarray) -> np.ndarray:
        """Points ``points_mm`` (..., 3) [mm] moved back by the inverse of this motion, same shape:
        ``R^T (x - centre - translation) + centre``."""
        p = np.asarray(points_mm, dtype=float)
        c = np.asarray(self.centre_mm, dtype=float)
        R = rotation_matrix(self.rotation_deg)
        return (p - c - np.asarray(self.translation_mm, dtype=float)) @ R + c
