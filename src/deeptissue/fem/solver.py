"""Quasi-static indentation of a hyperelastic limb: rigid bone motion, exact frictionless contact.

Entry points: :func:`solve_indentation`, :func:`solve_bone_rotation` (steps 1-3 once for all variants of a
mesh), :func:`solve_turned` (a variant turned from another's end state) and :func:`solve_prescribed`
(prescribed displacements, no contact: patch tests). The load parameter t runs through four steps of one
unit each: rotation of the bone about world x (t in [0, 1]), y ([1, 2]), z ([2, 3]) by the Euler angles of
``bone_motion.rotation_deg`` (deeptissue.rigid.euler_xyz_deg, so the bone ends exactly at R), then
([3, 4]) the translation together with the indenter's travel from ``start_mm`` to ``end_mm``. Steps that do
nothing are skipped. The bone facet nodes follow the rigid motion (Dirichlet on all their dofs); the limb
ends are free.

Contact with the rigid indenter and the rigid cast is imposed on weighted gaps gw_j of the skin nodes
(:class:`deeptissue.fem.contact.WeightedContact`) with multipliers lam_j [N] inside the Newton system.
Complementarity lam_j >= 0, gw_j >= 0, lam_j gw_j = 0 is the equation ``C_j = min(lam_j, c_j gw_j) = 0``
(c_j = E h_j [N/mm] scales a gap into a force); equilibrium is ``R(u, lam) = f_int(u) - G(u)^T lam = 0`` on the
free dofs (G = d gw / d u). Newton's method on (R, C) with the generalised derivative of min is the
primal-dual active-set method (Hintermueller, Ito and Kunisch 2002; Hueber and Wohlmuth 2005 for contact):
at each iteration the active set is A = {j : lam_j - c_j gw_j > 0}; an active node's linearised weighted gap
is closed, ``gw_j + G_j du = 0``, an inactive node's force is zero. Displacement, multipliers and active set
come from one symmetric saddle-point system ``[[K - sum_q A p N N H, G_A^T], [G_A, 0]]`` over the free dofs
and the active entries, solved through its augmented matrix ``K~ + G_A^T rho G_A`` of the size of the tangent
(a single-precision Cholesky factor and a few augmented-Lagrangian corrections in double precision,
:meth:`deeptissue.fem.linsolve.SymmetricSolver.solve_constrained`); they converge together,
superlinearly near the solution, with no penalty and no multiplier update loop. A non-monotone backtracking
line search on the merit 0.5 (|R|^2 + |C|^2) globalises each step; where the obstacles' curvature term makes
the consistent matrix useless (a pinch), the direction without it is tried.

An increment is converged when |R| <= rtol max(|f_int|, |G^T lam|) + atol and every candidate node satisfies
the complementarity to the gap tolerance: |min(lam_j, c_j gw_j)| <= c_j gap_tol_rel h_j (h_j the size of
the node's facets), i.e. no weighted gap is closed beyond gap_tol_rel h_j and no node pulls on the obstacle
by more than the force that would close that gap. Increments grow after few Newton iterations
and few active-set changes, shrink after many, and are cut after a failure (an inverted element, a
diverging residual, a line search without descent, too many iterations).
Units: mm, N, MPa, mJ, s.
"""

from __future__ import annotations

import json
import logging
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np
import scipy.sparse as sp

from ..mesh import TetMesh
from ..rigid import BoneMotion, euler_xyz_deg
from .assembly import Assembler, as_material_law
from .cast import Cast
from .contact import ContactSurface, WeightedContact
from .indenters import Indenter
from .linsolve import SymmetricSolver
from .progress import Progress, format_progress
from .skmesh import straighten_invalid

log = logging.getLogger(__name__)

__all__ = [
    "BoneState",
    "ContactSettings",
    "EndState",
    "FacetSets",
    "IncrementRecord",
    "IncrementSettings",
    "NewtonSettings",
    "Scene",
    "SolveResult",
    "SolverSettings",
    "end_state",
    "load_bone_state",
    "load_end_state",
    "save_bone_state",
    "save_end_state",
    "solve_bone_rotation",
    "solve_from",
    "solve_indentation",
    "solve_prescribed",
    "solve_turned",
    "solver_settings_from_config",
    "summed_costs",
]

# Fixed parts of the method (not settings: no scene has needed another value)
_ATOL_MU_REL = 1e-10  # absolute residual floor in units of mu V^(2/3) [N]
# the same before the end of the load (with rtol_intermediate): before the indenter touches, the forces are tiny
# (the tissue follows the bone, held only by the cast); those states only start the next increment
_ATOL_INTERMEDIATE_MU_REL = 1e-4
# the gap tolerance before the end of the load over the facet size (the end's gap_tol_rel where that is looser):
# those states only start the next increment. With rtol_intermediate 0.1, 5 % takes the demo's six base variants
# from their bone states in 146 Newton iterations, 1 % in 181 (the same end states); 10 % let the demo's rat01 bar
# accept a first touch 0.06 mm into the skin with no contact force and pass through it in the next increment
_GAP_TOL_INTERMEDIATE_REL = 5e-2
# a converged increment whose facets dip deeper than this into an obstacle between their nodes (over the facet size)
# has let the indenter pass between the skin's nodes (a coarse mesh: the weighted gaps close at the nodes only); it
# is cut back. Converged states of the demo, the paper study and the hard cases dip 2-5 % of a facet, flat (P1)
# facets of 2 mm on the 1.5 mm sphere 25 %; in the pinch of config/bone_at_indenter.yaml's gap005 an increment
# that dipped 44 % had the force fall from 0.45 to 0.37 N as the indenter advanced (the sphere through the skin)
_MAX_PENETRATION_REL = 0.3
# an indenter whose end overlaps the rigidly moved skin by more than this must push on it [mm]
_THROUGH_OVERLAP_MM = 0.1
_ARMIJO = 1e-4  # sufficient decrease of the merit, as a fraction of its predicted decrease
_MAX_BACKTRACKS = 12  # step halvings before a direction is given up
_NONMONOTONE_MEMORY = 5  # the Armijo test compares with the largest of this many last merits
# a step the residual's merit shortens below this is searched again on the augmented Lagrangian (_Problem.lagrangian):
# in tissue crushed against the bone the residual rises along a Newton direction on which the energy falls (the
# 45 deg bar of the hard cases kept 1/256-1/2048 of each step for 25 iterations at a fixed active set)
_SHORT_STEP = 0.125
# an increment whose merit this many Newton iterations after the bone reached its target is not below its merit there
# has left Newton's region of convergence and is cut back at once: on the demo's finer meshes a whole 15 deg turn of
# the sphere rose from 3.8e-5 to 1.5-4.6e-4 within 8 iterations and ran on to the 25-iteration limit (rat03's
# sphere_rz-15: 25 iterations, 128 s), while its thirds converged in 5, 3 and 5 iterations. Tested once, when the
# window closes: a merit that fell below its start within it may rise above it again on the way to the solution
# (deep3's sphere_rx-15 of config/bone_at_indenter.yaml: above at iteration 12 of an increment that converges in 18)
_PROGRESS_ITERATIONS = 8
# a turn's first increment moves the indenter's surface at the skin nodes it presses on by at most this many facet
# sizes (:func:`_first_turn`): a 15 deg turn of the 3 mm sphere about its tip moves it up to about 0.3 mm, 0.3 of a
# facet on the demo's first adaptive pass (whole turns: 5-6 Newton iterations, halves 7-10) and about one facet on
# the second (rat01 sphere_rx-15, rat02 sphere_rz-15, rat03 sphere_rz-15: 20, 17 and 21 iterations whole, 11 each
# in halves)
_TURN_STEP_FACETS = 0.5
# the augmented Lagrangian's penalty on a weighted gap, in units of the entry's c = E h: the Newton direction of an
# SPD tangent descends on it (its slope is checked), and it stays below the crushed elements' stiffness
_LAGRANGIAN_PENALTY = 10.0
# an increment this easy lets the next grow by _GROW: at most this many Newton iterations, and at most this fraction
# of the contact entries changing state, within its iterations or from its start to its end (loose intermediate
# states converge in one or two iterations while the contact area grows fast: on the 30 deg bar of the hard cases
# the increments doubled into the pinch, where they took 9, 18 and 25 iterations)
_EASY_ITERATIONS, _EASY_CHANGES_REL = 5, 0.25
_HARD_ITERATIONS = 10  # one that needs more shrinks the next by _SHRINK
_GROW, _SHRINK, _CUT = 2.0, 0.7, 0.35
# the augmentation of the Newton system's constraints, in units of the stiffness they meet: each augmented-
# Lagrangian correction of the linear solve gains about log10 of it in digits (a single-precision Cholesky of
# the augmented matrix still succeeds at 1e4 and fails at 1e6 on a limb)
_AUGMENTATION = 1e3
_REPORT_QUADRATURE_ORDER = 4  # facet quadrature on which the penetration between nodes is reported
# a quadrature point compressed below this volume ratio counts as crushed in the log of a cut increment: in the
# stalled pinch of the hard cases one element reaches 0.05 while 11-13 are below 0.2
_CRUSHED_J = 0.2
# a Newton step may lower det F at a quadrature point to this fraction of its value at most (a fraction-to-the-
# boundary rule, as interior-point methods keep their iterates inside the domain): the volumetric energy
# (J - 1)^2 / D stays finite as J -> 0, so nothing else keeps a step from crushing an element, which Newton then
# takes many short steps to undo. On the demo's rat02 bar at 75 615 DOFs the first step of the increment
# t 3.637 -> 3.802 raised the residual from 0.015 N to 30 N and the increment ended at the 25-iteration limit;
# with a bound of 0.1 or 0.25 it converges in 7 iterations. 0.25 also held back legitimate steps: rat02's
# sphere_rz+15, turned whole from its sphere's end state at 48 984 DOFs, ran to the 25-iteration limit
# instead of converging in 13 (as it does with 0.1 or no bound)
_STEP_DET_FRACTION = 0.1


