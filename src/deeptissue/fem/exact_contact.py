"""Quasi-static indentation with exact frictionless contact: weighted gaps and a semi-smooth Newton method.

Every obstacle is rigid (the analytical indenter, the rigid cast) and given by its signed distance g(x)
(outward normal n = grad g, H = grad n). Contact is a condition on the skin's quadratic facets, imposed
node by node on weighted gaps: for a node j of a contact facet set,
``gw_j = sum_q A_q psi_j(q) g(x_q) / m_j`` with ``m_j = sum_q A_q psi_j(q)``, where q runs over the
quadrature points of the facets around j (reference area weights A_q, current positions x_q) and psi_j is
j's piecewise-linear hat on the facets split into four subtriangles (positive, a partition of unity: the
mid-edge and corner nodes of a quadratic facet both get a positive weight, which the facet's own quadratic
shape functions do not give the corners). Its multiplier lam_j [N] is the node's share of the contact force:
the pressure ``p(q) = sum_j lam_j psi_j(q) / m_j`` is non-negative wherever every lam_j is, and the force
on the tissue is ``G^T lam`` with ``G = d gw / d u``. Complementarity lam_j >= 0, gw_j >= 0, lam_j gw_j = 0
is the equation ``C_j = min(lam_j, c_j gw_j) = 0`` (c_j = E h_j [N/mm] scales a gap into a force).
Equilibrium reads ``R(u, lam) = f_int(u) - G(u)^T lam = 0`` on the free dofs.

Newton's method on (R, C) with the generalised derivative of min is the primal-dual active-set method
(Hintermueller, Ito and Kunisch 2002; Hueber and Wohlmuth 2005 for contact): at each iteration the active
set is A = {j : lam_j - c_j gw_j > 0}; an active node's linearised weighted gap is closed,
``gw_j + G_j du = 0``, an inactive node's force is zero. Displacement, multipliers and active set come
from one symmetric saddle-point system ``[[K - sum_q A p N N H, G_A^T], [G_A, 0]]`` over the free dofs and
the candidate nodes (an inactive node's row is the identity), factorised by PARDISO in symmetric
indefinite mode; they converge together, superlinearly near the solution, with no penalty and no
multiplier update loop. A backtracking line search on the merit function 0.5 (|R|^2 + |C|^2) globalises
each step. The weighted gaps average the gap over each node's facets, so a facet cannot slip into a
curved obstacle between its nodes without closing a weighted gap (with constraints at the nodes alone, a
30 deg bar's rim cuts ~20 % of a facet into the skin and the active set cycles at the quadratic facets'
corner nodes, whose consistent share of a pressure is near zero).

An increment is converged when |R| <= rtol max(|f_int|, |G^T lam|) + atol and every candidate node
satisfies the complementarity to the gap tolerance: |min(lam_j, c_j gw_j)| <= c_j gap_tol_rel h_j (h_j the
size of the node's facets), i.e. no weighted gap is closed beyond gap_tol_rel h_j and no node pulls on the
obstacle by more than the force that would close that gap. It is also converged, with an unchanged active set,
the residual within rtol_intermediate and no longer falling tenfold in two iterations, when the Newton
correction moves no node by more than gap_tol_rel h_min (the correction is applied): the state is then
fixed to the gap tolerance, and the residual left is that of a point on an edge of the piecewise-flat cast,
whose normal jumps there (Newton alternates between the two faces).
Increments grow after few Newton iterations and few active-set changes, shrink after many, and are cut
after a failure.

The load schedule (bone rotation about x, y, z, then translation with the indenter's travel), the
assembler, the facet sets and the result type are those of :mod:`deeptissue.fem.solver`.
Units: mm, N, MPa, mJ, s.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from ..mesh import TetMesh
from .assembly import Assembler, as_material_law
from .cast import Cast
from .contact import ContactSurface, tri6_shape
from .indenters import Indenter
from .linsolve import PardisoSymmetric
from .solver import BoneMotion, BoneState, IncrementRecord, SolveResult, _bone_clearance_mm, _Schedule

log = logging.getLogger(__name__)

__all__ = ["ContactSettings", "ExactContactSettings", "IncrementSettings", "NewtonSettings", "solve_indentation_exact"]


@dataclass(frozen=True)
class NewtonSettings:
    """rtol: equilibrium residual over max(|internal force|, |contact force|) at the end of a load step
    (rtol_intermediate inside a step: the problem is path independent, only end states need accuracy);
    atol_mu_rel: absolute floor of the residual in units of mu V^(2/3) [N]; max_iterations per increment;
    armijo: the merit function must fall by this fraction of its predicted decrease below the largest of the
    last ``nonmonotone_memory`` merits (1: the monotone test); max_backtracks: step halvings before the
    direction is given up (then the increment is cut)."""

    rtol: float = 1e-6
    rtol_intermediate: float = 1e-3
    atol_mu_rel: float = 1e-10
    max_iterations: int = 25
    armijo: float = 1e-4
    max_backtracks: int = 12
    nonmonotone_memory: int = 5


@dataclass(frozen=True)
class IncrementSettings:
    """The indentation step starts with ``initial_increment`` (load units; a bone-rotation step is tried
    whole: the rigid predictor follows it); an increment converged in at most ``easy_iterations`` Newton
    iterations whose active set changed after its first iteration on at most ``easy_changes_rel`` of its contact
    nodes grows the next by
    ``grow_factor``, one that needed more than ``hard_iterations`` shrinks it by ``shrink_factor``, a failed
    one is cut by ``cut_factor``. first_touch_mm: the increment where the indenter first touches advances
    it at most this far past the first contact [mm]. start_clearance_mm: an indenter touching the skin at
    its start is moved back along its axis until this clear (as the penalty solver does)."""

    initial_increment: float = 0.25
    max_increment: float = 1.0
    min_increment: float = 1e-4
    max_increments: int = 400
    easy_iterations: int = 5
    easy_changes_rel: float = 0.25
    hard_iterations: int = 10
    grow_factor: float = 2.0
    shrink_factor: float = 0.7
    cut_factor: float = 0.35
    first_touch_mm: float = 0.1
    start_clearance_mm: float = 0.1
    secant_predictor: bool = True


@dataclass(frozen=True)
class ContactSettings:
    """gap_tol_rel: the complementarity tolerance as a weighted penetration over the node's facet size (0.1 %:
    the accuracy statement of a converged state); candidate_distance_rel: nodes closer than this many largest
    facet sizes to the indenter (cast_candidate_distance_mm to the cast) at the start of an increment are
    tested for contact (others are checked for penetration at convergence); report_quadrature_order: the
    facets' quadrature on which the reported penetration between nodes is measured."""

    gap_tol_rel: float = 1e-3
    candidate_distance_rel: float = 2.0
    cast_candidate_distance_mm: float = 0.1
    report_quadrature_order: int = 4


