"""The indenter's contrast fluid in a scan and the indenter's shape read from it.

Pure functions on arrays: a volume ``(I, J, K)`` with its 4x4 affine (voxel index -> world mm,
axial slices = constant K), and contour stacks ``(n_slices, n_points, 3)`` in world mm.
The fluid column is found as the largest bright component outside the skin
(:func:`find_fluid_component`), its axis is the inertia axis refined by a cylinder fit
(:func:`refine_axis_cylinder`); :func:`indenter_shape` reads the head and the fluid's radius from the fluid's
edge. The segmentation masks the indenter with it (:func:`deeptissue.segment.find_indenter`) and the pose
stage measures the axis with it (:mod:`deeptissue.pose`), so it lies below both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from matplotlib.path import Path as MplPath
from scipy import ndimage
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from skimage.measure import find_contours

from .pose_error import PoseError, _where

__all__ = [
    "CylinderFit",
    "FluidComponent",
    "FluidSearch",
    "IndenterShape",
    "find_fluid_component",
    "fluid_threshold",
    "indenter_shape",
    "inertia_axis",
    "inside_skin_mask",
    "orient_axis",
    "perpendicular_basis",
    "refine_axis_cylinder",
    "voxel_centres_mm",
]


@dataclass(frozen=True)
class FluidComponent:
    """The connected component of contrast fluid inside the indenter.

    ``points_mm`` (n, 3) voxel centres [mm] used for the axis; ``com_mm`` (3,) centre of mass [mm]
    (on the fitted axis line when the axis is refined); ``axis`` (3,) unit axis (sign not yet fixed);
    ``moments_mm2`` (3,) principal moments of inertia per unit mass [mm^2], ascending; ``volume_mm3``;
    ``candidate_volumes_mm3`` volumes of all candidate components, largest first; ``threshold`` the
    intensity threshold used; ``axis_inertia`` (3,) the inertia axis before the cylinder refinement.
    """

    points_mm: np.ndarray
    com_mm: np.ndarray
    axis: np.ndarray
    moments_mm2: np.ndarray
    volume_mm3: float
    candidate_volumes_mm3: tuple
    threshold: float
    axis_inertia: np.ndarray | None = None


def voxel_centres_mm(affine: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """World coordinates [mm] (n, 3) of voxel indices ``ijk`` (n, 3) through the 4x4 ``affine``."""
    ijk = np.asarray(ijk, dtype=float)
    return ijk @ np.asarray(affine, float)[:3, :3].T + np.asarray(affine, float)[:3, 3]


def inside_skin_mask(shape: tuple, affine: np.ndarray, skin_mm: np.ndarray) -> np.ndarray:
    """Boolean mask (I, J, K): voxel centre inside the skin contour of its axial slice.

    ``skin_mm`` (n_slices, n_points, 3) world mm; each contour is assigned to the volume slice K
    nearest its mean z. Slices without a contour are all False.
    """

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
        centres = voxel_centres_mm(
            affine, np.column_stack([ii.ravel(), jj.ravel(), np.full(ii.size, k)])
        )
        inside = MplPath(contour[:, :2]).contains_points(centres[:, :2])
        mask[:, :, k] = inside.reshape(ii.shape)
    return mask


def fluid_threshold(volume: np.ndarray, inside_mask: np.ndarray, *, ratio: float) -> float:
    """Automatic contrast-fluid threshold: ``ratio`` x the median intensity of the leg (voxels inside the skin)."""
    leg = np.asarray(volume, float)[inside_mask]
    if leg.size == 0:
        raise PoseError("no voxel inside the skin contours: cannot set the fluid threshold")
    return float(ratio * np.median(leg))


def inertia_axis(
    points_mm: np.ndarray, *, voxel_edges_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


@dataclass(frozen=True)
class FluidSearch:
    """How the contrast fluid is found: the keys ``fluid_threshold``, ``fluid_threshold_ratio``,
    ``min_component_mm3`` and ``ambiguity_ratio`` of the config section ``pose`` (see the schema for each), read
    alike by the segmentation's indenter mask and by the pose stage, whose options take their defaults from here."""

    fluid_threshold: float | None = None
    fluid_threshold_ratio: float = 1.6
    min_component_mm3: float = 1.0
    ambiguity_ratio: float = 0.5

    @classmethod
    def from_config(cls, section: dict | None) -> FluidSearch:
        """The search of a config section ``pose`` (None: all defaults); its other keys are ignored."""
        known = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in (section or {}).items() if k in known})

    def find(self, volume, affine, inside_mask, *, animal: str = "") -> FluidComponent:
        """The fluid component of ``volume`` outside ``inside_mask`` (:func:`find_fluid_component`), at
        ``fluid_threshold`` or, when it is None, at :func:`fluid_threshold` of ``fluid_threshold_ratio``."""
        thr = self.fluid_threshold
        if thr is None:
            thr = fluid_threshold(volume, inside_mask, ratio=self.fluid_threshold_ratio)
        return find_fluid_component(
            volume,
            affine,
            threshold=thr,
            exclude_mask=inside_mask,
            min_volume_mm3=self.min_component_mm3,
            ambiguity_ratio=self.ambiguity_ratio,
            animal=animal,
        )


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
        background = (
            np.median(vol[~bright & ~exclude_mask])
            if exclude_mask is not None
            else np.median(vol[~bright])
        )
        fluid_level = float(np.median(vol[labels == cands[0] + 1]))
        level = 0.5 * (fluid_level + float(background))
        axis, com = refine_axis_cylinder(
            vol,
            affine,
            pts_used,
            (com, axis),
            levels=(level, fluid_level),
            exclude_mask=exclude_mask,
        )
    return FluidComponent(
        points_mm=pts_used,
        com_mm=com,
        axis=axis,
        moments_mm2=moments,
        volume_mm3=cand_vols[0],
        candidate_volumes_mm3=cand_vols,
        threshold=float(threshold),
        axis_inertia=axis_inertia,
    )


