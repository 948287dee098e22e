"""Tetrahedral meshes from gmsh, as plain arrays (the hand-over between mesher and solver).

A :class:`TetMesh` holds every node of a second-order mesh (corner and mid-edge), the 10-node
tetrahedra in **gmsh's node order**, and named boundary facet sets as 6-node triangles (gmsh
order too). gmsh's Tetrahedron10 order is corners 0-3, then the mid-edge nodes of edges
(0,1), (1,2), (0,2), (0,3), (2,3), (1,3); scikit-fem orders the last two edges (1,3), (2,3), so a
conversion swaps local nodes 8 and 9 (done in the FE core, which owns scikit-fem meshes).
A first-order (linear) mesh is the same with 4-node tetrahedra and 3-node facets (``order`` 1).
Written and read only by :func:`save_tetmesh` / :func:`load_tetmesh` (``.npz``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .elements import GMSH_TET10_EDGES, tet10_shape_gradients
from .geometry import inside_polygon, polygon_area_mm2, select_patch
from .io import atomic_path, save_npz

log = logging.getLogger(__name__)

GMSH_TET10 = 11  # gmsh element type of the 10-node tetrahedron
GMSH_TRI6 = 9  # gmsh element type of the 6-node triangle
GMSH_TET4 = 4  # gmsh element type of the 4-node tetrahedron
GMSH_TRI3 = 2  # gmsh element type of the 3-node triangle
# nodes per tetrahedron / facet of each element order
TET_NODES = {1: 4, 2: 10}
FACET_NODES = {1: 3, 2: 6}


@dataclass(frozen=True)
class TetMesh:
    """Nodes, tetrahedra and named facet sets of a first- or second-order tetrahedral mesh.

    nodes_mm (n_nodes, 3) world mm; tets (n_tets, 10) gmsh Tetrahedron10 order (order 2) or
    (n_tets, 4) corners (order 1); facets: name -> (n_facets, 6) gmsh Triangle6 order (order 2) or
    (n_facets, 3) corners (order 1). Every facet set must have the order of the tetrahedra.
    """

    nodes_mm: np.ndarray  # (n_nodes, 3) world mm, corner and mid-edge nodes
    tets: (
        np.ndarray
    )  # (n_tets, 10) node indices, gmsh Tetrahedron10 order; or (n_tets, 4) for order 1
    facets: dict = field(
        default_factory=dict
    )  # name -> (n_facets, 6) gmsh Triangle6 order; or (n_facets, 3)

    def __post_init__(self):
        if self.nodes_mm.ndim != 2 or self.nodes_mm.shape[1] != 3:
            raise ValueError(f"TetMesh.nodes_mm: expected (n, 3), got {self.nodes_mm.shape}")
        if self.tets.ndim != 2 or self.tets.shape[1] not in (4, 10):
            raise ValueError(
                f"TetMesh.tets: expected (n, 10) (quadratic) or (n, 4) (linear), got {self.tets.shape}"
            )
        nf = FACET_NODES[self.order]
        for name, f in self.facets.items():
            if f.ndim != 2 or f.shape[1] != nf:
                raise ValueError(
                    f"TetMesh.facets[{name!r}]: expected (n, {nf}) for {self.tets.shape[1]}-node tetrahedra, got {f.shape}"
                )
        n = len(self.nodes_mm)
        for name, arr in [
            ("tets", self.tets),
            *((f"facets[{k!r}]", v) for k, v in self.facets.items()),
        ]:
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise ValueError(f"TetMesh.{name}: node index out of range 0..{n - 1}")

    @property
    def order(self) -> int:
        """Element order: 2 for 10-node, 1 for 4-node tetrahedra."""
        return 1 if self.tets.shape[1] == 4 else 2

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def volumes_mm3(self) -> np.ndarray:
        """Volumes of the straight-sided tetrahedra through the four corners (n_tets,) [mm^3]."""
        p = self.nodes_mm[self.tets[:, :4]]
        return (
            np.einsum(
                "ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]
            )
            / 6.0
        )


def edge_midpoints(tets, x) -> tuple[np.ndarray, np.ndarray]:
    """The mid-edge nodes (n, 6) of quadratic tetrahedra ``tets`` (n, 10) and the midpoints (n, 6, 3) of
    their edges' corners at the nodal positions ``x`` (n_nodes, 3): where a straight-sided element puts them."""
    e = np.asarray(GMSH_TET10_EDGES)
    tets = np.asarray(tets)
    return tets[:, 4:], 0.5 * (x[tets[:, e[:, 0]]] + x[tets[:, e[:, 1]]])


def _tet_frames(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corners (m, 4, 3) [mm], centroids (m, 3) [mm] and inverse edge matrices (m, 3, 3) [1/mm] of the straight
    tetrahedra through the mesh's corners (the edge matrix's columns: the edges from corner 0)."""
    corners = mesh.nodes_mm[mesh.tets[:, :4]]
    inverse = np.linalg.inv(np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1)))
    return corners, corners.mean(axis=1), inverse


def _barycentric(frames, points_mm: np.ndarray, elems: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 4) of each point (n, 3) [mm] in its element ``elems`` (n,) of ``frames``
    (:func:`_tet_frames`)."""
    corners, _, inverse = frames
    xi = np.einsum("nij,nj->ni", inverse[elems], points_mm - corners[elems, 0])
    return np.column_stack([1.0 - xi.sum(axis=1), xi])


def _locate_nearest(
    frames, points_mm: np.ndarray, nearest: int
) -> tuple[cKDTree, np.ndarray, np.ndarray]:
    """The centroids' KD-tree, and for each point (n, 3) [mm] the element among those with the ``nearest``
    nearest centroids whose smallest barycentric coordinate is largest (n,), with its coordinates (n, 4)."""
    tree = cKDTree(frames[1])
    n, k = len(points_mm), min(nearest, len(frames[1]))
    _, idx = tree.query(points_mm, k=k)
    idx = idx.reshape(n, k)
    lam = _barycentric(frames, np.repeat(points_mm, k, axis=0), idx.ravel()).reshape(n, k, 4)
    best = np.argmax(lam.min(axis=2), axis=1)
    rows = np.arange(n)
    return tree, idx[rows, best], lam[rows, best]


