"""Frictionless contact of skin facets with rigid obstacles: weighted gaps, and the penetration between nodes.

Every obstacle is rigid (the analytical indenter, the rigid cast) and given by a gap function
``gap(x, hessian) -> (g, n, H)``: signed distance g [mm] (negative = penetration; for the cast a smooth surface near
its facets), outward normal n = grad g and its gradient H = grad n [1/mm] (None if flat, or not asked for:
``gap(x, hessian=False)``). The skin side is a
set of 6-node triangles (TetMesh facets, gmsh Triangle6 order), or 3-node triangles of a first-order mesh.

Contact is imposed node by node on weighted gaps (:class:`WeightedContact`): for a node j of a contact facet
set, ``gw_j = sum_q A_q psi_j(q) g(x_q) / m_j`` with ``m_j = sum_q A_q psi_j(q)``, where q runs over the
quadrature points of the facets around j (reference area weights A_q, current positions x_q) and psi_j is
j's piecewise-linear hat on the facets split into four subtriangles (positive, a partition of unity: the
mid-edge and corner nodes of a quadratic facet both get a positive weight, which the facet's own quadratic
shape functions do not give the corners); on a 3-node facet psi_j is the linear shape function. Its
multiplier lam_j [N] is the node's share of the contact force: the pressure
``p(q) = sum_j lam_j psi_j(q) / m_j`` is non-negative wherever every lam_j is, and the force on the tissue
is ``G^T lam`` with ``G = d gw / d u``. Averaging over each node's facets keeps a facet from slipping into a
curved obstacle between its nodes without closing a weighted gap (with constraints at the nodes alone, a
bar tilted 30 deg cuts ~20 % of a facet into the skin and the active set cycles at the quadratic facets'
corner nodes, whose consistent share of a pressure is near zero).

:class:`ContactSurface` measures the penetration that is left between the nodes, at the facets' quadrature
points (reported, not constrained).
"""

from __future__ import annotations

import numpy as np
from skfem.quadrature import get_quadrature
from skfem.refdom import RefTri

__all__ = ["ContactSurface", "WeightedContact", "tri3_shape", "tri6_shape"]


def tri6_shape(xi: np.ndarray, eta: np.ndarray):
    """Shape functions N (Q, 6) and derivatives dN (Q, 6, 2) of gmsh's Triangle6 at (xi, eta)."""
    l0 = 1.0 - xi - eta
    N = np.stack(
        [
            l0 * (2 * l0 - 1),
            xi * (2 * xi - 1),
            eta * (2 * eta - 1),
            4 * l0 * xi,
            4 * xi * eta,
            4 * eta * l0,
        ],
        -1,
    )
    dxi = np.stack([-(4 * l0 - 1), 4 * xi - 1, 0 * xi, 4 * (l0 - xi), 4 * eta, -4 * eta], -1)
    deta = np.stack([-(4 * l0 - 1), 0 * xi, 4 * eta - 1, -4 * xi, 4 * xi, 4 * (l0 - eta)], -1)
    return N, np.stack([dxi, deta], -1)


def tri3_shape(xi: np.ndarray, eta: np.ndarray):
    """Shape functions N (Q, 3) and derivatives dN (Q, 3, 2) of the linear 3-node triangle at (xi, eta)."""
    N = np.stack([1.0 - xi - eta, xi, eta], -1)
    dxi = np.stack([-np.ones_like(xi), np.ones_like(xi), np.zeros_like(xi)], -1)
    deta = np.stack([-np.ones_like(xi), np.zeros_like(xi), np.ones_like(xi)], -1)
    return N, np.stack([dxi, deta], -1)


# the 4-subtriangle split of the reference 6-node triangle (gmsh order: corners 0,1,2; midsides 3 (0-1), 4 (1-2), 5 (2-0))
_LOCAL = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.5, 0.0], [0.5, 0.5], [0.0, 0.5]])
_SUB = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])


