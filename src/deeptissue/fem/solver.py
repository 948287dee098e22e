"""Quasi-static indentation of a hyperelastic limb: rigid bone motion, rigid indenter and cast contact.

Entry points: :func:`solve_indentation`, :func:`solve_bone_rotation` (steps 1-3 once for all variants of a
mesh) and :func:`solve_turned` (a variant turned from another's end state). Load parameter t runs through
four steps of one unit each:
rotation of the bone about world x (t in [0, 1]), y ([1, 2]), z ([2, 3]) by the Euler angles of
``bone_motion.rotation_deg`` (deeptissue.rigid.euler_xyz_deg, so the bone ends exactly at R), then
([3, 4]) the translation together with the indenter travel from ``start_mm`` to ``end_mm``.
Steps that do nothing are skipped. Bone facet nodes follow the rigid motion (Dirichlet on all their
dofs); the limb ends are free.

Each increment is solved by Newton's method on the total potential (strain energy + contact
potential) with the consistent tangent, a Dirichlet predictor, a backtracking line search on the
potential, and augmented-Lagrangian updates of the contact pressures until the penetration is
below ``penetration_tol`` x facet size. Increments are cut back on divergence, inverted elements
(det F <= 0 at a quadrature point) or too many iterations, and grow after easy increments.
Units: mm, N, MPa, mJ, s.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..mesh import TetMesh
from ..rigid import BoneMotion, euler_xyz_deg
from .assembly import Assembler, as_material_law
from .cast import Cast
from .contact import ContactSurface
from .indenters import Indenter
from .linsolve import PRECISIONS, NotPositiveDefinite, make_solver

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SolverSettings:
    """Newton, increment and contact settings (defaults are meant to work without tuning).

    rtol: residual norm over the free dofs relative to the internal-force norm at the end of each
    step (rtol_intermediate inside a step: the problem is path independent, so only converged end
    states need full accuracy; to record accurate curves set rtol_intermediate = rtol and
    energy_rtol_intermediate = energy_rtol); energy_rtol: alternatively converged when the Newton
    decrement |r . du| falls below this fraction of the first one of the increment (FEBio-style
    energy norm; ends stagnation caused by active-set chatter); atol_mu_rel: absolute floor, as a
    fraction of mu * V^(2/3) [N]; atol_intermediate_mu_rel: the same in the bone-rotation steps when
    loose_rotation_steps (their forces are tiny; inside the indentation step the floor would change
    the increment path). Increments are fractions of a load step.
    penalty_factor: penalty = factor * E / h (E small-strain Young's modulus, h facet size).
    penetration_tol: allowed penetration / facet size after the augmented-Lagrangian updates at the
    end of each step (penetration_tol_intermediate inside a step); penetration_accept: an increment whose
    state still penetrates more than this x facet size is cut back, never accepted.
    penalty_growth, max_penalty_growth: facets still penetrating more than the tolerance when an
    increment ends (the multiplier updates stalled: high pressure on a curved indenter makes the
    discrete contact soft in sliding) get their penalty multiplied by penalty_growth, up to
    max_penalty_growth x the initial one, for the following increments and the retry of a cut one.
    barrier_onset_rel, barrier_limit_rel, barrier_stiffness: the contact penetration barrier
    (deeptissue.fem.contact): it starts at a penetration of barrier_onset_rel x facet size, its
    potential would be infinite at barrier_limit_rel x facet size (by default penetration_accept's bound),
    and kappa = barrier_stiffness x the facet's initial penalty; barrier_onset_rel None (the default of
    the first try) switches it off, retry_barrier_onset_rel sets it for the retry. States within
    penetration_tol never feel it. It is off in the first try because an increment's predictor moves
    the indenter a whole increment into skin not yet in contact, beyond the limit, where the barrier's
    stiff continuation costs many iterations.
    decrement_cap: the energy criterion's reference, the increment's first Newton decrement, is capped at
    decrement_cap x the strain energy of the last converged state (at least 1 % of mu V) [mJ]; None
    (default): uncapped. A cap guards against a predictor far beyond the barrier's limit whose huge first
    decrement would let a crushed state pass as converged; it is off by default because it changes the
    increment path of pinched bars so that the 30 deg hard case no longer converges.
    easy_iterations: an increment that converged in at most this many Newton iterations lets the next one
    grow by grow_factor.
    first_touch_mm: at most this much indentation in the increment where contact starts.
    start_clearance_mm: an indenter that already touches or penetrates the skin at its start position
    (a tilted bar's end dips below the point where its axis meets the skin) is moved back along its
    axis, before the indentation step, until it is this far clear; the travel then starts there.
    The end state is the same (hyperelastic, frictionless: path independent), but starting inside
    the tissue is a jump that no increment size can resolve.
    contact_smoothing_rel: width of the rounded pressure kink as a penetration / facet size.
    contact_near_rel: points with a gap below this x facet size get penalty stiffness in the Newton
    matrix once an increment needs more than easy_iterations. Default 0 (off): that matrix is not the
    derivative of the residual and makes Newton converge only linearly after first touch.
    candidate_distance_mm: facets within this gap of the indenter are contact candidates (None: 2 x
    largest facet size). cast_candidate_distance_mm: the same for the cast (the skin starts a cast
    offset, 0.2 mm, away from it everywhere, so 2 facet sizes would make the whole skin a candidate);
    facets outside a candidate set that penetrate after a Newton solve are added and the solve repeated.
    stall_rtol: a Newton iteration that no longer makes progress (the residual has not halved in
    ``stall_iterations`` iterations: points entering and leaving contact between iterations) ends
    there, converged with its best state if that state's residual is below stall_rtol x the force
    scale (10 x looser than rtol by default, 100 x tighter than rtol_intermediate); so does one that
    runs out of iterations while converging only linearly (the contact curvature term dropped).
    secant_predictor: in the indentation step, start each increment from the last increment's
    displacement change scaled to the new increment (not from the rigid bone move alone).
    loose_rotation_steps: the bone-rotation steps are converged to the intermediate tolerances and
    the atol_intermediate_mu_rel floor (only the end of the last step is reported; the problem is path
    independent).
    shift_scales: diagonal shifts s tried (K + s |diag K|, consistent curvature kept) after the plain
    consistent matrix fails to be positive definite and before the curvature factors below; empty
    by default (the first try stays on the consistent matrix).
    retry_shift_scales: when a solve with shift_scales empty ends unconverged, it is solved once more
    from the start with shift_scales = these (empty: no retry). The shifted matrix gives a descent
    direction that follows an unstable mode (tissue pinched between indenter and bone escaping
    sideways, where even the material tangent is indefinite) instead of stalling at the saddle; a
    retry leaves every solve that converges unshifted exactly as it was. retry_max_iterations:
    max_iterations of the retry (if larger): near full depth a shifted Newton iteration crawls along
    the soft mode. retry_barrier_onset_rel: the retry also switches the penetration barrier on
    (barrier_onset_rel = this, if the first try had none; None: not): where a finite penalty lets the
    unstable mode run through the indenter, the barrier closes that way out.
    curvature_scales: factors tried in turn on the contact curvature term of the Newton matrix until
    the matrix is positive definite (the last one is used regardless; 0 drops the term).
    end_penalty_passes: when the last increment ends with a penetration above penetration_tol (the
    multiplier updates stalled; penalty_growth then stiffens the facets concerned, which otherwise only
    helps later increments), the end state is solved again with those stiffer facets, up to this many
    times while facets are still being stiffened; a pass that does not converge keeps the state before it.
    linear_solver: 'pardiso' | 'amg' | 'superlu'.
    linear_precision: 'mixed' (pardiso: Cholesky in single precision, refined in double precision to a
    normwise backward error of 1e-14, factorised again in double where the refinement does not contract;
    about half the factorisation time) | 'double'.
    retry_linear_precision: the precision of the retry (and of a pinched variant's first try), None: as
    linear_precision. Default 'double': the retry follows a near-singular mode at a bifurcation, where
    the Newton direction's component along that mode is only as accurate as the solve.
    linear_reuse_iterations, linear_reuse_rtol (mixed precision): a Newton matrix is first solved by up
    to this many conjugate-gradient iterations preconditioned by the last single-precision factor, to a
    relative residual of linear_reuse_rtol, and factorised as soon as they fall behind a geometric
    decrease to it over that many iterations (checked from the 3rd on; 0: factorise every matrix);
    non-positive curvature met on the way proves the matrix indefinite without a failed factorisation.
    The tolerance is tight so that the increment control sees the same Newton path as with exact solves.
    max_wall_s: wall-time budget of one solve, the retry included [s] (None: none); checked between
    increments, a solve that spends it ends unconverged with the load reached, like any other failure.
    pinch_clearance_mm: a solve whose indenter ends closer than this to the moved bone (but not closer
    than min_bone_clearance_mm) is tried first with the retry's settings (shifts, retry_max_iterations,
    the barrier) and, if that fails, plainly: tissue pinched between indenter and bone has the sideways
    escape mode the retry is for, and the plain first try there mostly spends time. None: always plain first.
    turn_initial_increment: the first increment of a turn from a base variant's end state
    (:func:`solve_turned`), as a fraction of the turn (initial_increment is the indentation's); 1 tries
    the whole turn at once and cuts back where it fails.
    min_bone_clearance_mm: a solve whose indenter, at the end of its travel, comes closer than this to
    the moved bone's nodes (negative: overlaps the bone) is not started: it ends at once, unconverged,
    with the reason "infeasible" (no tissue state fits between two overlapping rigid bodies).
    """

    rtol: float = 1e-6
    rtol_intermediate: float = 1e-3
    energy_rtol: float = 1e-9
    energy_rtol_intermediate: float = 1e-4
    atol_mu_rel: float = 1e-10
    atol_intermediate_mu_rel: float = 1e-4
    max_iterations: int = 14
    easy_iterations: int = 4
    initial_increment: float = 0.25
    min_increment: float = 1e-4
    max_increment: float = 1.0
    grow_factor: float = 1.6
    cut_factor: float = 0.35
    max_increments: int = 400
    penalty_factor: float = 30.0
    penetration_tol: float = 0.01
    penetration_tol_intermediate: float = 0.05
    penetration_accept: float = 0.1
    barrier_onset_rel: float | None = None
    barrier_limit_rel: float = 0.1
    barrier_stiffness: float = 1.0
    max_al_updates: int = 4
    penalty_growth: float = 3.0
    max_penalty_growth: float = 100.0
    max_al_iterations: int = 6
    stall_rtol: float = 1e-5
    stall_iterations: int = 3
    first_touch_mm: float = 0.1
    decrement_cap: float | None = None
    start_clearance_mm: float = 0.1
    contact_smoothing_rel: float = 1e-3
    contact_near_rel: float = 0.0
    candidate_distance_mm: float | None = None
    cast_candidate_distance_mm: float = 0.1
    inexact_al: bool = True
    secant_predictor: bool = True
    curvature_scales: tuple = (1.0, 0.0)
    shift_scales: tuple = ()
    retry_shift_scales: tuple = (0.1,)
    retry_max_iterations: int = 30
    retry_barrier_onset_rel: float | None = 0.03
    loose_rotation_steps: bool = True
    linear_solver: str = "pardiso"
    linear_precision: str = "mixed"
    retry_linear_precision: str | None = "double"
    linear_reuse_iterations: int = 20
    linear_reuse_rtol: float = 1e-10
    quadrature_order: int = 2
    contact_quadrature_order: int = 4
    end_penalty_passes: int = 3
    max_wall_s: float | None = None
    min_bone_clearance_mm: float = 0.0
    turn_initial_increment: float = 1.0
    pinch_clearance_mm: float | None = 0.6
    bone_set: str = "bone"
    indenter_set: str = "patch"
    cast_set: str = "skin"

    def __post_init__(self):
        for name, allowed in (("linear_precision", PRECISIONS), ("retry_linear_precision", (*PRECISIONS, None))):
            if getattr(self, name) not in allowed:
                raise ValueError(f"SolverSettings: {name} {getattr(self, name)!r}: expected one of {allowed}")
        if self.linear_reuse_iterations < 0 or not 0 < self.linear_reuse_rtol < 1:
            raise ValueError(f"SolverSettings: linear_reuse_iterations {self.linear_reuse_iterations} must be >= 0 "
                             f"and linear_reuse_rtol {self.linear_reuse_rtol} in (0, 1)")
        for name in ("barrier_onset_rel", "retry_barrier_onset_rel"):
            onset = getattr(self, name)
            if onset is not None and not 0 <= onset < self.barrier_limit_rel:
                raise ValueError(f"SolverSettings: the barrier needs 0 <= {name} < barrier_limit_rel, "
                                 f"got {onset} and {self.barrier_limit_rel}")


def solver_settings_from_config(solver_cfg: dict | None) -> SolverSettings:
    """SolverSettings from the ``fem.solver`` config section (unknown keys raise ValueError)."""
    cfg = dict(solver_cfg or {})
    known = set(SolverSettings.__dataclass_fields__)
    bad = sorted(set(cfg) - known)
    if bad:
        raise ValueError(f"fem.solver: unknown keys {bad}")
    return SolverSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items()})


@dataclass(frozen=True)
class IncrementRecord:
    step: int  # 1..4: rotation x, y, z, translation + indentation
    t_start: float
    t_end: float  # an end pass (end_penalty_passes): t_start == t_end == 4
    converged: bool
    reason: str  # "" if converged, else why it was cut
    iterations: int
    al_updates: int
    residuals: tuple  # residual norms [N] of the Newton iterations
    tip_mm: tuple
    indenter_force_N: float
    max_penetration_mm: float
    assembly_s: float
    linear_solve_s: float
    contact_s: float


@dataclass(frozen=True)
class SolveResult:
    """Result of :func:`solve_indentation`.

    displacement_mm (n_nodes, 3) in TetMesh node order; deformation_gradient (n_tets, 3, 3)
    volume-averaged per element; indenter_force_N: force the indenter applies to the tissue
    projected on the indenter axis (positive = pressing in) [N]; force_on_tissue_N (3,) that force as
    a vector; cast_force_N (3,) total force of the cast on the tissue; max_penetration_mm /
    max_penetration_rel: largest penetration at a contact quadrature point [mm] / over facet size.
    load_reached: load parameter reached (4 = done). Times in s: wall, assembly (material),
    linear_solve, contact.
    """

    converged: bool
    reason: str
    displacement_mm: np.ndarray
    deformation_gradient: np.ndarray
    history: tuple
    indenter_force_N: float
    force_on_tissue_N: np.ndarray
    cast_force_N: np.ndarray
    max_penetration_mm: float
    max_penetration_rel: float
    strain_energy_mJ: float
    n_dofs: int
    n_free_dofs: int
    increments: int
    newton_iterations: int
    load_reached: float
    wall_s: float
    assembly_s: float
    linear_solve_s: float
    contact_s: float
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class BoneState:
    """The converged state at the end of the bone-rotation steps (t = 3), without an indenter: the start
    of every variant of one mesh, bone motion and cast (the indenter, 1 mm clear, touches nothing before
    its step), so that the variants need not each solve it again (:func:`solve_bone_rotation`).

    displacement_mm (n_dofs,); the cast pair's multipliers lam_mpa (K, Q) and penalties eps (K,) (None
    without a cast); strain_energy_mJ of the state; history, newton_iterations and the times [s] of
    the steps that made it (a variant started from it reports them as its own, so its figures stay
    those of a whole solve); settings: the SolverSettings it was solved with (a start is only used by
    a try with the same settings, see :func:`solve_indentation`).
    """

    displacement_mm: np.ndarray
    cast_lam_mpa: np.ndarray | None
    cast_eps: np.ndarray | None
    strain_energy_mJ: float
    history: tuple
    newton_iterations: int
    wall_s: float
    assembly_s: float
    linear_solve_s: float
    contact_s: float
    settings: SolverSettings


def save_bone_state(path, state: BoneState) -> None:
    """Write a BoneState as .npz (arrays, and the rest as JSON), atomically."""
    import json
    from dataclasses import asdict

    from ..io import atomic_path

    meta = dict(strain_energy_mJ=state.strain_energy_mJ, newton_iterations=state.newton_iterations,
                wall_s=state.wall_s, assembly_s=state.assembly_s, linear_solve_s=state.linear_solve_s,
                contact_s=state.contact_s, history=[asdict(h) for h in state.history],
                settings=asdict(state.settings))
    arrays = dict(displacement_mm=state.displacement_mm, meta=np.array(json.dumps(meta)))
    if state.cast_lam_mpa is not None:
        arrays.update(cast_lam_mpa=state.cast_lam_mpa, cast_eps=state.cast_eps)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def load_bone_state(path) -> BoneState:
    """Read :func:`save_bone_state`'s file; ValueError naming the file if it is not one."""
    import json

    try:
        with np.load(path) as d:
            meta = json.loads(str(d["meta"]))
            lam = d["cast_lam_mpa"] if "cast_lam_mpa" in d else None
            eps = d["cast_eps"] if "cast_eps" in d else None
            u = d["displacement_mm"]
        history = tuple(IncrementRecord(**{k: tuple(v) if isinstance(v, list) else v for k, v in h.items()})
                        for h in meta["history"])
        settings = SolverSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in meta["settings"].items()})
        return BoneState(displacement_mm=u, cast_lam_mpa=lam, cast_eps=eps, strain_energy_mJ=float(meta["strain_energy_mJ"]),
                         history=history, newton_iterations=int(meta["newton_iterations"]), wall_s=float(meta["wall_s"]),
                         assembly_s=float(meta["assembly_s"]), linear_solve_s=float(meta["linear_solve_s"]),
                         contact_s=float(meta["contact_s"]), settings=settings)
    except (KeyError, OSError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: not a bone-state file ({type(exc).__name__}: {exc})") from exc


@dataclass(frozen=True)
class EndState:
    """The converged end state (t = 4) of one variant: the start of a variant that differs from it only by
    a turn of the indenter about the same final tip (:func:`solve_turned`).

    displacement_mm (n_dofs,); contact: pair name ('indenter', 'cast') -> (facets (K, n) node ids of the
    pair's skin facets, lam_mpa (K, Q) multipliers, eps (K,) penalties); indenter: the Indenter it was
    solved with; bone_motion: its BoneMotion; settings: its SolverSettings.
    """

    displacement_mm: np.ndarray
    contact: dict
    indenter: Indenter
    bone_motion: BoneMotion
    settings: SolverSettings


def end_state(result: SolveResult, mesh: TetMesh, *, indenter: Indenter, bone_motion: BoneMotion,
              settings: SolverSettings) -> EndState | None:
    """The EndState of a converged :func:`solve_indentation` result (None if it did not converge)."""
    if not result.converged:
        return None
    sets = _pair_sets(settings)
    contact = {name: (np.asarray(mesh.facets[sets[name]]), lam, eps)
               for name, (lam, eps) in result.extra.get("contact_state", {}).items()}
    return EndState(displacement_mm=result.displacement_mm.ravel().copy(), contact=contact, indenter=indenter,
                    bone_motion=bone_motion, settings=settings)


def save_end_state(path, state: EndState) -> None:
    """Write an EndState as .npz (arrays, and the rest as JSON), atomically."""
    import json
    from dataclasses import asdict

    from ..io import atomic_path

    meta = dict(indenter=asdict(state.indenter), bone_motion=asdict(state.bone_motion), settings=asdict(state.settings),
                pairs=sorted(state.contact))
    arrays = dict(displacement_mm=state.displacement_mm, meta=np.array(json.dumps(meta)))
    for name, (facets, lam, eps) in state.contact.items():
        arrays.update({f"{name}_facets": facets, f"{name}_lam_mpa": lam, f"{name}_eps": eps})
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def load_end_state(path) -> EndState:
    """Read :func:`save_end_state`'s file; ValueError naming the file if it is not one."""
    import json

    def tup(d):
        return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}

    try:
        with np.load(path) as d:
            meta = json.loads(str(d["meta"]))
            contact = {n: (d[f"{n}_facets"], d[f"{n}_lam_mpa"], d[f"{n}_eps"]) for n in meta["pairs"]}
            u = d["displacement_mm"]
        return EndState(displacement_mm=u, contact=contact, indenter=Indenter(**tup(meta["indenter"])),
                        bone_motion=BoneMotion(**tup(meta["bone_motion"])), settings=SolverSettings(**tup(meta["settings"])))
    except (KeyError, OSError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: not an end-state file ({type(exc).__name__}: {exc})") from exc


def summed_costs(*results: SolveResult) -> dict:
    """The Newton iterations and the assembly, linear-solve and contact seconds of several tries of one solve,
    summed (for ``dataclasses.replace`` of the result reported; its wall time is the caller's)."""
    return {k: sum(getattr(r, k) for r in results) for k in ("newton_iterations", "assembly_s", "linear_solve_s", "contact_s")}


def _pair_sets(settings: SolverSettings) -> dict:
    """The skin facet set of each contact pair, by pair name."""
    return {"indenter": settings.indenter_set, "cast": settings.cast_set}


def _same_start_settings(a: SolverSettings, b: SolverSettings) -> bool:
    """Whether a bone state solved with settings a is the start a try with settings b would reach
    (the indenter's facet set and the wall-time budget play no part before the indenter moves)."""
    return replace(a, indenter_set="", max_wall_s=None) == replace(b, indenter_set="", max_wall_s=None)


class _Schedule:
    def __init__(self, bone_motion: BoneMotion, indenter: Indenter | None):
        self.c = np.asarray(bone_motion.centre_mm, float)
        self.T = np.asarray(bone_motion.translation_mm, float)
        self.ang = np.radians(euler_xyz_deg(bone_motion.rotation_deg))
        self.ind = indenter

    @staticmethod
    def _rot(axis, a):
        c, s = np.cos(a), np.sin(a)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        R = np.eye(3)
        R[i, i] = R[j, j] = c
        R[i, j], R[j, i] = -s, s
        return R

    def rotation(self, t):
        R = np.eye(3)
        for k in range(3):
            R = self._rot(k, self.ang[k] * np.clip(t - k, 0.0, 1.0)) @ R
        return R

    def bone(self, X, t):
        return (X - self.c) @ self.rotation(t).T + self.c + np.clip(t - 3.0, 0.0, 1.0) * self.T

    def tip(self, t):
        return None if self.ind is None else self.ind.tip_at(float(np.clip(t - 3.0, 0.0, 1.0)))

    def predict(self, X, x, t0, t1):
        """Move the whole current configuration x (n, 3) by the bone's rigid increment t0 -> t1."""
        R = self.rotation(t1) @ self.rotation(t0).T
        T0 = np.clip(t0 - 3.0, 0.0, 1.0) * self.T
        T1 = np.clip(t1 - 3.0, 0.0, 1.0) * self.T
        return (x - self.c - T0) @ R.T + self.c + T1

    def active_steps(self):
        steps = [k for k in range(3) if abs(self.ang[k]) > 0]
        return steps + [3]

    def indenter(self, t):
        """The indenter (its shape and axis) at load t; its tip is :meth:`tip`."""
        return self.ind


class _TurnSchedule(_Schedule):
    """The bone at its final pose; in the one step (t 3 -> 4) the indenter turns about its final tip from
    the axis of ``ind_from`` to the axis of ``ind_to`` (the shortest rotation, at a uniform rate)."""

    def __init__(self, bone_motion: BoneMotion, ind_from: Indenter, ind_to: Indenter):
        super().__init__(bone_motion, ind_to)
        self.a0, a1 = ind_from.unit_axis, ind_to.unit_axis
        k = np.cross(self.a0, a1)
        self.angle = float(np.arctan2(np.linalg.norm(k), self.a0 @ a1))
        self.k = k / np.linalg.norm(k) if self.angle > 0 else np.zeros(3)
        self.tip_end = np.asarray(ind_to.end_mm, float)

    def bone(self, X, t):
        return super().bone(X, 4.0)

    def tip(self, t):
        return self.tip_end

    def predict(self, X, x, t0, t1):
        return x

    def active_steps(self):
        return [3]

    def indenter(self, t):
        s = float(np.clip(t - 3.0, 0.0, 1.0)) * self.angle
        a = self.a0 * np.cos(s) + np.cross(self.k, self.a0) * np.sin(s) + self.k * (self.k @ self.a0) * (1 - np.cos(s))
        return replace(self.ind, axis=tuple(a))


class _Pair:
    """A contact pair: skin facets (slave) against a rigid gap function."""

    def __init__(self, name, surf: ContactSurface, gap_of_t, eps, asm: Assembler):
        self.name, self.surf, self.gap_of_t, self.eps = name, surf, gap_of_t, eps
        fr, nd = asm.fidx[surf.dofs], surf.dofs.shape[1]  # (K, 18); 9 for 3-node facets
        rr = np.repeat(fr[:, :, None], nd, axis=2)
        cc = np.repeat(fr[:, None, :], nd, axis=1)
        pos = asm.pattern_index(rr, cc)
        pos[(rr > cc) | (rr < 0) | (cc < 0)] = -1
        self.pos = pos  # (K, 18, 18)
        self.cand = np.arange(surf.n_facets)
        self.gapfn = None
        self.eps0 = np.broadcast_to(np.asarray(eps, float), (surf.n_facets,)).copy()
        self.eps = self.eps0.copy()

    def stiffen(self, r, threshold_rel, growth, max_growth):
        """Raise the penalty of the facets of contact output r penetrating more than threshold_rel x
        their size (the multiplier updates could not push them out); returns how many."""
        if r is None or growth <= 1:
            return 0
        bad = r["cand"][np.max(-r["gap"], axis=1) > threshold_rel * r["h_mm"]]
        bad = bad[self.eps[bad] < max_growth * self.eps0[bad]]
        self.eps[bad] = np.minimum(self.eps[bad] * growth, max_growth * self.eps0[bad])
        return len(bad)

    def set_time(self, t):
        self.gapfn = self.gap_of_t(t)


def _al_state(pairs):
    return [p.surf.lam.copy() for p in pairs]


def _restore_al(pairs, st):
    for p, lam in zip(pairs, st):
        p.surf.lam[:] = lam


def solve_bone_rotation(mesh: TetMesh, *, material, bone_motion: BoneMotion, cast: Cast | None = None,
                        settings: SolverSettings = SolverSettings()) -> tuple[SolveResult, BoneState | None]:
    """The bone-rotation steps alone (t 0 -> 3, no indenter): (result, BoneState), the state None if they
    did not converge. Every variant on this mesh with these settings can start from the state
    (``solve_indentation(..., start=state)``) and takes the same path as if it had solved them itself."""
    r = _solve(mesh, material=material, indenter=None, schedule=_Schedule(bone_motion, None),
               bc_sets=(settings.bone_set,), cast=cast, settings=settings, rotation_only=True)
    if not r.converged:
        return r, None
    lam, eps = r.extra.get("contact_state", {}).get("cast", (None, None))
    return r, BoneState(displacement_mm=r.displacement_mm.ravel().copy(), cast_lam_mpa=lam, cast_eps=eps,
                        strain_energy_mJ=r.extra["last_energy_mJ"], history=r.history,
                        newton_iterations=r.newton_iterations, wall_s=r.wall_s, assembly_s=r.assembly_s,
                        linear_solve_s=r.linear_solve_s, contact_s=r.contact_s, settings=settings)


def solve_indentation(mesh: TetMesh, *, material, indenter: Indenter | None, bone_motion: BoneMotion,
                      cast: Cast | None = None, settings: SolverSettings = SolverSettings(),
                      start: BoneState | None = None) -> SolveResult:
    """Solve the indentation of ``mesh`` (TetMesh, mm) and return a :class:`SolveResult`.

    material: an Ogden parameter set (deeptissue.fem.material.Ogden) or an assembly.MaterialLaw.
    indenter: Indenter (contact with the ``settings.indenter_set`` facets) or None.
    bone_motion: BoneMotion of the ``settings.bone_set`` facets (Dirichlet on all their dofs).
    cast: a Cast (contact with the ``settings.cast_set`` facets) or None.
    Never raises for non-convergence: returns converged=False with the reason and the last
    converged state. Raises ValueError for missing facet sets.
    An unconverged solve is tried once more with ``settings.retry_shift_scales`` (see
    :class:`SolverSettings`); the result is the retry's (if both fail, the one that got further),
    with wall and component times and Newton iterations summed over both tries and
    ``extra['attempts']`` = 2. A solve whose indenter ends closer to the bone than
    ``settings.pinch_clearance_mm`` is tried with the retry's settings first and plainly second.
    ``extra``: 'shifted', 'barrier_onset_rel' and 'linear_precision' of the try returned, 'pinch_first',
    'started_from_bone_state'.
    start: a BoneState of this mesh, bone motion and cast (:func:`solve_bone_rotation`): a try whose
    settings are the state's starts from it at t = 3 instead of solving the bone rotation again (the
    retry's settings, e.g. of a pinched variant, solve it themselves).
    """
    if start is not None and start.displacement_mm.shape != (3 * len(mesh.nodes_mm),):
        raise ValueError(f"solve_indentation: the bone state has {start.displacement_mm.size} displacement dofs, "
                         f"the mesh {3 * len(mesh.nodes_mm)}: not this mesh's state")

    def run(st):
        use = start if start is not None and _same_start_settings(start.settings, st) else None
        r = _solve(mesh, material=material, indenter=indenter, schedule=_Schedule(bone_motion, indenter),
                   bc_sets=(st.bone_set,), cast=cast, settings=st, start=use)
        # only the retry's settings carry shifts (there is no retry when the settings already do)
        return replace(r, extra={**r.extra, "pinch_first": pinched, "shifted": bool(st.shift_scales),
                                 "started_from_bone_state": use is not None,
                                 "barrier_onset_rel": st.barrier_onset_rel, "linear_precision": st.linear_precision})

    t0 = time.perf_counter()
    s = settings
    again = None  # the retry's settings
    if s.retry_shift_scales and not s.shift_scales:
        barrier = s.barrier_onset_rel if s.barrier_onset_rel is not None else s.retry_barrier_onset_rel
        again = replace(s, shift_scales=s.retry_shift_scales, max_iterations=max(s.max_iterations, s.retry_max_iterations),
                        barrier_onset_rel=barrier, linear_precision=s.retry_linear_precision or s.linear_precision)
    bone = mesh.facets.get(s.bone_set)
    clearance = (None if bone is None or not len(bone) else
                 _bone_clearance_mm(_Schedule(bone_motion, indenter), mesh.nodes_mm[np.unique(bone)]))
    pinched = (again is not None and s.pinch_clearance_mm is not None and clearance is not None
               and s.min_bone_clearance_mm <= clearance < s.pinch_clearance_mm)

    def describe(st):
        return (f"diagonal shifts {st.shift_scales}, up to {st.max_iterations} iterations per increment"
                + ("" if st.barrier_onset_rel is None else f" and the penetration barrier from {st.barrier_onset_rel:g} x facet size"))

    tries = (again, s) if pinched else (s, again)
    if pinched:
        log.info("the indenter ends %.3f mm from the bone (pinch_clearance_mm %g): solving first with the "
                 "retry's settings (%s)", clearance, s.pinch_clearance_mm, describe(again))
    first = run(tries[0])
    if first.converged or first.extra["infeasible"] or tries[1] is None:
        return first
    st2 = tries[1]
    if s.max_wall_s is not None:
        budget = s.max_wall_s - (time.perf_counter() - t0)
        if budget <= 0:
            return first
        st2 = replace(st2, max_wall_s=budget)
    if pinched:
        log.warning("not converged (%s): solving again from the start without shifts or barrier", first.reason)
    else:
        log.warning("not converged (%s): solving again from the start with %s", first.reason, describe(again))
    second = run(st2)
    # both failed: keep the try that got further (its last converged state is the more useful)
    best = second if second.converged or second.load_reached >= first.load_reached else first
    other = first if best is second else second
    with_barrier = again.barrier_onset_rel is not None and s.barrier_onset_rel is None
    other_desc = (f"with shifts{' and barrier' if with_barrier else ''}" if other.extra["shifted"]
                  else f"without shifts{' or barrier' if with_barrier else ''}")
    reason = second.reason if second.converged else (
        f"{best.reason} (at t = {best.load_reached:.4f} of 4; the other try, {other_desc}, reached t = {other.load_reached:.4f})")
    return replace(best, reason=reason, **summed_costs(first, second), wall_s=time.perf_counter() - t0,
                   extra={**best.extra, "attempts": 2, "first_attempt_reason": first.reason,
                          "first_attempt_iterations": first.newton_iterations})


def solve_turned(mesh: TetMesh, *, material, base: EndState, indenter: Indenter, cast: Cast | None = None,
                 settings: SolverSettings = SolverSettings()) -> SolveResult:
    """Solve a variant whose indenter differs from the one of ``base`` (a converged end state on this mesh,
    :func:`end_state`) only by a turn about the same final tip: from that state, with the bone at its final
    pose, the indenter is turned about its final tip to ``indenter``'s axis in increments (one load step).
    Hyperelastic and frictionless, the end state does not depend on the path, so this is the variant's end
    state, reached without solving its indentation from the start. Never raises for non-convergence (the
    caller then solves the variant from the start); ValueError if ``indenter`` is not such a turn of
    ``base.indenter`` or the state is not of this mesh."""
    a, b = base.indenter, indenter
    if (a.kind, a.radius_mm, a.bar_length_mm) != (b.kind, b.radius_mm, b.bar_length_mm) or not np.allclose(
            a.end_mm, b.end_mm, rtol=0.0, atol=1e-9):
        raise ValueError(f"solve_turned: {b} is not a turn of {a} about its final tip")
    if base.displacement_mm.shape != (3 * len(mesh.nodes_mm),):
        raise ValueError(f"solve_turned: the end state has {base.displacement_mm.size} displacement dofs, the mesh "
                         f"{3 * len(mesh.nodes_mm)}: not this mesh's state")
    r = _solve(mesh, material=material, indenter=indenter, schedule=_TurnSchedule(base.bone_motion, a, b),
               bc_sets=(settings.bone_set,), cast=cast, settings=replace(settings, initial_increment=settings.turn_initial_increment),
               start=base)
    return replace(r, extra={**r.extra, "turned": True})


def _bone_clearance_mm(sched: _Schedule, Xb: np.ndarray) -> float | None:
    """Smallest gap [mm] between the indenter at the end of its travel and the bone's nodes Xb (n, 3) at
    their final (moved) position; None without an indenter or bone nodes."""
    if sched.ind is None or not len(Xb):
        return None
    return float(np.min(sched.ind.gap(sched.bone(Xb, 4.0), sched.tip(4.0))[0]))


class _Prescribed:
    def __init__(self, fn):
        self.fn = fn

    def bone(self, X, t):
        return X + self.fn(X, float(np.clip(t - 3.0, 0.0, 1.0)))

    def tip(self, t):
        return None

    def predict(self, X, x, t0, t1):
        s0, s1 = (float(np.clip(t - 3.0, 0.0, 1.0)) for t in (t0, t1))
        return x + self.fn(X, s1) - self.fn(X, s0)

    def active_steps(self):
        return [3]


def solve_prescribed(mesh: TetMesh, *, material, bc_sets, displacement_mm,
                     settings: SolverSettings = SolverSettings()) -> SolveResult:
    """Solve with a prescribed displacement on the nodes of facet sets ``bc_sets`` (no contact).

    displacement_mm(X (n, 3), s) -> (n, 3) [mm]: displacement at load fraction s in [0, 1].
    Used for patch tests and homogeneous deformations.
    """
    return _solve(mesh, material=material, indenter=None, schedule=_Prescribed(displacement_mm), bc_sets=tuple(bc_sets),
                  cast=None, settings=settings)


def _solve(mesh, *, material, indenter, schedule, bc_sets, cast, settings, start: BoneState | None = None,
           rotation_only: bool = False) -> SolveResult:
    t_wall = time.perf_counter()
    s = settings
    for name, need in [*((b, True) for b in bc_sets), (s.indenter_set, indenter is not None), (s.cast_set, cast is not None)]:
        if need and (name not in mesh.facets or len(mesh.facets[name]) == 0):
            raise ValueError(f"solve_indentation: mesh has no facet set {name!r} (sets: {sorted(mesh.facets)})")
    law = as_material_law(material)
    from .skmesh import straighten_invalid

    mesh, n_straightened = straighten_invalid(mesh, order=s.quadrature_order)
    if n_straightened:
        log.warning("straightened the edges of %d curved tets with a non-positive Jacobian", n_straightened)
    X = mesh.nodes_mm
    n_nodes = len(X)
    bone_nodes = np.unique(np.concatenate([mesh.facets[b].ravel() for b in bc_sets]))
    constrained = np.zeros(3 * n_nodes, bool)
    constrained[(3 * bone_nodes[:, None] + np.arange(3)).ravel()] = True
    asm = Assembler(mesh, law, constrained=constrained, intorder=s.quadrature_order)
    sched = schedule
    E_mod = law.young_mpa
    force_unit = law.mu_mpa * asm.volume_mm3 ** (2.0 / 3.0)  # [N]
    atol_final = s.atol_mu_rel * force_unit
    atol_intermediate = max(s.atol_intermediate_mu_rel * force_unit, atol_final)

    pairs = []
    if indenter is not None:
        surf = ContactSurface(X, mesh.facets[s.indenter_set], order=s.contact_quadrature_order)
        eps = s.penalty_factor * E_mod / surf.h_mm

        def ind_gap(t):
            tip, ind = sched.tip(t), sched.indenter(t)  # looked up at t: clear_start may move the start back, a turn turns it
            return lambda x: ind.gap(x, tip)

        pairs.append(_Pair("indenter", surf, ind_gap, eps, asm))
    if cast is not None:
        surf = ContactSurface(X, mesh.facets[s.cast_set], order=s.contact_quadrature_order)
        eps = s.penalty_factor * E_mod / surf.h_mm
        pairs.append(_Pair("cast", surf, lambda t, _c=cast: _c.gap, eps, asm))
    h_max = max([p.surf.h_mm.max() for p in pairs], default=1.0)
    cand_dist = s.candidate_distance_mm if s.candidate_distance_mm is not None else 2.0 * h_max
    for p in pairs:
        p.cand_dist = cand_dist if p.name == "indenter" else min(cand_dist, s.cast_candidate_distance_mm)

    solver = make_solver(s.linear_solver, coords_mm=X, free=asm.free, precision=s.linear_precision,
                         reuse_iterations=s.linear_reuse_iterations, reuse_rtol=s.linear_reuse_rtol)
    timers = dict(assembly=0.0, solve=0.0, contact=0.0)
    counts = dict(linear_solves=0, not_positive_definite=0)

    def contact_eval(u, tangent, near=False):
        tc = time.perf_counter()
        energy, force, out = 0.0, np.zeros(asm.n_dofs), []
        data = np.zeros(asm.nnz) if tangent else None
        data_geo = np.zeros(asm.nnz) if tangent else None
        for p in pairs:
            if len(p.cand) == 0:
                out.append(None)
                continue
            h = p.surf.h_mm[p.cand][:, None]  # facet sizes scale the smoothing, the near band and the barrier
            barrier = None if s.barrier_onset_rel is None else (
                s.barrier_onset_rel * h, s.barrier_limit_rel * h, s.barrier_stiffness * p.eps0[p.cand][:, None])
            r = p.surf.evaluate(u, p.gapfn, p.eps, p.cand, tangent=tangent, smoothing_mm=s.contact_smoothing_rel * h,
                                near_mm=s.contact_near_rel * h if near else 0.0, barrier=barrier)
            r["h_mm"] = h[:, 0]
            r["cand"] = p.cand.copy()
            energy += r["energy"]
            force += r["force"]
            if tangent:
                act = np.any(r["pressure"] > 0, axis=1)
                if np.any(act):
                    pos = p.pos[p.cand[act]].ravel()
                    ok = pos >= 0
                    data += np.bincount(pos[ok], weights=r["Kf"][act].ravel()[ok], minlength=asm.nnz)
                    if "Kf_geo" in r:
                        data_geo += np.bincount(pos[ok], weights=r["Kf_geo"][act].ravel()[ok], minlength=asm.nnz)
            out.append(r)
        timers["contact"] += time.perf_counter() - tc
        return energy, force, (data, data_geo), out

    def total_energy(u):
        ta = time.perf_counter()
        e = asm.energy(u)
        timers["assembly"] += time.perf_counter() - ta
        if not np.isfinite(e):
            return np.inf
        return e + contact_eval(u, False)[0]

    def update_candidates(u, t):
        tc = time.perf_counter()
        for p in pairs:
            p.set_time(t)
            g = p.surf.gaps(u, p.gapfn)
            p.cand = np.flatnonzero(np.min(g, axis=1) < p.cand_dist)
        timers["contact"] += time.perf_counter() - tc

    def missed_contact(u):
        """Facets outside the candidate set that penetrate: add them; True if any."""
        tc = time.perf_counter()
        added = False
        for p in pairs:
            g = p.surf.gaps(u, p.gapfn)
            pen = np.flatnonzero(np.min(g, axis=1) < 0)
            new = np.setdiff1d(pen, p.cand)
            if len(new):
                p.cand = np.union1d(p.cand, np.flatnonzero(np.min(g, axis=1) < p.cand_dist))
                added = True
        timers["contact"] += time.perf_counter() - tc
        return added

    def clear_start(u):
        """Move the indenter's start back along its axis until the skin is start_clearance_mm clear of it
        (in the current state, before the indentation step); returns the distance moved [mm]."""
        p, ind, back = pairs[0], sched.ind, 0.0
        a = ind.unit_axis
        for _ in range(100):
            p.set_time(3.0)
            gmin = float(np.min(p.surf.gaps(u, p.gapfn)))
            if gmin >= s.start_clearance_mm:
                break
            # a point's gap grows by at most the distance moved: repeat until clear
            back += s.start_clearance_mm - gmin
            sched.ind = replace(ind, start_mm=tuple(np.asarray(ind.start_mm, float) - back * a))
        return back

    energy_now = [0.0]  # the strain energy of newton()'s latest iterate [mJ]

    def newton(u, target_d, rtol, etol, max_it, stop_on_growth=False, atol=atol_final, energy_cap=None):
        """Iterate on u in place. Returns (ok, reason, iterations, residuals, contact outputs)."""
        d_tol = 1e-12 * (1.0 + float(np.max(np.abs(target_d), initial=0.0)) + float(np.max(np.abs(X))))
        residuals = []
        slope_first, slope_last = None, None
        best = (np.inf, None, None)  # (residual, u, contact outputs) of the best iterate without a prescribed increment
        for it in range(max_it + 1):
            ta = time.perf_counter()
            W, f, data, Ke_bc = asm.tangent(u)
            timers["assembly"] += time.perf_counter() - ta
            if not np.isfinite(W):
                return False, "inverted element", it, residuals, None
            Wc, fc, datac, outs = contact_eval(u, True, near=it >= s.easy_iterations)
            energy_now[0] = W
            r = f + fc
            du_d = np.zeros(asm.n_dofs)
            du_d[constrained] = target_d - u[constrained]
            # a prescribed increment of round-off size (the rigid predictor and the Dirichlet target
            # are computed by different formulas) is no increment: snap to the target, so that the
            # Armijo line search, the descent check and the convergence tests stay on
            has_d = float(np.max(np.abs(du_d), initial=0.0)) > d_tol
            if not has_d and np.any(du_d != 0):
                u[constrained] = target_d
                du_d[:] = 0.0
            rf = r[asm.free]
            res = float(np.linalg.norm(rf))
            residuals.append(res)
            scale = max(float(np.linalg.norm(f)), float(np.linalg.norm(fc)))
            if not np.isfinite(res):
                return False, "non-finite residual", it, residuals, None
            if not has_d and res <= rtol * scale + atol:
                return True, "", it, residuals, outs
            if not has_d and slope_first is not None and it >= 2 and abs(slope_last) <= etol * slope_ref:
                return True, "", it, residuals, outs
            if not has_d and res < best[0]:
                best = (res, u.copy(), outs)
            k_st = s.stall_iterations
            stalled = not has_d and len(residuals) > k_st and min(residuals[-k_st:]) > 0.5 * min(residuals[:-k_st])
            growing = stalled and all(a < b for a, b in zip(residuals[-k_st - 1:-1], residuals[-k_st:]))
            if (stalled or (it == max_it and not has_d)) and best[0] <= max(s.stall_rtol, rtol) * scale + atol:
                # no progress (contact chatter), or out of iterations while converging only linearly (the contact
                # curvature term dropped from a matrix that was not positive definite): the best iterate is as
                # converged as this problem gets
                log.debug("  %s at it %d: keeping the best iterate (residual %.2e)",
                          "stalled" if stalled else "out of iterations", it, best[0])
                u[:] = best[1]
                return True, "", it, residuals, best[2]
            if growing and stop_on_growth:
                # (only where a converged fallback state exists: AL passes and the final solve)
                # the residual grew in each of the last iterations while the energy fell: the iterates
                # slide along a soft contact mode away from this start; more iterations do not help
                return False, "residual growing", it, residuals, None
            if it == max_it:
                return False, "too many iterations", it, residuals, None
            if len(residuals) > 3 and res > 1e3 * min(residuals):
                return False, "diverging", it, residuals, None
            rhs = -rf
            if has_d:
                rhs = rhs - asm.bc_force(Ke_bc, du_d)[asm.free]
            # consistent tangent; where it is not positive definite (high contact pressure on a curved
            # indenter: the curvature term -p grad n outweighs a coarse facet's sliding stiffness), the
            # next (curvature factor, diagonal shift) is tried: the optional shifts keep the consistent
            # term and make the matrix positive definite, then the curvature term is scaled down
            # (curvature_scales; by default dropped)
            x = None
            if np.any(datac[1]) and not has_d:
                c0, *c_rest = s.curvature_scales
                scales = [(c0, 0.0), *((1.0, sh) for sh in s.shift_scales), *((c, 0.0) for c in c_rest)]
            else:
                scales = [(1.0, 0.0)]
            for j, (theta, shift) in enumerate(scales):
                K_data = data + datac[0] + theta * datac[1] if theta else data + datac[0]
                if shift:
                    K_data[asm.indptr[:-1]] += shift * np.abs(K_data[asm.indptr[:-1]])
                last = j == len(scales) - 1
                ts = time.perf_counter()
                counts["linear_solves"] += 1
                try:
                    x = solver.solve(asm.csr(K_data), rhs, **({} if last else {"spd_only": True}))
                except NotPositiveDefinite:
                    timers["solve"] += time.perf_counter() - ts
                    counts["not_positive_definite"] += 1
                    continue
                except np.linalg.LinAlgError as exc:
                    timers["solve"] += time.perf_counter() - ts
                    return False, f"linear solver: {exc}", it, residuals, None
                timers["solve"] += time.perf_counter() - ts
                slope = float(r[asm.free] @ x)
                if has_d or slope < 0 or last:
                    break
            if not has_d:
                slope_last = slope
                if slope_first is None:
                    slope_first = slope
                    slope_ref = abs(slope) if energy_cap is None else min(abs(slope), energy_cap)
                    if slope_ref < abs(slope):
                        log.debug("  first Newton decrement %.3e capped at %.3e", abs(slope), slope_ref)
            du = du_d.copy()
            du[asm.free] = x
            # line search
            Pi0 = W + Wc
            log.debug("  it %d res %.3e slope %.3e solver mode %s curvature %g shift %g", it, res, slope,
                      getattr(solver, "last_mode", None), theta, shift)
            step = 1.0
            accepted = False
            for _ in range(12):
                Pi1 = total_energy(u + step * du)
                if np.isfinite(Pi1):
                    if has_d:
                        accepted = True
                        break
                    if Pi1 <= Pi0 + 1e-4 * step * min(slope, 0.0) + 1e-11 * abs(Pi0) + 1e-300:
                        accepted = True
                        break
                    denom = 2.0 * (Pi1 - Pi0 - slope * step)
                    trial = -slope * step * step / denom if denom > 0 else 0.5 * step
                    step = float(np.clip(trial, 0.1 * step, 0.5 * step))
                else:
                    step *= 0.3
            if not accepted:
                return False, "line search failed", it, residuals, None
            log.debug("  it %d res %.3e step %.3g slope %.3e dPi %.3e", it, res, step, slope, Pi1 - Pi0)
            u += step * du
        return False, "too many iterations", max_it, residuals, None

    def penetration(outs):
        pen_mm, pen_rel = 0.0, 0.0
        for p, r in zip(pairs, outs):
            if r is None:
                continue
            g = r["gap"]
            if g.size:
                pm = np.max(-g, axis=1)
                pen_mm = max(pen_mm, float(pm.max()))
                pen_rel = max(pen_rel, float(np.max(pm / r["h_mm"])))
        return pen_mm, pen_rel

    def forces(outs):
        ft, fcast = np.zeros(3), np.zeros(3)
        for p, r in zip(pairs, outs):
            if r is None:
                continue
            if p.name == "indenter":
                ft = ft + r["traction_sum"]
            else:
                fcast = fcast + r["traction_sum"]
        return ft, fcast

    u = np.zeros(asm.n_dofs)
    history = []
    n_iter_total = 0
    steps = sched.active_steps()
    if rotation_only:
        steps = [k for k in steps if k < 3]
    w_conv = None  # strain energy of the last converged state [mJ]
    if isinstance(start, EndState):
        # a turned variant: from the end state of its base variant (solve_turned), multipliers and penalties
        # carried over facet by facet where the two contact sets share a facet
        u = start.displacement_mm.astype(float)
        for p in pairs:
            if p.name not in start.contact:
                continue
            facets, lam, eps = start.contact[p.name]
            where = {f.tobytes(): i for i, f in enumerate(np.asarray(facets, dtype=np.int64))}
            mine = np.asarray(mesh.facets[_pair_sets(s)[p.name]], dtype=np.int64)
            pairs_ij = [(j, where[f.tobytes()]) for j, f in enumerate(mine) if f.tobytes() in where]
            if pairs_ij:
                j, i = np.array(pairs_ij).T
                if lam.shape[1:] != p.surf.lam.shape[1:]:
                    raise ValueError("solve_turned: the end state's multipliers do not fit this mesh's contact facets")
                p.surf.lam[j] = lam[i]
                p.eps[j] = np.maximum(p.eps[j], eps[i])
    elif start is not None:
        # the bone-rotation steps were solved once for every variant (solve_bone_rotation): go on from there
        steps = [k for k in steps if k >= 3]
        u = start.displacement_mm.astype(float)
        history = list(start.history)
        n_iter_total = start.newton_iterations
        w_conv = start.strain_energy_mJ
        for p in pairs:
            if p.name == "cast" and start.cast_lam_mpa is not None:
                if start.cast_lam_mpa.shape != p.surf.lam.shape or start.cast_eps.shape != p.eps.shape:
                    raise ValueError("solve_indentation: the bone state's cast multipliers do not fit this mesh's skin facets")
                p.surf.lam[:] = start.cast_lam_mpa
                p.eps[:] = start.cast_eps
        for name, v in (("assembly", start.assembly_s), ("solve", start.linear_solve_s), ("contact", start.contact_s)):
            timers[name] += v
    reason_fail = ""
    last_outs = [None] * len(pairs)
    t = 0.0
    Xb = X[bone_nodes]
    axis = indenter.unit_axis if indenter is not None else np.zeros(3)
    travel = 0.0
    start_backoff_mm = 0.0
    energy_floor = 1e-2 * law.mu_mpa * asm.volume_mm3  # [mJ]
    done = True
    prev = None  # (t, t_before, u_before) of the last converged increment of the indentation step
    end_passes, redo = 0, False  # end_penalty_passes done; solve the end state again
    # the rigid bone and the rigid indenter at the end of the load: if they overlap, no tissue state
    # exists (the tissue between them would have to vanish), so say so instead of solving toward it
    bone_clearance_mm = None
    infeasible = False
    if isinstance(sched, _Schedule) and (bone_clearance_mm := _bone_clearance_mm(sched, Xb)) is not None:
        infeasible = bone_clearance_mm < s.min_bone_clearance_mm
        if infeasible:
            done = False
            where = (f"{-bone_clearance_mm:.3f} mm inside the moved bone" if bone_clearance_mm < 0
                     else f"{bone_clearance_mm:.3f} mm from the moved bone")
            reason_fail = (f"infeasible: the indenter ends {where} (min_bone_clearance_mm "
                           f"{s.min_bone_clearance_mm:g}): no tissue state fits between them")
            log.warning(reason_fail)
    for k in () if infeasible else steps:
        t = float(k)
        if k == 3 and indenter is not None and not isinstance(sched, _TurnSchedule):
            start_backoff_mm = clear_start(u)
            if start_backoff_mm > 0:
                log.warning("the indenter touches the skin at its start position: start moved %.3f mm back along "
                            "its axis (%.2f mm clear)", start_backoff_mm, s.start_clearance_mm)
            travel = float(np.linalg.norm(np.subtract(sched.ind.end_mm, sched.ind.start_mm)))
        # a bone rotation alone is followed exactly by the rigid predictor: try the whole step
        dt = s.max_increment if k < 3 else s.initial_increment
        while (t < k + 1 - 1e-12 or redo) and done:
            out_of_increments = len(history) >= s.max_increments
            out_of_time = s.max_wall_s is not None and time.perf_counter() - t_wall > s.max_wall_s
            if redo and (out_of_increments or out_of_time):
                break  # the converged end state stands, without more end passes
            if out_of_increments:
                done, reason_fail = False, f"more than {s.max_increments} increments"
                break
            if out_of_time:
                done, reason_fail = False, f"wall-time budget of {s.max_wall_s:g} s spent at t = {t:.4f}"
                break
            dt = 0.0 if redo else min(dt, s.max_increment, k + 1 - t)
            # first touch: do not jump deep into contact
            if k == 3 and pairs and pairs[0].name == "indenter" and travel > 0:
                pairs[0].set_time(t)
                gmin = float(np.min(pairs[0].surf.gaps(u, pairs[0].gapfn)))
                if gmin > 0 and travel * dt > gmin + s.first_touch_mm:
                    dt = max((gmin + s.first_touch_mm) / travel, s.min_increment)
            t1 = t + dt
            t0c = dict(timers)
            # predictor: the whole limb follows the bone's rigid increment (exact for rigid motion)
            u_try = (sched.predict(X, X + u.reshape(-1, 3), t, t1) - X).ravel()
            if s.secant_predictor and k == 3 and prev is not None and prev[0] == t:
                # in contact the last increment's deformation, scaled, is a far better guess than a rigid
                # move that leaves skin deep inside the indenter (the bone part is the same: linear in t)
                u_try = u + (t1 - t) / (t - prev[1]) * (u - prev[2])
            al_backup = _al_state(pairs)
            energy_cap = None if (s.decrement_cap is None or w_conv is None) else max(s.decrement_cap * w_conv, energy_floor)
            target = np.zeros(asm.n_dofs)
            target.reshape(-1, 3)[bone_nodes] = sched.bone(Xb, t1) - Xb
            target_d = target[constrained]
            update_candidates(u_try, t1)
            # only the end of the last step is reported: the problem is path independent (hyperelastic,
            # frictionless), so the ends of the bone-rotation steps only start the next one
            step_end = t1 >= k + 1 - 1e-12 and (k == 3 or not s.loose_rotation_steps)
            rtol = s.rtol if step_end else s.rtol_intermediate
            etol = s.energy_rtol if step_end else s.energy_rtol_intermediate
            pen_tol = s.penetration_tol if step_end else s.penetration_tol_intermediate
            ok, why, iters, al, outs, residuals = False, "", 0, 0, None, []
            last_good = None  # (u, multipliers, outs) of the last converged solve in this increment
            # at a step end with contact the augmented-Lagrangian passes are solved to the intermediate
            # tolerance and only the last state is polished to the full one (one tight solve, not one per pass)
            nested = s.inexact_al and step_end and bool(pairs) and rtol < s.rtol_intermediate
            polish, pre_polish = False, None
            while True:
                if polish and pre_polish is None:
                    # the state the tight solve starts from, kept in case it stalls
                    pre_polish = (u_try.copy(), outs, _al_state(pairs))
                tol = (rtol, etol) if (polish or not nested) else (s.rtol_intermediate, s.energy_rtol_intermediate)
                max_it = s.max_iterations if (al == 0 or polish) else s.max_al_iterations
                ok, why, it, res, outs = newton(u_try, target_d, *tol, max_it, stop_on_growth=al > 0 or polish,
                                                atol=atol_intermediate if (k < 3 and s.loose_rotation_steps) else atol_final,
                                                energy_cap=energy_cap)
                iters += it
                residuals += res
                if polish:
                    if ok and missed_contact(u_try):
                        polish, pre_polish = False, None
                        continue
                    if not ok:
                        # the tight solve stalled (contact chatter on facets coarser than the indenter):
                        # keep the state converged to the intermediate tolerance, and say so
                        log.warning("final solve stalled (%s) at residual %.2e: keeping the state converged to rtol %.0e",
                                    why, res[-1] if res else float("nan"), s.rtol_intermediate)
                        u_try[:], outs, ok, why = pre_polish[0], pre_polish[1], True, ""
                        _restore_al(pairs, pre_polish[2])
                    break
                if not ok:
                    if last_good is not None:
                        # the multiplier update did not converge (e.g. a facet coarser than the
                        # indenter cannot meet every point constraint): keep the converged penalty state
                        log.warning("AL update %d did not converge (%s): keeping the penalty solution", al, why)
                        u_try[:] = last_good[0]
                        _restore_al(pairs, last_good[1])
                        outs, ok, why = last_good[2], True, ""
                        if nested:
                            polish = True
                            continue
                    break
                if missed_contact(u_try):
                    continue
                pen_mm, pen_rel = penetration(outs)
                if pen_rel <= pen_tol or not pairs:
                    if nested:
                        polish = True
                        continue
                    break
                if al >= s.max_al_updates:
                    log.warning("penetration %.3g x facet size after %d AL updates", pen_rel, al)
                    if nested:
                        polish = True
                        continue
                    break
                last_good = (u_try.copy(), _al_state(pairs), outs)
                for p, r in zip(pairs, outs):
                    if r is not None:
                        p.surf.lam[r["cand"]] = r["pressure"]
                al += 1
            n_iter_total += iters
            pen_mm = float("nan")
            n_st = 0
            if ok:
                pen_mm, pen_rel_end = penetration(outs)
                # a state whose contact is violated this much is not a solution, whatever the residual:
                # cut the increment (the fallbacks above keep penalty or loosely converged states)
                if pairs and pen_rel_end > s.penetration_accept:
                    ok, why = False, f"penetration {pen_rel_end:.2f} x facet size > {s.penetration_accept}"
                    pen_mm = float("nan")
                if pairs and pen_rel_end > pen_tol:
                    # the multiplier updates stalled: a stiffer penalty on these facets pushes them out in
                    # the following increments (and in the retry of this one if it is cut)
                    n_st = sum(p.stiffen(r, pen_tol, s.penalty_growth, s.max_penalty_growth) for p, r in zip(pairs, outs))
                    if n_st:
                        log.info("penalty x %g on %d facets penetrating more than %g x their size", s.penalty_growth, n_st, pen_tol)
            ft, fc = forces(outs) if ok else (np.zeros(3), np.zeros(3))
            rec = IncrementRecord(
                step=k + 1, t_start=t, t_end=t1, converged=ok, reason=why, iterations=iters, al_updates=al,
                residuals=tuple(residuals), tip_mm=tuple(sched.tip(t1)) if indenter is not None else (),
                indenter_force_N=float(ft @ axis), max_penetration_mm=pen_mm,
                assembly_s=timers["assembly"] - t0c["assembly"], linear_solve_s=timers["solve"] - t0c["solve"],
                contact_s=timers["contact"] - t0c["contact"],
            )
            history.append(rec)
            log.info("step %d t %.4f->%.4f %s it %d al %d F %.4g N pen %.3g mm", k + 1, t, t1,
                     "ok" if ok else f"cut ({why})", iters, al, rec.indenter_force_N, pen_mm)
            if ok:
                # (an end pass has zero length: no secant)
                prev = (t1, t, u) if k == 3 and pairs and t1 > t else None
                u = u_try
                last_outs = outs
                w_conv = energy_now[0]
                t = t1
                redo = bool(n_st) and step_end and k == 3 and end_passes < s.end_penalty_passes
                if redo:
                    end_passes += 1
                    log.info("end state penetrates %.3g x facet size: solving it again with stiffer facets (pass %d of %d)",
                             pen_rel_end, end_passes, s.end_penalty_passes)
                if iters == 0:
                    dt = s.max_increment  # the rigid predictor was exact: finish the step at once
                elif iters <= s.easy_iterations:
                    dt *= s.grow_factor
            elif redo:
                # the end state with stiffer facets did not converge: the converged one before it stands
                _restore_al(pairs, al_backup)
                log.warning("end state with stiffer facets not converged (%s): keeping the one before", why)
                redo = False
            else:
                _restore_al(pairs, al_backup)
                dt *= s.cut_factor
                if dt < s.min_increment:
                    done, reason_fail = False, f"increment below {s.min_increment} at t = {t:.4f} ({why})"
        if not done:
            break
    solver.close()
    counts.update(getattr(solver, "counters", {}))  # PardisoSymmetric's (the other solvers count nothing)
    log.info("solve %s in %.1f s: %d Newton iterations, %s", "converged" if done else "unconverged",
             time.perf_counter() - t_wall, n_iter_total, ", ".join(f"{k} {v}" for k, v in counts.items()))
    # final state
    F = asm.deformation_gradient(u)
    Fe = np.einsum("eqij,eq->eij", F, asm.w) / asm.w.sum(axis=1)[:, None, None]
    ft, fc = forces(last_outs)
    pm, pr = penetration(last_outs)
    W = asm.energy(u)
    wall = time.perf_counter() - t_wall + (start.wall_s if isinstance(start, BoneState) else 0.0)
    contact_state = {p.name: (p.surf.lam.copy(), p.eps.copy()) for p in pairs}
    return SolveResult(
        converged=done, reason=reason_fail, displacement_mm=u.reshape(-1, 3).copy(), deformation_gradient=Fe,
        history=tuple(history), indenter_force_N=float(ft @ axis), force_on_tissue_N=ft, cast_force_N=fc,
        max_penetration_mm=pm, max_penetration_rel=pr, strain_energy_mJ=float(W), n_dofs=asm.n_dofs,
        n_free_dofs=asm.n_free, increments=sum(1 for h in history if h.converged), newton_iterations=n_iter_total,
        load_reached=t, wall_s=wall, assembly_s=timers["assembly"], linear_solve_s=timers["solve"],
        contact_s=timers["contact"], extra={"attempts": 1, "straightened_tets": n_straightened, "start_backoff_mm": start_backoff_mm,
                                            "bone_clearance_mm": bone_clearance_mm, "infeasible": infeasible, "end_passes": end_passes,
                                            "contact_state": contact_state, "last_energy_mJ": w_conv,
                                            **counts},
    )