@dataclass(frozen=True)
class NewtonSettings:
    """rtol: equilibrium residual over max(|internal force|, |contact force|) at the end of the load;
    rtol_intermediate: the same inside the indentation step and at the ends of the bone-rotation steps
    (the problem is path independent: only the end state needs accuracy); max_iterations: Newton iterations before an increment is cut back."""

    rtol: float = 1e-6
    rtol_intermediate: float = 0.1
    max_iterations: int = 25

    def __post_init__(self):
        if not (0 < self.rtol <= self.rtol_intermediate < 1) or self.max_iterations < 1:
            raise ValueError(
                f"NewtonSettings: need 0 < rtol <= rtol_intermediate < 1 and max_iterations >= 1, got {self}"
            )


@dataclass(frozen=True)
class IncrementSettings:
    """initial_increment: the indentation step's first increment (a fraction of the step; a bone-rotation step
    is tried whole: the rigid predictor follows it); max_increment: the largest (below 1 only to record a
    force-depth curve at more points); min_increment: the smallest before the solve gives up;
    max_increments: increments (attempts) per solve; first_touch_mm: the increment where the indenter first
    touches advances it at most this far past the first contact [mm]; start_clearance_mm: an indenter that
    touches the skin at its start is moved back along its axis until this clear [mm]; turn_initial_increment:
    the largest first increment of a turn from a base variant's end state (:func:`solve_turned`), a fraction of
    the turn, shortened where the indenter's surface would move more than half a facet at the pressed skin
    nodes (:func:`_first_turn`; 1: a turn that moves it less goes whole, cut back where it fails).

    A solve that creeps stops by itself with its reason, the load reached and its last converged state: when the
    load (t, 0-4) has advanced by no more than stall_load over the last stall_increments attempted increments,
    or over the last stall_wall_s seconds (None: no such window), or three times the slowest converged
    increment's wall time where that is longer. 1e-3 of the indentation step is 3 um of a 3 mm
    travel; 12 attempts is more than the cuts from a full step down to min_increment (8), so a solve stops there
    only when it alternates tiny accepted increments with failed long ones; 300 s is about four times the
    longest increment the demo's adaptive passes converge (68 s, docs/solver.md), so a study never spends
    more than that on a variant after it stops advancing; on a finer mesh whose converged increments take
    longer the window grows with them."""

    initial_increment: float = 0.25
    max_increment: float = 1.0
    min_increment: float = 1e-4
    max_increments: int = 400
    first_touch_mm: float = 0.1
    start_clearance_mm: float = 0.1
    turn_initial_increment: float = 1.0
    stall_increments: int = 12
    stall_load: float = 1e-3
    stall_wall_s: float | None = 300.0

    def __post_init__(self):
        if not (
            0 < self.min_increment <= self.initial_increment <= self.max_increment <= 1
            and self.min_increment <= self.turn_initial_increment <= 1
            and 1 <= self.stall_increments < np.inf
            and 0 <= self.stall_load < np.inf
            and (self.stall_wall_s is None or 0 < self.stall_wall_s < np.inf)
        ):
            raise ValueError(
                "IncrementSettings: need 0 < min_increment <= initial_increment <= max_increment <= 1, "
                "min_increment <= turn_initial_increment <= 1, stall_increments >= 1, a finite stall_load >= 0 "
                f"and a finite stall_wall_s > 0 or None, got {self}"
            )


@dataclass(frozen=True)
class ContactSettings:
    """gap_tol_rel: the complementarity tolerance as a weighted penetration over the node's facet size (the
    accuracy statement of a converged state); candidate_distance_rel: nodes closer than this many largest facet
    sizes to the indenter at the start of an increment are tested for contact; cast_candidate_distance_mm: the
    same for the cast [mm] (the skin starts a cast offset away from it everywhere); nodes outside the
    candidates are checked for penetration at convergence and the increment is solved again with them."""

    gap_tol_rel: float = 1e-3
    candidate_distance_rel: float = 2.0
    cast_candidate_distance_mm: float = 0.1

    def __post_init__(self):
        if not (
            self.gap_tol_rel > 0
            and self.candidate_distance_rel > 0
            and self.cast_candidate_distance_mm > 0
        ):
            raise ValueError(f"ContactSettings: every value must be > 0, got {self}")


@dataclass(frozen=True)
class SolverSettings:
    """All settings of the solver (config ``fem.solver``): ``newton``, ``increments``, ``contact``;
    quadrature_order: the volume quadrature (2: 4 points per tet, exact for a quadratic tet's small-strain
    stiffness); min_bone_clearance_mm: a solve whose indenter ends closer than this to the moved bone
    (negative: inside it) is not started (no tissue state fits between two overlapping rigid bodies);
    max_wall_s: wall-time budget of one solve [s] (None: none), checked between increments."""

    newton: NewtonSettings = field(default_factory=NewtonSettings)
    increments: IncrementSettings = field(default_factory=IncrementSettings)
    contact: ContactSettings = field(default_factory=ContactSettings)
    quadrature_order: int = 2
    min_bone_clearance_mm: float = 0.0
    max_wall_s: float | None = None


_GROUPS = {"newton": NewtonSettings, "increments": IncrementSettings, "contact": ContactSettings}


def solver_settings_from_config(solver_cfg: dict | None) -> SolverSettings:
    """SolverSettings from the ``fem.solver`` config section (its groups ``newton``, ``increments``,
    ``contact`` and the top-level keys); unknown keys raise ValueError naming them."""
    cfg = dict(solver_cfg or {})
    top = {f.name for f in fields(SolverSettings)} - set(_GROUPS)
    bad = sorted(set(cfg) - top - set(_GROUPS))
    if bad:
        raise ValueError(f"fem.solver: unknown keys {bad} (known: {sorted(top | set(_GROUPS))})")
    kw = {k: cfg[k] for k in top if k in cfg}
    for name, cls in _GROUPS.items():
        sub = dict(cfg.get(name) or {})
        known = {f.name for f in fields(cls)}
        bad = sorted(set(sub) - known)
        if bad:
            raise ValueError(f"fem.solver.{name}: unknown keys {bad} (known: {sorted(known)})")
        kw[name] = cls(**sub)
    return SolverSettings(**kw)


@dataclass(frozen=True)
class FacetSets:
    """The mesh's facet sets the solver uses: ``bone`` (moved rigidly), ``indenter`` (the skin facets that can
    touch the indenter: a variant's contact patch) and ``cast`` (the skin facets that can touch the cast)."""

    bone: str = "bone"
    indenter: str = "patch"
    cast: str = "skin"