def _weight_quadrature(n_nodes: int = 6):
    """Points (Q, 2) on the reference triangle, weights (Q,) (summing to its area 1/2) and the values (Q, n_nodes)
    of the weight functions psi_j: for 6-node facets the piecewise-linear hats of the 4-subtriangle split
    (positive, a partition of unity), for 3-node facets the linear shape functions; a degree-2 rule on each
    subtriangle (12 points)."""
    bary = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
    pts, w, psi = [], [], []
    for tri in _SUB:
        pts.append(bary @ _LOCAL[tri])
        w.append(np.full(3, 1 / 24))  # subtriangle area 1/8, three equal weights
        v = np.zeros((3, 6))
        v[:, tri] = bary
        psi.append(v)
    pts, w, psi = np.concatenate(pts), np.concatenate(w), np.concatenate(psi)
    if n_nodes == 3:
        psi = tri3_shape(pts[:, 0], pts[:, 1])[0]
    elif n_nodes != 6:
        raise ValueError(f"contact facets must have 3 or 6 nodes, got {n_nodes}")
    return pts, w, psi


class WeightedContact:
    """Weighted gaps of the skin nodes against the rigid obstacles, and their derivatives.

    For a node j of a contact facet set, its weighted gap is the average of the gap over the facets around it,
    weighted by the positive piecewise-linear function psi_j of the facets' 4-subtriangle split:
    ``gw_j = sum_q A_q psi_j(q) g(x_q) / m_j``, ``m_j = sum_q A_q psi_j(q)`` (A_q the reference area weight of
    quadrature point q, x_q its current position). The constraint is gw_j >= 0; its multiplier lam_j [N]
    is the node's share of the contact force, the pressure being ``p(q) = sum_j lam_j psi_j(q) / m_j`` >= 0
    wherever every lam_j >= 0. One entry per node and obstacle (a node of both facet sets has two);
    ``sets`` is a list of (obstacle name, facets (K, 6) or (K, 3) TetMesh node ids), ``excluded`` the nodes
    that get no entry (the bone's: prescribed), young_mpa scales a gap into a force (c = E h [N/mm]).
    Attributes: node, obstacle (index into names), h (the smallest facet size around the node [mm]), c,
    lam (multipliers [N]), cand (the candidate entries), gapfns (per obstacle: (x, hessian) -> (g, n, H)).
    """

    def __init__(self, X, sets, excluded, young_mpa):
        nodes, obst, h, self.names, self.sets = [], [], [], [], []
        for k, (name, facets) in enumerate(sets):
            facets = np.asarray(facets, np.int64)
            xi, w, psi = _weight_quadrature(facets.shape[1])
            N, dN = (tri6_shape if facets.shape[1] == 6 else tri3_shape)(xi[:, 0], xi[:, 1])
            Xf = X[facets]
            a1 = np.einsum("qa,kai->kqi", dN[..., 0], Xf)
            a2 = np.einsum("qa,kai->kqi", dN[..., 1], Xf)
            A = np.linalg.norm(np.cross(a1, a2), axis=-1) * w  # (F, Q) [mm^2]
            hf = np.sqrt(2.0 * A.sum(axis=1))
            nd = np.setdiff1d(np.unique(facets), excluded)
            hn = np.full(len(X), np.inf)
            np.minimum.at(hn, facets.ravel(), np.repeat(hf, facets.shape[1]))
            # local entry index of each facet node (-1: excluded node, no constraint)
            ent = np.full(len(X), -1, np.int64)
            ent[nd] = np.arange(len(nd)) + sum(len(n) for n in nodes)
            self.sets.append(
                dict(
                    facets=facets,
                    N=N,
                    psi=psi,
                    X=np.einsum("qa,kai->kqi", N, Xf),
                    A=A,
                    entry=ent[facets],
                )
            )
            nodes.append(nd)
            obst.append(np.full(len(nd), k))
            h.append(hn[nd])
            self.names.append(name)
        self.X = X
        self.node = np.concatenate(nodes) if nodes else np.zeros(0, np.int64)
        self.obstacle = np.concatenate(obst) if obst else np.zeros(0, np.int64)
        self.h = np.concatenate(h) if h else np.zeros(0)
        self.c = young_mpa * self.h
        self.lam = np.zeros(len(self.node))
        self.cand = np.ones(len(self.node), bool)
        self.gapfns = [None] * len(sets)

    def node_gaps(self, u, which=None):
        """Gaps g (E,) [mm] of the entries' nodes at u (inf outside ``which``, default the candidates)."""
        which = self.cand if which is None else which
        g = np.full(len(self.node), np.inf)
        x = self.X[self.node] + u.reshape(-1, 3)[self.node]
        for k, fn in enumerate(self.gapfns):
            sel = np.flatnonzero(which & (self.obstacle == k))
            if len(sel):
                g[sel] = fn(x[sel], hessian=False)[0]
        return g

    def facets_with(self, k, which):
        """Indices of obstacle k's facets (in the order of its facet set) with a node of the entries ``which``."""
        on = np.append(which & (self.obstacle == k), False)  # index -1 (no entry) -> False
        return np.flatnonzero(on[self.sets[k]["entry"]].any(axis=1))

    def ncp(self, lam, g):
        """min(lam, c g) per entry [N] (0 at a solution; 0 outside the candidates)."""
        return np.where(
            np.isfinite(g), np.minimum(lam, self.c * np.where(np.isfinite(g), g, 0.0)), 0.0
        )

    def weighted(self, u, which, lam=None, curvature=True):
        """Weighted gaps of the entries ``which`` at u.

        Returns gw (E,) [mm] (inf outside ``which`` and where no quadrature point around the node can touch),
        the rows of d gw / d u as COO (entry, dof, value [1]), and with ``lam`` (E,) [N] the curvature of the
        obstacles under the pressure those multipliers make: (dofs (F, 18), blocks (F, 18, 18) [N/mm]; 9 for 3-node facets) of
        ``-sum_q A_q p_q N_a N_b H_q`` (empty without ``curvature``), and the contact force on the tissue
        (n_dofs,) [N] (G^T lam).
        """
        E = len(self.node)
        m, num = np.zeros(E), np.zeros(E)
        u3 = u.reshape(-1, 3)
        parts = []
        for k, st in enumerate(self.sets):
            fsel = self.facets_with(k, which)
            if not len(fsel):
                continue
            fac, A, en, N, psi = (
                st["facets"][fsel],
                st["A"][fsel],
                st["entry"][fsel],
                st["N"],
                st["psi"],
            )
            x = st["X"][fsel] + np.einsum("qa,fai->fqi", N, u3[fac])
            F, Q = A.shape
            g, n, H = self.gapfns[k](x.reshape(-1, 3), hessian=lam is not None and curvature)
            g, n = g.reshape(F, Q), n.reshape(F, Q, 3)
            fin = np.isfinite(g)
            Aq = np.where(fin, A, 0.0)
            valid = en >= 0
            np.add.at(m, en[valid], np.einsum("fq,qj->fj", Aq, psi)[valid])
            np.add.at(
                num, en[valid], np.einsum("fq,qj->fj", Aq * np.where(fin, g, 0.0), psi)[valid]
            )
            B = np.einsum("fq,qj,qa,fqi->fjai", Aq, psi, N, np.where(fin[..., None], n, 0.0))
            Hq = None if H is None else np.where(fin[..., None, None], H.reshape(F, Q, 3, 3), 0.0)
            parts.append((fac, Aq, en, valid, B, Hq, N, psi))
        ok = which & (m > 0)
        gw = np.full(E, np.inf)
        gw[ok] = num[ok] / m[ok]
        inv_m = np.where(m > 0, 1.0 / np.where(m > 0, m, 1.0), 0.0)
        rows, cols, vals = [], [], []
        force = np.zeros(u.size) if lam is not None else None
        geo = []
        for fac, Aq, en, valid, B, Hq, N, psi in parts:
            e_safe = np.where(valid, en, 0)
            scale = np.where(valid, inv_m[e_safe], 0.0) * ok[e_safe]  # (F, 6)
            Bs = B * scale[:, :, None, None]  # d gw_j / d x_a (F, j, a, 3)
            dof = 3 * fac[:, :, None] + np.arange(3)  # (F, nodes, 3)
            keep = np.broadcast_to((valid & ok[e_safe])[:, :, None, None], Bs.shape)
            rows.append(np.broadcast_to(e_safe[:, :, None, None], Bs.shape)[keep])
            cols.append(np.broadcast_to(dof[:, None], Bs.shape)[keep])
            vals.append(Bs[keep])
            if lam is not None:
                lj = np.where(valid, lam[e_safe], 0.0) * scale  # lam_j / m_j
                np.add.at(force, dof.ravel(), np.einsum("fj,fjai->fai", lj, B).ravel())
                if curvature and Hq is not None:
                    p = np.einsum("fj,qj->fq", lj, psi)  # pressure at the points [MPa]
                    blk = -np.einsum("fq,qa,qb,fqij->faibj", Aq * p, N, N, Hq)
                    nd = dof.shape[1] * 3
                    geo.append((dof.reshape(len(fac), nd), blk.reshape(len(fac), nd, nd)))
        G = (
            np.concatenate(rows) if rows else np.zeros(0, np.int64),
            np.concatenate(cols) if cols else np.zeros(0, np.int64),
            np.concatenate(vals) if vals else np.zeros(0),
        )
        if lam is None:
            return gw, G
        return gw, G, geo, force