def _first_top(score: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For candidates in consecutive groups of ``counts`` (each > 0): each group's top ``score`` and the
    position of its first candidate reaching it."""
    starts = np.cumsum(counts) - counts
    top = np.maximum.reduceat(score, starts)
    pick = np.flatnonzero(score == np.repeat(top, counts))
    return top, pick[np.searchsorted(pick, starts)]


def locate_in_tets(mesh: TetMesh, points_mm, *, nearest: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(element (n,) int, its barycentric coordinates (n, 4)) of each point (n, 3) [mm] among the straight
    tetrahedra through the mesh's corners: the element whose smallest barycentric coordinate is largest
    (>= 0: the point is inside it; < 0: the point is outside every element, and this is the one it is least
    outside of). Candidates: the elements with the ``nearest`` nearest centroids, and for a point inside none
    of them, every element whose centroid is within the largest centroid-corner distance (the first in
    index order among equals). :func:`containing_tets` gives the containing element alone, faster."""
    P = np.asarray(points_mm, float).reshape(-1, 3)
    frames = _tet_frames(mesh)
    corners, cen, _ = frames
    tree, elem, out = _locate_nearest(frames, P, nearest)
    todo = np.flatnonzero(out.min(axis=1) < 0.0)
    if len(todo):
        reach = float(np.max(np.linalg.norm(corners - cen[:, None], axis=2)))
        cand = tree.query_ball_point(P[todo], reach)
        counts = np.fromiter((len(c) for c in cand), int, len(todo))
        has = counts > 0
        flat = np.fromiter((i for c in cand for i in c), np.int64, counts.sum())
        lam_c = _barycentric(frames, np.repeat(P[todo], counts, axis=0), flat)
        top, first = _first_top(lam_c.min(axis=1), counts[has])
        better = top > out[todo[has]].min(axis=1)
        at = todo[has][better]
        elem[at], out[at] = flat[first[better]], lam_c[first[better]]
    return elem, out


def containing_tets(
    mesh: TetMesh, points_mm, *, tol: float = 1e-9, nearest: int = 8
) -> np.ndarray:
    """The element of :func:`locate_in_tets` for each point (n, 3) [mm] where its smallest barycentric
    coordinate is >= ``-tol`` (the point is inside it), -1 elsewhere (n,) int; the same answer, without
    searching every element near a point that no element holds.

    An element where a point's barycentric coordinates are all >= ``-tol`` holds it in its copy scaled by
    ``1 + 4 tol`` about its centroid, so the point is within ``(1 + 4 tol)`` times the element's largest
    centroid-corner distance of its centroid. The points that the ``nearest`` candidates do not hold are
    searched for from the elements, each within that distance of its own centroid (a point outside the limb
    is near a few elements or none, where :func:`locate_in_tets` weighs every element within the largest
    such distance of all).
    """
    P = np.asarray(points_mm, float).reshape(-1, 3)
    frames = _tet_frames(mesh)
    corners, cen, _ = frames
    _, elem, out = _locate_nearest(frames, P, nearest)
    score = out.min(axis=1)
    found = np.where(score >= -tol, elem, -1)
    todo = np.flatnonzero(score < 0.0)
    if not len(todo):
        return found
    radius = np.linalg.norm(corners - cen[:, None], axis=2).max(axis=1)
    # (1 nm more, so that rounding cannot leave out an element that holds a point)
    near = cKDTree(P[todo]).query_ball_point(cen, radius * (1.0 + 4.0 * tol) + 1e-6)
    counts = np.fromiter((len(c) for c in near), int, len(near))
    el = np.repeat(np.arange(len(near)), counts)
    row = np.fromiter((i for c in near for i in c), np.int64, counts.sum())
    # the candidates of locate_in_tets: every element whose centroid is within the largest such distance
    keep = np.linalg.norm(P[todo[row]] - cen[el], axis=1) <= float(np.max(radius))
    order = np.lexsort((el[keep], row[keep]))
    el, row = el[keep][order], row[keep][order]
    if not len(row):
        return found
    lam = _barycentric(frames, P[todo[row]], el)
    points, counts = np.unique(row, return_counts=True)
    top, first = _first_top(lam.min(axis=1), counts)
    better = (top >= -tol) & (top > score[todo[points]])
    found[todo[points[better]]] = el[first[better]]
    return found


def extract_tetmesh(gmsh_module=None, *, order: int = 2) -> TetMesh:
    """Read the current gmsh model into a :class:`TetMesh` of ``order`` 2 (meshed with ``setOrder(2)``:
    10-node tets, 6-node facets) or 1 (first-order mesh: 4-node tets, 3-node facets).

    Boundary facet sets are the 2D physical groups, by name; only tetrahedra of 3D physical groups
    are kept (all of them if there is no 3D physical group). Nodes are renumbered 0..n-1 and unused
    nodes dropped.
    """
    if order not in TET_NODES:
        raise ValueError(f"extract_tetmesh: order must be 1 or 2, got {order}")
    if gmsh_module is None:
        import gmsh as gmsh_module
    g = gmsh_module
    tet_type, tri_type = (GMSH_TET10, GMSH_TRI6) if order == 2 else (GMSH_TET4, GMSH_TRI3)
    nt, nf = TET_NODES[order], FACET_NODES[order]
    tags, coords, _ = g.model.mesh.getNodes()
    coords = np.asarray(coords, float).reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags] = np.arange(len(tags))

    vol_groups = g.model.getPhysicalGroups(3)
    vol_entities = (
        [e for _, t in vol_groups for e in g.model.getEntitiesForPhysicalGroup(3, t)]
        if vol_groups
        else [t for _, t in g.model.getEntities(3)]
    )
    tet_chunks = []
    for ent in vol_entities:
        _, nodes = g.model.mesh.getElementsByType(tet_type, ent)
        tet_chunks.append(np.asarray(nodes, dtype=np.int64).reshape(-1, nt))
    if not tet_chunks or sum(len(c) for c in tet_chunks) == 0:
        how = "generate(3) and setOrder(2)" if order == 2 else "generate(3) (first order)"
        raise ValueError(f"gmsh model has no {nt}-node tetrahedra: mesh with {how}")
    tets = index[np.concatenate(tet_chunks)]

    facets = {}
    for dim, tag in g.model.getPhysicalGroups(2):
        name = g.model.getPhysicalName(dim, tag) or f"surface_{tag}"
        chunks = []
        for ent in g.model.getEntitiesForPhysicalGroup(dim, tag):
            _, nodes = g.model.mesh.getElementsByType(tri_type, ent)
            chunks.append(np.asarray(nodes, dtype=np.int64).reshape(-1, nf))
        facets[name] = index[np.concatenate(chunks)] if chunks else np.zeros((0, nf), np.int64)

    used = np.unique(np.concatenate([tets.ravel(), *[f.ravel() for f in facets.values()]]))
    renum = np.full(len(coords), -1, dtype=np.int64)
    renum[used] = np.arange(len(used))
    return TetMesh(
        nodes_mm=coords[used], tets=renum[tets], facets={k: renum[v] for k, v in facets.items()}
    )


def extract_tet10(gmsh_module=None) -> TetMesh:
    """Read the current gmsh model (meshed with ``setOrder(2)``) into a quadratic :class:`TetMesh`
    (:func:`extract_tetmesh` with ``order=2``)."""
    return extract_tetmesh(gmsh_module, order=2)


def save_tetmesh(path: str | Path, mesh: TetMesh) -> None:
    save_npz(
        path,
        nodes_mm=mesh.nodes_mm,
        tets=mesh.tets,
        **{f"facets__{k}": v for k, v in mesh.facets.items()},
    )


