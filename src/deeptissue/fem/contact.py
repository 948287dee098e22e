"""Frictionless penalty / augmented-Lagrangian contact at the quadrature points of quadratic facets.

The slave side is a set of 6-node skin triangles (TetMesh facets, gmsh Triangle6 order), or of
3-node triangles with linear shape functions for a first-order mesh; the master
is rigid and given by a gap function ``gap(x) -> (g, n, H)``: signed distance g [mm] (negative =
penetration), outward unit normal n = grad g and its gradient H = grad n [1/mm] (None if flat).

Per quadrature point (a material point of the skin) with multiplier lam [MPa] and penalty eps
[N/mm^3], the pressure is p = ramp(lam - eps g) (max(0, .) with its kink rounded over a tiny band)
and the potential ``Pi_c = sum_q dA0 (psi(lam - eps g) - psi(lam)) / eps`` with psi' = ramp
(integrated over the reference area). Its gradient is the contact force ``-sum_q dA0 p n N_a`` and
its Hessian the consistent tangent ``sum_q dA0 N_a N_b (eps ramp' n n^T - p H)`` (symmetric). The multipliers are updated
lam <- p between Newton solves until the penetration is below a fraction of the facet size.

Optionally (``barrier``) a penetration barrier is added at each point: with the distance to a limit
surface s = g + limit (limit > 0: the deepest penetration the solver ever accepts) and
s_hat = limit - onset, the IPC-type potential b(s) = -kappa (s - s_hat)^2 ln(s / s_hat) for
0 < s < s_hat (zero for penetrations below onset; C2 and convex), continued below s = 0.01 s_hat by its
second-order Taylor polynomial so that every state keeps a finite energy (an increment's predictor may
start beyond the limit). Its pressure -b'(s) adds to p and its stiffness b''(s) (about kappa s_hat^2 /
s^2 near the limit) to the normal tangent. A finite penalty lets pinched tissue lower its energy by
pushing through a curved indenter (the bar tilted 30 deg of the hard cases, docs/verification.md); the
barrier makes that way out cost more the deeper it goes, and is zero in the states the multiplier
updates deliver (penetration below penetration_tol < onset).
"""

from __future__ import annotations

import numpy as np
from skfem.quadrature import get_quadrature
from skfem.refdom import RefTri


def tri6_shape(xi: np.ndarray, eta: np.ndarray):
    """Shape functions N (Q, 6) and derivatives dN (Q, 6, 2) of gmsh's Triangle6 at (xi, eta)."""
    l0 = 1.0 - xi - eta
    N = np.stack([l0 * (2 * l0 - 1), xi * (2 * xi - 1), eta * (2 * eta - 1), 4 * l0 * xi, 4 * xi * eta, 4 * eta * l0], -1)
    dxi = np.stack([-(4 * l0 - 1), 4 * xi - 1, 0 * xi, 4 * (l0 - xi), 4 * eta, -4 * eta], -1)
    deta = np.stack([-(4 * l0 - 1), 0 * xi, 4 * eta - 1, -4 * xi, 4 * xi, 4 * (l0 - eta)], -1)
    return N, np.stack([dxi, deta], -1)


def tri3_shape(xi: np.ndarray, eta: np.ndarray):
    """Shape functions N (Q, 3) and derivatives dN (Q, 3, 2) of the linear 3-node triangle at (xi, eta)."""
    N = np.stack([1.0 - xi - eta, xi, eta], -1)
    dxi = np.stack([-np.ones_like(xi), np.ones_like(xi), np.zeros_like(xi)], -1)
    deta = np.stack([-np.ones_like(xi), np.zeros_like(xi), np.ones_like(xi)], -1)
    return N, np.stack([dxi, deta], -1)


def _ramp(z, delta):
    """p = max(0, z) rounded over |z| < delta (C1), its derivative and its integral psi (psi' = p)."""
    z = np.asarray(z, float)
    delta = np.broadcast_to(np.asarray(delta, float), z.shape) if np.ndim(delta) else np.full(z.shape, float(delta))
    if not np.any(delta > 0):
        p = np.maximum(z, 0.0)
        return p, (z > 0).astype(float), 0.5 * p * p
    d = np.maximum(delta, 1e-300)
    band = np.abs(z) < d
    hi = z >= d
    zb = z + d
    p = np.where(hi, z, np.where(band, zb * zb / (4 * d), 0.0))
    dp = np.where(hi, 1.0, np.where(band, zb / (2 * d), 0.0))
    psi = np.where(hi, 0.5 * z * z + d * d / 6.0, np.where(band, zb**3 / (12 * d), 0.0))
    return p, dp, psi


def _barrier(s, s_hat, kappa, s_min_rel=0.01):
    """b(s) = -kappa (s - s_hat)^2 ln(s / s_hat) for s < s_hat (0 beyond), continued below
    s_min = s_min_rel s_hat by its second-order Taylor polynomial; returns b, db/ds, d2b/ds2."""
    s = np.asarray(s, float)
    sh = np.broadcast_to(s_hat, s.shape)
    k = np.broadcast_to(kappa, s.shape)
    x = np.clip(s, s_min_rel * sh, sh)
    r, lg = x - sh, np.log(x / sh)
    b = -k * r * r * lg
    b1 = -k * (2 * r * lg + r * r / x)
    b2 = -k * (2 * lg + 4 * r / x - r * r / (x * x))
    ds = np.minimum(s - x, 0.0)  # < 0 only below s_min (0 beyond s_hat, where b is 0: no inf * 0 for a gap of inf)
    b, b1 = b + b1 * ds + 0.5 * b2 * ds * ds, b1 + b2 * ds
    on = s < sh
    return np.where(on, b, 0.0), np.where(on, b1, 0.0), np.where(on, b2, 0.0)


