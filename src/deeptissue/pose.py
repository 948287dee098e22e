"""The pose result type: indenter axis and travel, tibia rigid motion (``pose.json``).

The phantom's ``truth.json`` has the same keys, so estimate and truth compare key by key.
Conventions: points are world mm; ``indenter_axis`` is a unit vector pointing from the indenter
into the leg; the indenter tip travels from ``tip_start_mm`` to ``tip_end_mm``; the tibia moves
``x -> R (x - bone_com_mm) + bone_com_mm + bone_translation_mm`` with ``R`` the rotation vector
``bone_rotation_deg`` (see :mod:`deeptissue.rigid`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io import read_json, write_json

_VECTORS = ("indenter_axis", "tip_start_mm", "tip_end_mm", "bone_com_mm", "bone_rotation_deg", "bone_translation_mm")


@dataclass(frozen=True)
class Pose:
    indenter_axis: np.ndarray
    tip_start_mm: np.ndarray
    tip_end_mm: np.ndarray
    depth_mm: float
    bone_com_mm: np.ndarray
    bone_rotation_deg: np.ndarray
    bone_translation_mm: np.ndarray
    indenter_com_mm: np.ndarray | None = None
    extra: dict = field(default_factory=dict)  # fit residuals, provenance, overrides used

    def __post_init__(self):
        for name in _VECTORS:
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"pose.{name}: expected 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)
        n = np.linalg.norm(self.indenter_axis)
        if not np.isclose(n, 1.0, atol=1e-6):
            raise ValueError(f"pose.indenter_axis: not a unit vector (norm {n:.6g})")
        if self.indenter_com_mm is not None:
            object.__setattr__(self, "indenter_com_mm", np.asarray(self.indenter_com_mm, dtype=float))
        object.__setattr__(self, "depth_mm", float(self.depth_mm))

    @property
    def travel_mm(self) -> float:
        return float(np.linalg.norm(self.tip_end_mm - self.tip_start_mm))

    def to_dict(self) -> dict:
        d = {name: getattr(self, name).tolist() for name in _VECTORS}
        d["depth_mm"] = self.depth_mm
        if self.indenter_com_mm is not None:
            d["indenter_com_mm"] = self.indenter_com_mm.tolist()
        d.update(self.extra)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Pose":
        known = set(_VECTORS) | {"depth_mm", "indenter_com_mm"}
        missing = [k for k in (*_VECTORS, "depth_mm") if k not in d]
        if missing:
            raise ValueError(f"pose lacks key(s) {missing}")
        return cls(**{k: d[k] for k in known if k in d}, extra={k: v for k, v in d.items() if k not in known})


def save_pose(path: str | Path, pose: Pose) -> None:
    write_json(path, pose.to_dict())


def load_pose(path: str | Path) -> Pose:
    try:
        return Pose.from_dict(read_json(path))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


# ----------------------------------------------------------------------------------------------
# Estimation of the pose from the MRI (rule ``pose``).
#
# Pure functions on arrays: a volume ``(I, J, K)`` with its 4x4 affine (voxel index -> world mm,
# axial slices = constant K), and contour stacks ``(n_slices, n_points, 3)`` in world mm.
# ----------------------------------------------------------------------------------------------

from typing import TYPE_CHECKING  # noqa: E402

from .contours import slices_with_contour  # noqa: E402
from .rigid import rotation_matrix  # noqa: E402

if TYPE_CHECKING:
    from .contours import Contours


class PoseError(ValueError):
    """The pose cannot be read from the scan; the message names the animal and the reason."""


@dataclass(frozen=True)
class FluidComponent:
    """The connected component of contrast fluid inside the indenter.

    ``points_mm`` (n, 3) voxel centres [mm]; ``com_mm`` (3,) centre of mass [mm]; ``axis`` (3,) unit
    principal axis (smallest moment of inertia, sign not yet fixed); ``moments_mm2`` (3,) principal
    moments of inertia per unit mass [mm^2], ascending; ``volume_mm3``; ``candidate_volumes_mm3``
    volumes of all candidate components, largest first; ``threshold`` the intensity threshold used.
    """

    points_mm: np.ndarray
    com_mm: np.ndarray
    axis: np.ndarray
    moments_mm2: np.ndarray
    volume_mm3: float
    candidate_volumes_mm3: tuple
    threshold: float
    axis_inertia: np.ndarray | None = None


@dataclass(frozen=True)
class BoneMotion:
    """Rigid motion of the tibia, pre -> during: ``x -> R (x - com_mm) + com_mm + translation_mm``.

    ``com_mm`` (3,) pre-state centroid of the bone in the slab [mm]; ``rotation_deg`` (3,) rotation
    vector [deg]; ``translation_mm`` (3,); ``com_shift_mm`` (3,) raw centroid difference (the initial
    guess); ``rms_initial_mm`` / ``rms_com_mm`` / ``rms_final_mm``: RMS point-to-surface distance of the
    during bone vertices to the pre bone surface before any motion, after the centroid shift, after the fit.
    """

    com_mm: np.ndarray
    rotation_deg: np.ndarray
    translation_mm: np.ndarray
    com_shift_mm: np.ndarray
    rms_initial_mm: float
    rms_com_mm: float
    rms_final_mm: float
    method: str
    dof: int
    n_evaluations: int
    parameter_sd: np.ndarray | None = None  # (dof,) standard errors: rotation [deg], then translation [mm]
    fibula_slices: tuple = (0, 0)  # slices with a fibula contour used in the fit (pre, during); (0, 0): tibia alone


def _where(animal: str) -> str:
    return f"animal {animal}: " if animal else ""


def voxel_centres_mm(affine: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """World coordinates [mm] (n, 3) of voxel indices ``ijk`` (n, 3) through the 4x4 ``affine``."""
    ijk = np.asarray(ijk, dtype=float)
    return ijk @ np.asarray(affine, float)[:3, :3].T + np.asarray(affine, float)[:3, 3]


def inside_skin_mask(shape: tuple, affine: np.ndarray, skin_mm: np.ndarray) -> np.ndarray:
    """Boolean mask (I, J, K): voxel centre inside the skin contour of its axial slice.

    ``skin_mm`` (n_slices, n_points, 3) world mm; each contour is assigned to the volume slice K
    nearest its mean z. Slices without a contour are all False.
    """
    from matplotlib.path import Path as MplPath

    affine = np.asarray(affine, float)
    inv = np.linalg.inv(affine)
    mask = np.zeros(shape, dtype=bool)
    ii, jj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    for contour in np.asarray(skin_mm, float):
        ijk = contour @ inv[:3, :3].T + inv[:3, 3]
        k = int(round(float(ijk[:, 2].mean())))
        if not 0 <= k < shape[2]:
            continue
        # voxel centres of slice k in world mm, tested against the contour in world x, y
        centres = voxel_centres_mm(affine, np.column_stack([ii.ravel(), jj.ravel(), np.full(ii.size, k)]))
        inside = MplPath(contour[:, :2]).contains_points(centres[:, :2])
        mask[:, :, k] = inside.reshape(ii.shape)
    return mask


def fluid_threshold(volume: np.ndarray, inside_mask: np.ndarray, *, ratio: float) -> float:
    """Automatic contrast-fluid threshold: ``ratio`` x the median intensity of the leg (voxels inside the skin)."""
    leg = np.asarray(volume, float)[inside_mask]
    if leg.size == 0:
        raise PoseError("no voxel inside the skin contours: cannot set the fluid threshold")
    return float(ratio * np.median(leg))


def inertia_axis(points_mm: np.ndarray, *, voxel_edges_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre of mass, principal axis and principal moments of a set of equal voxels.

    ``points_mm`` (n, 3) voxel centres [mm]; ``voxel_edges_mm`` (3, 3) the voxel's edge vectors as
    columns (the affine's 3x3 block), so that each voxel counts as a solid parallelepiped (its own
    inertia J J^T / 12 is added; this matters with 1 mm slices and 0.1 mm pixels).
    Returns ``com_mm`` (3,), ``axis`` (3,) the eigenvector of the smallest moment of inertia (the long
    axis), ``moments_mm2`` (3,) ascending moments per unit mass [mm^2].
    """
    p = np.asarray(points_mm, float)
    J = np.asarray(voxel_edges_mm, float)
    com = p.mean(axis=0)
    d = p - com
    cov = d.T @ d / len(p) + J @ J.T / 12.0
    inertia = np.trace(cov) * np.eye(3) - cov
    moments, vecs = np.linalg.eigh(inertia)
    return com, vecs[:, 0] / np.linalg.norm(vecs[:, 0]), moments