@dataclass(frozen=True)
class ExactContactSettings:
    """All settings of :func:`solve_indentation_exact`; the facet sets default to those of SolverSettings."""

    newton: NewtonSettings = field(default_factory=NewtonSettings)
    increments: IncrementSettings = field(default_factory=IncrementSettings)
    contact: ContactSettings = field(default_factory=ContactSettings)
    quadrature_order: int = 2
    min_bone_clearance_mm: float = 0.0
    max_wall_s: float | None = None
    bone_set: str = "bone"
    indenter_set: str = "patch"
    cast_set: str = "skin"


# --------------------------------------------------------------------------------------------- contact



# the 4-subtriangle split of the reference 6-node triangle (gmsh order: corners 0,1,2; midsides 3 (0-1), 4 (1-2), 5 (2-0))
_LOCAL = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.5, 0.0], [0.5, 0.5], [0.0, 0.5]])
_SUB = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])


def _weight_quadrature():
    """Points (Q, 2) on the reference triangle, weights (Q,) (summing to its area 1/2) and the values (Q, 6) of
    the piecewise-linear weight functions psi_j of the 4-subtriangle split (positive, a partition of unity):
    a degree-2 rule on each subtriangle."""
    bary = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
    pts, w, psi = [], [], []
    for tri in _SUB:
        pts.append(bary @ _LOCAL[tri])
        w.append(np.full(3, 1 / 24))  # subtriangle area 1/8, three equal weights
        v = np.zeros((3, 6))
        v[:, tri] = bary
        psi.append(v)
    return np.concatenate(pts), np.concatenate(w), np.concatenate(psi)


