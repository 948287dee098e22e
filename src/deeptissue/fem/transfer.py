"""A solution carried from one mesh of a body to another (the start of a solve on a refined mesh).

:func:`interpolate_nodal` evaluates a nodal field of a quadratic (or linear) tetrahedral mesh at points:
each point is placed in the straight tetrahedron through an element's corners that holds it (a point just
outside every one, beyond a curved facet's chord, takes the element it is least outside of), its reference
coordinates in that element's own curved map are found by Newton's method from the straight ones, and the
element's shape functions are evaluated there. A field linear in x (a rigid motion) is carried exactly, also
to new nodes on the old mesh's curved facets or between them and the new mesh's; with the straight
coordinates alone such a node is off by a fraction of the facet's sagitta times the field's gradient.

:func:`mapped_end_state` is the start of a solve on the new mesh: a converged end state's displacement carried to another mesh of
the same limb, as an :class:`deeptissue.fem.solver.EndState` that :func:`deeptissue.fem.solver.solve_turned`
solves (with the same indenter: a turn of zero) at the end of the load, in a few Newton iterations instead
of the whole path. Units: mm.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from ..elements import tet10_shape_functions, tet10_shape_gradients, tet_shape_gradients
from ..mesh import TetMesh, edge_midpoints, locate_in_tets
from ..rigid import BoneMotion, apply_rigid
from .indenters import Indenter
from .skmesh import jacobian_points, reference_jacobians
from .solver import EndState, SolverSettings

__all__ = ["interpolate_nodal", "mapped_end_state"]

log = logging.getLogger(__name__)

_UNTANGLE_FLOOR = 0.05  # an untangled tet keeps at least this fraction of its reference Jacobian
_UNTANGLE_STAY = (
    1e-3  # weight of the distance moved (over the patch's mean edge) against the shortfall
)
_UNTANGLE_MAX_MOVE_REL = (
    0.25  # a repair that moves a node farther (of the patch's mean edge) is not a repair
)


def interpolate_nodal(mesh: TetMesh, values, points_mm) -> np.ndarray:
    """A nodal field ``values`` (n_nodes, ...) of ``mesh`` at ``points_mm`` (n, 3): (n, ...)."""
    V = np.asarray(values, float)
    if V.shape[0] != len(mesh.nodes_mm):
        raise ValueError(
            f"interpolate_nodal: {V.shape[0]} nodal values for a mesh of {len(mesh.nodes_mm)} nodes"
        )
    P = np.asarray(points_mm, float).reshape(-1, 3)
    elem, lam = locate_in_tets(mesh, P)
    if mesh.order == 1:
        return np.einsum("na,na...->n...", lam, V[mesh.tets[elem]])
    xi = _curved_coordinates(mesh, elem, lam[:, 1:], P)
    return np.einsum("na,na...->n...", tet10_shape_functions(xi), V[mesh.tets[elem]])


def _curved_coordinates(
    mesh: TetMesh, elem: np.ndarray, xi: np.ndarray, points_mm: np.ndarray, iterations: int = 8
) -> np.ndarray:
    """The reference coordinates (n, 3) of ``points_mm`` (n, 3) in the quadratic elements ``elem`` (n,): the
    inverse of each element's own (curved) map by Newton's method, started from the straight coordinates
    ``xi`` (n, 3). A point on a curved facet then lies on that facet in the old element, and a field linear
    in x (a rigid motion) is carried exactly; with the straight coordinates it is off by a fraction of the
    facet's sagitta times the field's gradient. Points where Newton's method does not settle keep ``xi``."""
    Xe = mesh.nodes_mm[mesh.tets[elem]]  # (n, 10, 3)
    z = xi.copy()
    for _ in range(iterations):
        r = np.einsum("na,nak->nk", tet10_shape_functions(z), Xe) - points_mm
        J = np.einsum("naj,nak->nkj", tet10_shape_gradients(z), Xe)
        ok = np.abs(np.linalg.det(J)) > 1e-300
        step = np.zeros_like(z)
        step[ok] = np.linalg.solve(J[ok], r[ok][..., None])[..., 0]
        z = z - step
    r = np.linalg.norm(np.einsum("na,nak->nk", tet10_shape_functions(z), Xe) - points_mm, axis=1)
    size = np.linalg.norm(Xe[:, 1] - Xe[:, 0], axis=1)
    lam = np.column_stack([1.0 - z.sum(axis=1), z])
    good = (r < 1e-9 * size + 1e-12) & (lam.min(axis=1) > -0.5)
    return np.where(good[:, None], z, xi)


