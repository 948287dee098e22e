"""TetMesh (gmsh order) -> scikit-fem ``MeshTet2`` (``MeshTet1`` for a linear mesh) with named facet sets.

scikit-fem numbers the P2 nodes as all vertices first, then one node per edge in its own edge
numbering; its local edge order in a tet is (0,1), (1,2), (0,2), (0,3), (1,3), (2,3) while gmsh's
Tetrahedron10 lists (0,3), (2,3), (1,3) last, i.e. local nodes 8 and 9 are swapped. Instead of
relying on the local order, every skfem edge is matched to the gmsh mid-node of the same vertex
pair, so curved geometry keeps its mid-nodes exactly. A first-order TetMesh (4-node tets) becomes
a ``MeshTet1`` on its corner nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skfem import MeshTet1, MeshTet2

from ..elements import GMSH_TET10_EDGES
from ..mesh import TetMesh, edge_midpoints

__all__ = [
    "GMSH_TO_SKFEM_TET10",
    "SkMesh",
    "jacobian_points",
    "reference_jacobians",
    "straighten_invalid",
    "to_skfem",
]

# gmsh -> skfem local node permutation of a 10-node tet (swap 8 and 9)
GMSH_TO_SKFEM_TET10 = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])


@dataclass(frozen=True)
class SkMesh:
    """A TetMesh as a scikit-fem mesh.

    mesh: skfem MeshTet2 (vertices = TetMesh corner nodes, edge nodes = TetMesh mid-nodes), or
    MeshTet1 for a first-order TetMesh.
    tetmesh_node: (n_skfem_nodes,) TetMesh node index of each skfem P2 node (vertices, then edges;
    vertices only for MeshTet1).
    vertex_of_node: (n_tetmesh_nodes,) skfem vertex index of each TetMesh node (-1 for mid-nodes).
    facets: name -> (K,) skfem facet indices, in the row order of TetMesh.facets[name].
    """

    mesh: MeshTet2 | MeshTet1
    tetmesh_node: np.ndarray
    vertex_of_node: np.ndarray
    facets: dict

    @property
    def order(self) -> int:
        """Element order: 2 for MeshTet2, 1 for MeshTet1."""
        return 2 if isinstance(self.mesh, MeshTet2) else 1  # (MeshTet2 is a subclass of MeshTet1)

    def element_nodes(self) -> np.ndarray:
        """(n_tets, 10) TetMesh node indices in skfem's local P2 order ((n_tets, 4) corners for P1)."""
        if self.order == 1:
            return self.tetmesh_node[self.mesh.t.T]
        return self.tetmesh_node[self.mesh.dofs.element_dofs.T]


def _pair_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    return lo.astype(np.int64) * n + hi


def to_skfem(tm: TetMesh) -> SkMesh:
    """Convert a :class:`deeptissue.mesh.TetMesh` to a :class:`SkMesh` (MeshTet2 + facet sets).

    Raises ValueError if a facet of a named set is not a face of the tetrahedra, or if the
    mid-node of an edge is inconsistent between neighbouring tets.
    """
    n_nodes = len(tm.nodes_mm)
    corners = np.unique(tm.tets[:, :4])
    vert = np.full(n_nodes, -1, dtype=np.int64)
    vert[corners] = np.arange(len(corners))
    t = vert[tm.tets[:, :4]].T
    m1 = MeshTet1(tm.nodes_mm[corners].T.copy(), np.ascontiguousarray(t))
    if tm.order == 1:
        return SkMesh(
            mesh=m1,
            tetmesh_node=corners,
            vertex_of_node=vert,
            facets=_facet_sets(tm, m1, vert, len(corners)),
        )
    m2 = MeshTet2.from_mesh(m1)

    # gmsh mid-node of every (vertex pair)
    ev = np.array(GMSH_TET10_EDGES)
    va, vb = vert[tm.tets[:, ev[:, 0]]].ravel(), vert[tm.tets[:, ev[:, 1]]].ravel()
    mids = tm.tets[:, 4:].ravel()
    keys = _pair_keys(va, vb, len(corners))
    order = np.argsort(keys, kind="stable")
    ks, ms = keys[order], mids[order]
    dup = ks[1:] == ks[:-1]
    if np.any(ms[1:][dup] != ms[:-1][dup]):
        raise ValueError("TetMesh: an edge has different mid-nodes in neighbouring tetrahedra")
    edges = m2.edges  # (2, n_edges) skfem vertex indices
    ekeys = _pair_keys(edges[0], edges[1], len(corners))
    pos = np.searchsorted(ks, ekeys)
    if np.any(pos >= len(ks)) or np.any(ks[np.minimum(pos, len(ks) - 1)] != ekeys):
        raise ValueError("TetMesh: a skfem edge has no gmsh mid-node")
    edge_mid = ms[pos]

    tetmesh_node = np.concatenate([corners, edge_mid])
    doflocs = tm.nodes_mm[tetmesh_node].T.copy()
    # skfem P2 dof numbering: vertices then edges (checked against element_dofs)
    ed = m2.dofs.element_dofs
    if not (np.array_equal(ed[:4], m2.t) and np.array_equal(ed[4:], m2.t2e + m2.nvertices)):
        raise AssertionError("unexpected skfem P2 dof numbering")
    mesh = MeshTet2(doflocs, m2.t.copy())
    return SkMesh(
        mesh=mesh,
        tetmesh_node=tetmesh_node,
        vertex_of_node=vert,
        facets=_facet_sets(tm, mesh, vert, len(corners)),
    )


