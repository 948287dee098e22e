"""The scan geometry the pose stage relies on: axial slices.

Contours are stacks of slices at constant z (:class:`~deeptissue.contours.Contours`), the contrast fluid
is searched slice by slice in the same planes, and the tip is interpolated between them. An oblique
slice breaks all three: :func:`check_axial_slices` refuses it, from the scan's affine alone.
"""

from __future__ import annotations

import numpy as np

from ..pose_error import PoseError

__all__ = ["MAX_SLICE_OBLIQUITY_DEG", "check_axial_slices", "slice_obliquity_deg"]

# Largest angle between a slice plane and the world's axial (x-y) plane. The pose stage treats each slice
# as the plane z = const; on a slice turned by an angle a, a skin point 5 mm from the leg's centre lies
# 5 sin(a) mm off that plane: 0.087 mm at 1 deg, under the 0.1 mm pixel of the scans.
MAX_SLICE_OBLIQUITY_DEG = 1.0


def slice_obliquity_deg(affine: np.ndarray) -> float:
    """Angle [deg] between the slice plane of ``affine`` (4, 4; voxel index -> world mm; slices at constant
    third index) and the world's x-y plane: the angle of the slice normal (the cross product of the first
    two voxel axes) from world z."""
    A = np.asarray(affine, float)[:3, :3]
    n = np.cross(A[:, 0], A[:, 1])
    cos = abs(float(n[2])) / float(np.linalg.norm(n))
    return float(np.degrees(np.arccos(min(cos, 1.0))))


def check_axial_slices(
    affine: np.ndarray, *, where: str, max_deg: float = MAX_SLICE_OBLIQUITY_DEG
) -> None:
    """Refuse a scan whose slices are not axial: :class:`PoseError` naming ``where`` (the animal and the
    file), the slices' angle from axial and the limit ``max_deg`` [deg]."""
    angle = slice_obliquity_deg(affine)
    if angle > max_deg:
        raise PoseError(
            f"{where}: the slices are oblique, {angle:.3g} deg from axial (limit {max_deg:g} deg); the pose "
            "stage needs axial slices (constant z): reslice both scans to axial slices"
        )
