"""Quasi-static indentation with exact frictionless contact: nodal constraints and a semi-smooth Newton method.

Every obstacle is rigid (the analytical indenter, the rigid cast), so contact is a condition on the skin
nodes alone: each node i of a contact facet set has a gap g_i(x_i) = g(x_i) to the obstacle (signed
distance, outward normal n_i = grad g, H_i = grad n_i) and a contact force lam_i n_i [N] on the tissue,
with the complementarity conditions lam_i >= 0, g_i >= 0, lam_i g_i = 0, written as the equation
``C_i = min(lam_i, c g_i) = 0`` (c [N/mm] only scales the gap into a force). Equilibrium reads
``R(u, lam) = f_int(u) - sum_i lam_i n_i(u) = 0`` on the free dofs.

Newton's method on (R, C) with the generalised derivative of min is the primal-dual active-set method
(Hintermueller, Ito and Kunisch 2002): at each iteration the active set is A = {i : lam_i - c g_i > 0};
an active node's linearised gap is closed, g_i + n_i . du_i = 0, and an inactive node's force set to
zero. The active nodes' normal displacements are therefore prescribed; in a frame (n_i, t1_i, t2_i) at
each active node (du = Q da, Q orthogonal) they are eliminated like Dirichlet dofs, so the matrix solved
is ``Q^T (K - sum_A lam_i H_i) Q`` with those rows and columns replaced by the identity: symmetric,
the size and sparsity pattern of the displacement problem (the PARDISO analysis is done once), and the
new forces are the active nodes' linearised normal reactions. Displacement, active set and forces
converge together, superlinearly near the solution; there is no penalty and no multiplier update loop.
A backtracking line search on the merit function 0.5 (|R|^2 + |C|^2) globalises each step.

An increment is converged when |R| <= rtol max(|f_int|, |contact force|) + atol and every candidate node
satisfies the complementarity to the gap tolerance: |min(lam_i, c g_i)| <= c gap_tol_rel h_i (h_i the
size of the node's facets), i.e. no node penetrates more than gap_tol_rel h_i and no node pulls on the
obstacle by more than the force that would close that gap. Increments grow after few Newton iterations
and few active-set changes, shrink after many, and are cut after a failure.

The load schedule (bone rotation about x, y, z, then translation with the indenter's travel), the
assembler, the linear solvers, the facet sets and the result type are those of
:mod:`deeptissue.fem.solver`. Units: mm, N, MPa, mJ, s.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..mesh import TetMesh
from .assembly import Assembler, as_material_law
from .cast import Cast
from .contact import ContactSurface
from .indenters import Indenter
from .linsolve import make_solver
from .solver import BoneMotion, BoneState, IncrementRecord, SolveResult, _bone_clearance_mm, _Schedule

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NewtonSettings:
    """rtol: equilibrium residual over max(|internal force|, |contact force|) at the end of a load step
    (rtol_intermediate inside a step: the problem is path independent, only end states need accuracy);
    atol_mu_rel: absolute floor of the residual in units of mu V^(2/3) [N]; max_iterations per increment;
    armijo: the merit function must fall by this fraction of its predicted decrease below the largest of the
    last ``nonmonotone_memory`` merits (1: the monotone test); max_backtracks: step halvings before the
    direction is given up; kink_retries: directions computed again per increment after freezing the nodes
    at a kink of the merit (then the increment is cut)."""

    rtol: float = 1e-6
    rtol_intermediate: float = 1e-3
    atol_mu_rel: float = 1e-10
    max_iterations: int = 25
    armijo: float = 1e-4
    max_backtracks: int = 12
    nonmonotone_memory: int = 5
    kink_retries: int = 3


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
    """gap_tol_rel: the complementarity tolerance as a penetration over the node's facet size (0.1 %: the
    accuracy statement of a converged state); candidate_distance_rel: nodes closer than this many largest
    facet sizes to the indenter (cast_candidate_distance_mm to the cast) at the start of an increment are
    tested for contact (others are checked for penetration at convergence); report_quadrature_order: the
    facets' quadrature on which the reported penetration between nodes is measured."""

    gap_tol_rel: float = 1e-3
    candidate_distance_rel: float = 2.0
    cast_candidate_distance_mm: float = 0.1
    report_quadrature_order: int = 4


@dataclass(frozen=True)
class LinearSettings:
    """The linear solver of :func:`deeptissue.fem.linsolve.make_solver` and its options."""

    solver: str = "pardiso"
    precision: str = "mixed"
    reuse_iterations: int = 20
    reuse_rtol: float = 1e-10