class _WeightedContact:
    """Weighted gaps of the skin nodes against the rigid obstacles, and their derivatives.

    For a node j of a contact facet set, its weighted gap is the average of the gap over the facets around it,
    weighted by the positive piecewise-linear function psi_j of the facets' 4-subtriangle split:
    ``gw_j = sum_q A_q psi_j(q) g(x_q) / m_j``, ``m_j = sum_q A_q psi_j(q)`` (A_q the reference area weight of
    quadrature point q, x_q its current position). The constraint is gw_j >= 0; its multiplier lam_j [N]
    is the node's share of the contact force, the pressure being ``p(q) = sum_j lam_j psi_j(q) / m_j`` >= 0
    wherever every lam_j >= 0. Entries e (one per node and obstacle) as in :class:`_NodalContact`.
    """

    def __init__(self, X, sets, excluded, young_mpa):
        xi, w, self.psi = _weight_quadrature()
        self.N, dN = tri6_shape(xi[:, 0], xi[:, 1])
        nodes, obst, h, self.names, self.sets = [], [], [], [], []
        for k, (name, facets) in enumerate(sets):
            facets = np.asarray(facets, np.int64)
            Xf = X[facets]
            a1 = np.einsum("qa,kai->kqi", dN[..., 0], Xf)
            a2 = np.einsum("qa,kai->kqi", dN[..., 1], Xf)
            A = np.linalg.norm(np.cross(a1, a2), axis=-1) * w  # (F, Q) [mm^2]
            hf = np.sqrt(2.0 * A.sum(axis=1))
            nd = np.setdiff1d(np.unique(facets), excluded)
            hn = np.full(len(X), np.inf)
            np.minimum.at(hn, facets.ravel(), np.repeat(hf, 6))
            # local entry index of each facet node (-1: excluded node, no constraint)
            ent = np.full(len(X), -1, np.int64)
            ent[nd] = np.arange(len(nd)) + sum(len(n) for n in nodes)
            self.sets.append(dict(facets=facets, X=np.einsum("qa,kai->kqi", self.N, Xf), A=A, entry=ent[facets]))
            nodes.append(nd)
            obst.append(np.full(len(nd), k))
            h.append(hn[nd])
            self.names.append(name)
        self.X = X
        self.node = np.concatenate(nodes)
        self.obstacle = np.concatenate(obst)
        self.h = np.concatenate(h)
        self.c = young_mpa * self.h
        self.lam = np.zeros(len(self.node))
        self.cand = np.ones(len(self.node), bool)
        self.gapfns = [None] * len(sets)

    def evaluate(self, u, which=None):
        """g (E,) [mm] (inf outside ``which``, default the candidates), n (E, 3), H (E, 3, 3) at u."""
        which = self.cand if which is None else which
        E = len(self.node)
        g, n, H = np.full(E, np.inf), np.zeros((E, 3)), np.zeros((E, 3, 3))
        x = self.X[self.node] + u.reshape(-1, 3)[self.node]
        for k, fn in enumerate(self.gapfns):
            sel = np.flatnonzero(which & (self.obstacle == k))
            if len(sel):
                gk, nk, Hk = fn(x[sel])
                g[sel], n[sel] = gk, nk
                if Hk is not None:
                    H[sel] = Hk
        return g, n, H

    def ncp(self, lam, g):
        """min(lam, c g) per entry [N] (0 at a solution; 0 outside the candidates)."""
        return np.where(np.isfinite(g), np.minimum(lam, self.c * np.where(np.isfinite(g), g, 0.0)), 0.0)

    def weighted(self, u, which, lam=None, curvature=True):
        """Weighted gaps of the entries ``which`` at u.

        Returns gw (E,) [mm] (inf outside ``which`` and where no quadrature point around the node can touch),
        the rows of d gw / d u as COO (entry, dof, value [1]), and with ``lam`` (E,) [N] the curvature of the
        obstacles under the pressure those multipliers make: (dofs (F, 18), blocks (F, 18, 18) [N/mm]) of
        ``-sum_q A_q p_q N_a N_b H_q`` (empty without ``curvature``), and the contact force on the tissue
        (n_dofs,) [N] (G^T lam).
        """
        E = len(self.node)
        m, num = np.zeros(E), np.zeros(E)
        u3 = u.reshape(-1, 3)
        parts = []
        for k, st in enumerate(self.sets):
            on = np.append(which & (self.obstacle == k), False)  # index -1 (no entry) -> False
            fsel = np.flatnonzero(on[st["entry"]].any(axis=1))
            if not len(fsel):
                continue
            fac, A, en = st["facets"][fsel], st["A"][fsel], st["entry"][fsel]
            x = st["X"][fsel] + np.einsum("qa,fai->fqi", self.N, u3[fac])
            F, Q = A.shape
            g, n, H = self.gapfns[k](x.reshape(-1, 3))
            g, n = g.reshape(F, Q), n.reshape(F, Q, 3)
            fin = np.isfinite(g)
            Aq = np.where(fin, A, 0.0)
            valid = en >= 0
            np.add.at(m, en[valid], np.einsum("fq,qj->fj", Aq, self.psi)[valid])
            np.add.at(num, en[valid], np.einsum("fq,qj->fj", Aq * np.where(fin, g, 0.0), self.psi)[valid])
            B = np.einsum("fq,qj,qa,fqi->fjai", Aq, self.psi, self.N, np.where(fin[..., None], n, 0.0))
            Hq = None if H is None else np.where(fin[..., None, None], H.reshape(F, Q, 3, 3), 0.0)
            parts.append((fac, Aq, en, valid, B, Hq))
        ok = which & (m > 0)
        gw = np.full(E, np.inf)
        gw[ok] = num[ok] / m[ok]
        inv_m = np.where(m > 0, 1.0 / np.where(m > 0, m, 1.0), 0.0)
        rows, cols, vals = [], [], []
        force = np.zeros(u.size) if lam is not None else None
        geo = []
        for fac, Aq, en, valid, B, Hq in parts:
            e_safe = np.where(valid, en, 0)
            scale = np.where(valid, inv_m[e_safe], 0.0) * ok[e_safe]  # (F, 6)
            Bs = B * scale[:, :, None, None]  # d gw_j / d x_a (F, 6 j, 6 a, 3)
            dof = 3 * fac[:, :, None] + np.arange(3)  # (F, 6, 3)
            keep = np.broadcast_to((valid & ok[e_safe])[:, :, None, None], Bs.shape)
            rows.append(np.broadcast_to(e_safe[:, :, None, None], Bs.shape)[keep])
            cols.append(np.broadcast_to(dof[:, None], Bs.shape)[keep])
            vals.append(Bs[keep])
            if lam is not None:
                lj = np.where(valid, lam[e_safe], 0.0) * scale  # lam_j / m_j
                np.add.at(force, dof.ravel(), np.einsum("fj,fjai->fai", lj, B).ravel())
                if curvature and Hq is not None:
                    p = np.einsum("fj,qj->fq", lj, self.psi)  # pressure at the points [MPa]
                    blk = -np.einsum("fq,qa,qb,fqij->faibj", Aq * p, self.N, self.N, Hq)
                    geo.append((dof.reshape(len(fac), 18), blk.reshape(len(fac), 18, 18)))
        G = (np.concatenate(rows) if rows else np.zeros(0, np.int64), np.concatenate(cols) if cols else np.zeros(0, np.int64),
             np.concatenate(vals) if vals else np.zeros(0))
        if lam is None:
            return gw, G
        return gw, G, geo, force