def _inverted(mesh: TetMesh, u: np.ndarray, order: int) -> np.ndarray:
    """The tets (bool (n_tets,)) that displacement ``u`` inverts: a Jacobian <= 0 at a corner or a quadrature point."""
    return np.any(
        reference_jacobians(TetMesh(nodes_mm=mesh.nodes_mm + u, tets=mesh.tets), order=order) <= 0,
        axis=1,
    )


def _unfolded(
    mesh: TetMesh, u: np.ndarray, fixed: np.ndarray, *, order: int, max_rounds: int = 3
) -> tuple[np.ndarray, int]:
    """(``u`` (n_nodes, 3) with the mid-edge nodes of every quadratic tet it inverts (a Jacobian <= 0 at a
    corner or a quadrature point of ``order``) moved to the midpoints of their deformed edges, except the
    ``fixed`` ones (bool (n_nodes,), the bone's, which the solver prescribes), the number of tets still
    inverted). Where strain varies fast, interpolated mid-edge nodes fold small curved tets; a source state
    inverted at element corners (the solver checks its quadrature points) folds corners, and a curved face
    on the bone may fold a tet pressed against it (:func:`_untangled`)."""
    if mesh.order == 1:
        return u, int(_inverted(mesh, u, order).sum())
    u = u.copy()
    for k in range(max_rounds + 1):
        x = mesh.nodes_mm + u
        bad = _inverted(mesh, u, order)
        if not np.any(bad) or k == max_rounds:  # the count returned is that of the u returned
            break
        m, mid = edge_midpoints(mesh.tets[bad], x)
        u[m] = np.where(fixed[m][..., None], u[m], mid - mesh.nodes_mm[m])
    return u, int(bad.sum())


def _untangled(
    mesh: TetMesh, u: np.ndarray, inverted: np.ndarray, fixed: np.ndarray, order: int
) -> np.ndarray | None:
    """``u`` (n_nodes, 3) with the nodes of the ``inverted`` tets (bool (n_tets,)) and of the tets that share a
    corner with them moved as little as gives every tet they belong to a Jacobian of at least
    ``_UNTANGLE_FLOOR`` of its reference one at its corners and the quadrature points of ``order`` (least
    squares on the shortfall and the distance moved, sparse Gauss-Newton trust region). ``fixed`` (bool
    (n_nodes,)): nodes that keep their displacement (the bone's, which the solver prescribes). A source state
    inverted at element corners, pinched at the bone, folds the new mesh's tets there; a few hundredths of a
    mm set them right. None if that takes moving a node by more than ``_UNTANGLE_MAX_MOVE_REL`` of the
    patch's mean edge: not a local repair."""
    X, corners = mesh.nodes_mm, mesh.tets[:, :4]
    ring = np.zeros(len(X), bool)
    ring[corners[inverted].ravel()] = True
    free = np.zeros(len(X), bool)
    free[mesh.tets[np.any(ring[corners], axis=1)].ravel()] = True
    free &= ~fixed
    ids = np.flatnonzero(free)
    T = mesh.tets[np.any(free[mesh.tets], axis=1)]
    dN = tet_shape_gradients(jacobian_points(order), mesh.order)
    x = X + u

    def jac(y, grad=True):  # Jacobians (m, q) and, if grad, their gradients (m, q, nodes, 3)
        c = np.einsum("man,qak->mqkn", y[T], dN)  # columns d x / d xi_k
        g0 = np.cross(c[:, :, 1], c[:, :, 2])  # dJ / d column 0
        J = np.einsum("mqn,mqn->mq", c[:, :, 0], g0)
        if not grad:
            return J
        g = np.stack(
            [g0, np.cross(c[:, :, 2], c[:, :, 0]), np.cross(c[:, :, 0], c[:, :, 1])], axis=2
        )
        return J, np.einsum("mqkn,qak->mqan", g, dN)

    J0 = jac(X, grad=False)
    sign, J0 = np.sign(J0), np.abs(J0)
    edge_mm = float(
        np.mean(np.linalg.norm(X[T][:, [1, 2, 3, 2, 3, 3]] - X[T][:, [0, 0, 0, 1, 1, 2]], axis=2))
    )
    slot = np.full(len(X), -1)
    slot[ids] = np.arange(len(ids))
    loc = slot[T]
    on = loc >= 0
    x0 = x[ids]

    # residuals: the shortfall of every Jacobian below the floor (over its reference one), and the distance
    # moved (over the mean edge) weighted by sqrt(_UNTANGLE_STAY); a sparse Gauss-Newton trust region
    m, q = J0.shape
    rows = np.broadcast_to(np.arange(m * q).reshape(m, q, 1, 1), (m, q, T.shape[1], 3))
    cols = np.broadcast_to(3 * loc[:, None, :, None] + np.arange(3), rows.shape)
    keep = np.broadcast_to(on[:, None, :, None], rows.shape)
    n_z = 3 * len(ids)
    stay = np.sqrt(_UNTANGLE_STAY) / edge_mm

    def residuals(z):
        y = x.copy()
        y[ids] = z.reshape(-1, 3)
        return np.concatenate(
            [
                np.maximum(_UNTANGLE_FLOOR * J0 - sign * jac(y, grad=False), 0.0).ravel()
                / J0.ravel(),
                stay * (z - x0.ravel()),
            ]
        )

    def jacobian(z):
        y = x.copy()
        y[ids] = z.reshape(-1, 3)
        J, dJ = jac(y)
        below = _UNTANGLE_FLOOR * J0 - sign * J > 0.0
        vals = (-(sign * below) / J0)[:, :, None, None] * dJ
        top = sparse.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(m * q, n_z))
        return sparse.vstack([top, stay * sparse.identity(n_z, format="csr")], format="csr")

    z = least_squares(
        residuals,
        x0.ravel(),
        jac=jacobian,
        method="trf",
        tr_solver="lsmr",
        max_nfev=50,
        x_scale=edge_mm,
    ).x
    worst_mm = float(np.linalg.norm(z.reshape(-1, 3) - x0, axis=1).max(initial=0.0))
    if worst_mm > _UNTANGLE_MAX_MOVE_REL * edge_mm:
        log.info(
            "untangling %d inverted tets would move a node %.3g mm (mean edge %.3g mm): not done",
            int(inverted.sum()),
            worst_mm,
            edge_mm,
        )
        return None
    out = u.copy()
    out[ids] = z.reshape(-1, 3) - X[ids]
    log.info(
        "untangled %d inverted tets by moving %d nodes up to %.3g mm",
        int(inverted.sum()),
        len(ids),
        worst_mm,
    )
    return out