@dataclass(frozen=True)
class CylinderFit:
    """Settings of :func:`refine_axis_cylinder`: edges within ``end_margin_mm`` of either end of the column
    (head sphere, truncation) and within ``exclude_margin_mm`` in-plane of the leg are left out; a fitted
    direction more than ``max_change_deg`` from the inertia axis is rejected."""

    exclude_margin_mm: float = 0.5
    end_margin_mm: float = 1.5
    max_change_deg: float = 5.0


def refine_axis_cylinder(
    volume: np.ndarray,
    affine: np.ndarray,
    points_mm: np.ndarray,
    start: tuple[np.ndarray, np.ndarray],
    *,
    levels: tuple[float, float],
    exclude_mask: np.ndarray | None = None,
    fit: CylinderFit = CylinderFit(),
) -> tuple[np.ndarray, np.ndarray]:
    """Axis (3,) of the fluid column refined by a cylinder fit to its in-plane edges, and the COM (3,)
    moved onto the fitted axis line.

    The inertia axis of voxels 1 mm thick is off by up to ~2 deg (the slices quantise the column
    across z). Within each axial slice the column's edge is known to a fraction of the 0.1 mm pixel:
    sub-pixel iso-contours of ``volume`` at the edge level near the component ``points_mm`` (n, 3) are
    points on a cylinder (:func:`_column_edges`); they are fitted by a cylinder (axis direction, position,
    radius; robust soft-L1 loss). ``start`` is the inertia estimate (COM (3,) [mm], axis (3,)); ``levels``
    the edge level (half-way between fluid and background) and the fluid's intensity; ``exclude_mask``
    (I, J, K) the leg, where the edge is against tissue, not background. The fitted direction is returned
    if it is within ``fit.max_change_deg`` of the start, else the start unchanged (the sign of the axis
    is kept). The voxel COM is off the axis by up to ~0.2 mm across the slices (quantisation); its
    projection on the fitted line is returned instead.
    """

    c0 = np.asarray(start[0], float)
    a0 = np.asarray(start[1], float) / np.linalg.norm(start[1])
    edge = _column_edges(
        volume, affine, np.asarray(points_mm, float), (c0, a0), levels, exclude_mask, fit
    )
    if len(edge) < 20:
        return a0, c0
    e1, e2 = perpendicular_basis(a0)
    r0 = float(np.median(np.linalg.norm((edge - c0) - np.outer((edge - c0) @ a0, a0), axis=1)))

    def residual(x):
        a = a0 + x[0] * e1 + x[1] * e2
        a = a / np.linalg.norm(a)
        d = edge - (c0 + x[2] * e1 + x[3] * e2)
        return np.linalg.norm(d - np.outer(d @ a, a), axis=1) - x[4]

    res = least_squares(residual, np.array([0.0, 0.0, 0.0, 0.0, r0]), loss="soft_l1", f_scale=0.05)
    a = a0 + res.x[0] * e1 + res.x[1] * e2
    a /= np.linalg.norm(a)
    if np.degrees(np.arccos(min(1.0, float(a @ a0)))) > fit.max_change_deg:
        return a0, c0
    p = c0 + res.x[2] * e1 + res.x[3] * e2
    return a, p + ((c0 - p) @ a) * a


