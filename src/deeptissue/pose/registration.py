"""The leg's motion in the cast between the two scans, from the skin away from the indenter.

The cast holds the leg: away from the indenter the during skin lies on the pre skin. A leg that moved
between the scans shows as a rigid offset of that far-field skin. :func:`register_leg` fits the leg's
in-plane rigid motion (a shift across the leg and a turn about the slice normal) to the during skin
vertices outside a guard sphere around the indenter; :meth:`LegRegistration.correct` maps any during
quantity back onto the pre scan, so that the pose is measured against the pre scan's leg.
Motion out of the slice plane (a tilt of the leg) is not corrected: it leaves the far-field skin off
the pre skin, which the residual (:attr:`LegRegistration.residual_mm`) shows.
Contour stacks are ``(n_slices, n_points, 3)`` arrays in world mm on shared axial slice planes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from ..bone_motion import parameter_sd
from ..pose_error import PoseError, _where
from ..rigid import BoneMotion

if TYPE_CHECKING:
    from ..contours import Contours

__all__ = ["MIN_TURN_DEG", "MIN_TURN_MM_PER_DEG", "LegGuard", "LegRegistration", "register_leg"]

# Smallest RMS motion [mm] of the far-field skin along its normals under a turn of 1 deg about the leg for
# the turn to be fitted: 0.010 mm/deg on the phantoms' elliptic legs; a round leg's skin does not show a
# turn (0 mm/deg), and the turn stays in the tibia's motion.
MIN_TURN_MM_PER_DEG = 0.003
# Smallest turn about the leg that is undone [deg]. On the unmoved phantoms the fit finds turns of up to
# 0.15 deg (the two scans' segmentations differ slightly); undoing them would turn the indenter axis and
# the tibia by as much. Smaller turns are left in place: the shift alone is fitted.
MIN_TURN_DEG = 0.3

# nearest-neighbour search in one slice: z is stretched so that no neighbour is found in another slice
_Z_STRETCH = 1e3


@dataclass(frozen=True)
class LegGuard:
    """The part of the skin the indenter deforms, left out of the registration: a sphere of ``radius_mm``
    [mm] about ``centre_mm`` (3,) [mm], the front of the indenter in the during scan.

    The default radius, 5 mm, holds the dimple of a 1.5 mm head pressed
    3 mm deep: on the phantom rat01 (2 mm deep) the segmented during skin lies within 0.05 mm of the pre
    skin beyond 4 mm of the tip, up to 0.29 mm at 3-4 mm.
    """

    centre_mm: np.ndarray
    radius_mm: float = 5.0


@dataclass(frozen=True)
class LegRegistration:
    """The leg's rigid motion pre -> during in the slice plane, fitted to the far-field skin.

    Attributes
    ----------
    motion : BoneMotion
        ``x_during = R (x_pre - c) + c + t``: a rotation about the slice normal (z) through the far-field
        skin's centre ``c``, then a translation across the leg (z component 0).
    residual_mm : float
        RMS distance [mm] of the far-field during skin, moved back by ``motion``, from the pre skin.
    residual_initial_mm : float
        The same before the correction [mm].
    n_points : int
        Far-field during skin vertices fitted.
    parameter_sd : (3,) array
        Standard errors of the rotation [deg] and the two translations [mm]; the rotation's is inf when the
        turn is not fitted (see :func:`register_leg`).
    """

    motion: BoneMotion
    residual_mm: float
    residual_initial_mm: float
    n_points: int
    parameter_sd: np.ndarray

    @property
    def shift_mm(self) -> float:
        """Length of the leg's translation across the slices [mm]."""
        return float(np.linalg.norm(self.motion.translation_mm))

    @property
    def rotation_deg(self) -> float:
        """The leg's turn about the slice normal [deg], signed (right-handed about +z)."""
        return float(self.motion.rotation_deg[2])

    def to_pre(self, points_mm: np.ndarray) -> np.ndarray:
        """Points (..., 3) [mm] of the during scan mapped onto the pre scan (the motion undone); NaN stays NaN."""
        return self.motion.undo(points_mm)

    def direction_to_pre(self, vector: np.ndarray) -> np.ndarray:
        """A direction (3,) of the during scan turned onto the pre scan."""
        v = np.asarray(vector, float)
        return self.motion.undo(v) - self.motion.undo(np.zeros(3))

    def matrix_to_pre(self) -> np.ndarray:
        """The 4x4 matrix of :meth:`to_pre` on homogeneous world coordinates (e.g. ``M @ affine``: the during
        scan's voxels on the pre scan)."""
        M = np.eye(4)
        M[:3, 3] = self.to_pre(np.zeros(3))
        M[:3, :3] = (self.to_pre(np.eye(3)) - M[:3, 3]).T
        return M

    def correct(self, contours: Contours) -> Contours:
        """The during contours (skin, tibia, fibula) mapped onto the pre scan; the slice planes are kept."""
        fib = None if contours.fibula is None else self.to_pre(contours.fibula)
        return replace(
            contours, skin=self.to_pre(contours.skin), bone=self.to_pre(contours.bone), fibula=fib
        )

    def to_extra(self) -> dict:
        """The keys of ``pose.json`` that report the correction."""
        return {
            "leg_shift_mm": self.shift_mm,
            "leg_translation_mm": list(self.motion.translation_mm),
            "leg_rotation_deg": self.rotation_deg,
            "leg_rotation_centre_mm": list(self.motion.centre_mm),
            "leg_skin_residual_mm": self.residual_mm,
            "leg_skin_residual_initial_mm": self.residual_initial_mm,
            "leg_skin_points": self.n_points,
            "leg_fit_sd": self.parameter_sd.tolist(),
        }