@dataclass(frozen=True)
class ExactContactSettings:
    """All settings of :func:`solve_indentation_exact`; the facet sets default to those of SolverSettings."""

    newton: NewtonSettings = field(default_factory=NewtonSettings)
    increments: IncrementSettings = field(default_factory=IncrementSettings)
    contact: ContactSettings = field(default_factory=ContactSettings)
    linear: LinearSettings = field(default_factory=LinearSettings)
    quadrature_order: int = 2
    min_bone_clearance_mm: float = 0.0
    max_wall_s: float | None = None
    bone_set: str = "bone"
    indenter_set: str = "patch"
    cast_set: str = "skin"


# --------------------------------------------------------------------------------------------- contact


class _NodalContact:
    """The (node, obstacle) pairs of all contact facet sets, their multipliers and their gaps.

    Entries e = 0..E-1: node[e] (TetMesh index), obstacle[e] (index into ``gapfns``), h[e] facet size [mm],
    lam[e] normal force [N] (>= 0 at a solution), cand[e] tested in this increment.
    """

    def __init__(self, X, sets, excluded, young_mpa):
        nodes, obst, h, self.names = [], [], [], []
        for k, (name, facets) in enumerate(sets):
            surf = ContactSurface(X, facets, order=2)
            hn = np.full(len(X), np.inf)
            np.minimum.at(hn, np.asarray(facets).ravel(), np.repeat(surf.h_mm, np.asarray(facets).shape[1]))
            nd = np.setdiff1d(np.unique(facets), excluded)
            nodes.append(nd)
            obst.append(np.full(len(nd), k))
            h.append(hn[nd])
            self.names.append(name)
        self.X = X
        self.node = np.concatenate(nodes) if nodes else np.zeros(0, np.int64)
        self.obstacle = np.concatenate(obst) if obst else np.zeros(0, np.int64)
        self.h = np.concatenate(h) if h else np.zeros(0)
        self.c = young_mpa * self.h  # [N/mm]: scales a gap into a force in min(lam, c g)
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

    def active_set(self, lam, g, n):
        """Entries with lam - c g > 0; a node active against two obstacles whose normals are within ~8 deg
        of each other (the constraints are then nearly dependent) keeps only the entry with the larger score."""
        score = lam - self.c * g
        act = score > 0
        idx = np.flatnonzero(act)
        if len(idx) > len(np.unique(self.node[idx])):
            order = idx[np.lexsort((-score[idx], self.node[idx]))]
            second = np.flatnonzero(self.node[order][1:] == self.node[order][:-1])
            a, b = order[second], order[second + 1]
            close = np.abs(np.einsum("ij,ij->i", n[a], n[b])) > 0.99
            act[b[close]] = False
        return act

    def ncp(self, lam, g):
        """min(lam, c g) per entry [N] (0 at a solution; 0 outside the candidates)."""
        return np.where(np.isfinite(g), np.minimum(lam, self.c * np.where(np.isfinite(g), g, 0.0)), 0.0)


def _frames(n):
    """Orthonormal frames (m, 3, 3) with columns (n, t1, t2)."""
    m = len(n)
    e = np.zeros((m, 3))
    e[np.arange(m), np.argmin(np.abs(n), axis=1)] = 1.0
    t1 = np.cross(n, e)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.cross(n, t1)
    return np.stack([n, t1, t2], axis=2)