def find_fluid_component(
    volume: np.ndarray,
    affine: np.ndarray,
    *,
    threshold: float,
    exclude_mask: np.ndarray | None = None,
    min_volume_mm3: float = 1.0,
    ambiguity_ratio: float = 0.5,
    refine_axis: bool = True,
    animal: str = "",
) -> FluidComponent:
    """The connected component of contrast fluid: voxels above ``threshold`` (26-connected).

    ``volume`` (I, J, K) intensities; ``affine`` 4x4; ``exclude_mask`` (I, J, K) voxels that cannot be
    fluid (inside the deformed skin: bright tissue). Components smaller than ``min_volume_mm3`` are
    noise. The largest remaining one is the indenter's fluid unless the runner-up reaches
    ``ambiguity_ratio`` of its volume (then :class:`PoseError`: several similar candidates).
    The axis is the inertia axis (after cutting the column perpendicular to it where it leaves the
    field of view), refined by :func:`refine_axis_cylinder` when ``refine_axis``.
    """
    from scipy import ndimage

    vol = np.asarray(volume, float)
    if vol.ndim != 3:
        raise PoseError(f"{_where(animal)}during volume is not 3D (shape {vol.shape})")
    affine = np.asarray(affine, float)
    bright = vol > threshold
    if exclude_mask is not None:
        bright &= ~exclude_mask
    labels, n = ndimage.label(bright, structure=np.ones((3, 3, 3), bool))
    voxel_mm3 = abs(float(np.linalg.det(affine[:3, :3])))
    counts = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    volumes = counts * voxel_mm3
    order = np.argsort(volumes)[::-1]
    cands = [int(i) for i in order if volumes[i] >= min_volume_mm3]
    if not cands:
        biggest = f"{volumes.max():.3g} mm^3" if n else "none"
        raise PoseError(
            f"{_where(animal)}no contrast fluid found in the during scan: no bright component outside the skin "
            f">= {min_volume_mm3} mm^3 above threshold {threshold:.4g} (largest: {biggest}); "
            "give pose_override.indenter_axis and tip_end_mm to proceed by hand"
        )
    cand_vols = tuple(float(volumes[i]) for i in cands)
    if len(cands) > 1 and cand_vols[1] >= ambiguity_ratio * cand_vols[0]:
        raise PoseError(
            f"{_where(animal)}several candidate contrast-fluid components of similar size "
            f"({', '.join(f'{v:.3g}' for v in cand_vols[:4])} mm^3): cannot tell which is the indenter; "
            "give pose_override.indenter_axis and tip_end_mm, or adjust pose.fluid_threshold"
        )
    ijk = np.argwhere(labels == cands[0] + 1)
    pts = voxel_centres_mm(affine, ijk)
    com, axis, moments = inertia_axis(pts, voxel_edges_mm=affine[:3, :3])
    # The fluid column usually leaves the field of view: the border cuts it obliquely, which tilts
    # the inertia axis (~0.5 deg for a 12 deg obliquity). Cut it instead by a plane perpendicular to
    # the axis just inside the border voxels, and iterate.
    shape = np.array(vol.shape)
    at_border = np.any((ijk[:, :2] == 0) | (ijk[:, :2] == shape[:2] - 1), axis=1)
    if at_border.any():
        for _ in range(4):
            s = (pts - com) @ axis
            head_side = -np.sign(np.mean(s[at_border]))  # the border cuts the back end
            sb = s[at_border] * head_side
            keep = s * head_side > sb.max() + 0.5
            if keep.sum() < 0.3 * len(pts):
                break
            com, new_axis, moments = inertia_axis(pts[keep], voxel_edges_mm=affine[:3, :3])
            new_axis = new_axis if new_axis @ axis >= 0 else -new_axis
            done = np.degrees(np.arccos(min(1.0, abs(float(new_axis @ axis))))) < 1e-3
            axis = new_axis
            if done:
                break
        pts_used = pts[keep] if keep.sum() >= 0.3 * len(pts) else pts
    else:
        pts_used = pts
    axis_inertia = axis
    if refine_axis:
        background = np.median(vol[~bright & ~exclude_mask]) if exclude_mask is not None else np.median(vol[~bright])
        fluid_level = float(np.median(vol[labels == cands[0] + 1]))
        level = 0.5 * (fluid_level + float(background))
        axis, com = refine_axis_cylinder(vol, affine, pts_used, com_mm=com, axis=axis, level=level,
                                         exclude_mask=exclude_mask, fluid_level=fluid_level)
    return FluidComponent(
        points_mm=pts_used, com_mm=com, axis=axis, moments_mm2=moments, volume_mm3=cand_vols[0],
        candidate_volumes_mm3=cand_vols, threshold=float(threshold), axis_inertia=axis_inertia,
    )