def _slice_curves(skin_mm: np.ndarray, upsample: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) of the closed contours of each slice, upsampled by a periodic cubic spline, and their
    in-plane unit normals (N, 3)."""
    c = np.asarray(skin_mm, float)
    n_p = c.shape[1]
    closed = np.concatenate([c, c[:, :1]], axis=1)
    spl = CubicSpline(np.arange(n_p + 1), closed, axis=1, bc_type="periodic")
    u = np.arange(n_p * upsample) / upsample
    pts, tan = spl(u), spl(u, 1)
    nrm = np.stack([tan[..., 1], -tan[..., 0], np.zeros_like(tan[..., 0])], axis=-1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
    return pts.reshape(-1, 3), nrm.reshape(-1, 3)


def register_leg(
    pre_skin_mm: np.ndarray, during_skin_mm: np.ndarray, guard: LegGuard, *, animal: str = ""
) -> LegRegistration:
    """The leg's in-plane rigid motion between the scans, fitted to the skin outside ``guard``.

    Every during skin vertex on a slice plane of the pre scan (within 0.001 mm) and farther than ``guard.radius_mm`` from ``guard.centre_mm`` is mapped back by a
    trial motion; its residual is the in-plane distance along the normal to the pre skin contour of its
    slice (a periodic cubic spline through the contour). Levenberg–Marquardt fits the turn about z through
    the leg's centre and the two translations across the leg from zero; when the skin does not show a turn
    (less than :data:`MIN_TURN_MM_PER_DEG`: a round leg) or the turn is under :data:`MIN_TURN_DEG`, the
    two translations alone.

    Parameters
    ----------
    pre_skin_mm, during_skin_mm : (n_slices, n_points, 3) array
        Skin contours [mm] of both scans.
    guard : LegGuard
        The indenter's region, left out.
    animal : str
        Named in error messages.

    Returns
    -------
    LegRegistration

    Raises
    ------
    PoseError
        If fewer than 20 during vertices lie outside the guard on slice planes of the pre scan.
    """
    pre = np.asarray(pre_skin_mm, float)
    dur = np.asarray(during_skin_mm, float)
    z_pre, z_dur = pre[..., 2].mean(axis=1), dur[..., 2].mean(axis=1)
    # the during slices on a pre slice plane (a during slice without one has no skin to lie on)
    shared = np.abs(z_dur[:, None] - z_pre[None, :]).min(axis=1) <= 1e-3
    q = dur[shared].reshape(-1, 3)
    q = q[np.linalg.norm(q - np.asarray(guard.centre_mm, float), axis=1) > guard.radius_mm]
    if len(q) < 20:
        raise PoseError(
            f"{_where(animal)}only {len(q)} during skin vertices lie on a pre slice plane and farther than "
            f"{guard.radius_mm:g} mm from the indenter: too few to check that the leg "
            "stayed in place between the scans; the pre and during scans must share their slices"
        )
    ref, nrm = _slice_curves(pre)
    stretch = np.array([1.0, 1.0, _Z_STRETCH])
    tree = cKDTree(ref * stretch)
    # the leg's centre (mean of the pre skin vertices): a turn about it moves a round leg's skin least
    centre = np.array([*pre[..., :2].reshape(-1, 2).mean(axis=0), 0.0])

    def motion_of(x) -> BoneMotion:
        return BoneMotion(
            rotation_deg=(0.0, 0.0, x[0]), centre_mm=centre, translation_mm=(x[1], x[2], 0.0)
        )

    def residuals(x):
        p = motion_of(x).undo(q)
        _, j = tree.query(p * stretch)
        return np.einsum("ij,ij->i", p - ref[j], nrm[j])

    fit = least_squares(residuals, np.zeros(3), method="lm", x_scale=np.array([1.0, 0.1, 0.1]))
    sd = parameter_sd(fit.jac, fit.fun)
    x = fit.x
    # how far the far-field skin moves along its normals under a turn of 1 deg (RMS): 0 for a round leg
    turn_mm_per_deg = float(np.linalg.norm(fit.jac[:, 0]) / np.sqrt(len(q)))
    if not (
        turn_mm_per_deg >= MIN_TURN_MM_PER_DEG and abs(x[0]) >= MIN_TURN_DEG
    ):  # the shift alone
        shift = least_squares(lambda t: residuals([0.0, *t]), np.zeros(2), method="lm")
        x = np.array([0.0, *shift.x])
        sd = np.array([np.inf, *parameter_sd(shift.jac, shift.fun)])
    return LegRegistration(
        motion=motion_of(x),
        residual_mm=float(np.sqrt(np.mean(residuals(x) ** 2))),
        residual_initial_mm=float(np.sqrt(np.mean(residuals(np.zeros(3)) ** 2))),
        n_points=len(q),
        parameter_sd=sd,
    )
