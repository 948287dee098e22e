"""A solution carried from one mesh of a body to another (the start of a solve on a refined mesh).

:func:`interpolate_nodal` evaluates a nodal field of a quadratic (or linear) tetrahedral mesh at points:
each point is placed in the straight tetrahedron through an element's corners that holds it, and the
element's shape functions are evaluated at its barycentric coordinates there. Points just outside every
straight tetrahedron (on a curved boundary, between a curved facet and its chord) take the element they are
least outside of, and the field is extrapolated a little. On a curved element the straight coordinates
differ from the element's own by a fraction of the facet's sagitta: the result is a start for Newton's
method on the new mesh, not a solution.

:func:`mapped_end_state` is such a start: a converged end state's displacement carried to another mesh of
the same limb, as an :class:`deeptissue.fem.solver.EndState` that :func:`deeptissue.fem.solver.solve_turned`
solves (with the same indenter: a turn of zero) at the end of the load, in a few Newton iterations instead
of the whole path. Units: mm.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from ..mesh import TetMesh
from ..rigid import BoneMotion, apply_rigid
from ..strain import tet10_shape_functions
from .indenters import Indenter
from .skmesh import GMSH_TET_EDGES, reference_jacobians
from .solver import EndState, SolverSettings

__all__ = ["interpolate_nodal", "locate_in_tets", "mapped_end_state"]

log = logging.getLogger(__name__)

_NEAREST = 12  # element centroids tried per point


def locate_in_tets(mesh: TetMesh, points_mm) -> tuple[np.ndarray, np.ndarray]:
    """(element (n,) int, its barycentric coordinates (n, 4)) of each point (n, 3) [mm] among the straight
    tetrahedra through the mesh's corners: among the ``_NEAREST`` elements with the nearest centroids, the one
    whose smallest barycentric coordinate is largest (>= 0: the point is inside it)."""
    P = np.asarray(points_mm, float).reshape(-1, 3)
    corners = mesh.nodes_mm[mesh.tets[:, :4]]  # (m, 4, 3)
    T = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # columns: the edges from corner 0
    Tinv = np.linalg.inv(T)
    k = min(_NEAREST, mesh.n_tets)
    _, idx = cKDTree(corners.mean(axis=1)).query(P, k=k)
    idx = idx.reshape(len(P), k)
    xi = np.einsum("nkij,nkj->nki", Tinv[idx], P[:, None, :] - corners[idx, 0])  # (n, k, 3)
    lam = np.concatenate([1.0 - xi.sum(axis=2, keepdims=True), xi], axis=2)  # (n, k, 4)
    best = np.argmax(lam.min(axis=2), axis=1)
    rows = np.arange(len(P))
    return idx[rows, best], lam[rows, best]


def interpolate_nodal(mesh: TetMesh, values, points_mm) -> np.ndarray:
    """A nodal field ``values`` (n_nodes, ...) of ``mesh`` at ``points_mm`` (n, 3): (n, ...)."""
    V = np.asarray(values, float)
    if V.shape[0] != len(mesh.nodes_mm):
        raise ValueError(f"interpolate_nodal: {V.shape[0]} nodal values for a mesh of {len(mesh.nodes_mm)} nodes")
    elem, lam = locate_in_tets(mesh, points_mm)
    N = tet10_shape_functions(lam[:, 1:]) if mesh.order == 2 else lam
    return np.einsum("na,na...->n...", N, V[mesh.tets[elem]])


def _unfolded(mesh: TetMesh, u: np.ndarray, *, order: int, max_rounds: int = 3) -> tuple[np.ndarray, int]:
    """(``u`` (n_nodes, 3) with the mid-edge nodes of every quadratic tet it inverts (a Jacobian <= 0 at a
    corner or a quadrature point of ``order``) moved to the midpoints of their deformed edges, the number of
    tets still inverted). A straight-sided tet is inverted only if its corners are: where strain varies
    fast, interpolated mid-edge nodes fold small curved tets; a source state inverted at element corners
    (the solver checks its quadrature points) folds corners too."""
    if mesh.order == 1:
        bad = np.any(reference_jacobians(TetMesh(nodes_mm=mesh.nodes_mm + u, tets=mesh.tets), order=order) <= 0, axis=1)
        return u, int(bad.sum())
    u = u.copy()
    for k in range(max_rounds + 1):
        x = mesh.nodes_mm + u
        bad = np.any(reference_jacobians(TetMesh(nodes_mm=x, tets=mesh.tets), order=order) <= 0, axis=1)
        if not np.any(bad) or k == max_rounds:  # the count returned is that of the u returned
            break
        t = mesh.tets[bad]
        for j, (a, b) in enumerate(GMSH_TET_EDGES):
            u[t[:, 4 + j]] = 0.5 * (x[t[:, a]] + x[t[:, b]]) - mesh.nodes_mm[t[:, 4 + j]]
    return u, int(bad.sum())


def mapped_end_state(src: TetMesh, displacement_mm, dst: TetMesh, *, indenter: Indenter, bone_motion: BoneMotion,
                     settings: SolverSettings, bone_set: str = "bone") -> EndState | None:
    """The end state ``displacement_mm`` (n_nodes, 3) of mesh ``src`` carried to the nodes of mesh ``dst`` (the
    same body meshed again): the start of :func:`deeptissue.fem.solver.solve_turned` with ``indenter`` on
    ``dst``. The nodes of facet set ``bone_set`` are moved by ``bone_motion``, the tets the state would
    invert are unfolded (:func:`_unfolded`), and it has no contact forces (the first Newton iteration finds
    the contact set). None (with a warning) if some tets stay inverted."""
    u = interpolate_nodal(src, np.asarray(displacement_mm, float).reshape(-1, 3), dst.nodes_mm)
    if bone_set in dst.facets:  # the bone's nodes follow its rigid motion exactly, as the solver prescribes
        b = np.unique(dst.facets[bone_set])
        X = dst.nodes_mm[b]
        u[b] = apply_rigid(X, rotation_deg=bone_motion.rotation_deg, centre_mm=bone_motion.centre_mm,
                           translation_mm=bone_motion.translation_mm) - X
    u, folded = _unfolded(dst, u, order=settings.quadrature_order)
    if folded:
        log.warning("the state carried to the new mesh inverts %d tets: not used", folded)
        return None
    return EndState(displacement_mm=u.ravel(), contact={}, indenter=indenter, bone_motion=bone_motion,
                    settings=settings)