def mapped_end_state(
    src: TetMesh,
    displacement_mm,
    dst: TetMesh,
    *,
    indenter: Indenter,
    bone_motion: BoneMotion,
    settings: SolverSettings,
    bone_set: str = "bone",
) -> EndState | None:
    """The end state ``displacement_mm`` (n_nodes, 3) of mesh ``src`` carried to the nodes of mesh ``dst`` (the
    same body meshed again): the start of :func:`deeptissue.fem.solver.solve_turned` with ``indenter`` on
    ``dst``. The nodes of facet set ``bone_set`` are moved by ``bone_motion``; the curved tets the state would
    invert are straightened (:func:`_unfolded`) and the rest untangled (:func:`_untangled`), the bone held.
    It has no contact forces (the first Newton iteration finds the contact set). None (with a warning) if
    some tets stay inverted."""
    u = interpolate_nodal(src, np.asarray(displacement_mm, float).reshape(-1, 3), dst.nodes_mm)
    fixed = np.zeros(len(dst.nodes_mm), bool)
    if (
        bone_set in dst.facets
    ):  # the bone's nodes follow its rigid motion exactly, as the solver prescribes
        b = np.unique(dst.facets[bone_set])
        X = dst.nodes_mm[b]
        u[b] = (
            apply_rigid(
                X,
                rotation_deg=bone_motion.rotation_deg,
                centre_mm=bone_motion.centre_mm,
                translation_mm=bone_motion.translation_mm,
            )
            - X
        )
        fixed[b] = True
    order = settings.quadrature_order
    counts = [int(_inverted(dst, u, order).sum())]
    u, folded = _unfolded(dst, u, fixed, order=order)
    counts.append(folded)
    if folded:
        repaired = _untangled(dst, u, _inverted(dst, u, order), fixed, order)
        if repaired is not None:
            u, folded = _unfolded(dst, repaired, fixed, order=order)
        counts.append(folded)
    log.info(
        "carried state: %s tets inverted (interpolated, mid-edge nodes straightened%s)",
        " -> ".join(map(str, counts)),
        ", untangled" if len(counts) > 2 else "",
    )
    if folded:
        log.warning("the state carried to the new mesh inverts %d tets: not used", folded)
        return None
    return EndState(
        displacement_mm=u.ravel(),
        contact={},
        indenter=indenter,
        bone_motion=bone_motion,
        settings=settings,
    )