def load_tetmesh(path: str | Path) -> TetMesh:
    try:
        with np.load(path) as d:
            nodes, tets = d["nodes_mm"], d["tets"]
            facets = {k[len("facets__") :]: d[k] for k in d.files if k.startswith("facets__")}
    except (KeyError, OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a tet mesh file ({exc})") from exc
    try:
        return TetMesh(
            nodes_mm=nodes.astype(float),
            tets=tets.astype(np.int64),
            facets={k: v.astype(np.int64) for k, v in facets.items()},
        )
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


# =========================================================================== limb meshing (model stage)
# The functions below build the limb solid in gmsh (OpenCASCADE), mesh it with quadratic tetrahedra,
# curve the boundary mid-edge nodes onto the geometry, check quality, and tag patches.

GMSH_LINE3 = 8
_ALGORITHMS_3D = {"delaunay": 1, "hxt": 10}


@dataclass(frozen=True)
class SizeField:
    """A background size for gmsh: corner nodes (n, 3) [mm], linear tetrahedra (m, 4) and node sizes (n,) [mm]."""

    nodes_mm: np.ndarray
    tets: np.ndarray
    size_mm: np.ndarray

    @classmethod
    def from_mesh(cls, mesh: TetMesh, node_size_mm) -> SizeField:
        """The field of ``mesh``'s corner nodes and sizes (the mid-edge nodes are dropped)."""
        corners = np.unique(mesh.tets[:, :4])
        index = np.full(len(mesh.nodes_mm), -1)
        index[corners] = np.arange(len(corners))
        return cls(
            mesh.nodes_mm[corners],
            index[mesh.tets[:, :4]],
            np.asarray(node_size_mm, float)[corners],
        )

    @property
    def h_min_mm(self) -> float:
        """The smallest size of the field [mm]."""
        return float(np.min(self.size_mm))


def set_background_size(gmsh, sizes: SizeField, *, method: str = "view") -> None:
    """Make ``sizes`` the background size field of the current gmsh model (call before generating).

    ``method='view'`` (default): a post-processing view of the linear tetrahedra and their node sizes
    (list data ``SS``) used through a ``PostView`` field: gmsh interpolates the sizes linearly and
    finds the tetrahedron holding a point with its own octree; a point of a curved face just outside
    the old mesh's flat facets still gets the size there. ``method='callback'``: the nearest node's
    size, looked up by a k-d tree from ``gmsh.model.mesh.setSizeCallback`` (piecewise constant).
    On the cylinder the view meshes in 0.15 s where the callback takes 0.21 s, and makes the same
    sizes in the refined regions with a quarter fewer elements (its sizes blend linearly instead of
    jumping at the midpoint between nodes). Either way the mesher's ``Mesh.MeshSizeMin`` and
    ``Mesh.MeshSizeMax`` still clip the size.
    """
    h = np.asarray(sizes.size_mm, float)
    if method == "callback":
        tree = cKDTree(sizes.nodes_mm)
        gmsh.model.mesh.setSizeCallback(
            lambda dim, tag, x, y, z, lc: float(min(lc, h[tree.query((x, y, z))[1]]))
        )
        return
    if method != "view":
        raise ValueError(f"method {method!r}: expected 'view' or 'callback'")
    X = sizes.nodes_mm[sizes.tets]  # (m, 4, 3)
    data = np.concatenate([X[:, :, 0], X[:, :, 1], X[:, :, 2], h[sizes.tets]], axis=1)
    view = gmsh.view.add("adapt_size")
    gmsh.view.addListData(view, "SS", len(sizes.tets), data.ravel().tolist())
    fv = gmsh.model.mesh.field.add("PostView")
    gmsh.model.mesh.field.setNumber(fv, "ViewTag", view)
    gmsh.model.mesh.field.setAsBackgroundMesh(fv)


class MeshQualityError(ValueError):
    """The mesh has inverted or degenerate elements; the message names the animal."""


class MeshSizeError(ValueError):
    """The mesh asked for would have more elements than fit in memory; nothing was meshed."""


@dataclass(frozen=True)
class RefineSegment:
    """A segment of indenter travel around which the mesh is refined (world mm)."""

    start_mm: np.ndarray  # (3,)
    end_mm: np.ndarray  # (3,)


@dataclass(frozen=True)
class PatchSpec:
    """A contact patch: skin facets whose centroid projected along ``axis`` lies within ``radius_mm``
    of the footprint (axis line, or the bar strip of half length ``half_length_mm`` along ``long_dir``)
    and whose outward normal faces the indenter."""

    point_mm: np.ndarray  # (3,) a point on the axis (final tip)
    axis: np.ndarray  # (3,) unit, from the indenter into the leg
    radius_mm: float
    half_length_mm: float = 0.0
    long_dir: np.ndarray | None = None


def _occ_loft(occ, rings: np.ndarray, n_spline: int, ruled: bool = False) -> int:
    """Solid through closed splines of every ring (n_slices, n_points, 3); returns the volume tag.

    ``ruled``: straight rulings between consecutive rings (one face per slice gap); else one smooth
    OpenCASCADE surface through all rings (which can bulge between noisy slices)."""
    step = max(1, int(np.ceil(rings.shape[1] / n_spline)))
    wires = []
    for r in rings:
        pts = [occ.addPoint(*q) for q in r[::step]]
        curve = occ.addSpline(pts + [pts[0]])
        wires.append(occ.addWire([curve]))
    out = occ.addThruSections(wires, makeSolid=True, makeRuled=ruled)
    vols = [t for d, t in out if d == 3]
    if len(vols) != 1:
        raise RuntimeError(f"loft gave {len(vols)} volumes")
    return vols[0]


def sample_lofted_surface(
    rings: np.ndarray, *, spline_points: int = 100, n_cols: int | None = None, dz_mm: float = 0.25
) -> tuple[np.ndarray, np.ndarray]:
    """Sample the lateral surface of the loft through a contour stack, exactly as :func:`mesh_limb` builds it.

    rings (n_slices, n_points, 3) CCW contours -> grid points (n_rows, n_cols, 3) and unit outward
    normals (n_rows, n_cols, 3): rows run from the first to the last contour (about ``dz_mm`` apart in
    parameter, first and last rows being the end contours), columns counter-clockwise seen from +z.
    Used for the cast, so that the cast is offset from the very surface the mesh lies on.
    """
    import gmsh

    rings = np.asarray(rings, float)
    n_cols = int(n_cols or max(rings.shape[1], 100))
    length = float(rings[-1, :, 2].mean() - rings[0, :, 2].mean())
    n_rows = max(2, int(np.ceil(length / dz_mm)) + 1)
    own_init = not gmsh.isInitialized()
    if own_init:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("loft_sample")
        vol = _occ_loft(gmsh.model.occ, rings, spline_points)
        gmsh.model.occ.synchronize()
        lateral = [
            t
            for _, t in gmsh.model.getBoundary([(3, vol)], oriented=False)
            if (lambda b: b[5] - b[2])(gmsh.model.getBoundingBox(2, t)) > 1e-6
        ]
        if len(lateral) != 1:
            raise RuntimeError(f"loft has {len(lateral)} lateral faces (expected 1)")
        face = lateral[0]
        lo, hi = (np.asarray(b, float) for b in gmsh.model.getParametrizationBounds(2, face))
        # which parameter runs along the leg? the one that changes z
        probe = np.asarray(
            gmsh.model.getValue(2, face, [lo[0], lo[1], lo[0], hi[1], hi[0], lo[1]]), float
        ).reshape(3, 3)
        along_v = abs(probe[1, 2] - probe[0, 2]) > abs(probe[2, 2] - probe[0, 2])
        a = (
            lo[0] + (hi[0] - lo[0]) * np.arange(n_cols) / n_cols
        )  # around (periodic: last column != first)
        b = np.linspace(lo[1], hi[1], n_rows)  # along
        if not along_v:
            a = lo[1] + (hi[1] - lo[1]) * np.arange(n_cols) / n_cols
            b = np.linspace(lo[0], hi[0], n_rows)
        A, B = np.meshgrid(a, b)  # (n_rows, n_cols)
        uv = np.stack([A, B], -1) if along_v else np.stack([B, A], -1)
        flat = uv.reshape(-1, 2).ravel()
        pts = np.asarray(gmsh.model.getValue(2, face, flat), float).reshape(n_rows, n_cols, 3)
        nrm = np.asarray(gmsh.model.getNormal(face, flat), float).reshape(n_rows, n_cols, 3)
    finally:
        if own_init:
            gmsh.finalize()
        else:
            gmsh.model.remove()
    if pts[-1, :, 2].mean() < pts[0, :, 2].mean():
        pts, nrm = pts[::-1], nrm[::-1]
    if polygon_area_mm2(pts[0]) < 0:
        pts, nrm = pts[:, ::-1], nrm[:, ::-1]
    # outward: away from each row's centroid
    out = np.einsum(
        "rck,rck->", nrm[..., :2], pts[..., :2] - pts[..., :2].mean(axis=1, keepdims=True)
    )
    if out < 0:
        nrm = -nrm
    # start each row at the same place as the contours (nearest sample to the contour's first point)
    j0 = int(np.argmin(np.linalg.norm(pts[0] - rings[0, 0], axis=1)))
    pts, nrm = np.roll(pts, -j0, axis=1), np.roll(nrm, -j0, axis=1)
    return pts, nrm / np.linalg.norm(nrm, axis=2, keepdims=True)


def _occ_limb(occ, skin: np.ndarray, bone: np.ndarray, n_spline: int, ruled: bool) -> int:
    """The limb solid: lofted skin and tibia faces closed by the two annular end faces and sewn into
    one volume (much faster than lofting two solids and cutting one from the other). Returns its tag."""

    def wires(rings):
        step = max(1, int(np.ceil(rings.shape[1] / n_spline)))
        ws, cs = [], []
        for r in rings:
            pts = [occ.addPoint(*q) for q in r[::step]]
            cu = occ.addSpline(pts + [pts[0]])
            cs.append(cu)
            ws.append(occ.addWire([cu]))
        return ws, cs

    ws, cs = wires(np.asarray(skin, float))
    wb, cb = wires(np.asarray(bone, float))
    faces = [t for _, t in occ.addThruSections(ws, makeSolid=False, makeRuled=ruled)]
    faces += [t for _, t in occ.addThruSections(wb, makeSolid=False, makeRuled=ruled)]
    for i in (0, -1):
        faces.append(occ.addPlaneSurface([occ.addCurveLoop([cs[i]]), occ.addCurveLoop([cb[i]])]))
    return occ.addVolume([occ.addSurfaceLoop(faces, sewing=True)])


def _midpoint_params(pa: np.ndarray, pb: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Parametric midpoints (m, k) of edges with end params pa, pb, wrapping across a periodic seam."""
    span = hi - lo
    d = pb - pa
    wrap = np.abs(d) > 0.5 * span
    pb = np.where(wrap & (d > 0), pb - span, np.where(wrap & (d < 0), pb + span, pb))
    m = 0.5 * (pa + pb)
    return np.where(m < lo, m + span, np.where(m > hi, m - span, m))


def _corner_params(g, entities_dim_tag) -> dict:
    """Parametric coordinates of the (first-order) mesh nodes of each entity, boundary included:
    {(dim, tag): (coordinates (n, 3), params (n, dim))}. Call before ``setOrder(2)`` (which renumbers
    nodes, hence the match by coordinates afterwards)."""
    out = {}
    for dim, tag in entities_dim_tag:
        ntags, xyz, npar = g.model.mesh.getNodes(
            dim, tag, includeBoundary=True, returnParametricCoord=True
        )
        if len(npar) == len(ntags) * dim:
            out[(dim, tag)] = (
                np.asarray(xyz, float).reshape(-1, 3),
                np.asarray(npar, float).reshape(-1, dim),
            )
    return out


def _curve_mid_nodes(
    g, entities_dim_tag, corner_params: dict, max_shift_ratio: float = 0.3
) -> tuple[dict, int]:
    """New positions of mid-edge nodes on curves and surfaces, evaluated on the geometry at the
    parametric midpoint of the edge (fast: no projection). Returns {node tag: (xyz, param)} and the
    number of edges left straight because the evaluated point moved implausibly far."""
    moved = {}
    n_straight = 0
    for dim, tag in entities_dim_tag:
        etype, k_pairs = (
            (GMSH_LINE3, [(0, 1, 2)])
            if dim == 1
            else (GMSH_TRI6, [(0, 1, 3), (1, 2, 4), (2, 0, 5)])
        )
        _, enodes = g.model.mesh.getElementsByType(etype, tag)
        if len(enodes) == 0:
            continue
        enodes = np.asarray(enodes, np.int64).reshape(-1, 3 if dim == 1 else 6)
        if (dim, tag) not in corner_params:
            continue
        xyz, par = corner_params[(dim, tag)]
        ntags, ncoord, _ = g.model.mesh.getNodes(dim, tag, includeBoundary=True)
        ncoord = np.asarray(ncoord, float).reshape(-1, 3)
        dist, idx = cKDTree(xyz).query(ncoord)
        pos = {int(t): int(i) for t, i, d in zip(ntags, idx, dist) if d < 1e-9}
        if not all(int(row[i]) in pos for row in enodes for i in range(3 if dim == 2 else 2)):
            continue  # a corner without parametric coordinates: leave this entity straight
        own, _, _ = g.model.mesh.getNodes(dim, tag, includeBoundary=False)
        own = set(np.asarray(own, np.int64).tolist())
        lo, hi = (np.asarray(b, float) for b in g.model.getParametrizationBounds(dim, tag))
        a_idx, b_idx, m_tags = [], [], []
        for ia, ib, im in k_pairs:
            for row in enodes:
                if row[im] in own and row[im] not in moved:
                    a_idx.append(pos[int(row[ia])])
                    b_idx.append(pos[int(row[ib])])
                    m_tags.append(row[im])
        if not m_tags:
            continue
        m_tags, first = np.unique(np.array(m_tags), return_index=True)
        a_idx, b_idx = np.array(a_idx)[first], np.array(b_idx)[first]
        pm = _midpoint_params(par[a_idx], par[b_idx], lo, hi)
        straight = 0.5 * (xyz[a_idx] + xyz[b_idx])
        # project the straight midpoint onto the entity: Gauss-Newton from the parametric midpoint
        # (gmsh's reparametrisation of boundary nodes can be off on faces whose edges have their own
        # parametrisation, e.g. ruled strips; the projection does not depend on it)
        for _ in range(6):
            x = np.asarray(g.model.getValue(dim, tag, pm.ravel()), float).reshape(-1, 3)
            J = np.asarray(g.model.getDerivative(dim, tag, pm.ravel()), float).reshape(
                -1, dim, 3
            )  # (m, dim, 3)
            JtJ = np.einsum("mik,mjk->mij", J, J)
            rhs = np.einsum("mik,mk->mi", J, straight - x)
            try:
                step = np.linalg.solve(JtJ + 1e-12 * np.eye(dim), rhs[..., None])[..., 0]
            except np.linalg.LinAlgError:
                break
            pm = pm + step
            if (
                dim == 2
            ):  # the along-leg parameter stays inside the face; the periodic one may wrap
                pm = np.where(np.isfinite(pm), pm, 0.0)
            if np.max(np.abs(step)) < 1e-10:
                break
        x = np.asarray(g.model.getValue(dim, tag, pm.ravel()), float).reshape(-1, 3)
        edge = np.linalg.norm(xyz[a_idx] - xyz[b_idx], axis=1)
        ok = np.linalg.norm(x - straight, axis=1) <= max_shift_ratio * edge
        n_straight += int(np.count_nonzero(~ok))
        for t, xi, pi, o in zip(m_tags, x, pm, ok):
            if o:
                moved[int(t)] = (xi, pi)
    return moved, n_straight


def _tet_dihedral_deg(p: np.ndarray) -> np.ndarray:
    """Dihedral angles (n, 6) [deg] of straight tetrahedra with corners p (n, 4, 3)."""
    faces = [
        (1, 2, 3),
        (0, 3, 2),
        (0, 1, 3),
        (0, 2, 1),
    ]  # face opposite corner i, outward for positive tets
    n = []
    for a, b, c in faces:
        v = np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a])
        n.append(v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300))
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    cosang = np.stack([-np.einsum("ij,ij->i", n[i], n[j]) for i, j in pairs], axis=1)
    return np.degrees(np.arccos(np.clip(cosang, -1, 1)))


def tet_scaled_jacobian(p: np.ndarray) -> np.ndarray:
    """Scaled Jacobian (n,) of straight tetrahedra with corners p (n, 4, 3): the smallest over the four
    corners of det(e1, e2, e3) / (|e1| |e2| |e3|), times sqrt(2) so the regular tet scores 1; <= 0 means
    inverted or flat (the Verdict library's definition)."""
    worst = np.full(len(p), np.inf)
    for i in range(4):
        # the three edges leaving corner i, ordered to keep the orientation of (1, 2, 3) from 0
        j, k, l = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)][i]
        e = p[:, [j, k, l]] - p[:, [i]]
        det = np.linalg.det(e)
        worst = np.minimum(worst, det / np.prod(np.linalg.norm(e, axis=2), axis=1))
    return np.sqrt(2.0) * worst


def tet10_min_det_jacobian(mesh: TetMesh) -> np.ndarray:
    """Smallest Jacobian determinant (n_tets,) [mm^3] of each 10-node tet, sampled at its 10 nodes,
    its centroid and its 4 face centroids (an independent check of gmsh's quality measure).
    A linear (4-node) mesh: det J / 6 is constant, the corner volume."""
    if mesh.order == 1:
        return mesh.volumes_mm3()
    ref = np.array(
        [
            [0, 0, 0],
            [1, 0, 0],
            [0, 1, 0],
            [0, 0, 1],
            [0.5, 0, 0],
            [0.5, 0.5, 0],
            [0, 0.5, 0],
            [0, 0, 0.5],
            [0, 0.5, 0.5],
            [0.5, 0, 0.5],
            [0.25, 0.25, 0.25],
            [1 / 3, 1 / 3, 0],
            [1 / 3, 0, 1 / 3],
            [0, 1 / 3, 1 / 3],
            [1 / 3, 1 / 3, 1 / 3],
        ]
    )

    x = mesh.nodes_mm[mesh.tets]  # (n, 10, 3)
    J = np.einsum("nic,pij->npcj", x, tet10_shape_gradients(ref))
    return np.min(np.linalg.det(J), axis=1) / 6.0


#: gmsh's mean tetrahedron volume over the cube of its size field [mm³ / mm³] (a regular tetrahedron of edge h
#: has 0.118 h³; gmsh's are larger on average), the factor of :func:`estimated_tets`
GMSH_TET_VOLUME = 0.21
#: the most degrees of freedom a mesh of :func:`mesh_limb` may have: a direct solve of 450 000 needs about
#: 24 GB (6.9 GB at 175 000 measured by the adaptive loop, memory growing as DOFs^(4/3) with the fill of a 3D
#: factorisation)
MAX_DOFS = 450_000
#: DOFs per tetrahedron of each element order: 3 per node, nodes per tetrahedron of gmsh's meshes of the
#: synthetic leg (tests/model_synth.py at 1.6 / 0.8 mm: 14 322 nodes of 8 698 quadratic tets, 2 118 of linear)
DOFS_PER_TET = {1: 0.73, 2: 4.9}
#: the spacing of the points :func:`estimated_limb_tets` samples the limb at [mm]
_ESTIMATE_SPACING_MM = 0.5


@dataclass(frozen=True)
class MeshSpec:
    """What :func:`mesh_limb` makes of a limb: sizes, refinement, contact patches, loft, order and quality gate.

    element_size_mm: element size away from the indenter [mm]; refine_size_mm, refine_radius_mm,
    refine_transition_mm: the size within ``refine_radius_mm`` of each of ``refine_segments``
    (:class:`RefineSegment`), growing back to ``element_size_mm`` over ``refine_transition_mm`` [mm];
    size_field: a background size (:class:`SizeField`: a previous mesh's nodes and the sizes its solution asks
    for, :func:`deeptissue.adapt.adapt`) in place of that refinement, capped at ``element_size_mm``;
    patches: name -> :class:`PatchSpec`, each the facet set of its skin facets, their union the set
    ``patch_union`` (none if None); spline_points: at most this many points of each contour in its closed
    spline; loft: "ruled" (straight between slices, the surface whose volume is the prismatoid sum) or
    "smooth" (one surface through all rings); curved: second order only, the boundary mid-edge nodes on the
    geometry, straightened again in any element whose Jacobian ratio would fall below ``min_curved_ratio``;
    min_scaled_jacobian, min_dihedral_deg [deg], min_curved_ratio: the quality gate's limits (corner-tet
    scaled Jacobian, dihedral angle, gmsh's curved-element Jacobian ratio); algorithm_3d: gmsh's 3-D
    algorithm, "hxt" (fast) or "delaunay"; order: 2 (10-node tets, 6-node facets) or 1 (4-node tets, 3-node
    facets) on the same geometry and size field.
    """

    element_size_mm: float = 1.0
    refine_size_mm: float = 0.5
    refine_radius_mm: float = 4.0
    refine_transition_mm: float = 2.0
    refine_segments: tuple = ()
    size_field: SizeField | None = None
    patches: dict | None = None
    patch_union: str | None = "patch"
    spline_points: int = 100
    loft: str = "ruled"
    curved: bool = True
    min_scaled_jacobian: float = 0.05
    min_dihedral_deg: float = 2.0
    min_curved_ratio: float = 0.2
    algorithm_3d: str = "hxt"
    order: int = 2

    def size_at(self, points_mm: np.ndarray) -> np.ndarray:
        """The size field [mm] at points (n, 3) [mm], as gmsh is given it (:func:`_mesh_size_field`): the
        background size (its nearest node's) or the refinement ramp, capped at ``element_size_mm``."""
        h = float(self.element_size_mm)
        if self.size_field is not None:
            near = cKDTree(self.size_field.nodes_mm).query(points_mm)[1]
            return np.minimum(np.asarray(self.size_field.size_mm, float)[near], h)
        hr = min(float(self.refine_size_mm), h)
        if not self.refine_segments or hr >= h:
            return np.full(len(points_mm), h)
        d = np.min([_segment_distance(points_mm, sg) for sg in self.refine_segments], axis=0)
        ramp = np.clip((d - self.refine_radius_mm) / self.refine_transition_mm, 0.0, 1.0)
        return hr + (h - hr) * ramp


def _segment_distance(points_mm: np.ndarray, seg: RefineSegment) -> np.ndarray:
    """Distance of points (n, 3) from a segment [mm]."""
    a, b = np.asarray(seg.start_mm, float), np.asarray(seg.end_mm, float)
    ab = b - a
    t = np.clip((points_mm - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(points_mm - (a + t[:, None] * ab), axis=1)


def estimated_tets(volume_mm3, h_mm) -> float:
    """Number of tetrahedra gmsh makes of regions of volume ``volume_mm3`` (n,) [mm³] meshed at sizes
    ``h_mm`` (n,) [mm]: the sum of each volume over gmsh's mean tetrahedron volume :data:`GMSH_TET_VOLUME` h³."""
    return float(
        np.sum(np.asarray(volume_mm3, float) / (GMSH_TET_VOLUME * np.asarray(h_mm, float) ** 3))
    )


def estimated_limb_tets(skin: np.ndarray, bone: np.ndarray, spec: MeshSpec) -> float:
    """The number of tetrahedra gmsh makes of the limb between two contour stacks at ``spec``'s sizes.

    The limb is sampled on a grid of :data:`_ESTIMATE_SPACING_MM` (coarser for a large limb: at most about a
    million points) through the ruled loft (straight between corresponding points of neighbouring slices),
    and each point's cell, inside the skin and outside the bone, counts with its size
    (:meth:`MeshSpec.size_at`) in :func:`estimated_tets`. Milliseconds to a second, before any meshing.
    """
    skin, bone = np.asarray(skin, float), np.asarray(bone, float)
    lo, hi = skin.reshape(-1, 3).min(axis=0), skin.reshape(-1, 3).max(axis=0)
    step = max(_ESTIMATE_SPACING_MM, float(np.prod(hi - lo) / 1e6) ** (1 / 3))
    xs, ys = np.arange(lo[0], hi[0], step) + step / 2, np.arange(lo[1], hi[1], step) + step / 2
    grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    points, volumes = [], []
    for k in range(len(skin) - 1):
        z0, z1 = skin[k, :, 2].mean(), skin[k + 1, :, 2].mean()
        n = max(1, int(round(abs(z1 - z0) / step)))
        for t in (np.arange(n) + 0.5) / n:
            s = (1 - t) * skin[k] + t * skin[k + 1]
            b = (1 - t) * bone[k] + t * bone[k + 1]
            keep = inside_polygon(grid, s) & ~inside_polygon(grid, b)
            z = np.full((int(keep.sum()), 1), (1 - t) * z0 + t * z1)
            points.append(np.hstack([grid[keep], z]))
            volumes.append(np.full(len(z), step * step * abs(z1 - z0) / n))
    points, volumes = np.vstack(points), np.concatenate(volumes)
    return estimated_tets(volumes, spec.size_at(points))


def mesh_limb(
    skin: np.ndarray,
    bone: np.ndarray,
    spec: MeshSpec = MeshSpec(),
    *,
    animal: str = "?",
    msh_path=None,
) -> tuple[TetMesh, dict]:
    """Quadratic (default) or linear tetrahedral mesh of the limb between a skin and a bone contour stack.

    The steps: the size check (:func:`estimated_limb_tets`, in DOFs against :data:`MAX_DOFS`), the limb solid
    (:func:`_occ_limb`) and its face groups (:func:`_boundary_groups`), the size field
    (:func:`_mesh_size_field`), meshing and curving of the boundary mid-edge nodes
    (:func:`_generate_and_curve`), the contact patches (:func:`_tag_patches`), extraction
    (:func:`extract_tetmesh`) and the quality gate (:func:`_quality_gate`).

    Parameters
    ----------
    skin, bone : (n_slices, n_points, 3) array
        Contour stacks [world mm] (checked by :func:`deeptissue.geometry.check_contours`). Skin and
        tibia are lofted (OpenCASCADE ``addThruSections`` through closed splines of at most
        ``spec.spline_points`` points per contour) and closed into the limb by the two annular end faces,
        the planes of the first (``distal``, lowest z) and last (``proximal``) slice.
    spec : MeshSpec
        Sizes, refinement, patches, loft, element order and the quality gate's limits.
    animal : str
        Named in every error message.
    msh_path : path, optional
        Where to write the gmsh ``.msh`` (physical groups, patches included).

    Returns
    -------
    mesh : TetMesh
        Facet sets ``bone``, ``skin``, ``proximal``, ``distal``, the patches and their union.
    stats : dict
        Element count (and the estimate made before meshing), quality, volumes [mm^3], timings [s].

    Raises
    ------
    MeshQualityError
        If an element is inverted or degenerate (a Jacobian determinant <= 0 anywhere sampled in a
        curved element, or a value below one of the gate's limits), a patch is empty, or gmsh fails.
    MeshSizeError
        If the estimated DOFs exceed :data:`MAX_DOFS` (nothing is meshed).
    ValueError
        For an unknown ``loft``, ``order`` or ``algorithm_3d``.
    """
    import gmsh

    t_start = time.perf_counter()
    _check_spec(spec, animal)
    estimate = estimated_limb_tets(skin, bone, spec)
    if estimate * DOFS_PER_TET[spec.order] > MAX_DOFS:
        raise MeshSizeError(
            f"animal {animal}: the mesh would have about {estimate:.3g} tetrahedra and "
            f"{estimate * DOFS_PER_TET[spec.order]:.3g} DOFs (element_size_mm {spec.element_size_mm:g}, "
            f"refine_size_mm {spec.refine_size_mm:g}), more than the {MAX_DOFS} DOFs whose solve fits in "
            "memory (deeptissue.mesh.MAX_DOFS); raise model.element_size_mm or model.refine_size_mm"
        )
    log.info(
        "animal %s: meshing about %.0f tetrahedra (estimated; the limit is %d DOFs)",
        animal,
        estimate,
        MAX_DOFS,
    )
    stats: dict = {"element_order": int(spec.order), "estimated_tets": estimate}
    own_init = not gmsh.isInitialized()
    if own_init:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(f"limb_{animal}")
        occ = gmsh.model.occ
        vol = _occ_limb(occ, skin, bone, spec.spline_points, ruled=spec.loft == "ruled")
        occ.synchronize()
        if len(gmsh.model.getEntities(3)) != 1 or occ.getMass(3, vol) <= 0:
            raise MeshQualityError(f"animal {animal}: the lofted limb is not one closed volume")
        stats["occ_volume_mm3"] = float(occ.getMass(3, vol))
        stats["occ_s"] = time.perf_counter() - t_start
        groups = _boundary_groups(gmsh, vol, skin, bone, animal=animal)
        _mesh_size_field(gmsh, spec)
        curved = bool(spec.curved) and spec.order == 2
        q = _generate_and_curve(
            gmsh,
            vol,
            groups,
            order=spec.order,
            curved=curved,
            min_curved_ratio=spec.min_curved_ratio,
            stats=stats,
        )
        if spec.patches:
            _tag_patches(
                gmsh,
                groups,
                bone,
                spec.patches,
                patch_union=spec.patch_union,
                order=spec.order,
                animal=animal,
            )
        mesh = extract_tetmesh(gmsh, order=spec.order)
        if msh_path is not None:
            with atomic_path(msh_path) as tmp:
                gmsh.write(str(tmp))
    except (MeshQualityError, ValueError):
        raise
    except Exception as exc:  # OpenCASCADE / gmsh failures come as bare Exceptions
        raise MeshQualityError(
            f"animal {animal}: gmsh could not build or mesh the limb: {exc}"
        ) from exc
    finally:
        if own_init:
            gmsh.finalize()
        else:
            gmsh.model.remove()
    _quality_gate(mesh, q, spec, animal=animal, stats=stats, t_start=t_start)
    return mesh, stats


def _check_spec(spec: MeshSpec, animal: str) -> None:
    """Refuse an unknown loft, element order or 3-D algorithm, naming the animal."""
    if spec.loft not in ("ruled", "smooth"):
        raise ValueError(f"animal {animal}: loft {spec.loft!r}: expected 'ruled' or 'smooth'")
    if spec.order not in TET_NODES:
        raise ValueError(
            f"animal {animal}: element order {spec.order!r}: expected 1 (4-node) or 2 (10-node tetrahedra)"
        )
    if spec.algorithm_3d not in _ALGORITHMS_3D:
        raise ValueError(
            f"animal {animal}: algorithm_3d {spec.algorithm_3d!r}: expected one of {sorted(_ALGORITHMS_3D)}"
        )


def _boundary_groups(g, vol: int, skin: np.ndarray, bone: np.ndarray, *, animal: str) -> dict:
    """Sort the boundary faces of the limb volume into physical groups.

    Flat faces are the ends (``distal`` nearer the first slice, ``proximal`` the last); a curved face is
    ``skin`` or ``bone`` by which contour stack is closer to its parametric centre. Adds the volume
    group ``limb`` and the four face groups to the gmsh model.

    Returns
    -------
    dict
        Face tags of each group {"skin", "bone", "distal", "proximal"}.
    """
    z_lo, z_hi = float(np.mean(skin[0, :, 2])), float(np.mean(skin[-1, :, 2]))
    groups = {"skin": [], "bone": [], "distal": [], "proximal": []}
    skin_pts = np.asarray(skin, float).reshape(-1, 3)
    bone_pts = np.asarray(bone, float).reshape(-1, 3)
    for _, s in g.model.getBoundary([(3, vol)], oriented=False):
        bb = g.model.getBoundingBox(2, s)
        if bb[5] - bb[2] < 1e-6:
            groups["distal" if abs(bb[2] - z_lo) < abs(bb[2] - z_hi) else "proximal"].append(s)
            continue
        lo, hi = g.model.getParametrizationBounds(2, s)
        x = np.asarray(g.model.getValue(2, s, 0.5 * (np.asarray(lo) + np.asarray(hi))))
        ds = np.min(np.linalg.norm(skin_pts - x, axis=1))
        db = np.min(np.linalg.norm(bone_pts - x, axis=1))
        groups["skin" if ds < db else "bone"].append(s)
    for name, ents in groups.items():
        if not ents:
            raise MeshQualityError(f"animal {animal}: the limb solid has no {name} surface")
    g.model.addPhysicalGroup(3, [vol], name="limb")
    for name, ents in groups.items():
        g.model.addPhysicalGroup(2, ents, name=name)
    return groups


def _mesh_size_field(g, spec: MeshSpec) -> None:
    """Set the meshing options and the size field: ``element_size_mm`` everywhere, ``refine_size_mm``
    within ``refine_radius_mm`` of each refine segment, a linear ramp back over ``refine_transition_mm``;
    or, with ``size_field`` (:class:`deeptissue.mesh.SizeField`), that background size instead."""
    h, hr = float(spec.element_size_mm), float(min(spec.refine_size_mm, spec.element_size_mm))
    g.option.setNumber("Mesh.MeshSizeMax", h)
    g.option.setNumber("Mesh.MeshSizeMin", hr * 0.5)
    g.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    g.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    g.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    g.option.setNumber("Mesh.Algorithm", 6)
    g.option.setNumber("Mesh.Algorithm3D", _ALGORITHMS_3D[spec.algorithm_3d])
    g.option.setNumber("General.NumThreads", 1)
    g.option.setNumber("Mesh.OptimizeNetgen", 1)
    g.option.setNumber("Mesh.ElementOrder", 1)
    g.option.setNumber("Mesh.SecondOrderLinear", 1)
    if spec.size_field is not None:
        g.option.setNumber("Mesh.MeshSizeMin", 0.5 * min(spec.size_field.h_min_mm, h))
        set_background_size(g, spec.size_field)
    elif spec.refine_segments and hr < h:
        # distance to points every refine_size/4 along each segment (free geometry points, not meshed
        # into the limb), then a linear ramp from refine_size to element_size
        occ = g.model.occ
        pts = []
        for seg in spec.refine_segments:
            a, b = np.asarray(seg.start_mm, float), np.asarray(seg.end_mm, float)
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / (0.25 * hr))) + 1)
            pts += [occ.addPoint(*(a + t * (b - a))) for t in np.linspace(0, 1, n)]
        occ.synchronize()
        fd = g.model.mesh.field.add("Distance")
        g.model.mesh.field.setNumbers(fd, "PointsList", pts)
        ft = g.model.mesh.field.add("Threshold")
        g.model.mesh.field.setNumber(ft, "InField", fd)
        g.model.mesh.field.setNumber(ft, "SizeMin", hr)
        g.model.mesh.field.setNumber(ft, "SizeMax", h)
        g.model.mesh.field.setNumber(ft, "DistMin", spec.refine_radius_mm)
        g.model.mesh.field.setNumber(
            ft, "DistMax", spec.refine_radius_mm + spec.refine_transition_mm
        )
        g.model.mesh.field.setAsBackgroundMesh(ft)