def refine_axis_cylinder(
    volume: np.ndarray, affine: np.ndarray, points_mm: np.ndarray, *, com_mm: np.ndarray, axis: np.ndarray,
    level: float, exclude_mask: np.ndarray | None = None, exclude_margin_mm: float = 0.5,
    end_margin_mm: float = 1.5, max_change_deg: float = 5.0, fluid_level: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Axis (3,) of the fluid column refined by a cylinder fit to its in-plane edges, and the COM (3,)
    moved onto the fitted axis line.

    The inertia axis of voxels 1 mm thick is off by up to ~2 deg (the slices quantise the column
    across z). Within each axial slice the column's edge is known to a fraction of the 0.1 mm pixel:
    sub-pixel iso-contours of ``volume`` at ``level`` (half-way between fluid and background) near the
    component ``points_mm`` (n, 3) are points on a cylinder; the ones more than ``end_margin_mm`` from
    both ends of the column (head sphere, truncation) and more than ``exclude_margin_mm`` in-plane
    from ``exclude_mask`` (I, J, K) (the leg: there the edge is against tissue, not background) are
    fitted by a cylinder (axis direction,
    position, radius; robust soft-L1 loss). The fitted direction is returned if it is within
    ``max_change_deg`` of ``axis``, else ``axis`` and ``com_mm`` unchanged (the sign of ``axis`` is
    kept). The voxel COM is off the axis by up to ~0.2 mm across the slices (quantisation); its
    projection on the fitted line is returned instead.
    Slices that only graze the column (95th-percentile intensity below 90 % of ``fluid_level``, the
    fluid's intensity; partial volume) are left out: their edges depend on the slice profile.
    """
    from scipy import ndimage
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree
    from skimage.measure import find_contours

    a0 = np.asarray(axis, float) / np.linalg.norm(axis)
    c0 = np.asarray(com_mm, float)
    affine = np.asarray(affine, float)
    pts = np.asarray(points_mm, float)
    s = (pts - c0) @ a0
    lo, hi = s.min() + end_margin_mm, s.max() - end_margin_mm
    if hi - lo < 2.0:
        return a0, c0
    inv = np.linalg.inv(affine)
    if fluid_level is None:
        fluid_level = 2.0 * level  # background ~ 0
    ks = np.unique(np.round((pts @ inv[:3, :3].T + inv[:3, 3])[:, 2]).astype(int))
    edge = []
    for k in ks:
        if not 0 <= k < volume.shape[2]:
            continue
        in_k = pts[np.abs((pts @ inv[:3, :3].T + inv[:3, 3])[:, 2] - k) < 0.5]
        if len(in_k) < 3:
            continue
        ijk_k = np.round(in_k @ inv[:3, :3].T + inv[:3, 3]).astype(int)
        peak = float(np.percentile(volume[ijk_k[:, 0], ijk_k[:, 1], k], 95))
        background = 2.0 * level - fluid_level
        if peak < background + 0.9 * (fluid_level - background):  # the slice only grazes the column
            continue
        tree = cKDTree(in_k)
        near_leg = None
        if exclude_mask is not None:
            pixel = float(np.min(np.linalg.norm(affine[:3, :2], axis=0)))
            n_dil = max(1, int(np.ceil(exclude_margin_mm / pixel)))
            near_leg = ndimage.binary_dilation(exclude_mask[:, :, k], iterations=n_dil)
        for c in find_contours(np.asarray(volume[:, :, k], float), level):
            w = voxel_centres_mm(affine, np.column_stack([c, np.full(len(c), k)]))
            d, _ = tree.query(w)
            sw = (w - c0) @ a0
            ok = (d <= 0.3) & (sw >= lo) & (sw <= hi)
            if near_leg is not None:
                ij = np.clip(np.round(c).astype(int), 0, np.array(near_leg.shape) - 1)
                ok &= ~near_leg[ij[:, 0], ij[:, 1]]
            edge.append(w[ok])
    edge = np.concatenate(edge) if edge else np.zeros((0, 3))
    if len(edge) < 20:
        return a0, c0
    e1, e2 = _perpendicular_basis(a0)
    r0 = float(np.median(np.linalg.norm((edge - c0) - np.outer((edge - c0) @ a0, a0), axis=1)))

    def residual(x):
        a = a0 + x[0] * e1 + x[1] * e2
        a = a / np.linalg.norm(a)
        d = edge - (c0 + x[2] * e1 + x[3] * e2)
        return np.linalg.norm(d - np.outer(d @ a, a), axis=1) - x[4]

    fit = least_squares(residual, np.array([0.0, 0.0, 0.0, 0.0, r0]), loss="soft_l1", f_scale=0.05)
    a = a0 + fit.x[0] * e1 + fit.x[1] * e2
    a /= np.linalg.norm(a)
    if np.degrees(np.arccos(min(1.0, float(a @ a0)))) > max_change_deg:
        return a0, c0
    p = c0 + fit.x[2] * e1 + fit.x[3] * e2
    return a, p + ((c0 - p) @ a) * a


def orient_axis(axis: np.ndarray, *, from_mm: np.ndarray, toward_mm: np.ndarray) -> np.ndarray:
    """``axis`` (3,) normalised and signed to point from ``from_mm`` toward ``toward_mm`` (e.g. the leg)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    return a if np.dot(a, np.asarray(toward_mm, float) - np.asarray(from_mm, float)) >= 0 else -a


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(a, u)


def tip_end_mm(
    skin_during_mm: np.ndarray,
    *,
    axis: np.ndarray,
    com_mm: np.ndarray,
    front_mm: float,
    roi_diameter_mm: float = 5.0,
    reach_mm: float = 1.5,
    head_radius_mm: float = 1.5,
    cap_radius_mm: float = 1.2,
    max_fit_rms_mm: float = 0.05,
    method: str = "sphere",
    animal: str = "",
) -> tuple[np.ndarray, dict]:
    """Final tip position [mm] (3,) from the deformed skin.

    ``skin_during_mm`` (n_slices, n_points, 3); ``axis`` (3,) unit, into the leg; ``com_mm`` (3,) the
    fluid's centre of mass; ``front_mm`` the fluid's farthest extent along the axis from the COM.
    The region of interest (ROI) is a cylinder of ``roi_diameter_mm`` about the axis, from the COM to
    ``reach_mm`` beyond the fluid front: it holds the skin under the head, not the far side of the leg.

    ``method='vertex'``: the deepest ROI vertex along the axis, projected on the axis through the COM
    (the paper's method; it fails when the axis is oblique to the skin and the depth small: the
    undeformed skin at the ROI rim then lies deeper along the axis than the tip).
    ``method='sphere'`` (default): the first crossing of the axis with the deformed skin surface
    (within the ROI length) seeds the cap of skin vertices within ``cap_radius_mm``; where the skin
    conforms to the indenter head they lie on a sphere of ``head_radius_mm`` whose centre is on the
    axis. Its position along the axis is fitted to them (robustly: vertices farther than
    ``max_fit_rms_mm`` from the sphere, where the skin leaves the head, are dropped) and the tip is
    the centre + radius * axis. This interpolates between the 1 mm slices, where the skin surface
    triangulated between slices cuts a chord under the curved dimple (up to ~0.1 mm). The crossing
    is kept (or the deepest vertex, if the axis misses the skin surface) if fewer than 8 cap
    vertices lie on the head, or the fit's RMS exceeds ``max_fit_rms_mm``, or it moves the tip more
    than 0.5 mm. Returns the tip and a dict of diagnostics.
    """
    from scipy.optimize import least_squares

    if method not in ("sphere", "vertex"):
        raise ValueError(f"tip_end_mm: method must be 'sphere' or 'vertex', got {method!r}")
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    c = np.asarray(com_mm, float)
    v = np.asarray(skin_during_mm, float).reshape(-1, 3)
    d = v - c
    s = d @ a
    r = np.linalg.norm(d - s[:, None] * a, axis=1)
    roi = (r <= roi_diameter_mm / 2) & (s >= 0) & (s <= front_mm + reach_mm)
    if not roi.any():
        raise PoseError(
            f"{_where(animal)}the indenter axis does not meet the deformed skin: no skin vertex within "
            f"{roi_diameter_mm / 2:g} mm of the axis up to {reach_mm:g} mm beyond the fluid; "
            "give pose_override.indenter_axis / tip_end_mm"
        )
    s_deep = float(s[roi].max())
    tip_vertex = c + s_deep * a
    info = {"tip_roi_vertices": int(roi.sum()), "tip_method": "deepest_vertex",
            "tip_deepest_vertex_mm": tip_vertex.tolist()}
    if method == "vertex":
        return tip_vertex, info
    t_hit = line_triangle_hits(c, a, skin_triangles(skin_during_mm))
    t_hit = t_hit[(t_hit >= 0) & (t_hit <= front_mm + reach_mm)]
    seed = c + t_hit[0] * a if t_hit.size else tip_vertex
    if t_hit.size:
        info.update(tip_method="axis_skin_crossing", tip_axis_crossing_mm=seed.tolist())
    cap = np.linalg.norm(v - seed, axis=1) <= cap_radius_mm
    if cap.sum() < 8:
        return seed, info
    pts = v[cap]
    s0 = float((seed - c) @ a) - head_radius_mm  # head centre on the axis: c + s a

    def head_residual(x, p):
        return np.linalg.norm(p - (c + x[0] * a), axis=1) - head_radius_mm

    keep = np.abs(head_residual([s0], pts)) <= 0.25  # near the head's sphere
    if keep.sum() < 8:
        return seed, info
    x = np.array([s0])
    for _ in range(5):  # fit, drop vertices off the head (skin leaving the indenter), refit
        fit = least_squares(head_residual, x, args=(pts[keep],))
        x = fit.x
        new_keep = np.abs(head_residual(x, pts)) <= max_fit_rms_mm
        if new_keep.sum() < 8 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    tip = c + (x[0] + head_radius_mm) * a
    rms_fit = float(np.sqrt(np.mean(head_residual(x, pts[keep]) ** 2)))
    if keep.sum() < 8 or rms_fit > max_fit_rms_mm or np.linalg.norm(tip - seed) > 0.5:
        info["tip_sphere_fit_rejected_rms_mm"] = rms_fit
        return seed, info
    info.update(tip_method="head_sphere_fit", tip_fit_vertices=int(keep.sum()), tip_fit_rms_mm=rms_fit)
    return tip, info


def skin_triangles(skin_mm: np.ndarray) -> np.ndarray:
    """Triangles (T, 3, 3) [mm] of the surface through a contour stack (n_slices, n_points, 3).

    Point j of slice k is joined to point j of slice k+1 (the contours share start angle and
    direction), each quad split in two; the ends are left open.
    """
    s = np.asarray(skin_mm, float)
    a, b = s[:-1], s[1:]
    a1, b1 = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    t1 = np.stack([a, a1, b1], axis=2).reshape(-1, 3, 3)
    t2 = np.stack([a, b1, b], axis=2).reshape(-1, 3, 3)
    return np.concatenate([t1, t2])


def line_triangle_hits(point_mm: np.ndarray, direction: np.ndarray, triangles_mm: np.ndarray) -> np.ndarray:
    """Parameters t of the points ``point + t * direction`` where the line crosses the triangles (T, 3, 3).

    Möller–Trumbore, vectorised; returns a sorted 1D array (empty if the line misses).
    """
    o = np.asarray(point_mm, float)
    dvec = np.asarray(direction, float)
    v0, v1, v2 = triangles_mm[:, 0], triangles_mm[:, 1], triangles_mm[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(dvec, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = o - v0
    u = np.einsum("ij,ij->i", tv, p) * inv
    q = np.cross(tv, e1)
    w = (q @ dvec) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1)
    return np.sort(t[hit])


def skin_entry_mm(
    skin_pre_mm: np.ndarray, *, axis: np.ndarray, point_mm: np.ndarray, animal: str = ""
) -> np.ndarray:
    """Where the line through ``point_mm`` along ``axis`` meets the undeformed skin, nearest ``point_mm``.

    ``skin_pre_mm`` (n_slices, n_points, 3). Raises :class:`PoseError` if the line misses the skin.
    """
    a = np.asarray(axis, float)
    t = line_triangle_hits(point_mm, a, skin_triangles(skin_pre_mm))
    if t.size == 0:
        raise PoseError(
            f"{_where(animal)}the indenter axis does not meet the undeformed (pre) skin surface; "
            "give pose_override.tip_start_mm or indenter_axis"
        )
    return np.asarray(point_mm, float) + t[np.argmin(np.abs(t))] * a


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


def dense_surface(contours_mm: np.ndarray, *, step_mm: float = 0.05, extend_mm: float = 0.5,
                  upsample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A dense point cloud on the surface through a contour stack, with unit normals.

    ``contours_mm`` (n_slices, n_points, 3), slices at increasing or decreasing z. Each contour is
    upsampled ``upsample`` times around (periodic cubic spline over the point index) and every point
    track is interpolated across the slices with a cubic spline in z every ``step_mm``, extrapolated
    ``extend_mm`` beyond the end slices (the moved bone reaches slightly outside the slab).
    Returns ``points_mm`` (N, 3) and ``normals`` (N, 3).
    """
    from scipy.interpolate import CubicSpline

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


def fit_bone_motion(
    bone_pre_mm: np.ndarray,
    bone_during_mm: np.ndarray,
    *,
    fibula_pre_mm: np.ndarray | None = None,
    fibula_during_mm: np.ndarray | None = None,
    method: str = "surface",
    dof: int = 5,
    surface_step_mm: float = 0.05,
    animal: str = "",
) -> BoneMotion:
    """Rigid motion of the tibia from the pre and during bone contour stacks (n_slices, n_points, 3).

    Translation: the shift of the bone centroid (initial guess). Rotation, and a translation
    correction (``dof=6``: all three components; ``dof=5``: across the leg only, the shift along z
    stays the centroid's; ``dof=3``: none), by Levenberg–Marquardt (``scipy.optimize.least_squares(method='lm')``) on
    the distances of every during bone vertex, mapped back to the pre state, to the pre bone:
    ``method='vertex'`` the distance to the nearest pre vertex (KD-tree) on the original slices;
    ``method='surface'`` the point-to-plane distance to the nearest point of a dense cubic
    interpolation of the pre surface between slices. The latter removes the bias that through-plane
    motion gives nearest-vertex distances between stacks sampled at the same 1 mm z planes.
    A bone that is (nearly) a prism along z cannot show a shift along z: its 6-DOF fit then drifts
    along z with the segmentation noise (check ``parameter_sd``); ``dof=5`` is the remedy.

    ``fibula_pre_mm`` / ``fibula_during_mm`` (n_slices, n_points_f, 3, NaN rows where absent): the
    fibula, which moves with the tibia as one rigid body. Its during vertices (on the slices where
    both states have a fibula contour) join the residuals, each matched to the pre fibula's own
    interpolated surface (never to the tibia's); the centre ``com_mm`` stays the tibia's centroid. A
    fibula that runs obliquely to the tibia moves across the slices under a shift along z, so with
    it ``dof=6`` resolves that shift. Used only when the pre state has it on at least
    ``MIN_FIBULA_SLICES`` slices and both states on as many common slices.
    """
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree

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
    if method not in ("surface", "vertex"):
        raise ValueError(f"fit_bone_motion: method must be 'surface' or 'vertex', got {method!r}")
    if dof not in (3, 5, 6):
        raise ValueError(f"fit_bone_motion: dof must be 3, 5 or 6, got {dof!r}")
    # the pre fibula's surface through all its slices; the during fibula on the slices that have one
    # in both states (a during section whose plane the pre fibula does not reach has no counterpart:
    # matched to the end of the pre surface, it would pull the fit along the bone)
    has_pre, has_dur = _fibula_mask(fibula_pre_mm, pre.shape[0]), _fibula_mask(fibula_during_mm, pre.shape[0])
    both = has_pre & has_dur
    use_fibula = has_pre.sum() >= MIN_FIBULA_SLICES and both.sum() >= MIN_FIBULA_SLICES
    if use_fibula:
        fib_pre = np.asarray(fibula_pre_mm, float)[has_pre]
        fib_dur = np.asarray(fibula_during_mm, float)[both]
    com_pre = bone_centroid_mm(pre)
    shift = bone_centroid_mm(dur) - com_pre
    # (during vertices, pre reference points, their normals, KD-tree) per bone
    bodies = [(pre, dur)] + ([(fib_pre, fib_dur)] if use_fibula else [])
    parts = []
    for b_pre, b_dur in bodies:
        if method == "surface":
            ref, nrm = dense_surface(b_pre, step_mm=surface_step_mm)
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

    def rms(r):
        return float(np.sqrt(np.mean(r**2)))

    rms0 = rms(residuals_for(np.zeros(3), np.zeros(3)))
    rms_com = rms(residuals_for(np.zeros(3), shift))
    def correction(x):  # translation correction (mm) added to the centroid shift
        return np.array([x[3], x[4], x[5] if dof == 6 else 0.0]) if dof > 3 else np.zeros(3)

    fun = lambda x: residuals_for(x[:3], shift + correction(x))  # noqa: E731
    x0 = np.zeros(dof)
    res = least_squares(fun, x0, method="lm", x_scale=np.ones_like(x0), diff_step=1e-4 if method == "surface" else None)
    rot = res.x[:3]
    trans = shift + correction(res.x)
    # standard errors of the parameters from the Jacobian (residual variance x (J^T J)^-1)
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * np.mean(res.fun**2) * len(res.fun) / max(len(res.fun) - dof, 1)
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        sd = np.full(dof, np.inf)
    return BoneMotion(
        com_mm=com_pre, rotation_deg=rot, translation_mm=np.asarray(trans, float), com_shift_mm=shift,
        rms_initial_mm=rms0, rms_com_mm=rms_com, rms_final_mm=rms(res.fun), method=method, dof=dof,
        n_evaluations=int(res.nfev), parameter_sd=sd,
        fibula_slices=(int(has_pre.sum()), int(both.sum())) if use_fibula else (0, 0),
    )


MIN_FIBULA_SLICES = 3  # a fibula seen on fewer slices of a state is not used by the bone fit


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
    return 5, (f"bone_dof auto -> 5: no usable fibula contours ({seen}; {MIN_FIBULA_SLICES} needed); "
               "tibia alone, the shift along the leg (z) is the centroid's")


@dataclass(frozen=True)
class PoseOptions:
    """Settings of :func:`estimate_pose` (config section ``pose``); see the schema for each key."""

    fluid_threshold: float | None = None
    fluid_threshold_ratio: float = 1.6
    min_component_mm3: float = 1.0
    ambiguity_ratio: float = 0.5
    roi_diameter_mm: float = 5.0
    roi_reach_mm: float = 1.5
    head_radius_mm: float = 1.5
    tip_method: str = "sphere"
    start_backoff_mm: float = 1.0
    bone_method: str = "surface"
    bone_dof: int | str = "auto"
    bone_surface_step_mm: float = 0.05

    @classmethod
    def from_config(cls, section: dict | None) -> "PoseOptions":
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in (section or {}).items() if k in known})


_OVERRIDE_KEYS = ("indenter_axis", "tip_end_mm", "tip_start_mm", "bone_rotation_deg", "bone_translation_mm")


def estimate_pose(
    during: np.ndarray,
    affine: np.ndarray,
    pre: Contours,
    during_contours: Contours,
    *,
    options: PoseOptions = PoseOptions(),
    override: dict | None = None,
    animal: str = "",
) -> tuple[Pose, dict]:
    """Indenter pose, depth and tibia motion of one animal.

    ``during`` (I, J, K) intensities of the during scan with its 4x4 ``affine`` (voxel -> world mm);
    ``pre`` / ``during_contours``: :class:`~deeptissue.contours.Contours` of both states.
    ``override``: any of ``indenter_axis``, ``tip_end_mm``, ``tip_start_mm``, ``bone_rotation_deg``,
    ``bone_translation_mm`` given by hand; these replace the automatic quantities, and the ones that
    depend on them are computed from them (start from the hand axis and tip, etc.). With both
    ``indenter_axis`` and ``tip_end_mm`` given the fluid is not needed at all.
    Returns the :class:`Pose` (fit diagnostics in ``extra``) and a dict of intermediate arrays for
    the QC figures (fluid points, ROI, bone motions).
    Raises :class:`PoseError` naming the animal and the reason when the scan cannot be read.
    """
    override = {k: np.asarray(v, float) for k, v in (override or {}).items() if v is not None}
    unknown = set(override) - set(_OVERRIDE_KEYS)
    if unknown:
        raise ValueError(f"{_where(animal)}unknown pose_override key(s) {sorted(unknown)}")
    extra: dict = {"overrides": sorted(override)}
    qc: dict = {}
    leg_centre = during_contours.skin.reshape(-1, 3).mean(axis=0)
    affine = np.asarray(affine, float)

    fluid = None
    if not ("indenter_axis" in override and "tip_end_mm" in override):
        mask = inside_skin_mask(np.shape(during), affine, during_contours.skin)
        thr = options.fluid_threshold
        if thr is None:
            thr = fluid_threshold(during, mask, ratio=options.fluid_threshold_ratio)
        fluid = find_fluid_component(
            during, affine, threshold=thr, exclude_mask=mask, min_volume_mm3=options.min_component_mm3,
            ambiguity_ratio=options.ambiguity_ratio, animal=animal,
        )
        m = fluid.moments_mm2
        extra.update(fluid_threshold=fluid.threshold, fluid_volume_mm3=fluid.volume_mm3,
                     fluid_candidate_volumes_mm3=list(fluid.candidate_volumes_mm3[:5]),
                     fluid_elongation=float(np.sqrt(m[2] / max(m[0], 1e-12))))
        qc["fluid_points_mm"] = fluid.points_mm

    if "indenter_axis" in override:
        axis = override["indenter_axis"] / np.linalg.norm(override["indenter_axis"])
    else:
        axis = orient_axis(fluid.axis, from_mm=fluid.com_mm, toward_mm=leg_centre)
    com = fluid.com_mm if fluid is not None else None

    if "tip_end_mm" in override:
        tip_end = override["tip_end_mm"]
    else:
        front = float(np.max((fluid.points_mm - com) @ axis))
        tip_end, info = tip_end_mm(
            during_contours.skin, axis=axis, com_mm=com, front_mm=front, roi_diameter_mm=options.roi_diameter_mm,
            reach_mm=options.roi_reach_mm, head_radius_mm=options.head_radius_mm, method=options.tip_method,
            animal=animal,
        )
        extra.update(info)
        qc["roi_front_mm"] = front

    if "tip_start_mm" in override:
        tip_start = override["tip_start_mm"]
        surface = tip_start + options.start_backoff_mm * axis
    else:
        # the line of travel: through the final tip along the axis; the skin crossing nearest the
        # indenter (the fluid COM, or the tip when the fluid was not used)
        ref = com if com is not None else tip_end - 5.0 * axis
        t_hits = line_triangle_hits(tip_end, axis, skin_triangles(pre.skin))
        if t_hits.size == 0:
            raise PoseError(
                f"{_where(animal)}the indenter axis does not meet the undeformed (pre) skin surface; "
                "give pose_override.tip_start_mm or indenter_axis"
            )
        hits = tip_end + t_hits[:, None] * axis
        surface = hits[np.argmin(np.linalg.norm(hits - ref, axis=1))]
        tip_start = surface - options.start_backoff_mm * axis
    depth = float((tip_end - surface) @ axis)
    extra["skin_entry_mm"] = surface

    if "bone_rotation_deg" in override and "bone_translation_mm" in override:
        com_pre = bone_centroid_mm(pre.bone)
        rot, trans = override["bone_rotation_deg"], override["bone_translation_mm"]
    else:
        dof, why = resolve_bone_dof(options.bone_dof, pre, during_contours)
        logging.getLogger(__name__).info("%s%s", _where(animal), why)
        motion = fit_bone_motion(
            pre.bone, during_contours.bone, fibula_pre_mm=pre.fibula, fibula_during_mm=during_contours.fibula,
            method=options.bone_method, dof=dof, surface_step_mm=options.bone_surface_step_mm, animal=animal,
        )
        extra["bone_dof_reason"] = why
        extra["bone_fibula_slices"] = list(motion.fibula_slices)
        com_pre = motion.com_mm
        rot = override.get("bone_rotation_deg", motion.rotation_deg)
        trans = override.get("bone_translation_mm", motion.translation_mm)
        extra.update(bone_method=motion.method, bone_dof=motion.dof, bone_com_shift_mm=motion.com_shift_mm,
                     bone_rms_initial_mm=motion.rms_initial_mm, bone_rms_com_mm=motion.rms_com_mm,
                     bone_rms_final_mm=motion.rms_final_mm, bone_fit_evaluations=motion.n_evaluations,
                     bone_fit_sd=motion.parameter_sd)
        qc["bone_com_shift_mm"] = motion.com_shift_mm

    pose = Pose(
        indenter_axis=axis, tip_start_mm=tip_start, tip_end_mm=tip_end, depth_mm=depth, bone_com_mm=com_pre,
        bone_rotation_deg=rot, bone_translation_mm=trans, indenter_com_mm=com, extra=extra,
    )
    return pose, qc


# tolerances of issue 3 (phantoms: tilt <= 25 deg, depth 1-3 mm, bone rotation <= 3 deg, snr >= 12)
ACCURACY_TOLERANCES = {
    "axis_error_deg": 1.0,
    "tip_end_error_mm": 0.1,
    "depth_error_mm": 0.1,
    "bone_rotation_error_deg": 0.3,
    "bone_translation_error_mm": 0.03,
}


def pose_errors(estimate: Pose, truth: Pose) -> dict:
    """Errors of a pose against the truth (phantom ``truth.json``).

    ``axis_error_deg`` angle between the axes; ``tip_end_error_mm`` / ``tip_start_error_mm`` distances;
    ``depth_error_mm`` |difference|; ``bone_rotation_error_deg`` angle of R_est R_true^T;
    ``bone_translation_error_mm``: the estimated motion re-expressed about the truth's centre
    (t' = t + (R - I)(c_true - c_est), the same motion) minus the true translation.
    """
    from scipy.spatial.transform import Rotation

    cos = float(np.clip(estimate.indenter_axis @ truth.indenter_axis, -1.0, 1.0))
    R_est = rotation_matrix(estimate.bone_rotation_deg)
    R_true = rotation_matrix(truth.bone_rotation_deg)
    rel = Rotation.from_matrix(R_est @ R_true.T).magnitude()
    t_about_truth = estimate.bone_translation_mm + (R_est - np.eye(3)) @ (truth.bone_com_mm - estimate.bone_com_mm)
    return {
        "axis_error_deg": float(np.degrees(np.arccos(cos))),
        "tip_end_error_mm": float(np.linalg.norm(estimate.tip_end_mm - truth.tip_end_mm)),
        "tip_start_error_mm": float(np.linalg.norm(estimate.tip_start_mm - truth.tip_start_mm)),
        "depth_error_mm": abs(estimate.depth_mm - truth.depth_mm),
        "bone_rotation_error_deg": float(np.degrees(rel)),
        "bone_translation_error_mm": float(np.linalg.norm(t_about_truth - truth.bone_translation_mm)),
        "bone_com_error_mm": float(np.linalg.norm(estimate.bone_com_mm - truth.bone_com_mm)),
    }


def accuracy_table(estimate: Pose, truth: Pose) -> list[dict]:
    """Rows ``quantity, error, tolerance, within_tolerance`` of :func:`pose_errors` (CSV-ready)."""
    rows = []
    for k, v in pose_errors(estimate, truth).items():
        tol = ACCURACY_TOLERANCES.get(k)
        rows.append({"quantity": k, "error": v, "tolerance": tol if tol is not None else "",
                     "within_tolerance": "" if tol is None else bool(v <= tol)})
    return rows


# ---------------------------------------------------------------------------------------------- QC

def plot_axis_qc(path, during: np.ndarray, affine: np.ndarray, pose: Pose, qc: dict, *, title: str = "") -> None:
    """Axial and sagittal cross-sections through the indenter COM with the fluid voxels and the axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io import atomic_path

    affine = np.asarray(affine, float)
    centre = pose.indenter_com_mm if pose.indenter_com_mm is not None else pose.tip_end_mm
    ijk = np.linalg.solve(affine[:3, :3], centre - affine[:3, 3])
    i, k = (int(np.clip(round(ijk[n]), 0, np.shape(during)[n] - 1)) for n in (0, 2))
    sx, sy, sz = np.abs(np.diag(affine[:3, :3]))
    x0, y0, z0 = affine[:3, 3]
    nx, ny, nz = np.shape(during)
    xs = np.sort([x0, x0 + (nx - 1) * affine[0, 0]])
    ys = np.sort([y0, y0 + (ny - 1) * affine[1, 1]])
    zs = np.sort([z0, z0 + (nz - 1) * affine[2, 2]])
    fig, axs = plt.subplots(1, 2, figsize=(11, 5))
    line = centre[None] + np.linspace(-8, 8, 2)[:, None] * pose.indenter_axis
    pts = qc.get("fluid_points_mm")
    axs[0].imshow(np.asarray(during)[:, :, k].T, origin="lower", cmap="gray",
                  extent=[xs[0] - sx / 2, xs[1] + sx / 2, ys[0] - sy / 2, ys[1] + sy / 2])
    axs[1].imshow(np.asarray(during)[i, :, :].T, origin="lower", cmap="gray", aspect="auto",
                  extent=[ys[0] - sy / 2, ys[1] + sy / 2, zs[0] - sz / 2, zs[1] + sz / 2])
    if pts is not None:
        sel = np.abs(pts[:, 2] - affine[2, 3] - k * affine[2, 2]) < sz / 2
        axs[0].plot(pts[sel, 0], pts[sel, 1], ",", color="tab:cyan", alpha=0.5)
        sel = np.abs(pts[:, 0] - affine[0, 3] - i * affine[0, 0]) < sx / 2
        axs[1].plot(pts[sel, 1], pts[sel, 2], "s", ms=2, color="tab:cyan", alpha=0.5)
    for ax, (a, b) in zip(axs, [(0, 1), (1, 2)]):
        ax.plot(line[:, a], line[:, b], "r-", lw=1, label="axis")
        ax.plot(*pose.tip_end_mm[[a, b]], "y+", ms=12, mew=2, label="tip end")
        ax.plot(*pose.tip_start_mm[[a, b]], "gx", ms=10, mew=2, label="tip start")
    axs[0].set(title=f"axial z = {zs[0] + k * sz:.1f} mm", xlabel="x [mm]", ylabel="y [mm]",
               xlim=(xs[0] - sx / 2, xs[1] + sx / 2), ylim=(ys[0] - sy / 2, ys[1] + sy / 2))
    axs[1].set(title=f"sagittal x = {xs[0] + i * sx:.2f} mm", xlabel="y [mm]", ylabel="z [mm]",
               xlim=(ys[0] - sy / 2, ys[1] + sy / 2), ylim=(zs[0] - sz / 2, zs[1] + sz / 2))
    axs[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(title + " — contrast fluid (cyan) and indenter axis")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def plot_tip_qc(path, pre: Contours, during_contours: Contours, pose: Pose, *, roi_diameter_mm: float = 5.0,
                title: str = "") -> None:
    """The skin ROI around the axis with the start and end points: depth along vs distance from the axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io import atomic_path

    a = pose.indenter_axis
    ref = pose.tip_start_mm
    fig, axs = plt.subplots(1, 2, figsize=(11, 5))
    for c, lab, col in [(pre.skin, "pre skin", "tab:blue"), (during_contours.skin, "during skin", "tab:orange")]:
        v = c.reshape(-1, 3)
        d = v - ref
        s = d @ a
        r = np.linalg.norm(d - s[:, None] * a, axis=1)
        sel = r <= roi_diameter_mm / 2
        axs[0].plot(r[sel], s[sel], ".", ms=3, color=col, label=f"{lab} in ROI")
    axs[0].axhline(0, color="g", lw=1, label="tip start")
    axs[0].axhline(float((pose.tip_end_mm - ref) @ a), color="r", lw=1, label="tip end")
    s_end = float((pose.tip_end_mm - ref) @ a)
    axs[0].set_ylim(s_end + 2.0, -1.0)  # the far side of the leg is outside the ROI's reach
    axs[0].set(xlabel="distance from axis [mm]", ylabel="depth along axis from tip start [mm]",
               title=f"ROI (⌀ {roi_diameter_mm:g} mm), depth = {pose.depth_mm:.3f} mm")
    axs[0].legend(fontsize=8)
    k = int(np.argmin(np.abs(during_contours.z_mm - pose.tip_end_mm[2])))
    for c, lab, col in [(pre.skin, "pre", "tab:blue"), (during_contours.skin, "during", "tab:orange")]:
        axs[1].plot(*np.vstack([c[k], c[k][:1]])[:, :2].T, "-", color=col, lw=1, label=f"{lab} skin")
    line = pose.tip_end_mm[None] + np.linspace(-6, 2, 2)[:, None] * a
    axs[1].plot(line[:, 0], line[:, 1], "r-", lw=0.8)
    axs[1].plot(*pose.tip_start_mm[:2], "gx", ms=10, mew=2, label="tip start")
    axs[1].plot(*pose.tip_end_mm[:2], "r+", ms=12, mew=2, label="tip end")
    axs[1].set(aspect="equal", xlabel="x [mm]", ylabel="y [mm]", title=f"slice z = {during_contours.z_mm[k]:.1f} mm")
    axs[1].legend(fontsize=8)
    fig.suptitle(title + " — skin region of interest, start and end of travel")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def plot_bone_qc(path, pre: Contours, during_contours: Contours, pose: Pose, *, title: str = "") -> None:
    """Bone contours (tibia, and the fibula when both states have it) before, after centroid alignment,
    and after the full rigid fit (x-y and y-z views)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io import atomic_path

    c = pose.bone_com_mm
    dur = during_contours.bone
    shift = np.asarray(pose.extra.get("bone_com_shift_mm", pose.bone_translation_mm), float)
    R = rotation_matrix(pose.bone_rotation_deg)
    fib_pre, fib_dur = pre.fibula_rows, during_contours.fibula_rows
    if len(fib_pre) and len(fib_dur):  # the fibula, moved with the tibia, is drawn with it
        pre_pts = np.concatenate([pre.bone.reshape(-1, 3), fib_pre.reshape(-1, 3)])
        dur = np.concatenate([dur.reshape(-1, 3), fib_dur.reshape(-1, 3)])
    else:
        pre_pts = pre.bone.reshape(-1, 3)
    back = [dur, dur - shift, (dur - c - pose.bone_translation_mm) @ R + c]
    names = ["as imaged", "after centroid alignment", "after rigid fit"]
    fig, axs = plt.subplots(2, 3, figsize=(13, 8))
    for j, (b, name) in enumerate(zip(back, names)):
        for row, (p, q) in enumerate([(0, 1), (1, 2)]):
            ax = axs[row, j]
            ax.plot(pre_pts[..., p].ravel(), pre_pts[..., q].ravel(), ".", ms=1, color="tab:blue", label="pre")
            ax.plot(b[..., p].ravel(), b[..., q].ravel(), ".", ms=1, color="tab:red", label="during, mapped back")
            ax.set(xlabel="xyz"[p] + " [mm]", ylabel="xyz"[q] + " [mm]")
            if row == 0:
                ax.set(aspect="equal", title=name)
    axs[0, 0].legend(fontsize=8, markerscale=6)
    e = pose.extra
    fig.suptitle(
        f"{title} — tibia: rotation {np.round(pose.bone_rotation_deg, 3)} deg, translation "
        f"{np.round(pose.bone_translation_mm, 3)} mm; RMS distance {e.get('bone_rms_initial_mm', np.nan):.3f} → "
        f"{e.get('bone_rms_com_mm', np.nan):.3f} → {e.get('bone_rms_final_mm', np.nan):.3f} mm"
    )
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def run_pose(
    *,
    during_nifti,
    pre_contours,
    during_contours,
    pose_json,
    axis_png,
    tip_png,
    bone_png,
    options: dict | None = None,
    override: dict | None = None,
    animal: str = "",
) -> Pose:
    """Rule ``pose``: read the during NIfTI and both contour files, write ``pose.json`` and the QC figures."""
    import nibabel as nib

    from .contours import load_contours

    img = nib.load(str(during_nifti))
    data = np.asanyarray(img.dataobj, dtype=float)
    if data.ndim != 3:
        raise PoseError(f"{_where(animal)}{during_nifti}: not a 3D volume (shape {data.shape})")
    pre = load_contours(pre_contours)
    dur = load_contours(during_contours)
    opts = PoseOptions.from_config(options)
    pose, qc = estimate_pose(data, img.affine, pre, dur, options=opts, override=override, animal=animal)
    plot_axis_qc(axis_png, data, img.affine, pose, qc, title=animal)
    plot_tip_qc(tip_png, pre, dur, pose, roi_diameter_mm=opts.roi_diameter_mm, title=animal)
    plot_bone_qc(bone_png, pre, dur, pose, title=animal)
    save_pose(pose_json, pose)
    return pose


def run_pose_accuracy(*, pose_json, truth_json, csv_path) -> list[dict]:
    """Rule ``pose_accuracy``: errors of ``pose.json`` against the phantom ``truth.json`` as CSV."""
    import csv

    from .io import atomic_path

    rows = accuracy_table(load_pose(pose_json), load_pose(truth_json))
    with atomic_path(csv_path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return rows