class ContactSurface:
    """Quadrature on a set of quadratic skin facets, or linear ones: where the penetration between the nodes
    is measured (the weighted gaps close it on average over each node's facets, not point by point).

    nodes_mm (n_nodes, 3), facets6 (K, 6) TetMesh node indices (or (K, 3) 3-node facets of a
    first-order mesh: then N (Q, 3), dofs (K, 9)). Attributes: N (Q, 6), dofs (K, 18),
    X (K, Q, 3) reference quadrature points [mm], dA0 (K, Q) reference area weights [mm^2],
    h_mm (K,) facet size sqrt(2 * area) [mm].
    """

    def __init__(self, nodes_mm: np.ndarray, facets6: np.ndarray, *, order: int = 4):
        facets6 = np.asarray(facets6, dtype=np.int64)
        if len(facets6) == 0:
            raise ValueError("contact surface: empty facet set")
        if facets6.ndim != 2 or facets6.shape[1] not in (3, 6):
            raise ValueError(
                f"contact surface: facets must be (K, 6) or (K, 3), got {facets6.shape}"
            )
        q, w = get_quadrature(RefTri, order)
        self.N, dN = (tri6_shape if facets6.shape[1] == 6 else tri3_shape)(q[0], q[1])
        Xf = nodes_mm[facets6]  # (K, 6, 3)
        a1 = np.einsum("qa,kai->kqi", dN[..., 0], Xf)
        a2 = np.einsum("qa,kai->kqi", dN[..., 1], Xf)
        self.dA0 = np.linalg.norm(np.cross(a1, a2), axis=-1) * w
        self.X = np.einsum("qa,kai->kqi", self.N, Xf)
        self.facets6 = facets6
        self.dofs = (3 * facets6[:, :, None] + np.arange(3)).reshape(
            len(facets6), 3 * facets6.shape[1]
        )
        self.h_mm = np.sqrt(2.0 * self.dA0.sum(axis=1))
        self.n_facets, self.n_qp = self.dA0.shape

    def positions(self, u: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """Current positions of the quadrature points (K', Q, 3) [mm] of facets idx (all if None)."""
        f = self.facets6 if idx is None else self.facets6[idx]
        X = self.X if idx is None else self.X[idx]
        ue = u.reshape(-1, 3)[f]
        return X + np.einsum("qa,kai->kqi", self.N, ue)

    def gaps(self, u: np.ndarray, gapfn, idx: np.ndarray | None = None) -> np.ndarray:
        """Gaps (K', Q) [mm] of facets idx."""
        x = self.positions(u, idx)
        g = gapfn(x.reshape(-1, 3), hessian=False)[0]
        return g.reshape(x.shape[:2])