def _column_edges(
    volume, affine, pts, start, levels, exclude_mask, fit: CylinderFit
) -> np.ndarray:
    """Sub-pixel in-plane edge points (n, 3) [mm] of the fluid column for :func:`refine_axis_cylinder`.

    Iso-contours of each axial slice at ``levels[0]`` within 0.3 mm of the column's voxels ``pts``, more
    than ``fit.end_margin_mm`` from both ends of the column along the axis of ``start`` (COM, axis) and
    more than ``fit.exclude_margin_mm`` in-plane from ``exclude_mask``. Slices that only graze the column
    (95th-percentile intensity below 90 % of the fluid's intensity ``levels[1]`` over the background;
    partial volume) are left out: their edges depend on the slice profile.
    """

    c0, a0 = start
    level, fluid_level = levels
    affine = np.asarray(affine, float)
    s = (pts - c0) @ a0
    lo, hi = s.min() + fit.end_margin_mm, s.max() - fit.end_margin_mm
    if hi - lo < 2.0:
        return np.zeros((0, 3))
    inv = np.linalg.inv(affine)
    background = 2.0 * level - fluid_level
    k_of = (pts @ inv[:3, :3].T + inv[:3, 3])[:, 2]
    edge = []
    for k in np.unique(np.round(k_of).astype(int)):
        in_k = pts[np.abs(k_of - k) < 0.5]
        if not 0 <= k < volume.shape[2] or len(in_k) < 3:
            continue
        ijk_k = np.round(in_k @ inv[:3, :3].T + inv[:3, 3]).astype(int)
        peak = float(np.percentile(volume[ijk_k[:, 0], ijk_k[:, 1], k], 95))
        if peak < background + 0.9 * (
            fluid_level - background
        ):  # the slice only grazes the column
            continue
        tree = cKDTree(in_k)
        near_leg = None
        if exclude_mask is not None:
            pixel = float(np.min(np.linalg.norm(affine[:3, :2], axis=0)))
            n_dil = max(1, int(np.ceil(fit.exclude_margin_mm / pixel)))
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
    return np.concatenate(edge) if edge else np.zeros((0, 3))


def orient_axis(axis: np.ndarray, *, from_mm: np.ndarray, toward_mm: np.ndarray) -> np.ndarray:
    """``axis`` (3,) normalised and signed to point from ``from_mm`` toward ``toward_mm`` (e.g. the leg)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    return a if np.dot(a, np.asarray(toward_mm, float) - np.asarray(from_mm, float)) >= 0 else -a


def perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(a, u)


@dataclass(frozen=True)
class IndenterShape:
    """The indenter in the during scan: a cylinder of outer radius ``radius_mm`` about ``axis`` that ends in a
    hemispherical head centred at ``head_centre_mm``; the contrast fluid fills it out to ``fluid_radius_mm``.

    ``axis`` (3,) unit vector into the leg; ``head_centre_mm`` (3,) [mm]; the wall is ``radius_mm -
    fluid_radius_mm`` thick.
    """

    axis: np.ndarray
    head_centre_mm: np.ndarray
    radius_mm: float
    fluid_radius_mm: float

    @property
    def wall_mm(self) -> float:
        """Thickness of the dark wall between the fluid and the tissue [mm]."""
        return self.radius_mm - self.fluid_radius_mm

    @property
    def tip_mm(self) -> np.ndarray:
        """The front of the head [mm] (3,)."""
        return self.head_centre_mm + self.radius_mm * self.axis

    def signed_distance_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Distance [mm] (...) of ``points_mm`` (..., 3) from the indenter's outer surface, negative inside."""
        p = np.asarray(points_mm, float) - self.head_centre_mm
        t = np.maximum(p @ -self.axis, 0.0)
        q = p + t[..., None] * self.axis
        return np.linalg.norm(q, axis=-1) - self.radius_mm