def _generate_and_curve(
    g, vol: int, groups: dict, *, order: int, curved: bool, min_curved_ratio: float, stats: dict
) -> np.ndarray:
    """Mesh the volume (first order, then ``order``) and, if ``curved``, move the boundary mid-edge
    nodes onto the geometry, straightening them again in elements whose Jacobian ratio (minSJ) falls
    below ``min_curved_ratio`` (at most five rounds). Records timings and node counts in ``stats``.

    Returns
    -------
    (n_tets,) array
        gmsh's curved-element Jacobian ratio of each tetrahedron (1 for first-order tets).
    """
    tet_type = GMSH_TET10 if order == 2 else GMSH_TET4
    t0 = time.perf_counter()
    g.model.mesh.generate(3)
    stats["generate_s"] = time.perf_counter() - t0
    ents = sorted(set((1, t) for d, t in g.model.getEntities(1))) + [
        (2, s) for e2 in groups.values() for s in e2
    ]
    corner_params = _corner_params(g, ents) if curved else {}
    if order == 2:
        g.model.mesh.setOrder(2)
    stats["order2_s"] = time.perf_counter() - t0 - stats["generate_s"]
    t0 = time.perf_counter()

    tet_tags, tet_nodes = g.model.mesh.getElementsByType(tet_type, vol)
    tet_nodes = np.asarray(tet_nodes, np.int64).reshape(-1, TET_NODES[order])
    n_curved = n_straightened = 0
    if curved:
        moved, n_bad = _curve_mid_nodes(g, ents, corner_params)
        straight = {}
        for t in moved:
            x, _, _, _ = g.model.mesh.getNode(t)
            straight[t] = np.asarray(x, float)
        for t, (x, p) in moved.items():
            g.model.mesh.setNode(t, list(x), list(p))
        n_curved = len(moved)
        stats["mid_nodes_left_straight_implausible"] = n_bad
        # straighten where curving spoils an element
        for _ in range(5):
            q = np.asarray(g.model.mesh.getElementQualities(tet_tags, "minSJ"), float)
            bad = q < min_curved_ratio
            if not bad.any():
                break
            fix = [
                t
                for t in np.unique(tet_nodes[bad][:, 4:])
                if int(t) in straight and int(t) in moved
            ]
            if not fix:
                break
            for t in fix:
                g.model.mesh.setNode(int(t), list(straight[int(t)]), [])
                moved.pop(int(t))
            n_straightened += len(fix)
    stats["mid_nodes_curved"] = n_curved - n_straightened
    stats["mid_nodes_straightened_for_quality"] = n_straightened
    q = (
        np.asarray(g.model.mesh.getElementQualities(tet_tags, "minSJ"), float)
        if order == 2
        else np.ones(len(tet_tags))
    )
    stats["curve_s"] = time.perf_counter() - t0
    return q