@dataclass(frozen=True)
class IncrementRecord:
    step: int  # 1..4: rotation x, y, z, translation + indentation
    t_start: float
    t_end: float
    converged: bool
    reason: str  # "" if converged, else why it was cut
    iterations: int
    active_set_changes: (
        int  # entries that entered or left the active set after the first iteration
    )
    residuals: tuple  # residual norms [N] of the Newton iterations
    tip_mm: tuple
    indenter_force_N: float
    max_penetration_mm: float  # between the nodes, on the facets of the contact candidates
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
    max_penetration_rel: largest penetration at a facet quadrature point between the nodes [mm] / over
    facet size. load_reached: load parameter reached (4 = done). Times in s: wall, assembly (material),
    linear_solve, contact. ``extra``: 'active_nodes' (count per obstacle), 'active_nodes_per_increment',
    'active_set_changes', 'node_penetration_rel' (deepest weighted gap over its facet size),
    'contact_entries' (per node and obstacle: node, obstacle, lam_N, weighted_gap_mm, h_mm),
    'contact_state' (per obstacle name: (nodes, lam_N)), 'min_force_N', 'infeasible', 'bone_clearance_mm',
    'start_backoff_mm', 'started_from_bone_state', 'straightened_tets', 'linear_solver' (the backend and its
    counters: symbolic analyses, factorisations, double-precision fallbacks, refinements).
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

    displacement_mm (n_dofs,); contact: obstacle name ('cast') -> (nodes, lam_N) of the entries with a nonzero multiplier;
    strain_energy_mJ of the state; history, newton_iterations and the times [s] of the steps that made it
    (a variant started from it reports them as its own, so its figures stay those of a whole solve);
    settings: the SolverSettings it was solved with (a start is only used by a solve with the same ones).
    """

    displacement_mm: np.ndarray
    contact: dict
    strain_energy_mJ: float
    history: tuple
    newton_iterations: int
    wall_s: float
    assembly_s: float
    linear_solve_s: float
    contact_s: float
    settings: SolverSettings


@dataclass(frozen=True)
class EndState:
    """The converged end state (t = 4) of one variant: the start of a variant that differs from it only by
    a turn of the indenter about the same final tip (:func:`solve_turned`).

    displacement_mm (n_dofs,); contact: obstacle name ('indenter', 'cast') -> (nodes, lam_N) of the entries with
    a nonzero multiplier; indenter: the Indenter it was solved with; bone_motion: its BoneMotion; settings: its SolverSettings.
    """

    displacement_mm: np.ndarray
    contact: dict
    indenter: Indenter
    bone_motion: BoneMotion
    settings: SolverSettings


def _contact_arrays(contact: dict) -> dict:
    return {
        k: v
        for name, (nodes, lam) in contact.items()
        for k, v in ((f"{name}_nodes", nodes), (f"{name}_lam_N", lam))
    }


def _write_state(path, displacement_mm, contact: dict, meta: dict) -> None:
    from ..io import atomic_path

    arrays = dict(
        displacement_mm=displacement_mm,
        meta=np.array(json.dumps({**meta, "obstacles": sorted(contact)})),
        **_contact_arrays(contact),
    )
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def _read_state(path):
    with np.load(path) as d:
        meta = json.loads(str(d["meta"]))
        contact = {n: (d[f"{n}_nodes"], d[f"{n}_lam_N"]) for n in meta["obstacles"]}
        return d["displacement_mm"], contact, meta


def _tuples(d: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


def save_bone_state(path, state: BoneState) -> None:
    """Write a BoneState as .npz (arrays, and the rest as JSON), atomically."""
    meta = dict(
        strain_energy_mJ=state.strain_energy_mJ,
        newton_iterations=state.newton_iterations,
        wall_s=state.wall_s,
        assembly_s=state.assembly_s,
        linear_solve_s=state.linear_solve_s,
        contact_s=state.contact_s,
        history=[asdict(h) for h in state.history],
        settings=asdict(state.settings),
    )
    _write_state(path, state.displacement_mm, state.contact, meta)


def load_bone_state(path) -> BoneState:
    """Read :func:`save_bone_state`'s file; ValueError naming the file if it is not one."""
    try:
        u, contact, meta = _read_state(path)
        return BoneState(
            displacement_mm=u,
            contact=contact,
            strain_energy_mJ=float(meta["strain_energy_mJ"]),
            history=tuple(IncrementRecord(**_tuples(h)) for h in meta["history"]),
            newton_iterations=int(meta["newton_iterations"]),
            wall_s=float(meta["wall_s"]),
            assembly_s=float(meta["assembly_s"]),
            linear_solve_s=float(meta["linear_solve_s"]),
            contact_s=float(meta["contact_s"]),
            settings=solver_settings_from_config(meta["settings"]),
        )
    except (KeyError, OSError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: not a bone-state file ({type(exc).__name__}: {exc})") from exc


def end_state(
    result: SolveResult,
    mesh: TetMesh,
    *,
    indenter: Indenter,
    bone_motion: BoneMotion,
    settings: SolverSettings,
) -> EndState | None:
    """The EndState of a converged :func:`solve_indentation` result (None if it did not converge)."""
    if not result.converged:
        return None
    return EndState(
        displacement_mm=result.displacement_mm.ravel().copy(),
        contact=dict(result.extra["contact_state"]),
        indenter=indenter,
        bone_motion=bone_motion,
        settings=settings,
    )


def save_end_state(path, state: EndState) -> None:
    """Write an EndState as .npz (arrays, and the rest as JSON), atomically."""
    meta = dict(
        indenter=asdict(state.indenter),
        bone_motion=asdict(state.bone_motion),
        settings=asdict(state.settings),
    )
    _write_state(path, state.displacement_mm, state.contact, meta)


def load_end_state(path) -> EndState:
    """Read :func:`save_end_state`'s file; ValueError naming the file if it is not one."""
    try:
        u, contact, meta = _read_state(path)
        return EndState(
            displacement_mm=u,
            contact=contact,
            indenter=Indenter(**_tuples(meta["indenter"])),
            bone_motion=BoneMotion(**_tuples(meta["bone_motion"])),
            settings=solver_settings_from_config(meta["settings"]),
        )
    except (KeyError, OSError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: not an end-state file ({type(exc).__name__}: {exc})") from exc


def summed_costs(*results: SolveResult) -> dict:
    """The Newton iterations and the assembly, linear-solve and contact seconds of several tries of one solve,
    summed (for ``dataclasses.replace`` of the result reported; its wall time is the caller's)."""
    return {
        k: sum(getattr(r, k) for r in results)
        for k in ("newton_iterations", "assembly_s", "linear_solve_s", "contact_s")
    }


# ------------------------------------------------------------------------------------------- load schedules


class _Schedule:
    """The bone's rigid motion and the indenter's travel as functions of the load t in [0, 4]."""

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
        return [k for k in range(3) if abs(self.ang[k]) > 0] + [3]

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
        a = (
            self.a0 * np.cos(s)
            + np.cross(self.k, self.a0) * np.sin(s)
            + self.k * (self.k @ self.a0) * (1 - np.cos(s))
        )
        return replace(self.ind, axis=tuple(a))


class _Prescribed:
    """A prescribed displacement fn(X, s) of the constrained nodes over the one step t 3 -> 4 (s = t - 3)."""

    ind = None

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

    def indenter(self, t):
        return None


def _bone_clearance_mm(sched, Xb: np.ndarray) -> float | None:
    """Smallest gap [mm] between the indenter at the end of its travel and the bone's nodes Xb (n, 3) at
    their final (moved) position; None without an indenter or bone nodes."""
    if sched.ind is None or not len(Xb):
        return None
    return float(np.min(sched.indenter(4.0).gap(sched.bone(Xb, 4.0), sched.tip(4.0))[0]))


def _skin_overlap_mm(sched, X: np.ndarray, u: np.ndarray, t: float) -> float:
    """How far [mm] the indenter at the end of its travel overlaps the skin nodes X (n, 3), displaced by u
    (n, 3) at load t and moved on rigidly with the bone; an end state with that overlap and no indenter force has
    let the tissue through the indenter."""
    x_end = sched.predict(X, X + u, t, 4.0)
    return -float(np.min(sched.indenter(4.0).gap(x_end, sched.tip(4.0))[0]))


# ------------------------------------------------------------------------------------------- entry points


def solve_indentation(
    mesh: TetMesh,
    *,
    material,
    indenter: Indenter | None,
    bone_motion: BoneMotion,
    cast: Cast | None = None,
    settings: SolverSettings = SolverSettings(),
    sets: FacetSets = FacetSets(),
    start: BoneState | None = None,
) -> SolveResult:
    """Solve the indentation of ``mesh`` (TetMesh, mm) and return a :class:`SolveResult`.

    material: an Ogden parameter set (deeptissue.fem.material.Ogden) or an assembly.MaterialLaw.
    indenter: Indenter (contact with the ``sets.indenter`` facets) or None.
    bone_motion: BoneMotion of the ``sets.bone`` facets (Dirichlet on all their dofs).
    cast: a Cast (contact with the ``sets.cast`` facets) or None.
    start: a BoneState of this mesh, bone motion and cast (:func:`solve_bone_rotation`): with the same
    settings the solve starts from it at t = 3 instead of solving the bone rotation again.
    Never raises for non-convergence: returns converged=False with the reason and the last converged
    state. Raises ValueError for missing facet sets or a start of another mesh.
    """
    if start is not None and start.displacement_mm.shape != (3 * len(mesh.nodes_mm),):
        raise ValueError(
            f"solve_indentation: the bone state has {start.displacement_mm.size} displacement dofs, "
            f"the mesh {3 * len(mesh.nodes_mm)}: not this mesh's state"
        )
    use = start if start is not None and _path(start.settings) == _path(settings) else None
    return _solve(
        _SolveJob(
            mesh,
            material=material,
            indenter=indenter,
            schedule=_Schedule(bone_motion, indenter),
            bc_sets=(sets.bone,),
            cast=cast,
            settings=settings,
            sets=sets,
            start=use,
        )
    )


def _path(s: SolverSettings) -> SolverSettings:
    """The settings that decide a solve's path: without its budgets (wall time, stall guards), which only
    decide where it stops."""
    inc = replace(s.increments, stall_increments=1, stall_load=0.0, stall_wall_s=None)
    return replace(s, max_wall_s=None, increments=inc)


def solve_bone_rotation(
    mesh: TetMesh,
    *,
    material,
    bone_motion: BoneMotion,
    cast: Cast | None = None,
    settings: SolverSettings = SolverSettings(),
    sets: FacetSets = FacetSets(),
) -> tuple[SolveResult, BoneState | None]:
    """The bone-rotation steps alone (t 0 -> 3, no indenter): (result, BoneState), the state None if they
    did not converge. Every variant on this mesh with these settings can start from the state
    (``solve_indentation(..., start=state)``) and takes the same path as if it had solved them itself."""
    r = _solve(
        _SolveJob(
            mesh,
            material=material,
            indenter=None,
            schedule=_Schedule(bone_motion, None),
            bc_sets=(sets.bone,),
            cast=cast,
            settings=settings,
            sets=sets,
            rotation_only=True,
        )
    )
    if not r.converged:
        return r, None
    return r, BoneState(
        displacement_mm=r.displacement_mm.ravel().copy(),
        contact=dict(r.extra["contact_state"]),
        strain_energy_mJ=r.strain_energy_mJ,
        history=r.history,
        newton_iterations=r.newton_iterations,
        wall_s=r.wall_s,
        assembly_s=r.assembly_s,
        linear_solve_s=r.linear_solve_s,
        contact_s=r.contact_s,
        settings=settings,
    )


def solve_turned(
    mesh: TetMesh,
    *,
    material,
    base: EndState,
    indenter: Indenter,
    cast: Cast | None = None,
    settings: SolverSettings = SolverSettings(),
    sets: FacetSets = FacetSets(),
) -> SolveResult:
    """Solve a variant whose indenter differs from the one of ``base`` (a converged end state on this mesh,
    :func:`end_state`) only by a turn about the same final tip: from that state (displacement and contact
    forces), with the bone at its final pose, the indenter is turned about its final tip to ``indenter``'s
    axis in increments (one load step). Hyperelastic and frictionless, the end state does not depend on the
    path, so this is the variant's end state, reached without solving its indentation from the start. Never
    raises for non-convergence (the caller then solves the variant from the start); ValueError if
    ``indenter`` is not such a turn of ``base.indenter`` or the state is not of this mesh."""
    a, b = base.indenter, indenter
    if (a.kind, a.radius_mm, a.bar_length_mm) != (
        b.kind,
        b.radius_mm,
        b.bar_length_mm,
    ) or not np.allclose(a.end_mm, b.end_mm, rtol=0.0, atol=1e-9):
        raise ValueError(f"solve_turned: {b} is not a turn of {a} about its final tip")
    if base.displacement_mm.shape != (3 * len(mesh.nodes_mm),):
        raise ValueError(
            f"solve_turned: the end state has {base.displacement_mm.size} displacement dofs, the mesh "
            f"{3 * len(mesh.nodes_mm)}: not this mesh's state"
        )
    inc = settings.increments
    inc = replace(inc, initial_increment=min(inc.turn_initial_increment, inc.max_increment))
    turn = replace(settings, increments=inc)
    r = _solve(
        _SolveJob(
            mesh,
            material=material,
            indenter=indenter,
            schedule=_TurnSchedule(base.bone_motion, a, b),
            bc_sets=(sets.bone,),
            cast=cast,
            settings=turn,
            sets=sets,
            start=base,
        )
    )
    return replace(r, extra={**r.extra, "turned": True})


@dataclass(frozen=True)
class Scene:
    """What a variant's solve loads: the tissue ``material`` law, the rigid ``indenter``, the ``bone_motion``
    (identity by default: the bone held), an optional rigid ``cast``, and the facet ``sets`` the indenter,
    bone and cast act on."""

    material: object
    indenter: Indenter
    bone_motion: BoneMotion = BoneMotion()
    cast: Cast | None = None
    sets: FacetSets = FacetSets()


def solve_from(
    mesh: TetMesh,
    scene: Scene,
    *,
    base: EndState | None = None,
    start: BoneState | None = None,
    settings: SolverSettings = SolverSettings(),
) -> SolveResult:
    """Solve ``scene`` on ``mesh`` from the nearest converged state there is: from ``base``
    (:func:`solve_turned`: an end state on this mesh whose indenter turns about the same final tip into the
    scene's indenter), and from ``start`` (:func:`solve_indentation`) where
    there is no base or that solve does not converge. The costs of a try that did not converge are added to
    the result's; its reason is ``extra['turn_failed']``, and ``extra['turned']`` says whether the base was
    used."""
    first = None
    if base is not None:
        first = solve_turned(
            mesh,
            material=scene.material,
            base=base,
            indenter=scene.indenter,
            cast=scene.cast,
            settings=settings,
            sets=scene.sets,
        )
        if first.converged:
            return first
        log.warning(
            "solving from the given end state did not converge (%s): solving from the start",
            first.reason,
        )
    r = solve_indentation(
        mesh,
        material=scene.material,
        indenter=scene.indenter,
        bone_motion=scene.bone_motion,
        cast=scene.cast,
        settings=settings,
        sets=scene.sets,
        start=start,
    )
    if first is None:
        return r
    return replace(
        r,
        **summed_costs(r, first),
        wall_s=r.wall_s + first.wall_s,
        extra={**r.extra, "turn_failed": first.reason},
    )


def solve_prescribed(
    mesh: TetMesh,
    *,
    material,
    bc_sets,
    displacement_mm,
    settings: SolverSettings = SolverSettings(),
) -> SolveResult:
    """Solve with a prescribed displacement on the nodes of facet sets ``bc_sets`` (no contact).

    displacement_mm(X (n, 3), s) -> (n, 3) [mm]: displacement at load fraction s in [0, 1].
    Used for patch tests and homogeneous deformations.
    """
    return _solve(
        _SolveJob(
            mesh,
            material=material,
            indenter=None,
            schedule=_Prescribed(displacement_mm),
            bc_sets=tuple(bc_sets),
            cast=None,
            settings=settings,
            sets=FacetSets(),
        )
    )


# ------------------------------------------------------------------------------------------- the solve


class _Problem:
    """The fixed parts of one solve: settings, assembler, contact, linear solver, timers."""

    def __init__(
        self,
        s: SolverSettings,
        asm: Assembler,
        contact: WeightedContact,
        constrained: np.ndarray,
        force_unit_N: float,
    ):
        self.s, self.asm, self.contact, self.constrained = s, asm, contact, constrained
        self.gap_tol = s.contact.gap_tol_rel * contact.h  # [mm]
        self.gap_tol_intermediate = (
            max(s.contact.gap_tol_rel, _GAP_TOL_INTERMEDIATE_REL) * contact.h
        )
        self.atol = _ATOL_MU_REL * force_unit_N
        self.atol_intermediate = _ATOL_INTERMEDIATE_MU_REL * force_unit_N
        self.fmap = np.full(
            asm.n_dofs, -1, np.int64
        )  # dof -> row of the free dofs (-1: prescribed)
        self.fmap[asm.free] = np.arange(asm.n_free)
        self.solver = SymmetricSolver()
        self.timers = dict(assembly=0.0, solve=0.0, contact=0.0)
        self.last = None  # (f, gw, fc) of the last finite merit evaluation
        self.min_det: np.ndarray | float = 0.0  # the merits' bound on det F (E, Q): step_bound

    @contextmanager
    def step_bound(self, u: np.ndarray):
        """Within the block, the merits refuse a point whose det F is at or below _STEP_DET_FRACTION of its
        value at u at any quadrature point (outside it, only an inverted one); yields the smallest det F at
        u."""
        det = self.asm.det_f(u)
        self.min_det = _STEP_DET_FRACTION * det
        try:
            yield float(det.min())
        finally:
            self.min_det = 0.0

    def weighted(self, u, lam, curvature=True):
        tc = time.perf_counter()
        out = self.contact.weighted(u, self.contact.cand, lam, curvature=curvature)
        self.timers["contact"] += time.perf_counter() - tc
        return out

    def merit(self, u, lam):
        """0.5 (|R_free|^2 + |C|^2) at (u, lam), R = f_int - G^T lam, C = min(lam, c gw); inf if det F falls to
        the step's bound anywhere (:meth:`step_bound`; 0 outside a line search). The internal force, weighted
        gaps and contact force of the last finite evaluation are kept in ``last``
        (the line search's last evaluation is the point it accepts: the next iteration's test of convergence
        reads them instead of assembling a tangent it may not need)."""
        ta = time.perf_counter()
        _, f = self.asm.force(u, self.min_det)
        self.timers["assembly"] += time.perf_counter() - ta
        self.last = None
        if f is None:
            return np.inf
        gw, _, _, fc = self.weighted(u, lam, curvature=False)
        R = (f - fc)[self.asm.free]
        C = self.contact.ncp(lam, gw)
        self.last = (f, gw, fc)
        return 0.5 * (float(R @ R) + float(C @ C))

    def lagrangian(self, u, lam):
        """Rockafellar's augmented Lagrangian of the energy and the contact constraints at (u, lam) [mJ]:
        ``W(u) + sum_j psi(gw_j, lam_j)``, psi = -lam g + rho g^2 / 2 where lam - rho g > 0, else -lam^2 / (2 rho),
        rho = _LAGRANGIAN_PENALTY c; inf where :meth:`merit` is."""
        ta = time.perf_counter()
        W = self.asm.energy(u, self.min_det)
        self.timers["assembly"] += time.perf_counter() - ta
        if not np.isfinite(W):
            return np.inf
        gw = self.weighted(u, None)[0]  # the gaps only: no contact force
        return W + float(np.sum(self._psi(gw, lam)[0]))

    def _psi(self, gw, lam):
        """psi (E,) of :meth:`lagrangian` and its derivatives by g and by lam (0 outside the candidates)."""
        fin = np.isfinite(gw)
        g = np.where(fin, gw, 0.0)
        rho = _LAGRANGIAN_PENALTY * self.contact.c
        on = fin & (lam - rho * g > 0)
        psi = np.where(
            on, -lam * g + 0.5 * rho * g * g, np.where(fin, -lam * lam / (2.0 * rho), 0.0)
        )
        return (
            psi,
            np.where(on, rho * g - lam, 0.0),
            np.where(on, -g, np.where(fin, -lam / rho, 0.0)),
        )

    def lagrangian_slope(self, f, gw, G, lam, du, dlam):
        """Derivative of :meth:`lagrangian` along (du, dlam) at the point of internal force f, weighted gaps gw
        and their derivative G (COO)."""
        rows, cols, vals = G
        dg = np.bincount(rows, weights=vals * du[cols], minlength=len(gw))
        _, d_g, d_lam = self._psi(gw, lam)
        return float(f @ du) + float(d_g @ dg + d_lam @ dlam)


def _line_search(merit, u, lam, du, dlam, ref, slope, whole=False):
    """The longest step 1, 1/2, ... (at most _MAX_BACKTRACKS halvings) with merit(step) <= ref + _ARMIJO step
    slope, or None; ``whole``: the first step whose merit is finite."""
    step = 1.0
    for _ in range(_MAX_BACKTRACKS):
        phi = merit(u + step * du, lam + step * dlam)
        if np.isfinite(phi) and (whole or phi <= ref + _ARMIJO * step * slope):
            return step
        step *= 0.5
    return None


def _solve_increment(p: _Problem, u, lam, target_d, rtol, atol, gap_tol):
    """Solve one increment in place on (u, lam) by semi-smooth Newton with a line search, to the equilibrium
    tolerances ``rtol``, ``atol`` [N] and the complementarity tolerance ``gap_tol`` [mm].
    Returns (ok, reason, iterations, residuals, active-set changes)."""
    s, asm, contact = p.s, p.asm, p.contact
    residuals, changes, merits = [], 0, []
    start_merit, start_it = None, 0
    act = lam > 0
    p.last = None
    for it in range(s.newton.max_iterations + 1):
        if p.last is None:  # the increment's first iteration: a tangent is needed
            W, f, data, Ke_bc = _tangent(p, u)
            if not np.isfinite(W):
                return False, "inverted element", it, residuals, changes
            gw, G, geo, fc = p.weighted(u, lam)
        else:  # after a step: the line search's last merit evaluation is this point's force and gaps
            (f, gw, fc), data = p.last, None
        du_d = np.zeros(asm.n_dofs)
        du_d[p.constrained] = target_d - u[p.constrained]
        has_d = bool(np.any(np.abs(du_d) > 1e-12 * (1.0 + np.abs(target_d).max(initial=0.0))))
        if not has_d:
            u[p.constrained] = target_d
            du_d[:] = 0.0
        R = (f - fc)[asm.free]
        res = float(np.linalg.norm(R))
        residuals.append(res)
        if not np.isfinite(res):
            return False, "non-finite residual", it, residuals, changes
        C = contact.ncp(lam, gw)
        ncp_ok = bool(np.all(np.abs(C) <= contact.c * gap_tol))
        scale = max(float(np.linalg.norm(f[asm.free])), float(np.linalg.norm(fc[asm.free])))
        if not has_d and ncp_ok and res <= rtol * scale + atol:
            return True, "", it, residuals, changes
        if it == s.newton.max_iterations:
            return False, "too many iterations", it, residuals, changes
        if len(residuals) > 3 and res > 1e3 * min(residuals[1:]):
            return False, "diverging", it, residuals, changes
        if data is None:
            _, f, data, Ke_bc = _tangent(p, u)
            gw, G, geo, fc = p.weighted(u, lam)
        lin = _Linearisation(data=data, Ke_bc=Ke_bc, f=f, gw=gw, G=G, geo=geo)
        new_act = (
            contact.cand
            & np.isfinite(gw)
            & (lam - contact.c * np.where(np.isfinite(gw), gw, 0.0) > 0)
        )
        if it > 0:
            changes += int(np.count_nonzero(new_act != act))
        act = new_act
        phi0 = 0.5 * (float(R @ R) + float(C @ C))
        merits.append(phi0)
        if start_merit is None and not has_d:
            start_merit, start_it = phi0, it  # the bone at its target: progress counts from here
        if (
            start_merit is not None
            and it - start_it == _PROGRESS_ITERATIONS
            and phi0 >= start_merit
        ):
            return False, f"no progress in {it} iterations", it, residuals, changes
        # non-monotone Armijo test (Grippo, Lampariello and Lucidi 1986) against the largest of the last few
        # merits: a change of the active set may raise the merit for one step on the way to the solution
        phi_ref = max(merits[-_NONMONOTONE_MEMORY:])
        # the consistent direction first; where the merit rises within the shortest step or the linear solve
        # fails, the direction without the obstacles' curvature (which can make the tangent indefinite in a pinch)
        step = None
        with p.step_bound(u) as min_det:
            for curvature in (1.0, 0.0):
                du, lam_new = _direction(p, lin, du_d, act, curvature=curvature)
                if du is None:
                    if curvature and geo:
                        continue
                    return False, "linear solver failed", it, residuals, changes
                dlam = lam_new - lam
                # a step that moves the bone is taken whole wherever no element inverts
                step = _line_search(p.merit, u, lam, du, dlam, phi_ref, -2.0 * phi0, whole=has_d)
                if not has_d and (step is None or step < _SHORT_STEP):
                    slope = p.lagrangian_slope(f, gw, G, lam, du, dlam)
                    if slope < 0:
                        al_step = _line_search(
                            p.lagrangian, u, lam, du, dlam, p.lagrangian(u, lam), slope
                        )
                        if al_step is not None and (step is None or al_step > step):
                            step = al_step
                            p.merit(
                                u + step * du, lam + step * dlam
                            )  # ``last``: the next iteration's force and gaps
                if step is not None or not geo:
                    break
        if step is None:
            return False, "line search failed", it, residuals, changes
        log.debug(
            "  it %d res %.3e active %d (changed %d) step %.3g min lam %.2e min det F %.3g",
            it,
            res,
            int(act.sum()),
            int(np.count_nonzero(new_act != (lam > 0))),
            step,
            float(lam_new.min(initial=0.0)),
            min_det,
        )
        u += step * du
        lam += step * dlam
    return False, "too many iterations", s.newton.max_iterations, residuals, changes


def _tangent(p: _Problem, u):
    """The assembler's (energy, internal force, tangent data, Dirichlet blocks) at u, timed."""
    ta = time.perf_counter()
    out = p.asm.tangent(u)
    p.timers["assembly"] += time.perf_counter() - ta
    return out


@dataclass(frozen=True)
class _Linearisation:
    """The solve's linearisation at one point: the tangent's data and Dirichlet blocks (Assembler.tangent), the
    internal force f (n_dofs,) [N], the candidates' weighted gaps gw (E,) [mm], their derivative G (COO triple)
    and the obstacles' curvature blocks geo (WeightedContact.weighted)."""

    data: object
    Ke_bc: object
    f: np.ndarray
    gw: np.ndarray
    G: tuple
    geo: list


def _direction(p: _Problem, lin: _Linearisation, du_d, act, curvature=1.0):
    """One semi-smooth Newton direction for active set ``act``: (du (n_dofs,), new multipliers (E,)), or
    (None, None) if the linear solve failed.

    Solves the saddle-point system of the free dofs and the active entries, ``K~ du - G_A^T lam_A = -(f + K_fd
    du_d)``, ``G_A du = -gw_A`` (K~ = K - curvature sum_q A p N N H), through its augmented matrix
    ``K~ + G_A^T diag(rho) G_A`` (:meth:`SymmetricSolver.solve_constrained`), rho_j = _AUGMENTATION times the
    median diagonal stiffness over |G_j|^2. The inactive candidates enter that matrix's pattern with zero values,
    so PARDISO's analysis is shared by every active set of an increment. An inactive entry's multiplier is zero.
    """
    asm, contact = p.asm, p.contact
    free, n_free, fmap = asm.free, asm.n_free, p.fmap
    data, Ke_bc, f, gw, G, geo = lin.data, lin.Ke_bc, lin.f, lin.gw, lin.G, lin.geo
    Kc = asm.csr(data)
    Ku = Kc.tocoo()
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
    rmap = np.full(len(contact.node), -1, np.int64)
    rmap[cand] = np.arange(len(cand))
    keep = (fmap[cols] >= 0) & (rmap[rows] >= 0)
    Gc = sp.csr_matrix(
        (vals[keep], (rmap[rows[keep]], fmap[cols[keep]])), shape=(len(cand), n_free)
    )
    a_row = act[cand]
    g2 = np.asarray(Gc.multiply(Gc).sum(axis=1)).ravel()
    rho = _AUGMENTATION * float(np.median(Kc.diagonal())) / np.where(g2 > 0, g2, 1.0)
    for on, values in ((a_row, True), (~a_row, False)):  # the inactive rows: their pattern only
        if np.any(on):
            P = sp.triu(Gc.T @ sp.diags(np.where(on, rho, 0.0)) @ Gc).tocoo()
            r_parts.append(P.row)
            c_parts.append(P.col)
            v_parts.append(P.data if values else np.zeros_like(P.data))
    A = sp.coo_matrix(
        (np.concatenate(v_parts), (np.concatenate(r_parts), np.concatenate(c_parts))),
        shape=(n_free, n_free),
    ).tocsr()
    A.sort_indices()
    bc = asm.bc_force(Ke_bc, du_d) if np.any(du_d) else np.zeros(asm.n_dofs)
    ts = time.perf_counter()
    try:
        x, lam_a = p.solver.solve_constrained(
            A, Gc[a_row], rho[a_row], -(f + bc)[free], -gw[cand][a_row]
        )
    except np.linalg.LinAlgError:
        return None, None
    finally:
        p.timers["solve"] += time.perf_counter() - ts
    du = np.zeros(asm.n_dofs)
    du[free] = x
    du[asm.constrained] = du_d[asm.constrained]
    lam_new = np.zeros(len(contact.node))
    lam_new[cand[a_row]] = lam_a
    return du, lam_new


def _start_multipliers(contact: WeightedContact, state_contact: dict) -> np.ndarray:
    """The multipliers (E,) [N] of a saved state's contact ({name: (nodes, lam_N)}) on this contact's entries
    (entries of nodes the state does not have, or of another obstacle set, start at zero)."""
    lam = np.zeros(len(contact.node))
    for name, (nodes, lam_s) in state_contact.items():
        if name not in contact.names:
            continue
        sel = np.flatnonzero(contact.obstacle == contact.names.index(name))
        mine = contact.node[sel]  # sorted (np.unique)
        idx = np.clip(np.searchsorted(mine, nodes), 0, max(len(mine) - 1, 0))
        ok = (mine[idx] == nodes) if len(mine) else np.zeros(len(nodes), bool)
        lam[sel[idx[ok]]] = np.asarray(lam_s, float)[ok]
    return lam


def _clear_start(sched, contact, k_ind, u, clearance_mm):
    """Move the indenter's start back along its axis until the skin is ``clearance_mm`` clear (starting inside
    the tissue is a jump no increment resolves; the end state, path independent, is the same); returns the
    distance moved [mm]."""
    ind, back = sched.ind, 0.0
    a = ind.unit_axis
    sel = contact.obstacle == k_ind
    x = contact.X[contact.node[sel]] + u.reshape(-1, 3)[contact.node[sel]]
    for _ in range(100):
        gmin = float(np.min(sched.indenter(3.0).gap(x, sched.tip(3.0))[0]))
        if gmin >= clearance_mm:
            break
        back += clearance_mm - gmin
        sched.ind = replace(ind, start_mm=tuple(np.asarray(ind.start_mm, float) - back * a))
    if back > 0:
        log.warning(
            "the indenter touches the skin at its start position: start moved %.3f mm back along its axis "
            "(%.2f mm clear)",
            back,
            clearance_mm,
        )
    return back


def _forces(contact, u, lam, k_ind, k_cast):
    """(force of the indenter on the tissue (3,), force of the cast on the tissue (3,)) [N]."""
    out = []
    for k in (k_ind, k_cast):
        sel = (lam != 0) & (contact.obstacle == k) if k is not None else np.zeros(len(lam), bool)
        out.append(
            contact.weighted(u, sel, np.where(sel, lam, 0.0), curvature=False)[3]
            .reshape(-1, 3)
            .sum(axis=0)
            if np.any(sel)
            else np.zeros(3)
        )
    return out[0], out[1]


def _penetration(surfaces, contact, u, which=None):
    """Largest penetration [mm] and over facet size at the facets' quadrature points (between the nodes): on
    every facet, or (``which``, entries) on the facets with a node of those entries."""
    pen_mm, pen_rel = 0.0, 0.0
    for k, name in enumerate(contact.names):
        surf, fn = surfaces[name], contact.gapfns[k]
        idx = (
            None if which is None else contact.facets_with(k, which)
        )  # the surface has the contact set's facets
        if idx is not None and not len(idx):
            continue
        gq = surf.gaps(u, fn, idx)
        pm = np.max(-np.where(np.isfinite(gq), gq, np.inf), axis=1)
        pen_mm = max(pen_mm, float(pm.max()))
        pen_rel = max(pen_rel, float(np.max(pm / (surf.h_mm if idx is None else surf.h_mm[idx]))))
    return max(pen_mm, 0.0), max(pen_rel, 0.0)


@dataclass(frozen=True)
class _SolveJob:
    """What :func:`_solve` solves: the mesh and material, the indenter (None: none) and the load schedule of the
    rigid bodies, the facet sets held by the schedule (``bc_sets``) and in contact (``sets``), the cast, the
    settings, a start state (a BoneState at t = 3 or an EndState to turn from) and whether only the
    bone-rotation steps are solved."""

    mesh: TetMesh
    material: object
    indenter: Indenter | None
    schedule: object
    bc_sets: tuple
    cast: Cast | None
    settings: SolverSettings
    sets: FacetSets
    start: BoneState | EndState | None = None
    rotation_only: bool = False


def _check_sets(job: _SolveJob) -> None:
    mesh, sets = job.mesh, job.sets
    for name, need in [
        *((b, True) for b in job.bc_sets),
        (sets.indenter, job.indenter is not None),
        (sets.cast, job.cast is not None),
    ]:
        if need and (name not in mesh.facets or len(mesh.facets[name]) == 0):
            raise ValueError(
                f"solve_indentation: mesh has no facet set {name!r} (sets: {sorted(mesh.facets)})"
            )


class _Run:
    """The state of one solve as its increments advance: the fixed problem (assembler, contact, linear solver),
    the current converged state (u, lam at load t), the history and the counters."""

    def __init__(self, job: _SolveJob):
        self.t_wall = time.perf_counter()
        self.job, s = job, job.settings
        _check_sets(job)
        mesh, self.n_straightened = straighten_invalid(job.mesh, order=s.quadrature_order)
        if self.n_straightened:
            log.warning(
                "straightened the edges of %d curved tets with a non-positive Jacobian",
                self.n_straightened,
            )
        law = as_material_law(job.material)
        X = self.X = mesh.nodes_mm
        self.bone_nodes = np.unique(np.concatenate([mesh.facets[b].ravel() for b in job.bc_sets]))
        constrained = np.zeros(X.size, bool)
        constrained[(3 * self.bone_nodes[:, None] + np.arange(3)).ravel()] = True
        self.asm = Assembler(mesh, law, constrained=constrained, intorder=s.quadrature_order)
        self.sched = job.schedule
        pair_sets = [
            (n, mesh.facets[fs])
            for n, fs, on in (
                ("indenter", job.sets.indenter, job.indenter is not None),
                ("cast", job.sets.cast, job.cast is not None),
            )
            if on
        ]
        contact = self.contact = WeightedContact(X, pair_sets, self.bone_nodes, law.young_mpa)
        self.surfaces = {
            n: ContactSurface(X, f, order=_REPORT_QUADRATURE_ORDER) for n, f in pair_sets
        }
        self.k_ind = contact.names.index("indenter") if job.indenter is not None else None
        self.k_cast = contact.names.index("cast") if job.cast is not None else None
        if self.k_cast is not None:
            contact.gapfns[self.k_cast] = job.cast.gap
        h_max = float(contact.h.max()) if len(contact.h) else 1.0
        self.cand_dist = np.where(
            contact.obstacle == self.k_cast,
            s.contact.cast_candidate_distance_mm,
            s.contact.candidate_distance_rel * h_max,
        )
        force_unit = law.mu_mpa * self.asm.volume_mm3 ** (2.0 / 3.0)
        self.p = _Problem(s, self.asm, contact, constrained, force_unit)
        self.u = np.zeros(self.asm.n_dofs)
        self.lam = np.zeros(len(contact.node))
        self.history, self.n_iter, self.total_changes = [], 0, 0
        self.active_per_increment = []  # the nodes in contact after each converged increment
        self.progress = []  # (wall time [s], load t) after each attempted increment
        self.longest_ok_s = 0.0  # wall time of the slowest converged increment [s]
        self.prev = (
            None  # (t, u, lam) before the last converged increment, for the secant predictor
        )
        self.steps = self.sched.active_steps()
        if job.rotation_only:
            self.steps = [k for k in self.steps if k < 3]
        self._take_start(job.start)
        self.Xb = X[self.bone_nodes]
        self.axis = job.indenter.unit_axis if job.indenter is not None else np.zeros(3)
        self.done, self.reason, self.t = True, "", 0.0
        self.start_backoff_mm, self.travel, self.end_overlap_mm = 0.0, 0.0, 0.0
        self.bone_clearance_mm = _bone_clearance_mm(self.sched, self.Xb)
        self.infeasible = (
            self.bone_clearance_mm is not None and self.bone_clearance_mm < s.min_bone_clearance_mm
        )
        if self.infeasible:
            c = self.bone_clearance_mm
            where = (
                f"{-c:.3f} mm inside the moved bone"
                if c < 0
                else f"{c:.3f} mm from the moved bone"
            )
            self.fail(
                f"infeasible: the indenter ends {where} (min_bone_clearance_mm "
                f"{s.min_bone_clearance_mm:g}): no tissue state fits between them"
            )
            log.warning(self.reason)

    def _take_start(self, start) -> None:
        """Start from a bone state (t = 3, every variant of the mesh) or a base variant's end state (a turn)."""
        if start is None:
            return
        self.steps = [k for k in self.steps if k >= 3]
        self.u = start.displacement_mm.astype(float).copy()
        self.lam = _start_multipliers(self.contact, start.contact)
        if isinstance(start, BoneState):
            self.history, self.n_iter = list(start.history), start.newton_iterations
            for name, v in (
                ("assembly", start.assembly_s),
                ("solve", start.linear_solve_s),
                ("contact", start.contact_s),
            ):
                self.p.timers[name] += v

    def fail(self, reason: str) -> None:
        self.done, self.reason = False, reason

    def set_time(self, t: float) -> None:
        """The indenter's gap function at load t."""
        if self.k_ind is not None:
            tip, ind = self.sched.tip(t), self.sched.indenter(t)
            self.contact.gapfns[self.k_ind] = lambda x, hessian=True: ind.gap(
                x, tip, hessian=hessian
            )

    def elapsed_s(self) -> float:
        start = self.job.start
        return (
            time.perf_counter()
            - self.t_wall
            + (start.wall_s if isinstance(start, BoneState) else 0.0)
        )


def _solve(job: _SolveJob) -> SolveResult:
    """The load steps in turn, each a loop of increments (:func:`_load_step`); then the result."""
    run = _Run(job)
    if not run.infeasible:
        for k in run.steps:
            if not _load_step(run, k):
                break
    return _result(run)


def _stop_reason(run: _Run) -> str:
    """Why the solve must stop before its next increment ('' if it need not): the increment count, the wall-time
    budget, or a load that has stopped advancing (:class:`IncrementSettings`' stall settings)."""
    s, inc = run.job.settings, run.job.settings.increments
    if len(run.history) >= inc.max_increments:
        return f"more than {inc.max_increments} increments"
    now = time.perf_counter() - run.t_wall
    if s.max_wall_s is not None and now > s.max_wall_s:
        return f"wall-time budget of {s.max_wall_s:g} s spent at t = {run.t:.4f}"
    marks = run.progress
    if len(marks) > inc.stall_increments:
        advanced = run.t - marks[-inc.stall_increments - 1][1]
        if advanced <= inc.stall_load:
            return (
                f"stalled: the load advanced {advanced:.2g} in the last {inc.stall_increments} increments "
                f"(stall_load {inc.stall_load:g}) at t = {run.t:.4f}"
            )
    # a window of stall_wall_s, or longer where the converged increments themselves take that long (fine meshes)
    window = None if inc.stall_wall_s is None else max(inc.stall_wall_s, 3.0 * run.longest_ok_s)
    if window is not None and now > window:
        then = [t for w, t in marks if w <= now - window]
        if then and run.t - then[-1] <= inc.stall_load:
            return (
                f"stalled: the load advanced {run.t - then[-1]:.2g} in the last {window:.3g} s "
                f"(stall_load {inc.stall_load:g}) at t = {run.t:.4f}"
            )
    return ""


def _load_step(run: _Run, k: int) -> bool:
    """Load step k (0-2: the bone's rotations, 3: translation and indentation) by increments; False if the
    solve stops in it (the reason in ``run.reason``)."""
    job, inc = run.job, run.job.settings.increments
    run.t = float(k)
    if k == 3 and job.indenter is not None:
        contact = run.contact
        if not isinstance(run.sched, _TurnSchedule):
            run.start_backoff_mm = _clear_start(
                run.sched, contact, run.k_ind, run.u, inc.start_clearance_mm
            )
            run.travel = float(
                np.linalg.norm(np.subtract(run.sched.ind.end_mm, run.sched.ind.start_mm))
            )
        skin = contact.node[contact.obstacle == run.k_ind]
        run.end_overlap_mm = _skin_overlap_mm(
            run.sched, run.X[skin], run.u.reshape(-1, 3)[skin], run.t
        )
    dt = inc.max_increment if k < 3 else inc.initial_increment
    if k == 3 and isinstance(run.sched, _TurnSchedule):
        dt = min(dt, _first_turn(run))
    run.prev = None
    cut = False  # an increment of this step has been cut back
    while run.t < k + 1 - 1e-12:
        why = _stop_reason(run)
        if why:
            run.fail(why)
            log.warning(why)
            return False
        dt = _first_touch(run, k, min(dt, inc.max_increment, k + 1 - run.t))
        ok, why, iters, changes = _increment(run, k, dt)
        if not ok:
            cut = True
            dt *= _CUT
            if dt < inc.min_increment:
                run.fail(f"increment below {inc.min_increment} at t = {run.t:.4f} ({why})")
                return False
        elif iters == 0 and not cut:
            # the predictor was exact: finish the step at once; after a cut, where a loose intermediate state can
            # need no iteration while the rest of the step needs many, it grows as after an easy increment
            dt = inc.max_increment
        elif iters <= _EASY_ITERATIONS and changes <= _EASY_CHANGES_REL * max(
            np.count_nonzero(run.lam), 1
        ):
            dt *= _GROW
        elif iters > _HARD_ITERATIONS:
            dt *= _SHRINK
    return True


def _first_touch(run: _Run, k: int, dt: float) -> float:
    """dt, shortened where the indenter has no force yet so that it advances at most first_touch_mm past the
    first contact (it would jump deep into the skin)."""
    inc, contact = run.job.settings.increments, run.contact
    if k != 3 or run.k_ind is None or run.travel <= 0:
        return dt
    sel = contact.obstacle == run.k_ind
    if np.any(run.lam[sel] > 0):
        return dt
    run.set_time(run.t)
    gmin = max(float(np.min(contact.node_gaps(run.u, sel)[sel])), 0.0)
    if run.travel * dt > gmin + inc.first_touch_mm:
        dt = max((gmin + inc.first_touch_mm) / run.travel, inc.min_increment)
    return dt


def _first_turn(run: _Run) -> float:
    """The first increment of a turn (a fraction of it): the indenter's surface moves at most _TURN_STEP_FACETS
    of a facet at the skin nodes it presses on (the largest change of their gap over the whole turn, against the
    median facet size there); 1 where the turn moves it less, or nothing presses."""
    if run.k_ind is None:
        return 1.0
    contact, inc = run.contact, run.job.settings.increments
    sel = (contact.obstacle == run.k_ind) & (run.lam > 0)
    if not np.any(sel):
        return 1.0
    moved = []
    for t in (3.0, 4.0):
        run.set_time(t)
        moved.append(contact.node_gaps(run.u, sel)[sel])
    run.set_time(run.t)
    shift_mm = float(np.max(np.abs(moved[1] - moved[0])))
    h_mm = float(np.median(contact.h[sel]))
    if not shift_mm > _TURN_STEP_FACETS * h_mm:
        return 1.0
    return max(_TURN_STEP_FACETS * h_mm / shift_mm, inc.min_increment)


def _predicted(run: _Run, k: int, dt: float):
    """The start (u, lam) of the increment t -> t + dt and its target displacement of the constrained dofs."""
    t, t1, X = run.t, run.t + dt, run.X
    if k == 3 and run.prev is not None:
        # in contact the last increment's change, scaled, is a far better guess than a rigid move
        t_prev, u_prev, lam_prev = run.prev
        w = dt / (t - t_prev)
        u_try = run.u + w * (run.u - u_prev)
        lam_try = np.maximum(run.lam + w * (run.lam - lam_prev), 0.0)
    else:
        u_try = (run.sched.predict(X, X + run.u.reshape(-1, 3), t, t1) - X).ravel()
        lam_try = run.lam.copy()
    target = np.zeros(run.asm.n_dofs)
    target.reshape(-1, 3)[run.bone_nodes] = run.sched.bone(run.Xb, t1) - run.Xb
    return u_try, lam_try, target[run.p.constrained]


def _newton(run: _Run, u, lam, target_d, end: bool):
    """Newton on the increment from (u, lam) in place, with the nodes that penetrate outside the candidates
    added and the increment solved on: (ok, reason, iterations, residuals, active-set changes)."""
    s, p, contact = run.job.settings, run.p, run.contact
    g0 = contact.node_gaps(u, np.ones(len(contact.node), bool))
    contact.cand = g0 < run.cand_dist
    lam[~contact.cand] = 0.0
    # only the end of the load is reported (path independent: the ends of the bone-rotation steps only start
    # the next one)
    tol = (
        (s.newton.rtol, p.atol, p.gap_tol)
        if end
        else (s.newton.rtol_intermediate, p.atol_intermediate, p.gap_tol_intermediate)
    )
    iters, residuals, changes = 0, [], 0
    while True:
        ok, why, it, res, ch = _solve_increment(p, u, lam, target_d, *tol)
        iters, residuals, changes = iters + it, residuals + res, changes + ch
        if not ok:
            return ok, why, iters, residuals, changes
        # nodes outside the candidates that now penetrate: add them and go on
        g_all = contact.node_gaps(u, ~contact.cand)
        missed = np.isfinite(g_all) & (g_all < -tol[2])
        if not np.any(missed):
            return ok, why, iters, residuals, changes
        contact.cand |= g_all < run.cand_dist


def _increment(run: _Run, k: int, dt: float) -> tuple[bool, str, int, int]:
    """One increment of load step k from run.t by dt: solved, checked, recorded and, if it converged, taken as
    the new state. Returns (converged, reason, Newton iterations, entries whose contact state changed)."""
    t, t1, timers, contact = run.t, run.t + dt, run.p.timers, run.contact
    t0c, w0 = dict(timers), time.perf_counter()
    u, lam, target_d = _predicted(run, k, dt)
    run.set_time(t1)
    ok, why, iters, residuals, changes = _newton(run, u, lam, target_d, t1 >= 4.0 - 1e-12)
    run.n_iter += iters
    run.total_changes += changes
    # between the nodes, on the facets of the candidates (the others are too far from an obstacle)
    pen = _penetration(run.surfaces, contact, u, contact.cand) if ok else (np.nan, np.nan)
    if ok and pen[1] > _MAX_PENETRATION_REL:
        ok, why = (
            False,
            f"the indenter passes between the skin's nodes ({pen[1]:.0%} of a facet deep)",
        )
    force = _forces(contact, u, lam, run.k_ind, run.k_cast) if ok else (np.zeros(3), np.zeros(3))
    run.history.append(
        IncrementRecord(
            step=k + 1,
            t_start=t,
            t_end=t1,
            converged=ok,
            reason=why,
            iterations=iters,
            active_set_changes=changes,
            residuals=tuple(residuals),
            tip_mm=tuple(run.sched.tip(t1)) if run.job.indenter is not None else (),
            indenter_force_N=float(force[0] @ run.axis),
            max_penetration_mm=pen[0],
            assembly_s=timers["assembly"] - t0c["assembly"],
            linear_solve_s=timers["solve"] - t0c["solve"],
            contact_s=timers["contact"] - t0c["contact"],
        )
    )
    log.info(
        "step %d t %.4f->%.4f %s it %d changes %d F %.4g N pen %.3g mm",
        k + 1,
        t,
        t1,
        "ok" if ok else f"cut ({why})",
        iters,
        changes,
        run.history[-1].indenter_force_N,
        pen[0],
    )
    if not ok:
        _log_crush(run, u)
    moved = 0
    if ok:
        run.active_per_increment.append(np.unique(contact.node[lam > 0]))
        # the entries whose contact state the increment changed, from its start to its end
        moved = int(np.count_nonzero((lam > 0) != (run.lam > 0)))
        run.prev = (t, run.u, run.lam) if k == 3 else None
        run.u, run.lam, run.t = u, lam, t1
        run.longest_ok_s = max(run.longest_ok_s, time.perf_counter() - w0)
    else:
        run.prev = None
    run.progress.append((time.perf_counter() - run.t_wall, run.t))
    _log_progress(run)
    return ok, why, iters, max(changes, moved)


def _log_crush(run: _Run, u: np.ndarray) -> None:
    """One line on the most compressed quadrature point of the state a cut increment stopped at: its element,
    det F and principal stretches, and how many elements have a point below _CRUSHED_J. A pinch that stalls shows
    here whether one crushed element holds Newton back (the stall is read from the solve's log)."""
    F = run.asm.deformation_gradient(u)
    J = np.linalg.det(F)
    e, q = np.unravel_index(int(np.argmin(J)), J.shape)
    if J[e, q] <= 0:
        log.info("  its state is inverted at %d quadrature points", int(np.count_nonzero(J <= 0)))
        return
    stretches = np.sort(np.linalg.svd(F[e, q], compute_uv=False))[::-1]
    log.info(
        "  its smallest det F is %.3g, in element %d (principal stretches %.3g, %.3g, %.3g); %d elements have a "
        "point below %g",
        J[e, q],
        e,
        *stretches,
        int(np.count_nonzero(J.min(axis=1) < _CRUSHED_J)),
        _CRUSHED_J,
    )


def _log_progress(run: _Run) -> None:
    """One line per attempted increment (:mod:`deeptissue.fem.progress`, read by ``python -m
    deeptissue.status``): the load reached, the increments, the Newton iterations and the elapsed time."""
    done = sum(1 for h in run.history if h.converged)
    p = Progress(run.t, done, len(run.history), run.n_iter, run.elapsed_s())
    log.info("%s", format_progress(p))


def _result(run: _Run) -> SolveResult:
    """The SolveResult of the state reached: forces, penetrations, element deformation gradients, contact."""
    contact, asm, u, lam = run.contact, run.asm, run.u, run.lam
    linear_solver = {"backend": run.p.solver.backend, **run.p.solver.counters}
    run.p.solver.close()
    run.set_time(run.t)
    gw_end = contact.weighted(u, contact.cand)[0]
    ft, fcast = _forces(contact, u, lam, run.k_ind, run.k_cast)
    force_N = float(ft @ run.axis)
    if run.done and run.end_overlap_mm > _THROUGH_OVERLAP_MM and not force_N > 0:
        run.fail(
            f"the tissue passed through the indenter: its end overlaps the rigidly moved skin by "
            f"{run.end_overlap_mm:.2f} mm, yet it pushes with {force_N:.3g} N"
        )
        log.warning(run.reason)
    pen_mm, pen_rel = _penetration(run.surfaces, contact, u)
    node_pen = float(
        np.max(np.where(np.isfinite(gw_end), -gw_end / contact.h, -np.inf), initial=0.0)
    )
    F = asm.deformation_gradient(u)
    Fe = np.einsum("eqij,eq->eij", F, asm.w) / asm.w.sum(axis=1)[:, None, None]
    on = lam > 0
    active = {
        name: int(np.count_nonzero(on & (contact.obstacle == j)))
        for j, name in enumerate(contact.names)
    }
    # every nonzero multiplier: a state before the end of the load may hold small negative ones (within its gap
    # tolerance), and a solve started from it must take the same path as one that went on from it
    held = lam != 0
    state = {
        name: (
            contact.node[held & (contact.obstacle == j)].copy(),
            lam[held & (contact.obstacle == j)].copy(),
        )
        for j, name in enumerate(contact.names)
    }
    wall, timers, history = run.elapsed_s(), run.p.timers, run.history
    # the end line deeptissue.fem.progress.parse_end reads
    log.info(
        "solve %s in %.1f s: %d increments, %d Newton iterations, %d active-set changes",
        "converged" if run.done else f"not converged ({run.reason})",
        wall,
        len(history),
        run.n_iter,
        run.total_changes,
    )
    return SolveResult(
        converged=run.done,
        reason=run.reason,
        displacement_mm=u.reshape(-1, 3).copy(),
        deformation_gradient=Fe,
        history=tuple(history),
        indenter_force_N=force_N,
        force_on_tissue_N=ft,
        cast_force_N=fcast,
        max_penetration_mm=pen_mm,
        max_penetration_rel=pen_rel,
        strain_energy_mJ=float(asm.energy(u)),
        n_dofs=asm.n_dofs,
        n_free_dofs=asm.n_free,
        increments=sum(1 for h in history if h.converged),
        newton_iterations=run.n_iter,
        load_reached=run.t,
        wall_s=wall,
        assembly_s=timers["assembly"],
        linear_solve_s=timers["solve"],
        contact_s=timers["contact"],
        extra={
            "straightened_tets": run.n_straightened,
            "linear_solver": linear_solver,
            "start_backoff_mm": run.start_backoff_mm,
            "bone_clearance_mm": run.bone_clearance_mm,
            "infeasible": run.infeasible,
            "active_nodes": active,
            "active_nodes_per_increment": tuple(run.active_per_increment),
            "active_set_changes": run.total_changes,
            "node_penetration_rel": max(node_pen, 0.0),
            "min_force_N": float(lam.min(initial=0.0)),
            "started_from_bone_state": isinstance(run.job.start, BoneState),
            "contact_state": state,
            "contact_entries": {
                "nodes": contact.node.copy(),
                "obstacle": contact.obstacle.copy(),
                "lam_N": lam.copy(),
                "weighted_gap_mm": gw_end,
                "h_mm": contact.h.copy(),
            },
        },
    )