class _BlockPattern:
    """The node-block structure of the Assembler's upper-triangular CSR pattern of the free dofs.

    Free dofs come in whole nodes (the bone's nodes have all three dofs constrained), free index 3 m + i for
    free node m. blocks (nb, 3, 3) hold for node pair (a <= b) the data positions of entries (i, j) (the
    lower entries of a diagonal block point to their mirror), so a block is ``data[pos]``.
    """

    def __init__(self, asm: Assembler):
        n_free = asm.n_free
        if n_free % 3 or np.any(asm.free.reshape(-1, 3) // 3 != (asm.free[0::3] // 3)[:, None]):
            raise ValueError("exact contact: the constrained dofs must be whole nodes")
        self.free_node = asm.free[0::3] // 3  # TetMesh node of free node m
        self.fnode = np.full(asm.n_nodes, -1, np.int64)
        self.fnode[self.free_node] = np.arange(len(self.free_node))
        rows = np.repeat(np.arange(n_free), np.diff(asm.indptr))
        cols = asm.indices.astype(np.int64)
        self.rows, self.cols = rows, cols
        a, b = rows // 3, cols // 3
        key = a * len(self.free_node) + b
        ukey, inv = np.unique(key, return_inverse=True)
        self.block_a, self.block_b = ukey // len(self.free_node), ukey % len(self.free_node)
        pos = np.full((len(ukey), 3, 3), -1, np.int64)
        e = np.arange(len(rows))
        pos[inv, rows % 3, cols % 3] = e
        diag = self.block_a == self.block_b
        low = diag[:, None, None] & (np.arange(3)[:, None] > np.arange(3)[None, :])[None]
        pos[low] = np.transpose(pos, (0, 2, 1))[low]
        if np.any(pos < 0):
            raise ValueError("exact contact: the tangent pattern is not node-block complete")
        self.pos = pos
        self.is_diag = diag
        self.diag_block = np.full(len(self.free_node), -1, np.int64)
        self.diag_block[self.block_a[diag]] = np.flatnonzero(diag)

    def blocks_of(self, fn_active):
        """Indices of the blocks touching free nodes fn_active."""
        mark = np.zeros(len(self.free_node), bool)
        mark[fn_active] = True
        return np.flatnonzero(mark[self.block_a] | mark[self.block_b])


def _sym_matvec(asm, data, v):
    U = asm.csr(data)
    return U @ v + U.T @ v - U.diagonal() * v


# ------------------------------------------------------------------------------------------------ solve


def solve_indentation_exact(mesh: TetMesh, *, material, indenter: Indenter | None, bone_motion: BoneMotion,
                            cast: Cast | None = None, settings: ExactContactSettings = ExactContactSettings(),
                            start: BoneState | None = None) -> SolveResult:
    """Solve the indentation of ``mesh`` (TetMesh, mm) with exact contact; returns a SolveResult.

    The arguments are those of :func:`deeptissue.fem.solver.solve_indentation`; ``start`` (a BoneState of
    this mesh and bone motion) gives the displacement at t = 3 (its multipliers, of another formulation, are
    not used: the first Newton iteration finds the contact forces). Never raises for non-convergence
    (converged=False with the reason and the last converged state); ValueError for missing facet sets.
    ``extra``: 'active_nodes' (count per pair name), 'active_nodes_per_increment' (the TetMesh nodes in contact
    after each converged increment), 'active_set_changes', 'node_penetration_rel',
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
    pattern = _BlockPattern(asm)
    sched = _Schedule(bone_motion, indenter)
    pair_sets = [(n, mesh.facets[fs]) for n, fs, on in (("indenter", s.indenter_set, indenter is not None),
                                                        ("cast", s.cast_set, cast is not None)) if on]
    contact = _NodalContact(X, pair_sets, bone_nodes, law.young_mpa)
    surfaces = {n: ContactSurface(X, f, order=s.contact.report_quadrature_order) for n, f in pair_sets}
    k_ind = contact.names.index("indenter") if indenter is not None else None
    k_cast = contact.names.index("cast") if cast is not None else None
    if k_cast is not None:
        contact.gapfns[k_cast] = cast.gap
    h_max = float(contact.h.max()) if len(contact.h) else 1.0
    cand_dist = np.where(contact.obstacle == k_cast, s.contact.cast_candidate_distance_mm,
                         s.contact.candidate_distance_rel * h_max)
    gap_tol = s.contact.gap_tol_rel * contact.h  # [mm]
    force_unit = law.mu_mpa * asm.volume_mm3 ** (2.0 / 3.0)
    atol = s.newton.atol_mu_rel * force_unit
    solver = make_solver(s.linear.solver, coords_mm=X, free=asm.free, precision=s.linear.precision,
                         reuse_iterations=s.linear.reuse_iterations, reuse_rtol=s.linear.reuse_rtol)
    timers = dict(assembly=0.0, solve=0.0, contact=0.0)

    def set_time(t):
        if k_ind is not None:
            tip, ind = sched.tip(t), sched.indenter(t)
            contact.gapfns[k_ind] = lambda x: ind.gap(x, tip)

    def contact_state(u, lam, which=None):
        tc = time.perf_counter()
        g, n, H = contact.evaluate(u, which)
        timers["contact"] += time.perf_counter() - tc
        return g, n, H

    def residual(f, lam, act, n):
        R = f.copy()
        R3 = R.reshape(-1, 3)
        np.add.at(R3, contact.node[act], -lam[act, None] * n[act])
        return R

    def merit(u, lam, ncp):
        """0.5 (|R_free|^2 + |C|^2) at (u, lam), C = ncp(lam, g); inf if inverted."""
        ta = time.perf_counter()
        _, f = asm.force(u)
        timers["assembly"] += time.perf_counter() - ta
        if f is None:
            return np.inf
        g, n, _ = contact_state(u, lam)
        on = lam != 0
        R = residual(f, lam, on, n)[asm.free]
        C = ncp(lam, g)
        return 0.5 * (float(R @ R) + float(C @ C))

    def newton(u, lam, target_d, rtol):
        """Solve one increment in place on (u, lam). Returns (ok, reason, iterations, residuals, changes)."""
        residuals, changes, merits = [], 0, []
        act = lam > 0
        flips = np.zeros(len(lam), int)  # active-set changes of each entry in this increment
        frozen, frozen_state, switched = (np.zeros(len(lam), bool) for _ in range(3))
        kink_retries = 0

        def ncp(lam, g):
            # a frozen entry's complementarity function is the branch its state implies
            C = contact.ncp(lam, g)
            fa, fi = frozen & frozen_state, frozen & ~frozen_state
            C[fa] = contact.c[fa] * g[fa]
            C[fi] = lam[fi]
            return C

        for it in range(s.newton.max_iterations + 1):
            ta = time.perf_counter()
            W, f, data, Ke_bc = asm.tangent(u)
            timers["assembly"] += time.perf_counter() - ta
            if not np.isfinite(W):
                return False, "inverted element", it, residuals, changes
            g, n, H = contact_state(u, lam)
            du_d = np.zeros(asm.n_dofs)
            du_d[constrained] = target_d - u[constrained]
            has_d = bool(np.any(np.abs(du_d) > 1e-12 * (1.0 + np.abs(target_d).max(initial=0.0))))
            if not has_d:
                u[constrained] = target_d
                du_d[:] = 0.0
            on = lam != 0
            R = residual(f, lam, on, n)
            res = float(np.linalg.norm(R[asm.free]))
            residuals.append(res)
            if not np.isfinite(res):
                return False, "non-finite residual", it, residuals, changes
            fc = np.linalg.norm(lam[on, None] * n[on]) if np.any(on) else 0.0
            C = ncp(lam, g)
            # converged: equilibrium, and the true complementarity (frozen nodes too) within the tolerance
            C_true = contact.ncp(lam, g)
            ncp_ok = bool(np.all(np.abs(C_true) <= contact.c * gap_tol))
            res_ok = res <= rtol * max(float(np.linalg.norm(f[asm.free])), fc) + atol
            if not has_d and ncp_ok and res_ok:
                return True, "", it, residuals, changes
            if not has_d and res_ok:
                # a frozen node in the wrong state (pulling, or penetrating) beyond the tolerance switches, once
                wrong = frozen & (np.abs(C_true) > contact.c * gap_tol) & ~switched
                frozen_state[wrong] = ~frozen_state[wrong]
                switched |= wrong
            if it == s.newton.max_iterations:
                worst = int(np.argmax(np.abs(C) / (contact.c * gap_tol)))
                log.debug("  out of iterations: residual %.2e (%s), worst complementarity at node %d (%s): force %.3e N, "
                          "gap %.3e mm (%.2f x tolerance), frozen %s", res, "ok" if res_ok else "not ok",
                          contact.node[worst], contact.names[contact.obstacle[worst]], lam[worst], g[worst],
                          abs(C[worst]) / (contact.c[worst] * gap_tol[worst]), bool(frozen[worst]))
                return False, "too many iterations", it, residuals, changes
            if len(residuals) > 3 and res > 1e3 * min(residuals[1:]):
                return False, "diverging", it, residuals, changes
            new_act = contact.active_set(lam, g, n)
            if it > 0:
                changed = new_act != act
                changes += int(np.count_nonzero(changed))
                flips += changed
                # a node back in a state it left cycles (degenerate: force and gap both near zero, where the
                # two linearisations undo each other): its state is frozen active, so that Newton converges
                # on a fixed set; the convergence test then holds its force and gap to the tolerance
                newly = (flips >= 2) & ~frozen
                frozen |= newly
                frozen_state[newly] = True
            new_act[frozen] = frozen_state[frozen]
            act = new_act
            phi0 = 0.5 * (float(R[asm.free] @ R[asm.free]) + float(C @ C))
            merits.append(phi0)
            # non-monotone Armijo test (Grippo, Lampariello and Lucidi 1986) against the largest of the last
            # few merits: a change of the active set may raise the merit for one step on the way to the solution
            phi_ref = max(merits[-s.newton.nonmonotone_memory:])
            # the consistent direction first; where the merit rises within the shortest step (a nearly singular
            # matrix, the obstacle's curvature term cancelling the tissue's stiffness in a pinch, gives a huge
            # direction), the direction without the curvature term
            for curvature in (1.0, 0.0):
                du, lam_new = _step(asm, pattern, contact, data, Ke_bc, f, du_d, act, g, n, H, lam, timers, solver,
                                    curvature=curvature)
                if du is None:
                    return False, "linear solver failed", it, residuals, changes
                dlam = lam_new - lam
                if log.isEnabledFor(logging.DEBUG) and not has_d:
                    eps = 1e-7
                    slope = (merit(u + eps * du, lam + eps * dlam, ncp) - phi0) / eps
                    log.debug("    merit slope along the direction %.3e (Newton: %.3e), curvature %g", slope, -2.0 * phi0,
                              curvature)
                step = 1.0
                for _ in range(s.newton.max_backtracks):
                    phi = merit(u + step * du, lam + step * dlam, ncp)
                    if has_d and np.isfinite(phi):
                        break
                    if phi <= phi_ref - 2.0 * s.newton.armijo * step * phi0:
                        break
                    step *= 0.5
                else:
                    step = None
                if step is not None or not np.any(H[lam != 0]):
                    break
            if step is None:
                log.debug("  it %d: no step along the direction lowers the merit %.3e (last tried %.3e)", it, phi0, phi)
                # the merit has a kink here: nodes at the switch of min(lam, c g) change branch at once along
                # the step. Freeze them in the branch they move into (the merit is then smooth in them) and
                # compute the direction again from the same state.
                gt, nt, _ = contact_state(u + 2.0 ** -s.newton.max_backtracks * du, lam)
                moved = (contact.active_set(lam + 2.0 ** -s.newton.max_backtracks * dlam, gt, nt) != act) & ~frozen
                if kink_retries < s.newton.kink_retries and np.any(moved):
                    kink_retries += 1
                    frozen |= moved
                    frozen_state[moved] = ~act[moved]
                    merits.clear()
                    log.debug("  it %d: %d nodes at a kink of the merit frozen", it, int(moved.sum()))
                    continue
                return False, "line search failed", it, residuals, changes
            log.debug("  it %d res %.3e active %d step %.3g", it, res, int(act.sum()), step)
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
               "nodal_contact": {"nodes": contact.node.copy(), "obstacle": contact.obstacle.copy(), "lam_N": lam.copy()}},
    )


_TRIU = np.arange(3)[:, None] <= np.arange(3)[None, :]  # the entries of a diagonal block stored in the data


def _step(asm, pattern, contact, data, Ke_bc, f, du_d, act, g, n, H, lam, timers, solver, curvature=1.0):
    """One semi-smooth Newton direction for active set ``act``: (du (n_dofs,), new multipliers (E,)), or
    (None, None) if the linear solve failed.

    K~ = K - curvature sum lam_i H_i (curvature 1: the consistent tangent); an active node's displacement is Q_i da_i with its normal components prescribed
    (n_i . du_i = -g_i for each active obstacle); the rest solve Q^T K~ Q da = -Q^T (f + K~ du_p + K_fd du_d)
    with the prescribed rows and columns replaced by the identity; an active node's new force is the normal
    part of its linearised reaction (f + K~ du + K_fd du_d)_i.
    """
    free = asm.free
    ia = np.flatnonzero(act)
    Kt = data.copy()
    # the curvature of the obstacle: -lam H on the diagonal blocks of the nodes with a force (a released
    # node's force goes to zero along the step, its derivative is still -lam H)
    cur = np.flatnonzero(lam != 0)
    if np.any(H[cur]):
        db = pattern.diag_block[pattern.fnode[contact.node[cur]]]
        contrib = -curvature * lam[cur, None, None] * H[cur]
        np.add.at(Kt, pattern.pos[db][:, _TRIU].ravel(), contrib[:, _TRIU].ravel())
    # prescribed parts: the bone's increment and the active normal displacements
    bc = asm.bc_force(Ke_bc, du_d) if np.any(du_d) else np.zeros(asm.n_dofs)
    nodes, Q, k, a_p, lam_map = _node_frames(contact.node[ia], n[ia], g[ia])
    fn = pattern.fnode[nodes]
    du_p = np.zeros(asm.n_dofs)
    du_p.reshape(-1, 3)[nodes] = np.einsum("kia,ka->ki", Q, a_p)
    rhs = -(f + bc)[free] - _sym_matvec(asm, Kt, du_p[free])
    # rotate the active nodes into their frames (normals first, then tangents)
    Qf = np.broadcast_to(np.eye(3), (len(pattern.free_node), 3, 3)).copy()
    Qf[fn] = Q
    blk = pattern.blocks_of(fn)
    B = Kt[pattern.pos[blk]]  # (nb', 3, 3)
    Br = np.einsum("kia,kij,kjb->kab", Qf[pattern.block_a[blk]], B, Qf[pattern.block_b[blk]])
    Kr = Kt.copy()
    up = _TRIU[None] | ~pattern.is_diag[blk][:, None, None]
    Kr[pattern.pos[blk][up]] = Br[up]
    rhs3 = rhs.reshape(-1, 3)
    rhs3[fn] = np.einsum("kia,ki->ka", Q, rhs3[fn])
    # eliminate the prescribed (normal) dofs
    pres = np.zeros(asm.n_free, bool)
    pres[3 * fn] = True
    pres[3 * fn[k > 1] + 1] = True
    diag_pos = asm.indptr[:-1]
    dval = np.abs(Kr[diag_pos[pres]])
    hit = pres[pattern.rows] | pres[pattern.cols]
    Kr[hit] = 0.0
    Kr[diag_pos[pres]] = np.maximum(dval, 1e-12 * np.abs(Kr[diag_pos]).max())
    rhs[pres] = 0.0
    ts = time.perf_counter()
    try:
        da = solver.solve(asm.csr(Kr), rhs)
    except np.linalg.LinAlgError:
        return None, None
    finally:
        timers["solve"] += time.perf_counter() - ts
    if log.isEnabledFor(logging.DEBUG):
        lin = _sym_matvec(asm, Kr, da) - rhs
        log.debug("    linear solve: relative residual %.2e, mode %s", np.linalg.norm(lin) / max(np.linalg.norm(rhs), 1e-300),
                  getattr(solver, "last_mode", None))
    da3 = da.reshape(-1, 3)
    da3[fn] = np.einsum("kia,ka->ki", Q, da3[fn])
    du = du_p.copy()
    du[free] += da
    du[asm.constrained] = du_d[asm.constrained]
    # the linearised reactions of the active nodes, in their frames, give the new forces
    f_lin = f + bc
    f_lin[free] += _sym_matvec(asm, Kt, du[free])
    r_loc = np.einsum("kia,ki->ka", Q, f_lin.reshape(-1, 3)[nodes])
    lam_new = np.zeros_like(lam)
    lam_new[ia] = lam_map(r_loc)
    return du, lam_new


def _node_frames(node, n, g):
    """Frames of the active nodes from their active entries (node (m,), normals (m, 3), gaps (m,)).

    A node has one or two active entries (one per obstacle; two only with independent normals, see
    :meth:`_NodalContact.active_set`). Returns the distinct nodes (p,), frames Q (p, 3, 3) whose first k
    columns span the normals, k (p,), the prescribed local displacements a_p (p, 3) (N^T Q a = -g) and a
    function mapping local reactions (p, 3) to the entries' forces (m,) (N lam = the reaction's normal part).
    """
    nodes, first, k = np.unique(node, return_index=True, return_counts=True)
    Q = _frames(n[first])
    a_p = np.zeros((len(nodes), 3))
    a_p[:, 0] = -g[first]
    pos = np.searchsorted(nodes, node)
    Rk = {}
    for j in np.flatnonzero(k > 1):
        e = np.flatnonzero(pos == j)
        N = n[e].T  # (3, 2)
        q, r = np.linalg.qr(N)
        Q[j] = np.column_stack([q, np.cross(q[:, 0], q[:, 1])])
        a_p[j, :2] = np.linalg.solve(r.T, -g[e])
        Rk[j] = (e, r)

    def lam_map(r_loc):
        lam = r_loc[pos, 0].copy()
        for j, (e, r) in Rk.items():
            lam[e] = np.linalg.solve(r, r_loc[j, :2])
        return lam

    return nodes, Q, k, a_p, lam_map


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
    on = lam != 0
    g, n, _ = contact.evaluate(u, on)
    out = []
    for k in (k_ind, k_cast):
        sel = on & (contact.obstacle == k) if k is not None else np.zeros_like(on)
        out.append((lam[sel, None] * n[sel]).sum(axis=0) if np.any(sel) else np.zeros(3))
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