def _tag_patches(
    g,
    groups: dict,
    bone: np.ndarray,
    patches: dict,
    *,
    patch_union: str | None,
    order: int,
    animal: str,
) -> None:
    """Add each contact patch (name -> :class:`PatchSpec`), and their union as ``patch_union``, as a
    discrete surface holding copies of the selected skin triangles, with a physical group of its name.

    Skin normals are turned to point away from the bone's axis (interpolated along z); a patch
    without a facet raises :class:`MeshQualityError`.
    """
    tri_type, n_fn = (GMSH_TRI6, 6) if order == 2 else (GMSH_TRI3, 3)
    sk_nodes = []
    for s in groups["skin"]:
        _, en_ = g.model.mesh.getElementsByType(tri_type, s)
        sk_nodes.append(np.asarray(en_, np.int64).reshape(-1, n_fn))
    sk_nodes = np.concatenate(sk_nodes)
    ntags, ncoord, _ = g.model.mesh.getNodes()
    coords = np.zeros((int(np.max(ntags)) + 1, 3))
    coords[np.asarray(ntags, np.int64)] = np.asarray(ncoord, float).reshape(-1, 3)
    p = coords[sk_nodes[:, :3]]
    cen = p.mean(axis=1)
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    # make the normals point out of the limb: skin faces are outward if they point away from the bone axis
    bone_c = np.asarray(bone, float).mean(axis=1)
    zc = cen[:, 2]
    bc = np.stack(
        [np.interp(zc, bone_c[:, 2], bone_c[:, 0]), np.interp(zc, bone_c[:, 2], bone_c[:, 1])],
        axis=1,
    )
    outward = np.einsum("ij,ij->i", nrm[:, :2], cen[:, :2] - bc)
    if np.median(np.sign(outward)) < 0:
        nrm = -nrm
    next_el = int(g.model.mesh.getMaxElementTag()) + 1
    sels = {}
    for name, spec in patches.items():
        sels[name] = select_patch(
            cen,
            nrm,
            point_mm=spec.point_mm,
            axis=spec.axis,
            radius_mm=spec.radius_mm,
            half_length_mm=spec.half_length_mm,
            long_dir=spec.long_dir,
        )
        if not sels[name].any():
            raise MeshQualityError(
                f"animal {animal}: patch {name!r} is empty: no skin facet within {spec.radius_mm} mm of the axis faces the indenter"
            )
    if patch_union and patch_union not in sels:
        sels[patch_union] = np.any(list(sels.values()), axis=0)
    for name, sel in sels.items():
        ent = g.model.addDiscreteEntity(2)
        tags = np.arange(next_el, next_el + int(sel.sum()))
        next_el += len(tags)
        g.model.mesh.addElementsByType(
            ent, tri_type, tags.tolist(), sk_nodes[sel].ravel().tolist()
        )
        g.model.addPhysicalGroup(2, [ent], name=name)