def solve_indentation_exact(mesh: TetMesh, *, material, indenter: Indenter | None, bone_motion: BoneMotion,
                            cast: Cast | None = None, settings: ExactContactSettings = ExactContactSettings(),
                            start: BoneState | None = None) -> SolveResult:
    """Solve the indentation of ``mesh`` (TetMesh, mm) with exact contact; returns a SolveResult.

    The arguments are those of :func:`deeptissue.fem.solver.solve_indentation`; ``start`` (a BoneState of
    this mesh and bone motion) gives the displacement at t = 3 (its multipliers, of another formulation, are
    not used: the first Newton iteration finds the contact forces). Never raises for non-convergence
    (converged=False with the reason and the last converged state); ValueError for missing facet sets.
    ``extra``: 'active_nodes' (count per pair name), 'active_nodes_per_increment' (the TetMesh nodes in contact
    after each converged increment), 'active_set_changes', 'node_penetration_rel' (the deepest node over its
    facet size), 'contact_entries' (per node and obstacle: node, obstacle, force lam_N, weighted_gap_mm, h_mm),
    'min_force_N' (the most tensile contact force), 'infeasible', 'bone_clearance_mm', 'start_backoff_mm'.
    """
    t_wall = time.perf_counter()
    s = settings
    sets = [(s.bone_set, True), (s.indenter_set, indenter is not None), (s.cast_set, cast is not None)]
    for name, need in sets:
        if need and (name not in mesh.facets or len(mesh.facets[name]) == 0):
            raise ValueError(f"solve_indentation_exact: mesh has no facet set {name!r} (sets: {sorted(mesh.facets)})")
    if start is not None and start.displacement_mm.shape != (3 * len(mesh.nodes_mm),):
        raise ValueError(f"solve_indentation_exact: the bone state has {start.displacement_mm.size} displacement dofs, "
                         f"the mesh {3 * len(mesh.nodes_mm)}: not this mesh's state")
    from .skmesh import straighten_invalid

    mesh, n_straightened = straighten_invalid(mesh, order=s.quadrature_order)
    law = as_material_law(material)
    X = mesh.nodes_mm
    bone_nodes = np.unique(mesh.facets[s.bone_set])
    constrained = np.zeros(X.size, bool)
    constrained[(3 * bone_nodes[:, None] + np.arange(3)).ravel()] = True
    asm = Assembler(mesh, law, constrained=constrained, intorder=s.quadrature_order)
    sched = _Schedule(bone_motion, indenter)
    pair_sets = [(n, mesh.facets[fs]) for n, fs, on in (("indenter", s.indenter_set, indenter is not None),
                                                        ("cast", s.cast_set, cast is not None)) if on]
    contact = _WeightedContact(X, pair_sets, bone_nodes, law.young_mpa)
    surfaces = {n: ContactSurface(X, f, order=s.contact.report_quadrature_order) for n, f in pair_sets}
    k_ind = contact.names.index("indenter") if indenter is not None else None
    k_cast = contact.names.index("cast") if cast is not None else None
    if k_cast is not None:
        contact.gapfns[k_cast] = cast.gap
    h_max = float(contact.h.max()) if len(contact.h) else 1.0
    cand_dist = np.where(contact.obstacle == k_cast, s.contact.cast_candidate_distance_mm,
                         s.contact.candidate_distance_rel * h_max)
    gap_tol = s.contact.gap_tol_rel * contact.h  # [mm]
    h_min = float(contact.h.min()) if len(contact.h) else 1.0
    force_unit = law.mu_mpa * asm.volume_mm3 ** (2.0 / 3.0)
    atol = s.newton.atol_mu_rel * force_unit
    solver = PardisoSymmetric("double")
    timers = dict(assembly=0.0, solve=0.0, contact=0.0)

    def set_time(t):
        if k_ind is not None:
            tip, ind = sched.tip(t), sched.indenter(t)
            contact.gapfns[k_ind] = lambda x: ind.gap(x, tip)

    def weighted_state(u, lam, curvature=True):
        tc = time.perf_counter()
        out = contact.weighted(u, contact.cand, lam, curvature=curvature)
        timers["contact"] += time.perf_counter() - tc
        return out

    def merit(u, lam):
        """0.5 (|R_free|^2 + |C|^2) at (u, lam), R = f_int - G^T lam, C = min(lam, c gw); inf if inverted."""
        ta = time.perf_counter()
        _, f = asm.force(u)
        timers["assembly"] += time.perf_counter() - ta
        if f is None:
            return np.inf
        gw, _, _, fc = weighted_state(u, lam, curvature=False)
        R = (f - fc)[asm.free]
        C = contact.ncp(lam, gw)
        return 0.5 * (float(R @ R) + float(C @ C))

    def newton(u, lam, target_d, rtol):
        """Solve one increment in place on (u, lam). Returns (ok, reason, iterations, residuals, changes)."""
        residuals, changes, merits = [], 0, []
        act = lam > 0
        for it in range(s.newton.max_iterations + 1):
            ta = time.perf_counter()
            W, f, data, Ke_bc = asm.tangent(u)
            timers["assembly"] += time.perf_counter() - ta
            if not np.isfinite(W):
                return False, "inverted element", it, residuals, changes
            gw, G, geo, fc = weighted_state(u, lam)
            du_d = np.zeros(asm.n_dofs)
            du_d[constrained] = target_d - u[constrained]
            has_d = bool(np.any(np.abs(du_d) > 1e-12 * (1.0 + np.abs(target_d).max(initial=0.0))))
            if not has_d:
                u[constrained] = target_d
                du_d[:] = 0.0
            R = (f - fc)[asm.free]
            res = float(np.linalg.norm(R))
            residuals.append(res)
            if not np.isfinite(res):
                return False, "non-finite residual", it, residuals, changes
            C = contact.ncp(lam, gw)
            ncp_ok = bool(np.all(np.abs(C) <= contact.c * gap_tol))
            scale = max(float(np.linalg.norm(f[asm.free])), float(np.linalg.norm(fc[asm.free])))
            res_ok = res <= rtol * scale + atol
            if not has_d and ncp_ok and res_ok:
                return True, "", it, residuals, changes
            if it == s.newton.max_iterations:
                return False, "too many iterations", it, residuals, changes
            if len(residuals) > 3 and res > 1e3 * min(residuals[1:]):
                return False, "diverging", it, residuals, changes
            new_act = contact.cand & np.isfinite(gw) & (lam - contact.c * np.where(np.isfinite(gw), gw, 0.0) > 0)
            if it > 0:
                changes += int(np.count_nonzero(new_act != act))
            act = new_act
            phi0 = 0.5 * (float(R @ R) + float(C @ C))
            merits.append(phi0)
            # non-monotone Armijo test (Grippo, Lampariello and Lucidi 1986) against the largest of the last
            # few merits: a change of the active set may raise the merit for one step on the way to the solution
            phi_ref = max(merits[-s.newton.nonmonotone_memory:])
            # the consistent direction first; where the merit rises within the shortest step, the direction
            # without the obstacles' curvature (which can make the tangent indefinite in a pinch)
            for curvature in (1.0, 0.0):
                du, lam_new = _step(asm, contact, data, Ke_bc, f, du_d, act, gw, G, geo, timers, solver,
                                    curvature=curvature)
                if du is None:
                    return False, "linear solver failed", it, residuals, changes
                if (curvature and not has_d and ncp_ok and not np.any(new_act != (lam > 0)) and len(residuals) > 2
                        and res > 0.1 * residuals[-3] and res <= s.newton.rtol_intermediate * scale
                        and float(np.abs(du).max()) <= s.contact.gap_tol_rel * h_min):
                    # the residual stalls while the corrections no longer move the state beyond the gap
                    # tolerance: what is left is the kink of a piecewise-flat obstacle (the cast's facets) that
                    # a point sits on, not an error Newton can remove
                    u += du
                    lam[:] = lam_new
                    return True, "", it + 1, residuals, changes
                dlam = lam_new - lam
                step = 1.0
                for _ in range(s.newton.max_backtracks):
                    phi = merit(u + step * du, lam + step * dlam)
                    if has_d and np.isfinite(phi):
                        break
                    if phi <= phi_ref - 2.0 * s.newton.armijo * step * phi0:
                        break
                    step *= 0.5
                else:
                    step = None
                if step is not None or not geo:
                    break
            if step is None:
                return False, "line search failed", it, residuals, changes
            if log.isEnabledFor(logging.DEBUG):
                viol = np.abs(C) / (contact.c * gap_tol)
                w = int(np.argmax(viol))
                tol = rtol * max(float(np.linalg.norm(f[asm.free])), float(np.linalg.norm(fc[asm.free]))) + atol
                log.debug("  it %d res %.3e (%.1f x tol) active %d (%s) step %.3g; worst complementarity %.2f x tol at "
                          "node %d (%s, lam %.2e N, gw %.2e mm)", it, res, res / tol, int(act.sum()),
                          ", ".join(f"{nm} {int(np.count_nonzero(act & (contact.obstacle == k)))}"
                                    for k, nm in enumerate(contact.names)), step, viol[w], contact.node[w],
                          contact.names[contact.obstacle[w]], lam[w], gw[w])
            u += step * du
            lam += step * dlam
        return False, "too many iterations", s.newton.max_iterations, residuals, changes

    # -------------------------------------------------------------------- the increment loop
    u = np.zeros(asm.n_dofs)
    lam = contact.lam
    history, n_iter, total_changes = [], 0, 0
    active_per_increment = []  # the nodes in contact after each converged increment
    steps = sched.active_steps()
    if start is not None:
        steps = [k for k in steps if k >= 3]
        u = start.displacement_mm.astype(float).copy()
        history, n_iter = list(start.history), start.newton_iterations
        for name, v in (("assembly", start.assembly_s), ("solve", start.linear_solve_s), ("contact", start.contact_s)):
            timers[name] += v
    Xb = X[bone_nodes]
    axis = indenter.unit_axis if indenter is not None else np.zeros(3)
    done, reason_fail, t = True, "", 0.0
    start_backoff_mm = 0.0
    bone_clearance_mm = _bone_clearance_mm(sched, Xb)
    infeasible = bone_clearance_mm is not None and bone_clearance_mm < s.min_bone_clearance_mm
    if infeasible:
        done = False
        reason_fail = (f"infeasible: the indenter ends {bone_clearance_mm:.3f} mm from the moved bone "
                       f"(min_bone_clearance_mm {s.min_bone_clearance_mm:g}): no tissue state fits between them")
    inc = s.increments
    travel = 0.0
    for k in () if infeasible else steps:
        t = float(k)
        if k == 3 and indenter is not None:
            start_backoff_mm = _clear_start(sched, contact, k_ind, u, inc.start_clearance_mm)
            travel = float(np.linalg.norm(np.subtract(sched.ind.end_mm, sched.ind.start_mm)))
        dt = inc.max_increment if k < 3 else inc.initial_increment
        prev = None  # (t, u, lam) of the increment before the last converged one, for the secant predictor
        while t < k + 1 - 1e-12:
            if len(history) >= inc.max_increments:
                done, reason_fail = False, f"more than {inc.max_increments} increments"
                break
            if s.max_wall_s is not None and time.perf_counter() - t_wall > s.max_wall_s:
                done, reason_fail = False, f"wall-time budget of {s.max_wall_s:g} s spent at t = {t:.4f}"
                break
            dt = min(dt, inc.max_increment, k + 1 - t)
            if k == 3 and k_ind is not None and travel > 0 and not np.any(lam[contact.obstacle == k_ind] > 0):
                # first touch: do not jump deep into contact
                set_time(t)
                sel = contact.obstacle == k_ind
                gmin = float(np.min(contact.evaluate(u, sel)[0][sel]))
                if gmin > 0 and travel * dt > gmin + inc.first_touch_mm:
                    dt = max((gmin + inc.first_touch_mm) / travel, inc.min_increment)
            t1 = t + dt
            t0c = dict(timers)
            if inc.secant_predictor and k == 3 and prev is not None:
                w = dt / (t - prev[0])
                u_try, lam_try = u + w * (u - prev[1]), np.maximum(lam + w * (lam - prev[2]), 0.0)
            else:
                u_try = (sched.predict(X, X + u.reshape(-1, 3), t, t1) - X).ravel()
                lam_try = lam.copy()
            target = np.zeros(asm.n_dofs)
            target.reshape(-1, 3)[bone_nodes] = sched.bone(Xb, t1) - Xb
            set_time(t1)
            g0 = contact.evaluate(u_try, np.ones(len(contact.node), bool))[0]
            contact.cand = g0 < cand_dist
            lam_try[~contact.cand] = 0.0
            step_end = t1 >= k + 1 - 1e-12
            rtol = s.newton.rtol if step_end else s.newton.rtol_intermediate
            iters, residuals, changes = 0, [], 0
            while True:
                contact.lam = lam_try
                ok, why, it, res, ch = newton(u_try, lam_try, target[constrained], rtol)
                iters, residuals, changes = iters + it, residuals + res, changes + ch
                if not ok:
                    break
                # nodes outside the candidates that now penetrate: add them and go on
                g_all = contact.evaluate(u_try, ~contact.cand)[0]
                missed = np.isfinite(g_all) & (g_all < -gap_tol)
                if not np.any(missed):
                    break
                contact.cand |= g_all < cand_dist
            n_iter += iters
            total_changes += changes
            pen = _penetration(surfaces, contact, u_try) if ok else (np.nan, np.nan)
            force = _forces(contact, u_try, lam_try, k_ind, k_cast) if ok else (np.zeros(3), np.zeros(3))
            history.append(IncrementRecord(
                step=k + 1, t_start=t, t_end=t1, converged=ok, reason=why, iterations=iters, al_updates=0,
                residuals=tuple(residuals), tip_mm=tuple(sched.tip(t1)) if indenter is not None else (),
                indenter_force_N=float(force[0] @ axis), max_penetration_mm=pen[0],
                assembly_s=timers["assembly"] - t0c["assembly"], linear_solve_s=timers["solve"] - t0c["solve"],
                contact_s=timers["contact"] - t0c["contact"]))
            log.info("step %d t %.4f->%.4f %s it %d changes %d F %.4g N pen %.3g mm", k + 1, t, t1,
                     "ok" if ok else f"cut ({why})", iters, changes, history[-1].indenter_force_N, pen[0])
            if ok:
                active_per_increment.append(np.unique(contact.node[lam_try > 0]))
                prev = (t, u, lam) if k == 3 else None
                u, lam, t = u_try, lam_try, t1
                if iters == 0:
                    dt = inc.max_increment
                elif iters <= inc.easy_iterations and changes <= inc.easy_changes_rel * max(np.count_nonzero(lam), 1):
                    dt *= inc.grow_factor
                elif iters > inc.hard_iterations:
                    dt *= inc.shrink_factor
            else:
                dt *= inc.cut_factor
                prev = None
                if dt < inc.min_increment:
                    done, reason_fail = False, f"increment below {inc.min_increment} at t = {t:.4f} ({why})"
                    break
        if not done:
            break
    solver.close()
    contact.lam = lam
    set_time(t)
    g, n, _ = contact.evaluate(u, contact.cand)
    ft, fcast = _forces(contact, u, lam, k_ind, k_cast)
    pen_mm, pen_rel = _penetration(surfaces, contact, u)
    node_pen = float(np.max(np.where(np.isfinite(g), -g / contact.h, -np.inf), initial=0.0))
    F = asm.deformation_gradient(u)
    Fe = np.einsum("eqij,eq->eij", F, asm.w) / asm.w.sum(axis=1)[:, None, None]
    on = lam > 0
    active = {name: int(np.count_nonzero(on & (contact.obstacle == j))) for j, name in enumerate(contact.names)}
    wall = time.perf_counter() - t_wall + (start.wall_s if start is not None else 0.0)
    return SolveResult(
        converged=done, reason=reason_fail, displacement_mm=u.reshape(-1, 3).copy(), deformation_gradient=Fe,
        history=tuple(history), indenter_force_N=float(ft @ axis), force_on_tissue_N=ft, cast_force_N=fcast,
        max_penetration_mm=pen_mm, max_penetration_rel=pen_rel, strain_energy_mJ=float(asm.energy(u)),
        n_dofs=asm.n_dofs, n_free_dofs=asm.n_free, increments=sum(1 for h in history if h.converged),
        newton_iterations=n_iter, load_reached=t, wall_s=wall, assembly_s=timers["assembly"],
        linear_solve_s=timers["solve"], contact_s=timers["contact"],
        extra={"attempts": 1, "formulation": "exact", "straightened_tets": n_straightened,
               "start_backoff_mm": start_backoff_mm, "bone_clearance_mm": bone_clearance_mm, "infeasible": infeasible,
               "active_nodes": active, "active_nodes_per_increment": tuple(active_per_increment),
               "active_set_changes": total_changes, "node_penetration_rel": max(node_pen, 0.0),
               "min_force_N": float(lam.min(initial=0.0)), "started_from_bone_state": start is not None,
               "contact_entries": {"nodes": contact.node.copy(), "obstacle": contact.obstacle.copy(), "lam_N": lam.copy(),
                                   "weighted_gap_mm": contact.weighted(u, contact.cand)[0], "h_mm": contact.h.copy()}},
    )



