"""Geometry of the animal model: contour checks, volumes, the rigid cast with its hole, patch selection.

Pure numpy functions on contour stacks (``(n_slices, n_points, 3)`` world mm, counter-clockwise seen
from +z, one axial slice per row, see :mod:`deeptissue.contours`) and triangle surfaces
(``vertices_mm`` (V, 3), ``triangles`` (T, 3) int). The gmsh solid model and the mesh live in
:mod:`deeptissue.mesh`.

Cast offset: every contour point is moved **along the local outward normal** of the skin surface
(in its slice plane, lengthened by ``1 / (n_plane . n_surface)`` so the 3D distance to the lofted skin
is the offset even where the leg tapers). The paper offset radially from the slice centre; a radial
move of ``d`` leaves a normal gap of only ``d cos(a)`` where the contour is oblique to the ray
(``a`` up to ~15-20 deg on an 11 x 8.6 mm ellipse, i.e. 0.19 instead of 0.2 mm) and is undefined
where a contour is not star-shaped about its centre. ``offset_direction="radial"`` reproduces the
paper and falls back to the normal for contours that are not star-shaped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    "ModelInputError",
    "axis_distance_mm",
    "bar_direction",
    "CastSpec",
    "build_cast",
    "check_contours",
    "closest_point_on_triangles",
    "extend_rings",
    "footprint_distance_mm",
    "grid_normals",
    "grid_triangles",
    "is_star_shaped",
    "limb_volume_mm3",
    "loft_rings",
    "offset_rings",
    "point_triangle_distance",
    "polygon_area_mm2",
    "prismatoid_volume_mm3",
    "resample_arclength",
    "select_patch",
    "surface_distance_mm",
    "triangle_areas",
    "triangle_normals",
]

log = logging.getLogger(__name__)


class ModelInputError(ValueError):
    """Contours or pose that cannot make a model; the message names the animal and the problem."""


# --------------------------------------------------------------------------- contours, areas, volumes


def polygon_area_mm2(ring: np.ndarray) -> np.ndarray:
    """Signed area of closed polygon(s) in the xy plane (..., n_points, >=2) -> (...) [mm^2], > 0 if CCW."""
    x, y = ring[..., 0], ring[..., 1]
    return 0.5 * np.sum(x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y, axis=-1)


def prismatoid_volume_mm3(rings: np.ndarray) -> float:
    """Volume enclosed by a stack of contours (n_slices, n_points, 3) joined point by point [mm^3].

    Between two slices the surface joining corresponding points by straight lines is a prismatoid:
    its cross-section area is quadratic in z, so Simpson's rule ``h/6 (A0 + 4 Am + A1)`` with ``Am``
    the area of the mid contour (mean of corresponding points) is exact. Slices may be unevenly spaced.
    """
    rings = np.asarray(rings, float)
    z = rings[:, :, 2].mean(axis=1)
    a = polygon_area_mm2(rings)
    am = polygon_area_mm2(0.5 * (rings[1:] + rings[:-1]))
    return float(np.sum(np.diff(z) / 6.0 * (a[:-1] + 4.0 * am + a[1:])))


def limb_volume_mm3(skin: np.ndarray, bone: np.ndarray) -> float:
    """Prismatoid volume between the skin and the bone contour stacks [mm^3]."""
    return prismatoid_volume_mm3(skin) - prismatoid_volume_mm3(bone)


def _segments_intersect(ring: np.ndarray) -> bool:
    """True if a closed polygon (n, 2) crosses itself (non-adjacent edges intersect)."""
    p = ring[:, :2]
    q = np.roll(p, -1, axis=0)
    n = len(p)
    d = q - p
    # orientation tests of every edge pair
    r = p[None, :, :] - p[:, None, :]  # p_j - p_i
    cross = lambda a, b: a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]  # noqa: E731
    den = cross(d[:, None, :], d[None, :, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross(r, d[None, :, :]) / den
        u = cross(r, d[:, None, :]) / den
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    adjacent = (np.abs(i - j) <= 1) | (np.abs(i - j) == n - 1)
    hit = (den != 0) & (t > 0) & (t < 1) & (u > 0) & (u < 1) & ~adjacent
    return bool(hit.any())


def inside_polygon(points: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Even-odd test of points (m, >=2) against a closed polygon (n, >=2) -> (m,) bool."""
    x, y = points[:, 0][:, None], points[:, 1][:, None]
    x0, y0 = ring[:, 0][None, :], ring[:, 1][None, :]
    x1, y1 = np.roll(ring[:, 0], -1)[None, :], np.roll(ring[:, 1], -1)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = ((y0 > y) != (y1 > y)) & (x < (x1 - x0) * (y - y0) / (y1 - y0) + x0)
    return (np.count_nonzero(cond, axis=1) % 2) == 1