def indenter_shape(
    volume: np.ndarray,
    affine: np.ndarray,
    fluid: FluidComponent,
    *,
    axis: np.ndarray,
    radius_mm: float,
    exclude_mask: np.ndarray | None = None,
    animal: str = "",
) -> IndenterShape:
    """The indenter's head and fluid radius from the contrast fluid's sub-pixel edge.

    The edge is the iso-contour of each axial slice of ``volume`` half-way between the fluid (median of the
    component) and the background outside the leg, near the component's voxels. The fluid radius is the
    median distance of the edge from the axis line where the column is a cylinder (more than 1.5 mm behind
    its front); the head centre is the point of the axis whose sphere of that radius fits the edge points
    of the front hemisphere best (least squares, robust). The outer radius ``radius_mm`` is the indenter's
    known size (config ``pose.head_radius_mm``); the wall lies between the two.

    Parameters
    ----------
    volume : (I, J, K) array
        The during scan.
    affine : (4, 4) array
        Voxel index -> world mm.
    fluid : FluidComponent
        From :func:`find_fluid_component`.
    axis : (3,) array
        Axis into the leg (:func:`orient_axis`).
    radius_mm : float
        Outer radius of the indenter and its head [mm].
    exclude_mask : (I, J, K) bool array or None
        Voxels inside the leg, left out of the background level.
    animal : str
        Named in error messages.

    Returns
    -------
    IndenterShape

    Raises
    ------
    PoseError
        If the fluid's edge has too few points to fit, or the fluid is wider than ``radius_mm``.
    """

    vol = np.asarray(volume, float)
    affine = np.asarray(affine, float)
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    c0 = np.asarray(fluid.com_mm, float)
    inv = np.linalg.inv(affine)
    pts = np.asarray(fluid.points_mm, float)
    ijk = np.round(pts @ inv[:3, :3].T + inv[:3, 3]).astype(int)
    fluid_level = float(np.median(vol[ijk[:, 0], ijk[:, 1], ijk[:, 2]]))
    outside = vol < fluid.threshold
    if exclude_mask is not None:
        outside &= ~exclude_mask
    background = float(np.median(vol[outside])) if outside.any() else 0.0
    level = 0.5 * (fluid_level + background)
    tree = cKDTree(pts)
    edge = []
    for k in np.unique(ijk[:, 2]):
        for cont in find_contours(vol[:, :, k], level):
            w = voxel_centres_mm(affine, np.column_stack([cont, np.full(len(cont), k)]))
            d, _ = tree.query(w)
            edge.append(w[d <= 0.3])
    edge = np.concatenate(edge) if edge else np.zeros((0, 3))
    if len(edge) < 20:
        raise PoseError(
            f"{_where(animal)}the contrast fluid's edge has {len(edge)} points: too few to fit the "
            "indenter's head"
        )
    rel = edge - c0
    s = rel @ a
    r = np.linalg.norm(rel - np.outer(s, a), axis=1)
    front = float(s.max())
    body = s < front - 1.5
    r_fluid = float(np.median(r[body])) if body.sum() >= 20 else float(np.median(r))
    if r_fluid >= radius_mm:
        raise PoseError(
            f"{_where(animal)}the contrast fluid is {2 * r_fluid:.3g} mm across, wider than the "
            f"indenter ({2 * radius_mm:g} mm, pose.head_radius_mm); check pose.head_radius_mm"
        )
    s_head = front - r_fluid
    for _ in range(3):  # the front hemisphere: edge points ahead of the head centre
        cap = edge[s >= s_head]
        if len(cap) < 10:
            break
        fit = least_squares(
            lambda x, cap=cap: np.linalg.norm(cap - (c0 + x[0] * a), axis=1) - r_fluid,
            [s_head],
            loss="soft_l1",
            f_scale=0.05,
        )
        s_head = float(fit.x[0])
    return IndenterShape(
        axis=a, head_centre_mm=c0 + s_head * a, radius_mm=float(radius_mm), fluid_radius_mm=r_fluid
    )