def _facet_sets(tm: TetMesh, mesh, vert: np.ndarray, nv: int) -> dict:
    """name -> (K,) skfem facet indices of each TetMesh facet set (matched by corner triples)."""
    facets = {}
    fkeys_sk = np.sort(mesh.facets, axis=0).astype(np.int64)
    fk = (fkeys_sk[0] * nv + fkeys_sk[1]) * nv + fkeys_sk[2]
    forder = np.argsort(fk)
    fks = fk[forder]
    for name, f6 in tm.facets.items():
        if len(f6) == 0:
            facets[name] = np.zeros(0, dtype=np.int64)
            continue
        v = np.sort(vert[f6[:, :3]], axis=1)
        if np.any(v < 0):
            raise ValueError(f"TetMesh.facets[{name!r}]: a facet corner is not a tet corner")
        k = (v[:, 0] * nv + v[:, 1]) * nv + v[:, 2]
        p = np.searchsorted(fks, k)
        ok = (p < len(fks)) & (fks[np.minimum(p, len(fks) - 1)] == k)
        if not np.all(ok):
            raise ValueError(
                f"TetMesh.facets[{name!r}]: {np.count_nonzero(~ok)} facets are not faces of the tetrahedra"
            )
        facets[name] = forder[p]
    return facets


def jacobian_points(order: int, *, corners: bool = True) -> np.ndarray:
    """Reference points (n, 3) where a tet must keep a positive Jacobian: the points of the quadrature rule of
    ``order`` (the solver's) and, if ``corners``, the 4 corners."""
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    xi = get_quadrature(RefTet, order)[0].T
    return np.concatenate([xi, np.eye(3), np.zeros((1, 3))]) if corners else xi


def reference_jacobians(
    tm: TetMesh, *, order: int = 4, skmesh: SkMesh | None = None, corners: bool = True
) -> np.ndarray:
    """det(dX/dxi) (n_tets, n_points) of the (curved) P2 geometry (straight P1 geometry for order 1) at the points of a quadrature
    rule of ``order`` (and at the 4 corners if ``corners``): must be > 0 where the solver integrates."""
    sk = skmesh if skmesh is not None else to_skfem(tm)
    return sk.mesh._mapping().detDF(jacobian_points(order, corners=corners).T)


def straighten_invalid(tm: TetMesh, *, order: int = 2, max_rounds: int = 5) -> tuple[TetMesh, int]:
    """Move the mid-nodes of tets whose P2 Jacobian is <= 0 at a quadrature point (of ``order``) or
    at a corner onto their straight edges (gmsh's curved boundary elements can fold near tight
    curvature). Returns (mesh, number of tets straightened); the mesh is unchanged if none.
    A first-order mesh has nothing to straighten: it is returned as is, or ValueError if inverted."""
    if tm.order == 1:
        bad = np.any(reference_jacobians(tm, order=order) <= 0, axis=1)
        if np.any(bad):
            raise ValueError(
                f"mesh: {int(bad.sum())} linear tetrahedra are inverted or flat, e.g. tet {int(np.flatnonzero(bad)[0])}"
            )
        return tm, 0
    nodes = tm.nodes_mm.copy()
    fixed = np.zeros(len(tm.tets), bool)
    for _ in range(max_rounds):
        cur = TetMesh(nodes_mm=nodes, tets=tm.tets, facets=tm.facets)
        bad = np.any(reference_jacobians(cur, order=order) <= 0, axis=1)
        if not np.any(bad):
            return cur, int(fixed.sum())
        fixed |= bad
        m, mid = edge_midpoints(tm.tets[bad], nodes)
        nodes[m] = mid
    raise ValueError(
        f"mesh: {int(bad.sum())} tetrahedra stay inverted after straightening their edges"
    )