def _ring_distance(points: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Distance in the xy plane from points (m, >=2) to a closed polyline (n, >=2) -> (m,) [mm]."""
    a = ring[:, :2]
    b = np.roll(a, -1, axis=0)
    ab = b - a
    ap = points[:, None, :2] - a[None]
    t = np.clip(
        np.einsum("mnk,nk->mn", ap, ab) / np.maximum(np.einsum("nk,nk->n", ab, ab), 1e-300), 0, 1
    )
    return np.min(np.linalg.norm(ap - t[..., None] * ab[None], axis=2), axis=1)


def check_contours(
    skin: np.ndarray, bone: np.ndarray, *, animal: str = "?", min_gap_mm: float = 0.05
) -> dict:
    """Refuse contours that cannot make a limb model; return per-slice facts used later.

    Checks: at least 2 slices of >= 8 points each, finite, every contour in one axial plane, slices
    strictly increasing in z, counter-clockwise, not self-intersecting, bone strictly inside the skin
    with a gap of at least ``min_gap_mm``. Raises :class:`ModelInputError` naming animal, slice, problem.
    Returns ``{"z_mm": (n_slices,), "min_gap_mm": (n_slices,)}``.
    """
    skin = np.asarray(skin, float)
    bone = np.asarray(bone, float)
    for name, a in (("skin", skin), ("bone", bone)):
        if a.ndim != 3 or a.shape[2] != 3:
            raise ModelInputError(
                f"animal {animal}: {name} contours: expected (n_slices, n_points, 3), got {a.shape}"
            )
        if a.shape[0] < 2:
            raise ModelInputError(
                f"animal {animal}: {name} contours: need at least 2 slices, got {a.shape[0]}"
            )
        if a.shape[1] < 8:
            raise ModelInputError(
                f"animal {animal}: {name} contours: need at least 8 points per contour, got {a.shape[1]}"
            )
        if not np.all(np.isfinite(a)):
            raise ModelInputError(f"animal {animal}: {name} contours: non-finite coordinates")
    if skin.shape[0] != bone.shape[0]:
        raise ModelInputError(
            f"animal {animal}: {skin.shape[0]} skin slices but {bone.shape[0]} bone slices"
        )
    z = skin[:, :, 2].mean(axis=1)
    gaps = np.zeros(len(z))
    for k in range(len(z)):
        for name, a in (("skin", skin[k]), ("bone", bone[k])):
            if np.ptp(a[:, 2]) > 1e-6 or abs(a[:, 2].mean() - z[k]) > 1e-6:
                raise ModelInputError(
                    f"animal {animal}: slice {k}: {name} contour is not in one axial plane z = {z[k]:.3f} mm"
                )
            area = polygon_area_mm2(a)
            if area <= 0:
                raise ModelInputError(
                    f"animal {animal}: slice {k}: {name} contour is {'clockwise' if area < 0 else 'degenerate'} (expected counter-clockwise seen from +z)"
                )
            if _segments_intersect(a):
                raise ModelInputError(f"animal {animal}: slice {k}: {name} contour crosses itself")
        if not np.all(inside_polygon(bone[k], skin[k])):
            raise ModelInputError(
                f"animal {animal}: slice {k}: bone contour is not inside the skin contour"
            )
        gaps[k] = _ring_distance(bone[k], skin[k]).min()
        if gaps[k] < min_gap_mm:
            raise ModelInputError(
                f"animal {animal}: slice {k}: bone comes within {gaps[k]:.3f} mm of the skin (minimum {min_gap_mm} mm): no tissue to mesh"
            )
    if np.any(np.diff(z) <= 0):
        k = int(np.argmin(np.diff(z)))
        raise ModelInputError(
            f"animal {animal}: slices {k} and {k + 1}: z not strictly increasing ({z[k]:.3f}, {z[k + 1]:.3f} mm)"
        )
    return {"z_mm": z, "min_gap_mm": gaps}


# --------------------------------------------------------------------------- loft (spline in z)


def resample_arclength(rings: np.ndarray, n_points: int | None = None) -> np.ndarray:
    """Contours (..., n, 3) resampled to ``n_points`` points equidistant in arc length along each closed
    polygon, starting at its first point (so lofts joining points by index join them by arc length,
    as OpenCASCADE's chord-length splines do)."""
    rings = np.asarray(rings, float)
    n = rings.shape[-2]
    m = int(n_points or n)
    flat = rings.reshape(-1, n, 3)
    out = np.empty((len(flat), m, 3))
    for i, r in enumerate(flat):
        closed = np.vstack([r, r[:1]])
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
        t = np.linspace(0.0, s[-1], m, endpoint=False)
        out[i] = np.stack([np.interp(t, s, closed[:, c]) for c in range(3)], axis=1)
    return out.reshape(*rings.shape[:-2], m, 3)


def loft_rings(rings: np.ndarray, *, dz_mm: float = 0.25, ruled: bool = False) -> np.ndarray:
    """Resample a contour stack finely along z: corresponding points joined by a cubic spline in z, or
    by straight lines (``ruled``).

    rings (n_slices, n_points, 3) -> (n_out, n_points, 3), with the input slices kept and about
    ``dz_mm`` between output rows. Two slices give straight lines.
    """
    z = rings[:, :, 2].mean(axis=1)
    n_sub = np.maximum(1, np.ceil(np.diff(z) / dz_mm).astype(int))
    zs = np.concatenate(
        [np.linspace(z[k], z[k + 1], n_sub[k], endpoint=False) for k in range(len(z) - 1)]
        + [z[-1:]]
    )
    if len(z) < 3 or ruled:
        xy = np.stack(
            [np.interp(zs, z, rings[:, j, c]) for j in range(rings.shape[1]) for c in range(2)],
            axis=1,
        )
        xy = xy.reshape(len(zs), rings.shape[1], 2)
    else:
        xy = CubicSpline(z, rings[:, :, :2], axis=0, bc_type="not-a-knot")(zs)
    return np.concatenate(
        [xy, np.broadcast_to(zs[:, None, None], (len(zs), rings.shape[1], 1))], axis=2
    )


def grid_normals(rings: np.ndarray) -> np.ndarray:
    """Outward unit normals (n_slices, n_points, 3) of the surface through a CCW contour stack."""
    tc = np.roll(rings, -1, axis=1) - np.roll(rings, 1, axis=1)  # along the contour (CCW)
    tz = (
        np.gradient(rings, axis=0)
        if len(rings) > 1
        else np.broadcast_to([0.0, 0.0, 1.0], rings.shape)
    )
    n = np.cross(tc, tz)  # CCW tangent x +z direction = outward
    return n / np.linalg.norm(n, axis=2, keepdims=True)


def is_star_shaped(ring: np.ndarray) -> bool:
    """True if every ray from the contour's centroid meets it once (polar angle strictly increasing)."""
    c = ring[:, :2].mean(axis=0)
    ang = np.unwrap(np.arctan2(ring[:, 1] - c[1], ring[:, 0] - c[0]))
    step = np.diff(np.append(ang, ang[0] + 2 * np.pi))
    return bool(np.all(step > 0))


def offset_rings(
    rings: np.ndarray, offset_mm: float, *, direction: str = "normal", animal: str = "?"
) -> tuple[np.ndarray, list[str]]:
    """Offset every contour of a stack outward by ``offset_mm`` within its slice plane.

    ``direction="normal"``: along the in-plane outward normal, lengthened so the 3D distance to the
    surface through the stack is ``offset_mm``; where the offset contour would cross itself (a
    concavity tighter than the offset), the normals are smoothed along the contour until it does not.
    ``direction="radial"``: away from the slice centroid (the paper); contours that are not
    star-shaped use the normal. Returns the offset stack (same shape) and log messages.
    """
    if direction not in ("normal", "radial"):
        raise ValueError(
            f"animal {animal}: cast offset direction {direction!r}: expected 'normal' or 'radial'"
        )
    msgs = []
    n3 = grid_normals(rings)
    n2 = n3.copy()
    n2[..., 2] = 0.0
    n2 /= np.linalg.norm(n2, axis=2, keepdims=True)
    stretch = 1.0 / np.clip(np.einsum("skc,skc->sk", n2, n3), 0.5, None)
    out = rings.copy()
    for k in range(len(rings)):
        if direction == "radial":
            if is_star_shaped(rings[k]):
                c = rings[k, :, :2].mean(axis=0)
                r = rings[k, :, :2] - c
                out[k, :, :2] += offset_mm * r / np.linalg.norm(r, axis=1, keepdims=True)
                continue
            msgs.append(
                f"cast: slice {k} is not star-shaped about its centroid: offset along the normal instead of radially"
            )
        d = n2[k, :, :2] * (offset_mm * stretch[k])[:, None]
        for it in range(50):
            cand = rings[k, :, :2] + d
            if not _segments_intersect(cand):
                break
            d = (np.roll(d, 1, axis=0) + 2 * d + np.roll(d, -1, axis=0)) / 4.0
        else:
            raise ModelInputError(
                f"animal {animal}: slice {k}: cannot offset the skin contour by {offset_mm} mm without self-intersection"
            )
        if it:
            msgs.append(
                f"cast: slice {k}: offset contour crossed itself at a tight concavity; normals smoothed {it}x"
            )
        out[k, :, :2] = cand
    return out, msgs


def extend_rings(rings: np.ndarray, extension_mm: float) -> np.ndarray:
    """Duplicate the first and last contour ``extension_mm`` beyond the ends (along -z and +z)."""
    first = rings[:1].copy()
    last = rings[-1:].copy()
    first[..., 2] -= extension_mm
    last[..., 2] += extension_mm
    return np.concatenate([first, rings, last], axis=0)


def grid_triangles(n_rows: int, n_cols: int, *, inward: bool) -> np.ndarray:
    """Triangles of a (n_rows x n_cols) grid closed in the column direction (T, 3).

    Rows are slices (increasing z), columns run CCW; the normal points outward unless ``inward``.
    """
    i, j = np.meshgrid(np.arange(n_rows - 1), np.arange(n_cols), indexing="ij")
    a = i * n_cols + j
    b = i * n_cols + (j + 1) % n_cols
    c = (i + 1) * n_cols + (j + 1) % n_cols
    d = (i + 1) * n_cols + j
    tri = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return tri[:, [0, 2, 1]] if inward else tri


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals (T, 3) of triangles by the right-hand rule."""
    p = vertices[triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Areas (T,) of triangles (T, 3) on vertices (V, 3) [mm^2 for vertices in mm]."""
    p = vertices[triangles]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


# --------------------------------------------------------------------------- axis distances, patches


def axis_distance_mm(points: np.ndarray, *, point_mm, axis) -> np.ndarray:
    """Distance of points (..., 3) from the infinite line through ``point_mm`` along unit ``axis`` [mm]."""
    a = np.asarray(axis, float)
    r = np.asarray(points, float) - np.asarray(point_mm, float)
    return np.linalg.norm(r - np.einsum("...k,k->...", r, a)[..., None] * a, axis=-1)


def footprint_distance_mm(
    points: np.ndarray, *, point_mm, axis, half_length_mm: float = 0.0, long_dir=None
) -> np.ndarray:
    """Distance from points to an indenter footprint projected along ``axis`` [mm].

    The footprint is the axis line (sphere) or, with ``half_length_mm > 0``, the strip swept by the
    axis along ``long_dir`` (the bar's segment, ⟂ axis) from -half_length to +half_length.
    """
    a = np.asarray(axis, float)
    r = np.asarray(points, float) - np.asarray(point_mm, float)
    r = r - np.einsum("...k,k->...", r, a)[..., None] * a  # in the plane perpendicular to the axis
    if half_length_mm > 0:
        b = np.asarray(long_dir, float)
        s = np.clip(np.einsum("...k,k->...", r, b), -half_length_mm, half_length_mm)
        r = r - s[..., None] * b
    return np.linalg.norm(r, axis=-1)


def bar_direction(axis) -> np.ndarray:
    """Long direction of the bar: world z projected onto the plane perpendicular to the axis (unit)."""
    a = np.asarray(axis, float)
    b = np.array([0.0, 0.0, 1.0]) - a[2] * a
    n = np.linalg.norm(b)
    if n < 1e-6:
        raise ValueError("bar indenter: axis along the leg (world z): bar direction undefined")
    return b / n


def select_patch(
    centroids: np.ndarray,
    normals: np.ndarray,
    *,
    point_mm,
    axis,
    radius_mm: float,
    half_length_mm: float = 0.0,
    long_dir=None,
) -> np.ndarray:
    """Facets of the skin that may touch the indenter: (n,) bool.

    A facet is in the patch when its centroid, projected along ``axis``, lies within ``radius_mm`` of
    the footprint (the axis for a sphere, the bar's strip for a bar) and its outward normal faces the
    indenter (``normal . axis < 0``; the axis points from the indenter into the leg).
    """
    d = footprint_distance_mm(
        centroids, point_mm=point_mm, axis=axis, half_length_mm=half_length_mm, long_dir=long_dir
    )
    return (d <= radius_mm) & (normals @ np.asarray(axis, float) < 0)


# --------------------------------------------------------------------------- cast with hole


def _clip_surface(
    vertices: np.ndarray, triangles: np.ndarray, f: np.ndarray, active: np.ndarray, level=None
):
    """Remove the part of a triangle surface where ``f < 0`` on ``active`` triangles, cut along f = 0.

    Straddling triangles are split on their edges at the zero of the level function ``level(points
    (m, 3)) -> (m,)`` found by bisection (default: the linear zero of the vertex values f). A vertex
    with f == 0 is on the cut and reused. Cut points are shared between neighbours, so the cut edge
    is watertight. Returns new vertices and triangles.
    """
    fv = f[triangles]
    neg = fv < 0
    nneg = neg.sum(axis=1)
    keep_whole = ~active | (nneg == 0)
    straddle = active & (nneg > 0) & (nneg < 3)
    # every edge of a straddling triangle that crosses f = 0 between two non-zero values
    st = triangles[straddle]
    e = np.concatenate([st[:, [0, 1]], st[:, [1, 2]], st[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    e = e[((f[e[:, 0]] < 0) != (f[e[:, 1]] < 0)) & (f[e[:, 0]] != 0) & (f[e[:, 1]] != 0)]
    pa, pb = vertices[e[:, 0]], vertices[e[:, 1]]
    if level is None:
        t = f[e[:, 0]] / (f[e[:, 0]] - f[e[:, 1]])
    else:
        lo, hi = np.zeros(len(e)), np.ones(len(e))
        neg_a = f[e[:, 0]] < 0
        for _ in range(45):
            mid = 0.5 * (lo + hi)
            same = (level(pa + mid[:, None] * (pb - pa)) < 0) == neg_a
            lo = np.where(same, mid, lo)
            hi = np.where(same, hi, mid)
        t = 0.5 * (lo + hi)
    n_v = len(vertices)
    edge_index: dict[tuple[int, int], int] = {}
    new_pts = []
    for (a, b), tk in zip(e.tolist(), t):
        if (
            tk <= 1e-9 or tk >= 1 - 1e-9
        ):  # the cut passes through a vertex: reuse it (no duplicate)
            edge_index[(a, b)] = a if tk <= 1e-9 else b
        else:
            new_pts.append(vertices[a] + tk * (vertices[b] - vertices[a]))
            edge_index[(a, b)] = n_v + len(new_pts) - 1

    def cut(a, b):
        if f[a] == 0 or f[b] == 0:  # the outline passes through a (snapped) vertex: reuse it
            return a if f[a] == 0 else b
        return edge_index[(a, b) if a < b else (b, a)]

    extra = []
    for tri, ng in zip(st, neg[straddle]):
        # rotate so the pattern starts at a fixed place, preserving orientation
        for r in range(3):
            tr = np.roll(tri, -r)
            m = np.roll(ng, -r)
            if ng.sum() == 1 and m[0]:
                # t0 removed, t1 t2 kept: quad p01, t1, t2, p20
                p01, p20 = cut(tr[0], tr[1]), cut(tr[2], tr[0])
                extra += [(p01, tr[1], tr[2]), (p01, tr[2], p20)]
                break
            if ng.sum() == 2 and not m[0]:
                # t0 kept, t1 t2 removed
                extra.append((tr[0], cut(tr[0], tr[1]), cut(tr[2], tr[0])))
                break
    verts = np.concatenate([vertices, np.array(new_pts).reshape(-1, 3)])
    tris = np.concatenate([triangles[keep_whole], np.array(extra, dtype=np.int64).reshape(-1, 3)])
    return verts, tris


def _compact(vertices: np.ndarray, triangles: np.ndarray):
    used = np.unique(triangles)
    renum = np.full(len(vertices), -1, np.int64)
    renum[used] = np.arange(len(used))
    return vertices[used], renum[triangles]


@dataclass(frozen=True)
class CastSpec:
    """How the cast is made from the skin: offset_mm, the gap to the skin [mm]; offset_direction, 'normal'
    (along the skin's normal) or 'radial' (away from each slice's centroid); extension_mm, how far the end
    contours are repeated past the leg's ends [mm]; dz_mm, the spacing of the lofted rings along the leg [mm];
    ruled, straight lines between the offset contours in place of a cubic spline in z; hole_diameter_mm, the
    hole's diameter [mm] about each indenter footprint (0: no hole)."""

    offset_mm: float = 0.2
    offset_direction: str = "normal"
    extension_mm: float = 1.0
    dz_mm: float = 0.25
    ruled: bool = False
    hole_diameter_mm: float = 6.0


def build_cast(
    skin: np.ndarray,
    footprints: list,
    spec: CastSpec = CastSpec(),
    *,
    axis,
    point_mm,
    surface: tuple | None = None,
    animal: str = "?",
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The rigid cast around the pre skin: offset, extended, lofted, with the indenter hole.

    skin (n_slices, n_points, 3) world mm; ``footprints``: the indenter footprints ``(point_mm, axis,
    half_length_mm, long_dir)`` (see :func:`footprint_distance_mm`; axis a unit vector from the indenter into
    the leg, point_mm a point on it, the final tip) whose circles of ``spec.hole_diameter_mm``, each projected
    along its own axis (a bar's swept along it), make the hole; ``axis`` (unit, from the indenter into the
    leg) and ``point_mm`` (on it, the final tip): the estimated indenter axis, whose side of the cast is cut
    and whose nearest sheet is cut where there are several; ``surface``: optionally the lofted skin
    surface sampled as a grid ``(points (n_rows, n_cols, 3), outward unit normals (n_rows, n_cols, 3))``, rows
    from the first to the last contour (:func:`deeptissue.mesh.sample_lofted_surface`, the surface the mesh
    lies on): then that grid is offset (along the 3D normal, or radially about each row's centroid) instead
    of the contours lofted here (by a cubic spline in z, or by straight lines if ``spec.ruled``). Returns
    ``vertices_mm`` (V, 3), ``triangles`` (T, 3) with normals pointing toward the leg, and log messages saying
    how the hole was cut.

    The hole is cut on the side of the cast that faces the indenter (outward normal . axis < 0): cast
    triangles are clipped exactly on the projected outline. Where the projection cannot cut cleanly it is
    resolved, and logged: a cut vertex almost on the outline is snapped onto it (no slivers); a circle wider
    than the facing side of the cast stops at the silhouette (the far side is never cut); a circle reaching
    past an end of the cast opens the hole into that end; of several facing sheets hit (a fold) only the one
    nearest the indenter is cut. A hole diameter of 0 leaves the cast closed around the leg.
    """
    msgs: list[str] = []
    rings = _cast_rings(skin, spec, surface, animal=animal, msgs=msgs)
    n_rows, n_cols = rings.shape[:2]
    verts = rings.reshape(-1, 3)
    tris = grid_triangles(n_rows, n_cols, inward=True)
    if spec.hole_diameter_mm <= 0:
        return verts, tris, msgs + ["cast: no hole (hole_diameter_mm = 0)"]
    fps = [
        (
            np.asarray(p_, float),
            np.asarray(a_, float) / np.linalg.norm(a_),
            float(h_),
            None if d_ is None else np.asarray(d_, float),
        )
        for p_, a_, h_, d_ in footprints
    ]
    facing = (np.asarray(point_mm, float), np.asarray(axis, float))
    v2, t2, n_cut = _cut_hole(rings, fps, facing, spec, animal=animal, msgs=msgs)
    what = (
        f"union of {len(fps)} variants' {spec.hole_diameter_mm} mm outlines"
        if len(fps) > 1
        else f"{spec.hole_diameter_mm} mm circle"
    )
    msgs.append(
        f"cast: hole ({what}) cut on the facing side ({n_cut} triangles clipped or removed)"
    )
    return v2, t2, msgs


def _cast_rings(skin, spec: CastSpec, surface, *, animal: str, msgs: list) -> np.ndarray:
    """The cast's rings (n_rows, n_cols, 3) [mm]: the skin contours (or the sampled ``surface``) offset by
    ``spec.offset_mm``, extended past the leg's ends and lofted; ``msgs`` gains what was resolved."""
    if surface is None:
        off, m = offset_rings(
            np.asarray(skin, float), spec.offset_mm, direction=spec.offset_direction, animal=animal
        )
        msgs += m
        return loft_rings(extend_rings(off, spec.extension_mm), dz_mm=spec.dz_mm, ruled=spec.ruled)
    grid, normals = (np.asarray(a, float) for a in surface)
    rings = grid + spec.offset_mm * normals
    if spec.offset_direction == "radial":
        for k in range(len(grid)):
            if is_star_shaped(grid[k]):
                r = grid[k, :, :2] - grid[k, :, :2].mean(axis=0)
                rings[k] = grid[k]
                rings[k, :, :2] += spec.offset_mm * r / np.linalg.norm(r, axis=1, keepdims=True)
            elif not any("not star-shaped" in m for m in msgs):
                msgs.append(
                    f"cast: the skin is not star-shaped about its centroid at z = {grid[k, :, 2].mean():.2f} mm (and maybe elsewhere): offset along the normal there instead of radially"
                )
    for k in range(len(rings)):
        if _segments_intersect(rings[k]):
            raise ModelInputError(
                f"animal {animal}: the cast offset by {spec.offset_mm} mm crosses itself at z = {rings[k, :, 2].mean():.2f} mm (a concavity of the skin tighter than the offset)"
            )
    return extend_rings(rings, spec.extension_mm)


def _hole_level(fps: list, radius: float):
    """``level(x) -> (signed distance-like level (m,), in-plane vector (m, 3))`` of points (m, 3): < 0 inside
    the hole's projected outline, and the vector from the nearest footprint point (for snapping onto it)."""

    def level(x):
        best = np.full(len(x), np.inf)
        vec = np.zeros((len(x), 3))
        for p_, a_, h_, d_ in fps:
            r_ = x - p_
            r_ = r_ - (r_ @ a_)[:, None] * a_
            if h_ > 0:
                s_ = np.clip(r_ @ d_, -h_, h_)
                r_ = r_ - s_[:, None] * d_
            d = np.linalg.norm(r_, axis=1)
            take = d < best
            best = np.where(take, d, best)
            vec[take] = r_[take]
        return best - radius, vec

    return level


def _cut_hole(
    rings: np.ndarray, fps: list, facing: tuple, spec: CastSpec, *, animal: str, msgs: list
):
    """(vertices (V, 3), triangles (T, 3), triangles clipped or removed) of the lofted cast ``rings`` with the
    hole of the footprints ``fps`` cut on the side facing the indenter; ``msgs`` gains what was resolved."""
    n_rows, n_cols = rings.shape[:2]
    verts = rings.reshape(-1, 3)
    tris = grid_triangles(n_rows, n_cols, inward=True)
    vnorm_out = grid_normals(rings).reshape(-1, 3)
    radius = 0.5 * spec.hole_diameter_mm
    point, axis = facing
    hole_level = _hole_level(fps, radius)
    f, _ = hole_level(verts)
    facing_v = vnorm_out @ axis < 0
    tri_out = -triangle_normals(verts, tris)  # outward normals
    facing_t = tri_out @ axis < 0
    in_cyl = np.any(f[tris] < 0, axis=1)
    if not np.any(in_cyl & facing_t):
        raise ModelInputError(
            f"animal {animal}: the indenter axis does not meet the cast (no cast surface within {radius} mm of the axis facing the indenter)"
        )
    # snap near-outline vertices (closer than 2% of the local edge length) onto the outline
    edge = np.linalg.norm(rings[:, 1:2] - rings[:, 0:1], axis=2).mean() if n_cols > 1 else 1.0
    snap = np.abs(f) < 0.02 * min(edge, spec.dz_mm)
    if np.any(snap & facing_v):
        msgs.append(
            f"cast: hole: {int(np.sum(snap & facing_v))} vertex(es) within {0.02 * min(edge, spec.dz_mm):.4f} mm of the hole outline snapped onto it (no sliver triangles)"
        )
        _, vec = hole_level(verts[snap])
        verts = verts.copy()
        verts[snap] += (radius / np.linalg.norm(vec, axis=1) - 1.0)[:, None] * vec
        f = np.where(snap, 0.0, f)

    # triangles to cut: facing and touching the cylinder; keep only the sheet nearest the indenter
    cand = facing_t & np.any(f[tris] < 0, axis=1)
    comp = _components(tris, cand, len(verts))
    if comp.max() > 0:
        t_along = (verts[tris].mean(axis=1) - point) @ axis
        labels = np.unique(comp[comp >= 0])
        mean_t = np.array([t_along[comp == lab].mean() for lab in labels])
        nearest = labels[np.argmin(mean_t)]
        if len(labels) > 1:
            msgs.append(
                f"cast: hole: the projected circle meets {len(labels)} facing sheets; cut only the one nearest the indenter"
            )
        cand = comp == nearest
    # silhouette: removed region bounded by non-facing vertices still inside the circle
    sil = np.any((f[tris] < 0) & ~facing_v[tris], axis=1) & cand
    if np.any(sil):
        msgs.append(
            f"cast: hole: the {spec.hole_diameter_mm} mm circle is wider than the side of the cast facing the indenter; the hole stops at the silhouette ({int(sil.sum())} triangles there)"
        )
    # ends
    end_rows = np.concatenate(
        [np.arange(n_cols), np.arange((n_rows - 1) * n_cols, n_rows * n_cols)]
    )
    cut_v = np.zeros(len(verts), bool)
    cut_v[tris[cand].ravel()] = True
    if np.any(cut_v[end_rows] & (f[end_rows] < 0)):
        which = (
            "proximal"
            if np.any(cut_v[end_rows[n_cols:]] & (f[end_rows[n_cols:]] < 0))
            else "distal"
        )
        msgs.append(
            f"cast: hole: the projected circle reaches past the {which} end of the cast; the hole opens into that end (a notch)"
        )
    v2, t2 = _clip_surface(verts, tris, f, cand, level=lambda x: hole_level(x)[0])
    area = triangle_areas(v2, t2)
    t2 = t2[area > 1e-12]
    return (*_compact(v2, t2), int(cand.sum()))


def _components(tris: np.ndarray, mask: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected components (by shared vertices) of the masked triangles; -1 elsewhere (T,)."""
    idx = np.flatnonzero(mask)
    out = np.full(len(tris), -1)
    if len(idx) == 0:
        return out
    rows = np.repeat(np.arange(len(idx)), 3)
    inc = coo_matrix(
        (np.ones(rows.size), (rows, tris[idx].ravel())), shape=(len(idx), n_vertices)
    ).tocsr()
    adj = inc @ inc.T
    _, lab = connected_components(adj, directed=False)
    out[idx] = lab
    return out


# --------------------------------------------------------------------------- distances to a triangle surface


def closest_point_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p, all (m, 3). Returns (q (m, 3), region (m,))
    with region 0 = face interior, 1/2/3 = edge ab/bc/ca, 4/5/6 = vertex a/b/c (Ericson's method)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    denom = np.where(np.abs(denom) > 0, denom, 1.0)
    v = vb / denom
    w = vc / denom
    q = a + v[:, None] * ab + w[:, None] * ac
    region = np.zeros(len(p), dtype=np.int64)

    def put(mask, val, reg):
        nonlocal q
        q = np.where(mask[:, None], val, q)
        region[mask] = reg
        return mask

    done = np.zeros(len(p), bool)
    # vertex regions
    m = (d1 <= 0) & (d2 <= 0)
    done |= put(m & ~done, a, 4)
    m = (d3 >= 0) & (d4 <= d3)
    done |= put(m & ~done, b, 5)
    m = (d6 >= 0) & (d5 <= d6)
    done |= put(m & ~done, c, 6)
    # edge regions
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t = d1 / np.where(d1 - d3 != 0, d1 - d3, 1.0)
    done |= put(m & ~done, a + t[:, None] * ab, 1)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t = d2 / np.where(d2 - d6 != 0, d2 - d6, 1.0)
    done |= put(m & ~done, a + t[:, None] * ac, 3)
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    t = (d4 - d3) / np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) + (d5 - d6), 1.0)
    done |= put(m & ~done, b + t[:, None] * (c - b), 2)
    return q, region


def point_triangle_distance(p, a, b, c) -> np.ndarray:
    """Exact Euclidean distance from points ``p`` to triangles ``(a, b, c)`` (all (n, 3)) -> (n,) [mm].

    The closest point of :func:`closest_point_on_triangles` (Voronoi regions: vertex, edge or face,
    Ericson, *Real-Time Collision Detection*, 5.1.5); degenerate (zero-area) triangles fall back to the
    nearest of their edges.
    """
    p, a, b, c = (np.asarray(x, float) for x in (p, a, b, c))
    q, _ = closest_point_on_triangles(p, a, b, c)
    dist = np.linalg.norm(p - q, axis=1)
    ab, ac = b - a, c - a
    flat = np.linalg.norm(np.cross(ab, ac), axis=1) <= 1e-12 * (_dot(ab, ab) + _dot(ac, ac))
    if np.any(flat):
        pf, af, bf, cf = p[flat], a[flat], b[flat], c[flat]
        dist[flat] = np.min(
            [_seg_dist(pf, af, bf), _seg_dist(pf, bf, cf), _seg_dist(pf, cf, af)], axis=0
        )
    return dist


def _dot(x, y):
    return np.einsum("ij,ij->i", x, y)


def _seg_dist(p, a, b):
    ab = b - a
    L2 = _dot(ab, ab)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(L2 > 0, _dot(p - a, ab) / L2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def surface_distance_mm(points_mm, vertices_mm, triangles) -> np.ndarray:
    """Exact distance from each point (..., 3) to a triangle surface -> (n_points,) [mm].

    Candidates come from a KD-tree on triangle centroids: with ``d0`` the distance to the triangles of
    the nearest few centroids and ``R`` the largest centroid-to-vertex distance, every triangle closer
    than ``d0`` has its centroid within ``d0 + R``; all of those are checked exactly.
    """
    P = np.asarray(points_mm, float).reshape(-1, 3)
    V = np.asarray(vertices_mm, float)
    T = np.asarray(triangles, np.int64)
    if len(T) == 0:
        raise ValueError("surface_distance_mm: the surface has no triangles")
    if len(P) == 0:
        return np.zeros(0)
    tri = V[T]  # (T, 3, 3)
    cen = tri.mean(axis=1)
    R = float(np.max(np.linalg.norm(tri - cen[:, None], axis=2)))
    tree = cKDTree(cen)
    k = min(8, len(T))
    _, idx = tree.query(P, k=k)
    idx = idx.reshape(len(P), k)
    rows = np.repeat(np.arange(len(P)), k)
    d0 = (
        point_triangle_distance(P[rows], *(tri[idx.ravel(), j] for j in range(3)))
        .reshape(len(P), k)
        .min(axis=1)
    )
    cand = tree.query_ball_point(P, d0 + R + 1e-9)
    counts = np.fromiter((len(c) for c in cand), int, len(P))
    flat = np.fromiter((i for c in cand for i in c), np.int64, counts.sum())
    rows = np.repeat(np.arange(len(P)), counts)
    d = point_triangle_distance(P[rows], tri[flat, 0], tri[flat, 1], tri[flat, 2])
    out = np.full(len(P), np.inf)
    np.minimum.at(out, rows, d)
    return np.minimum(out, d0)