def _step(asm, contact, data, Ke_bc, f, du_d, act, gw, G, geo, timers, solver, curvature=1.0):
    """One semi-smooth Newton direction for active set ``act``: (du (n_dofs,), new multipliers (E,)), or
    (None, None) if the linear solve failed.

    Solves the symmetric saddle-point system of the free dofs and the candidate entries with a weighted gap
    ``[[K~, (S G_A)^T], [S G_A, 0]] [du; -lam_A / S] = [-(f + K_fd du_d); -S gw_A]`` (K~ = K - curvature
    sum_q A p N N H, S = c the entries' scale [N/mm] that gives both blocks the size of the stiffness); an
    inactive entry's row is its multiplier set to zero (identity row times S), so the pattern is that of all
    candidates and PARDISO's analysis is shared by every active set of an increment.
    """
    free, n_free = asm.free, asm.n_free
    fmap = np.full(asm.n_dofs, -1, np.int64)
    fmap[free] = np.arange(n_free)
    Ku = asm.csr(data).tocoo()
    r_parts, c_parts, v_parts = [Ku.row], [Ku.col], [Ku.data]
    if curvature and geo:
        for dofs, blk in geo:
            fr, fc = fmap[dofs][:, :, None], fmap[dofs][:, None, :]
            keep = (fr >= 0) & (fc >= 0) & (fr <= fc)
            fr, fc = np.broadcast_to(fr, blk.shape), np.broadcast_to(fc, blk.shape)
            r_parts.append(fr[keep])
            c_parts.append(fc[keep])
            v_parts.append(curvature * blk[keep])
    rows, cols, vals = G
    cand = np.flatnonzero(contact.cand & np.isfinite(gw))
    m = len(cand)
    rmap = np.full(len(contact.node), -1, np.int64)
    rmap[cand] = np.arange(m)
    S = contact.c[cand]
    a_row = act[cand]
    keep = (fmap[cols] >= 0) & (rmap[rows] >= 0)
    rr = rmap[rows[keep]]
    r_parts.append(fmap[cols[keep]])
    c_parts.append(n_free + rr)
    v_parts.append(vals[keep] * S[rr] * a_row[rr])
    r_parts.append(n_free + np.arange(m))
    c_parts.append(n_free + np.arange(m))
    v_parts.append(np.where(a_row, 0.0, S))
    N = n_free + m
    U = sp.coo_matrix((np.concatenate(v_parts), (np.concatenate(r_parts), np.concatenate(c_parts))), shape=(N, N)).tocsr()
    U.sort_indices()
    bc = asm.bc_force(Ke_bc, du_d) if np.any(du_d) else np.zeros(asm.n_dofs)
    b = np.concatenate([-(f + bc)[free], np.where(a_row, -S * gw[cand], 0.0)])
    ts = time.perf_counter()
    try:
        x = solver.solve_indefinite(U, b)
    except np.linalg.LinAlgError:
        return None, None
    finally:
        timers["solve"] += time.perf_counter() - ts
    du = np.zeros(asm.n_dofs)
    du[free] = x[:n_free]
    du[asm.constrained] = du_d[asm.constrained]
    lam_new = np.zeros(len(contact.node))
    lam_new[cand[a_row]] = -S[a_row] * x[n_free:][a_row]
    return du, lam_new