class ContactSurface:
    """Quadrature on a set of quadratic skin facets (the contact slave side), or linear ones.

    nodes_mm (n_nodes, 3), facets6 (K, 6) TetMesh node indices (or (K, 3) 3-node facets of a
    first-order mesh: then N (Q, 3), dofs (K, 9) and the matrices below are 9 x 9). Attributes: N (Q, 6), dofs (K, 18),
    X (K, Q, 3) reference quadrature points [mm], dA0 (K, Q) reference area weights [mm^2],
    h_mm (K,) facet size sqrt(2 * area) [mm], lam (K, Q) multipliers [MPa].
    """

    def __init__(self, nodes_mm: np.ndarray, facets6: np.ndarray, *, order: int = 4):
        facets6 = np.asarray(facets6, dtype=np.int64)
        if len(facets6) == 0:
            raise ValueError("contact surface: empty facet set")
        if facets6.ndim != 2 or facets6.shape[1] not in (3, 6):
            raise ValueError(f"contact surface: facets must be (K, 6) or (K, 3), got {facets6.shape}")
        q, w = get_quadrature(RefTri, order)
        self.N, dN = (tri6_shape if facets6.shape[1] == 6 else tri3_shape)(q[0], q[1])
        Xf = nodes_mm[facets6]  # (K, 6, 3)
        a1 = np.einsum("qa,kai->kqi", dN[..., 0], Xf)
        a2 = np.einsum("qa,kai->kqi", dN[..., 1], Xf)
        self.dA0 = np.linalg.norm(np.cross(a1, a2), axis=-1) * w
        self.X = np.einsum("qa,kai->kqi", self.N, Xf)
        self.facets6 = facets6
        self.dofs = (3 * facets6[:, :, None] + np.arange(3)).reshape(len(facets6), 3 * facets6.shape[1])
        self.h_mm = np.sqrt(2.0 * self.dA0.sum(axis=1))
        self.lam = np.zeros_like(self.dA0)
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
        g = gapfn(x.reshape(-1, 3))[0]
        return g.reshape(x.shape[:2])

    def evaluate(self, u: np.ndarray, gapfn, eps: np.ndarray, idx: np.ndarray, *, tangent: bool = True,
                 smoothing_mm: float = 0.0, near_mm: float = 0.0, barrier=None):
        """Contact potential, force and tangent of candidate facets idx.

        eps (K,) penalty per facet [N/mm^3]; smoothing_mm: the kink of p = max(0, z), z = lam - eps g,
        is rounded to a C1 ramp over |z| < eps * smoothing_mm (a penetration-equivalent width), which
        keeps Newton from cycling when points enter and leave contact; near_mm: points closer than
        this (not yet in contact) get the penalty stiffness in the tangent too, so a Newton step does
        not drive them deep into the master (a stabilised, not exactly consistent tangent: only the
        search direction changes, the potential and force stay exact); barrier: None or (onset_mm, limit_mm,
        kappa) per candidate facet (K', 1) [mm, mm, N/mm^3], the penetration barrier of the module
        docstring (pressure and tangent include it). Returns dict: energy [mJ], force (n_dofs,) [N] (internal
        force contribution), traction_sum (3,) [N] (force applied by the master on the skin),
        pressure (K', Q) [MPa], gap (K', Q) [mm], and if tangent: Kf (K', 18, 18) [N/mm] (normal part,
        positive semi-definite), Kf_geo (K', 18, 18) (curvature part -p grad n, absent for flat masters;
        the consistent tangent is Kf + Kf_geo), dofs (K', 18).
        """
        n_dofs = u.size
        nd = self.dofs.shape[1]  # 18 (6-node facets) or 9 (3-node)
        x = self.positions(u, idx)
        K, Q = x.shape[:2]
        g, nrm, H = gapfn(x.reshape(-1, 3))
        g = g.reshape(K, Q)
        nrm = nrm.reshape(K, Q, 3)
        lam = self.lam[idx]
        e = eps[idx][:, None]
        z = lam - e * g
        p, dp, psi = _ramp(z, e * smoothing_mm)
        psi0 = _ramp(lam, e * smoothing_mm)[2]
        dA = self.dA0[idx]
        energy = float(np.sum(dA * (psi - psi0) / e))
        k_b = 0.0
        if barrier is not None:
            onset_mm, limit_mm, kappa = barrier
            b, b1, k_b = _barrier(g + limit_mm, limit_mm - onset_mm, kappa)
            energy += float(np.sum(dA * b))
            p = p - b1
        t = (dA * p)[..., None] * nrm  # (K, Q, 3) force on the skin
        fe = -np.einsum("qa,kqi->kai", self.N, t).reshape(K, nd)
        force = np.bincount(self.dofs[idx].ravel(), weights=fe.ravel(), minlength=n_dofs)
        out = dict(energy=energy, force=force, traction_sum=t.sum(axis=(0, 1)), pressure=p, gap=g)
        if tangent:
            if near_mm is not None and np.any(np.asarray(near_mm) > 0):
                dp = np.maximum(dp, (g < near_mm).astype(float))
            kq = (dA * (e * dp + k_b))[..., None, None] * nrm[..., :, None] * nrm[..., None, :]
            out["Kf"] = np.einsum("qa,qb,kqij->kaibj", self.N, self.N, kq).reshape(K, nd, nd)
            if H is not None:
                kg = -(dA * p)[..., None, None] * H.reshape(K, Q, 3, 3)
                out["Kf_geo"] = np.einsum("qa,qb,kqij->kaibj", self.N, self.N, kg).reshape(K, nd, nd)
            out["dofs"] = self.dofs[idx]
        return out