def _quality_gate(
    mesh: TetMesh, q: np.ndarray, spec: MeshSpec, *, animal: str, stats: dict, t_start: float
) -> None:
    """Check the extracted mesh with numpy (independently of gmsh) and record its quality in ``stats``.

    Raises :class:`MeshQualityError` naming every violated limit of ``spec``: a Jacobian determinant <= 0
    in a (curved) element, a corner-tet scaled Jacobian below ``min_scaled_jacobian``, a dihedral angle
    below ``min_dihedral_deg``, or a gmsh Jacobian ratio ``q`` below ``min_curved_ratio``.
    """
    min_scaled_jacobian, min_dihedral_deg = spec.min_scaled_jacobian, spec.min_dihedral_deg
    min_curved_ratio, algorithm_3d = spec.min_curved_ratio, spec.algorithm_3d
    corners = mesh.nodes_mm[mesh.tets[:, :4]]
    dih = _tet_dihedral_deg(corners)
    sj = tet_scaled_jacobian(corners)
    detj = tet10_min_det_jacobian(mesh)
    stats.update(
        n_tets=int(mesh.n_tets),
        n_nodes=int(len(mesh.nodes_mm)),
        min_scaled_jacobian=float(sj.min()),
        scaled_jacobian_p01=float(np.percentile(sj, 1)),
        min_dihedral_deg=float(dih.min()),
        max_dihedral_deg=float(dih.max()),
        min_curved_ratio=float(q.min()),
        min_det_jacobian_mm3=float(detj.min()),
        mesh_volume_mm3=float(tet10_volume_mm3(mesh)),
        facet_counts={k: int(len(v)) for k, v in mesh.facets.items()},
        algorithm_3d=algorithm_3d,
        wall_s=time.perf_counter() - t_start,
    )
    problems = []
    if detj.min() <= 0:
        problems.append(
            f"{int(np.sum(detj <= 0))} inverted element(s) (min det J {detj.min():.3g} mm^3)"
        )
    if sj.min() < min_scaled_jacobian:
        problems.append(
            f"{int(np.sum(sj < min_scaled_jacobian))} element(s) with scaled Jacobian below {min_scaled_jacobian} (min {sj.min():.3g})"
        )
    if dih.min() < min_dihedral_deg:
        problems.append(
            f"{int(np.sum(dih.min(axis=1) < min_dihedral_deg))} degenerate element(s) with a dihedral angle below {min_dihedral_deg} deg (min {dih.min():.3g})"
        )
    if q.min() < min_curved_ratio:
        problems.append(
            f"{int(np.sum(q < min_curved_ratio))} curved element(s) with a Jacobian ratio below {min_curved_ratio} (min {q.min():.3g})"
        )
    if problems:
        raise MeshQualityError(f"animal {animal}: mesh refused: " + "; ".join(problems))


def tet10_volume_mm3(mesh: TetMesh) -> float:
    """Volume of a quadratic tet mesh [mm^3], exact for curved 10-node tets: the Jacobian determinant
    is a cubic polynomial, integrated exactly by the degree-3 Keast rule (5 points). A linear
    (4-node) mesh: the sum of the corner volumes."""
    if mesh.order == 1:
        return float(mesh.volumes_mm3().sum())
    # degree-3 exact rule on the reference tet (Keast, 5 points, one negative weight)
    pts = np.array(
        [
            [0.25, 0.25, 0.25],
            [1 / 6, 1 / 6, 1 / 6],
            [0.5, 1 / 6, 1 / 6],
            [1 / 6, 0.5, 1 / 6],
            [1 / 6, 1 / 6, 0.5],
        ]
    )
    w = np.array([-4 / 5, 9 / 20, 9 / 20, 9 / 20, 9 / 20]) / 6.0

    x = mesh.nodes_mm[mesh.tets]
    return float(
        np.einsum(
            "np,p->", np.linalg.det(np.einsum("nic,pij->npcj", x, tet10_shape_gradients(pts))), w
        )
    )