def _clear_start(sched, contact, k_ind, u, clearance_mm):
    """Move the indenter's start back along its axis until the skin is ``clearance_mm`` clear (as the
    penalty solver does, so both solve the same problem); returns the distance moved [mm]."""
    ind, back = sched.ind, 0.0
    a = ind.unit_axis
    sel = contact.obstacle == k_ind
    for _ in range(100):
        tip, cur = sched.tip(3.0), sched.indenter(3.0)
        gmin = float(np.min(cur.gap(contact.X[contact.node[sel]] + u.reshape(-1, 3)[contact.node[sel]], tip)[0]))
        if gmin >= clearance_mm:
            break
        back += clearance_mm - gmin
        sched.ind = replace(ind, start_mm=tuple(np.asarray(ind.start_mm, float) - back * a))
    if back > 0:
        log.warning("the indenter touches the skin at its start: start moved %.3f mm back", back)
    return back


def _forces(contact, u, lam, k_ind, k_cast):
    """(force of the indenter on the tissue (3,), force of the cast on the tissue (3,)) [N]."""
    out = []
    for k in (k_ind, k_cast):
        sel = (lam != 0) & (contact.obstacle == k) if k is not None else np.zeros(len(lam), bool)
        out.append(contact.weighted(u, sel, np.where(sel, lam, 0.0), curvature=False)[3].reshape(-1, 3).sum(axis=0) if np.any(sel)
                   else np.zeros(3))
    return out[0], out[1]


def _penetration(surfaces, contact, u):
    """Largest penetration [mm] and over facet size at the facets' quadrature points (between the nodes)."""
    pen_mm, pen_rel = 0.0, 0.0
    for k, name in enumerate(contact.names):
        surf, fn = surfaces[name], contact.gapfns[k]
        gq = surf.gaps(u, fn)
        gq = np.where(np.isfinite(gq), gq, np.inf)
        pm = np.max(-gq, axis=1)
        pen_mm = max(pen_mm, float(pm.max()))
        pen_rel = max(pen_rel, float(np.max(pm / surf.h_mm)))
    return max(pen_mm, 0.0), max(pen_rel, 0.0)
