"""The indenter's final tip in the during scan, from the deformed skin.

The final tip is where the fluid's axis (:mod:`deeptissue.fluid`) meets the deformed skin, refined by a fit of
the indenter's head sphere (:func:`tip_end_mm`); the start of the travel, where the axis meets the undeformed skin,
is found by :mod:`.estimate` with :func:`line_triangle_hits`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..pose_error import PoseError, _where

__all__ = [
    "TipSearch",
    "line_triangle_hits",
    "skin_triangles",
    "tip_end_mm",
]


@dataclass(frozen=True)
class TipSearch:
    """Where :func:`tip_end_mm` looks for the deformed skin under the indenter.

    The region of interest (ROI) is a cylinder of ``roi_diameter_mm`` about ``axis`` (3,) (into the leg),
    from the fluid's centre of mass ``com_mm`` (3,) [mm] to ``reach_mm`` beyond the fluid's farthest extent
    ``front_mm`` along the axis from ``com_mm``: it holds the skin under the head, not the far side of the leg.
    """

    axis: np.ndarray
    com_mm: np.ndarray
    front_mm: float
    roi_diameter_mm: float = 5.0
    reach_mm: float = 1.5


def tip_end_mm(
    skin_during_mm: np.ndarray,
    search: TipSearch,
    *,
    head_radius_mm: float = 1.5,
    cap_radius_mm: float = 1.2,
    max_fit_rms_mm: float = 0.05,
    method: str = "sphere",
    animal: str = "",
) -> tuple[np.ndarray, dict]:
    """Final tip position [mm] from the deformed skin in the region of interest of ``search``.

    ``method='vertex'``: the deepest ROI vertex along the axis, projected on the axis through the COM
    (the paper's method; it fails when the axis is oblique to the skin and the depth small: the
    undeformed skin at the ROI rim then lies deeper along the axis than the tip).
    ``method='sphere'`` (default): the first crossing of the axis with the deformed skin surface
    (within the ROI length) seeds the cap of skin vertices within ``cap_radius_mm``; where the skin
    conforms to the indenter head they lie on a sphere of ``head_radius_mm`` whose centre is on the
    axis (:func:`_head_sphere_fit`). This interpolates between the 1 mm slices, where the skin surface
    triangulated between slices cuts a chord under the curved dimple (up to ~0.1 mm). The crossing is
    kept (or the deepest vertex, if the axis misses the skin surface) when the fit is rejected.

    Parameters
    ----------
    skin_during_mm : (n_slices, n_points, 3) array
        Deformed skin contours [mm].
    search : TipSearch
        The axis, the fluid's COM and front, and the ROI.
    head_radius_mm, cap_radius_mm : float
        Radius of the indenter's head sphere, and of the skin cap around the axis crossing fitted by it [mm].
    max_fit_rms_mm : float
        Largest distance [mm] of a fitted vertex from the head sphere, and largest RMS of the fit.
    method : {'sphere', 'vertex'}
        See above.
    animal : str
        Named in error messages.

    Returns
    -------
    tip_mm : (3,) array
        The final tip [mm].
    info : dict
        Diagnostics for ``pose.json``: ``tip_method`` (``deepest_vertex``, ``axis_skin_crossing`` or
        ``head_sphere_fit``), the ROI's vertex count, the candidate points and the fit's RMS.

    Raises
    ------
    PoseError
        If no skin vertex lies in the ROI (the axis misses the leg).
    """
    if method not in ("sphere", "vertex"):
        raise ValueError(f"tip_end_mm: method must be 'sphere' or 'vertex', got {method!r}")
    a = np.asarray(search.axis, float)
    a = a / np.linalg.norm(a)
    c = np.asarray(search.com_mm, float)
    v = np.asarray(skin_during_mm, float).reshape(-1, 3)
    d = v - c
    s = d @ a
    r = np.linalg.norm(d - s[:, None] * a, axis=1)
    length = search.front_mm + search.reach_mm
    roi = (r <= search.roi_diameter_mm / 2) & (s >= 0) & (s <= length)
    if not roi.any():
        raise PoseError(
            f"{_where(animal)}the indenter axis does not meet the deformed skin: no skin vertex within "
            f"{search.roi_diameter_mm / 2:g} mm of the axis up to {search.reach_mm:g} mm beyond the fluid; "
            "give pose_override.indenter_axis / tip_end_mm"
        )
    tip_vertex = c + float(s[roi].max()) * a
    info = {
        "tip_roi_vertices": int(roi.sum()),
        "tip_method": "deepest_vertex",
        "tip_deepest_vertex_mm": tip_vertex.tolist(),
    }
    if method == "vertex":
        return tip_vertex, info
    t_hit = line_triangle_hits(c, a, skin_triangles(skin_during_mm))
    t_hit = t_hit[(t_hit >= 0) & (t_hit <= length)]
    seed = c + t_hit[0] * a if t_hit.size else tip_vertex
    if t_hit.size:
        info.update(tip_method="axis_skin_crossing", tip_axis_crossing_mm=seed.tolist())
    cap = v[np.linalg.norm(v - seed, axis=1) <= cap_radius_mm]
    fit = _head_sphere_fit(cap, seed, a, head_radius_mm=head_radius_mm, max_rms_mm=max_fit_rms_mm)
    if fit is None:
        return seed, info
    tip, n_fit, rms_fit = fit
    if n_fit < 8 or rms_fit > max_fit_rms_mm or np.linalg.norm(tip - seed) > 0.5:
        info["tip_sphere_fit_rejected_rms_mm"] = rms_fit
        return seed, info
    info.update(tip_method="head_sphere_fit", tip_fit_vertices=n_fit, tip_fit_rms_mm=rms_fit)
    return tip, info


def _head_sphere_fit(
    cap_mm: np.ndarray,
    seed_mm: np.ndarray,
    axis: np.ndarray,
    *,
    head_radius_mm: float,
    max_rms_mm: float,
) -> tuple[np.ndarray, int, float] | None:
    """The tip of the head sphere fitted to the skin cap ``cap_mm`` (n, 3) around ``seed_mm``: the sphere of
    ``head_radius_mm`` centred on the line through ``seed_mm`` along the unit ``axis``.

    Its position along the axis is fitted to the cap vertices near the sphere (robustly: vertices farther
    than ``max_rms_mm`` from it, where the skin leaves the head, are dropped and the fit repeated). Returns
    (tip (3,), vertices fitted, RMS [mm]), or None with fewer than 8 cap vertices near the head.
    """

    if len(cap_mm) < 8:
        return None

    def head_residual(x, p):
        return np.linalg.norm(p - (seed_mm + x[0] * axis), axis=1) - head_radius_mm

    x = np.array([-head_radius_mm])  # head centre on the axis: seed + x axis
    keep = np.abs(head_residual(x, cap_mm)) <= 0.25  # near the head's sphere
    if keep.sum() < 8:
        return None
    for _ in range(5):  # fit, drop vertices off the head (skin leaving the indenter), refit
        x = least_squares(head_residual, x, args=(cap_mm[keep],)).x
        new_keep = np.abs(head_residual(x, cap_mm)) <= max_rms_mm
        if new_keep.sum() < 8 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    rms = float(np.sqrt(np.mean(head_residual(x, cap_mm[keep]) ** 2)))
    return seed_mm + (x[0] + head_radius_mm) * axis, int(keep.sum()), rms


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


def line_triangle_hits(
    point_mm: np.ndarray, direction: np.ndarray, triangles_mm: np.ndarray
) -> np.ndarray:
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
