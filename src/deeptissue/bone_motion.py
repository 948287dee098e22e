"""The tibia's rigid motion between the pre and during scans, fitted to their bone contours.

The fit (:func:`fit_bone_motion`) maps every during bone vertex back by a trial motion and
minimises its distance to a dense interpolation of the pre bone surface (:func:`dense_surface`);
the fibula, where both scans show it, joins the fit as part of the same rigid body.
:func:`resolve_bone_dof` chooses the fit's degrees of freedom from what the contours can show.
Contour stacks are ``(n_slices, n_points, 3)`` arrays in world mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from .contours import resample_closed, slices_with_contour
from .pose_error import PoseError, _where
from .rigid import BoneMotion, rotation_matrix

if TYPE_CHECKING:
    from .contours import Contours

__all__ = [
    "MIN_FIBULA_SLICES",
    "BoneDistance",
    "BoneFit",
    "bone_centroid_mm",
    "dense_surface",
    "fit_bone_motion",
    "moved_section",
    "parameter_sd",
    "resolve_bone_dof",
]

MIN_FIBULA_SLICES = 3  # a fibula seen on fewer slices of a state is not used by the bone fit


@dataclass(frozen=True)
class BoneFit:
    """The tibia's fitted rigid motion with the fit's statistics.

    Attributes
    ----------
    motion : BoneMotion
        Rotation about the tibia's pre-state centroid in the slab (``motion.centre_mm``), then translation.
    com_shift_mm : (3,) array
        Raw centroid difference during - pre [mm] (the fit's initial translation).
    rms_initial_mm, rms_com_mm, rms_final_mm : float
        RMS distance [mm] of the during bone vertices, mapped back, to the pre bone surface: before
        any motion, after the centroid shift, after the fit.
    method : {'surface', 'vertex'}
        The distance used (see :func:`fit_bone_motion`).
    dof : {3, 5, 6}
        Degrees of freedom fitted.
    n_evaluations : int
        Residual evaluations of the least-squares fit.
    parameter_sd : (dof,) array or None
        Standard errors of the parameters: rotation vector [deg], then translation correction [mm].
    fibula_slices : tuple of 2 int
        Slices with a fibula contour used in the fit (pre, common to both states); (0, 0): tibia alone.
    """

    motion: BoneMotion
    com_shift_mm: np.ndarray
    rms_initial_mm: float
    rms_com_mm: float
    rms_final_mm: float
    method: str
    dof: int
    n_evaluations: int
    parameter_sd: np.ndarray | None = None
    fibula_slices: tuple = (0, 0)


def bone_centroid_mm(bone_mm: np.ndarray) -> np.ndarray:
    """Centroid [mm] (3,) of the bone in the slab: area-weighted centroids of the slice polygons.

    ``bone_mm`` (n_slices, n_points, 3); every slice is an equally thick slab.
    """
    b = np.asarray(bone_mm, float)
    x, y = b[..., 0], b[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * y1 - x1 * y
    area = cross.sum(axis=1) / 2
    cx = ((x + x1) * cross).sum(axis=1) / (6 * area)
    cy = ((y + y1) * cross).sum(axis=1) / (6 * area)
    cz = b[..., 2].mean(axis=1)
    w = np.abs(area)
    return np.array([np.sum(w * cx), np.sum(w * cy), np.sum(w * cz)]) / w.sum()


def dense_surface(
    contours_mm: np.ndarray, *, step_mm: float = 0.05, extend_mm: float = 0.5, upsample: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """A dense point cloud on the surface through a contour stack, with unit normals.

    ``contours_mm`` (n_slices, n_points, 3), slices at increasing or decreasing z. Each contour is
    upsampled ``upsample`` times around (periodic cubic spline over the point index) and every point
    track is interpolated across the slices with a cubic spline in z every ``step_mm``, extrapolated
    ``extend_mm`` beyond the end slices (the moved bone reaches slightly outside the slab).
    Returns ``points_mm`` (N, 3) and ``normals`` (N, 3).
    """

    c = np.asarray(contours_mm, float)
    n_s, n_p, _ = c.shape
    if upsample > 1:
        idx = np.arange(n_p + 1)
        closed = np.concatenate([c, c[:, :1]], axis=1)
        spl = CubicSpline(idx, closed, axis=1, bc_type="periodic")
        c = spl(np.arange(n_p * upsample) / upsample)
    z = c[..., 2].mean(axis=1)
    order = np.argsort(z)
    z, c = z[order], c[order]
    if n_s >= 2:
        zf = np.arange(z[0] - extend_mm, z[-1] + extend_mm + step_mm / 2, step_mm)
        spl_z = CubicSpline(z, c[..., :2], axis=0, bc_type="natural")
        xy = spl_z(zf)
        dxy_dz = spl_z(zf, 1)
    else:
        zf = z
        xy = c[..., :2]
        dxy_dz = np.zeros_like(xy)
    pts = np.concatenate([xy, np.broadcast_to(zf[:, None, None], xy.shape[:2] + (1,))], axis=2)
    t_z = np.concatenate([dxy_dz, np.ones(xy.shape[:2] + (1,))], axis=2)
    t_c = np.roll(pts, -1, axis=1) - np.roll(pts, 1, axis=1)
    nrm = np.cross(t_c, t_z)
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    return pts.reshape(-1, 3), nrm.reshape(-1, 3)


@dataclass(frozen=True)
class BoneDistance:
    """The distance :func:`fit_bone_motion` minimises (config ``pose.bone_method``,
    ``pose.bone_surface_step_mm``).

    ``method='surface'``: the point-to-plane distance to the nearest point of a dense cubic interpolation of
    the pre surface between slices, every ``surface_step_mm`` [mm] along z (:func:`dense_surface`);
    ``method='vertex'``: the distance to the nearest pre vertex on the original slices, which through-plane
    motion biases (stacks sampled at the same 1 mm z planes).
    """

    method: str = "surface"
    surface_step_mm: float = 0.05

    def __post_init__(self):
        if self.method not in ("surface", "vertex"):
            raise ValueError(
                f"fit_bone_motion: method must be 'surface' or 'vertex', got {self.method!r}"
            )


def fit_bone_motion(
    bone_pre_mm: np.ndarray,
    bone_during_mm: np.ndarray,
    *,
    fibula_pre_mm: np.ndarray | None = None,
    fibula_during_mm: np.ndarray | None = None,
    distance: BoneDistance = BoneDistance(),
    dof: int = 5,
    during_slices: np.ndarray | None = None,
    animal: str = "",
) -> BoneFit:
    """Rigid motion of the tibia from the pre and during bone contour stacks.

    Translation: the shift of the bone centroid (initial guess). Rotation, and a translation
    correction (``dof=6``: all three components; ``dof=5``: across the leg only, the shift along z
    stays the centroid's; ``dof=3``: none), by Levenberg–Marquardt (``scipy.optimize.least_squares(method='lm')``) on
    the ``distance`` (:class:`BoneDistance`) of every during bone vertex, mapped back to the pre state, to
    the pre bone. A bone that is (nearly) a prism along z cannot show a shift along z: its 6-DOF fit then
    drifts along z with the segmentation noise (check ``parameter_sd``); ``dof=5`` is the remedy.

    ``fibula_pre_mm`` / ``fibula_during_mm`` (n_slices, n_points_f, 3, NaN rows where absent): the
    fibula, which moves with the tibia as one rigid body. Its during vertices (on the slices where
    both states have a fibula contour) join the residuals, each matched to the pre fibula's own
    interpolated surface (never to the tibia's); the centre stays the tibia's centroid. A
    fibula that runs obliquely to the tibia moves across the slices under a shift along z, so with
    it ``dof=6`` resolves that shift. Used only when the pre state has it on at least
    ``MIN_FIBULA_SLICES`` slices and both states on as many common slices.

    Parameters
    ----------
    bone_pre_mm, bone_during_mm : (n_slices, n_points, 3) array
        Tibia contours [mm] of both states on the same slice planes.
    fibula_pre_mm, fibula_during_mm : (n_slices, n_points_f, 3) array or None
        Fibula contours [mm], NaN rows where a slice has none.
    distance : BoneDistance
        The distance minimised.
    dof : {3, 5, 6}
        Degrees of freedom: rotation, plus the translation correction across the leg (5) or in all
        directions (6).
    during_slices : (n_slices,) bool array or None
        The during slices whose tibia (and fibula) contours join the fit; None: all. Slices where the bone
        cannot be seen (against the indenter) are left out; the pre surface keeps all its slices.
    animal : str
        Named in error messages.

    Returns
    -------
    BoneFit
        The motion (rotation about the tibia's pre centroid) and the fit's statistics.

    Raises
    ------
    PoseError
        If the two stacks do not share their slice planes.
    ValueError
        For an unknown ``dof``.
    """

    pre, dur, use = _matched_stacks(bone_pre_mm, bone_during_mm, during_slices, animal)
    if dof not in (3, 5, 6):
        raise ValueError(f"fit_bone_motion: dof must be 3, 5 or 6, got {dof!r}")
    # the pre fibula's surface through all its slices; the during fibula on the slices that have one
    # in both states (a during section whose plane the pre fibula does not reach has no counterpart:
    # matched to the end of the pre surface, it would pull the fit along the bone)
    has_pre = _fibula_mask(fibula_pre_mm, pre.shape[0])
    both = has_pre & _fibula_mask(fibula_during_mm, pre.shape[0]) & use
    use_fibula = has_pre.sum() >= MIN_FIBULA_SLICES and both.sum() >= MIN_FIBULA_SLICES
    bodies = [(pre, dur[use])]
    if use_fibula:
        bodies.append(
            (np.asarray(fibula_pre_mm, float)[has_pre], np.asarray(fibula_during_mm, float)[both])
        )
    com_pre = bone_centroid_mm(pre)
    shift = bone_centroid_mm(dur[use]) - bone_centroid_mm(pre[use])
    residuals_for = _residual_function(bodies, com_pre, distance)

    def rms(r):
        return float(np.sqrt(np.mean(r**2)))

    def correction(x):  # translation correction (mm) added to the centroid shift
        return np.array([x[3], x[4], x[5] if dof == 6 else 0.0]) if dof > 3 else np.zeros(3)

    res = least_squares(
        lambda x: residuals_for(x[:3], shift + correction(x)),
        np.zeros(dof),
        method="lm",
        x_scale=np.ones(dof),
        diff_step=1e-4 if distance.method == "surface" else None,
    )
    return BoneFit(
        motion=BoneMotion(
            rotation_deg=res.x[:3], centre_mm=com_pre, translation_mm=shift + correction(res.x)
        ),
        com_shift_mm=shift,
        rms_initial_mm=rms(residuals_for(np.zeros(3), np.zeros(3))),
        rms_com_mm=rms(residuals_for(np.zeros(3), shift)),
        rms_final_mm=rms(res.fun),
        method=distance.method,
        dof=dof,
        n_evaluations=int(res.nfev),
        parameter_sd=parameter_sd(res.jac, res.fun),
        fibula_slices=(int(has_pre.sum()), int(both.sum())) if use_fibula else (0, 0),
    )


def _matched_stacks(bone_pre_mm, bone_during_mm, during_slices, animal: str):
    """Both tibia stacks as arrays and the during slices used (bool (n_slices,)); :class:`PoseError` when
    they do not share their slice planes or fewer than 2 during slices are used."""
    pre = np.asarray(bone_pre_mm, float)
    dur = np.asarray(bone_during_mm, float)
    if pre.ndim != 3 or dur.ndim != 3 or pre.shape[0] != dur.shape[0]:
        raise PoseError(
            f"{_where(animal)}during bone contours cannot be matched to the pre bone: "
            f"{dur.shape[0] if dur.ndim == 3 else dur.shape} slices during vs "
            f"{pre.shape[0] if pre.ndim == 3 else pre.shape} pre"
        )
    dz = np.abs(np.sort(pre[..., 2].mean(axis=1)) - np.sort(dur[..., 2].mean(axis=1)))
    if dz.max() > 1e-3:
        raise PoseError(
            f"{_where(animal)}during bone contours cannot be matched to the pre bone: slice planes differ "
            f"by up to {dz.max():.3g} mm"
        )
    use = np.ones(pre.shape[0], bool) if during_slices is None else np.asarray(during_slices, bool)
    if use.shape != (pre.shape[0],) or use.sum() < 2:
        raise PoseError(
            f"{_where(animal)}the bone fit needs the tibia on at least 2 during slices, "
            f"got {int(use.sum()) if use.shape == (pre.shape[0],) else use.shape}"
        )
    return pre, dur, use


def _residual_function(bodies, com_pre: np.ndarray, distance: BoneDistance):
    """``f(rotation_deg, translation_mm) -> residuals``: the ``distance`` of every during vertex of each
    (pre stack, during stack) body, mapped back by the motion about ``com_pre``, to that body's pre bone."""

    parts = []
    for b_pre, b_dur in bodies:
        if distance.method == "surface":
            ref, nrm = dense_surface(b_pre, step_mm=distance.surface_step_mm)
        else:
            ref, nrm = b_pre.reshape(-1, 3), None
        parts.append((b_dur.reshape(-1, 3), ref, nrm, cKDTree(ref)))

    def residuals_for(rot_deg, trans):
        R = rotation_matrix(rot_deg)
        out = []
        for q, ref, nrm, tree in parts:
            p = (q - com_pre - trans) @ R + com_pre  # R^T (q - c - t) + c, row vectors
            _, j = tree.query(p)
            if nrm is None:
                out.append(np.linalg.norm(p - ref[j], axis=1))
            else:
                out.append(np.einsum("ij,ij->i", p - ref[j], nrm[j]))
        return np.concatenate(out)

    return residuals_for


def parameter_sd(jac: np.ndarray, fun: np.ndarray) -> np.ndarray:
    """Standard errors of least-squares parameters from the Jacobian ``jac`` (m, n) and the residuals ``fun``
    (m,): the residual variance times the diagonal of (J^T J)^-1; inf for a singular J^T J."""
    n = jac.shape[1]
    try:
        cov = np.linalg.inv(jac.T @ jac) * np.sum(fun**2) / max(len(fun) - n, 1)
    except np.linalg.LinAlgError:
        return np.full(n, np.inf)
    return np.sqrt(np.clip(np.diag(cov), 0, None))


def moved_section(
    bone_pre_mm: np.ndarray,
    motion: BoneMotion,
    z_mm: float,
    *,
    n_points: int = 100,
    start_angle_deg: float = 90.0,
) -> np.ndarray:
    """The section at the plane ``z = z_mm`` of the pre bone surface moved by ``motion``: (n_points, 3) [mm].

    The surface is :func:`dense_surface` of ``bone_pre_mm`` (n_slices, n_points, 3); each of its point tracks
    along the bone, moved, is cut by the plane (linear interpolation in z), and the section is resampled
    as a segmented contour (:func:`deeptissue.contours.resample_closed`). Raises ValueError if the moved
    surface does not reach the plane.
    """

    pre = np.asarray(bone_pre_mm, float)
    pts, _ = dense_surface(pre, upsample=2)
    tracks = motion.apply(pts).reshape(-1, 2 * pre.shape[1], 3)
    z = tracks[..., 2]
    if not (z.min(axis=0) <= z_mm).all() or not (z.max(axis=0) >= z_mm).all():
        raise ValueError(f"moved_section: the moved bone surface does not reach z = {z_mm:.3g} mm")
    xy = np.empty((tracks.shape[1], 2))
    for j in range(tracks.shape[1]):
        order = np.argsort(z[:, j])
        for d in range(2):
            xy[j, d] = np.interp(z_mm, z[order, j], tracks[order, j, d])
    out = resample_closed(xy, n_points=n_points, start_angle_deg=start_angle_deg)
    return np.column_stack([out, np.full(n_points, float(z_mm))])


def _fibula_mask(fibula_mm, n_slices: int) -> np.ndarray:
    """Boolean (n_slices,): the slices of a fibula stack (n_slices, n_points, 3; NaN rows where absent)
    that have a contour; all False for None."""
    if fibula_mm is None:
        return np.zeros(n_slices, bool)
    f = np.asarray(fibula_mm, float)
    if f.ndim != 3 or f.shape[0] != n_slices:
        raise PoseError(f"fibula contours: expected ({n_slices}, n_points, 3), got {f.shape}")
    return slices_with_contour(f)


def resolve_bone_dof(bone_dof, pre: Contours, during_contours: Contours) -> tuple[int, str]:
    """The fit's degrees of freedom for the config value ``bone_dof`` (3, 5, 6 or 'auto') and why.

    'auto': 6 when both states have fibula contours on at least ``MIN_FIBULA_SLICES`` common slices
    (the oblique fibula makes the shift along the leg observable), else 5 (the tibia alone cannot
    show it; the shift along z stays the centroid's).
    """
    if pre.n_slices != during_contours.n_slices:  # fit_bone_motion names the problem
        n_pre = n_both = 0
    else:
        n_pre = int(pre.fibula_slices.sum())
        n_both = int((pre.fibula_slices & during_contours.fibula_slices).sum())
    has = n_pre >= MIN_FIBULA_SLICES and n_both >= MIN_FIBULA_SLICES
    seen = f"fibula on {n_pre} pre slices, {n_both} of them also during"
    if bone_dof != "auto":
        if bone_dof not in (3, 5, 6):
            raise ValueError(f"pose.bone_dof must be 3, 5, 6 or 'auto', got {bone_dof!r}")
        return int(bone_dof), f"bone_dof {bone_dof} as configured ({seen})"
    if has:
        return 6, f"bone_dof auto -> 6: tibia and fibula fitted together ({seen})"
    return 5, (
        f"bone_dof auto -> 5: no usable fibula contours ({seen}; {MIN_FIBULA_SLICES} needed); "
        "tibia alone, the shift along the leg (z) is the centroid's"
    )
