"""Solution-driven mesh refinement: solve, estimate, remesh where the estimate says, solve again.

One pass solves on a mesh, estimates the discretisation error of the VOI, its bins and the force
(:class:`PassEstimate`), and stops when every estimate meets its goal (:class:`AdaptSettings`) or the
budget of passes or wall time is spent; otherwise it turns the per-element indicator into a target
element size (:func:`target_sizes`), carries the sizes to the nodes with a bounded gradation
(:func:`node_sizes`), caps the element count (:func:`fit_budget`) and hands the sizes to the mesher
as a gmsh background size field (:func:`deeptissue.mesh.set_background_size`). :func:`adapt` takes the mesher, the solver and the estimator as
callables, so the same loop serves the cylinder scene (:mod:`deeptissue.verification.cylinder`) and a limb.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from .elements import tet_subdivision
from .fem.progress import NEXT_PASS
from .mesh import GMSH_TET_VOLUME, SizeField, TetMesh

__all__ = [
    "AdaptPass",
    "AdaptResult",
    "AdaptSettings",
    "GMSH_EDGE_RATIO",
    "GMSH_GRADED_EXCESS",
    "PassEstimate",
    "SAME_MESH_GROWTH",
    "adapt",
    "element_sizes",
    "estimated_tets",
    "extrapolated_error",
    "fit_budget",
    "goal_verdict",
    "voi_error_percent",
    "node_sizes",
    "target_sizes",
]

# the 6 edges of a tetrahedron by its corner indices
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
# gmsh's tetrahedra for a size h: mean corner-edge length 1.3 h (1.26 to 1.32 on uniform cylinder
# meshes of 1.6 to 0.4 mm) and mean volume 0.21 h³ (0.19 to 0.22: deeptissue.mesh.GMSH_TET_VOLUME)
GMSH_EDGE_RATIO = 1.3
# where a background size varies, gmsh makes more tetrahedra than its integral of 1/(0.21 h³): 12-20 %
# more on the 1.6 mm cylinder refined to 0.2-0.5 mm within 1-3 mm of the top (and on its uniform 1.6 mm
# remesh), 2 % less on uniform 1 and 0.6 mm remeshes; the count is an upper estimate for the budget
GMSH_GRADED_EXCESS = 1.2
# a next mesh expected to have at most this many times the elements of the present one is almost the
# same mesh: where the element budget holds the loop there, a further pass changes a region too little
# to extrapolate. Expected: estimated_tets of its graded sizes over GMSH_GRADED_EXCESS (gmsh made
# 0.79-0.81 of the estimate at each of the three refinements of rat02's bar of the demo; an unchanged
# mesh is expected at 0.83). That bar, at a budget of 20 000: 10 110 tets at pass 1 (expected growth
# about 1.65, the budget over 1.2 x 10 110; gmsh made 15 739), 15 739 at pass 2 (expected 1.05, its
# log's `the next sizes give` line; gmsh made 16 152 at the pass after it, which the rule skips)
SAME_MESH_GROWTH = 1.2
# points per element at which the linear size field is integrated (tet_subdivision(2): 64; within 3 % of
# the converged integral for a size falling from 1.6 to 0.2 mm across one element)
_SIZE_POINTS, _ = tet_subdivision(2)
_SIZE_N = np.column_stack([1.0 - _SIZE_POINTS.sum(axis=1), _SIZE_POINTS])


@dataclass(frozen=True)
class AdaptSettings:
    """Goals and budget of the adaptive loop, and the limits of one remeshing.

    The goals are those of the study's accuracy goal: the VOI within 2 %, every bin within 1 pp, the
    force within 2 %. ``h_min_mm`` 0.1 mm: a small VOI needs elements below 0.2 mm where γ crosses the
    threshold (rat03's sphere of the demo, 5 mm³: the estimate stalls at 3.1 % with 0.2 mm, and meets the
    goal at pass 3 with 0.1 mm, 114 480 DOFs, 147 s on one core). ``h_max_mm`` 1.6 mm is
    the study's default element size. One pass shrinks an element at most by ``max_shrink`` and grows
    it at most by ``max_growth`` (1: no coarsening, since the loop starts from a coarse mesh and the
    field outside the indicator's elements is not estimated). ``max_shrink`` 0.25 lets the first
    refinement reach the sizes its estimate predicts with the estimate's order (h²): the first pass's
    estimates are 10-40 times their goals on the cylinder and the demo, which asks for a fifth to a
    third of the size; by halves that took two refinements. On the cylinder the loop meets its goal at
    pass 2 instead of 3 (2 mm: 79 566 DOFs against 77 415; 0.5 mm: 23 013 against 32 709).
    ``safety`` 0.7 aims each remeshing at that fraction of the goal: the indicator follows the size
    rule closely (on the cylinder at 2 mm, a pass aimed at 1.4 % gave 1.36 %), so a small margin
    makes the next pass meet the goal without refining further than needed. ``grading`` bounds the
    size's growth away from a small element [mm/mm] (gmsh honours a background size only where it
    varies gently).

    From the second pass on, every estimate extrapolates the change from the previous pass
    (:func:`extrapolated_error`, Richardson): with the mean element size of the region that decides a
    quantity shrunk by f, an error ∝ h^p shrinks by r = f^p, so this pass's error is |ΔQ| r / (1 − r).
    The region of the VOI is the elements its threshold indicator marks (γ* and γh on different sides
    of the threshold), that of the bins every element the indicator marks, that of the force the
    contact zone; p is ``voi_order`` for the VOI and every bin, ``force_order`` for the force. The
    first pass, and a pass whose VOI or bin region was not refined enough and holds no verdict, are
    judged by the recovered-strain estimate (:func:`deeptissue.errorest.voi_error_estimate`), which
    also says where to refine. ``voi_order`` 2: the strain of quadratic elements converges as h², and
    so does the band between the threshold surfaces of two solutions; on the cylinder at 1.5 mm, the one
    pass after the first whose true VOI error (0.61 %) the reference resolves, orders 1.5, 2 and 2.5 put
    the estimate at 2.8, 1.27 and 0.60 times it, and at 2 and 3 mm the passes it judges meet the goal at
    pass 1 with 30 537 and 48 459 DOFs, within it against the reference (VOI +0.25 %, −0.05 %). On the
    cylinder the force's true error falls as h^1.9-2.0 at 0.5 mm, h^2.4-2.0 at 2 mm and h^2.9 at 3 mm;
    1.75 puts the estimate at 1.0 to 2.8 times the true error on those passes (the change alone: 1.1 to
    7.8 times). An extrapolation is valid where the region's mean size shrank to at most
    ``valid_shrink`` of the previous pass's (a barely changed region changes the quantity by
    nothing, whatever its error; a change of its mean size within that factor either way is the
    mesher's scatter). Once such an estimate is within its goal, the verdict holds for the later
    passes while the region is not coarsened past that scatter: a finer region has no larger error,
    so passes that refine only for the other quantities stop on their goals; the held estimate is
    the larger of the verdict's and the quantity's change since that pass. A VOI or bin region that
    misses its goal is refined to at most ``valid_shrink`` of its size, so that the next pass has an
    estimate. While the force's estimate misses its goal or is unknown,
    the contact zone is refined to at most ``valid_shrink`` of its size, unless ``h_min_mm`` or
    the element budget keep it from shrinking that far: such a refinement cannot give an estimate, so
    the budget goes to the VOI and bins, and the pass records why (:class:`AdaptPass`). Where the
    budget or ``h_min_mm`` hold the next sizes to almost the same mesh (:data:`SAME_MESH_GROWTH`) and
    keep a VOI or bin region that misses its goal above ``valid_shrink``, the next pass could not
    extrapolate it either and would be judged by its recovered estimate on an almost unchanged mesh:
    this pass is judged by its own recovered estimate instead, and stops there if that meets the goal.
    ``max_tets`` caps the next mesh's size (:func:`estimated_tets` of the graded node sizes, an upper
    estimate of gmsh's count; 20 000 quadratic tetrahedra are about 90 000 DOFs, a few minutes per
    solve on one core and under 4 GB): the refined sizes are scaled up together until it fits
    (:func:`fit_budget`). The first refinement has at most ``first_refinement_tets`` (12 000): it is
    aimed by the first pass's recovered estimate, several times the true error (on the demo the VOI
    moves by 0.3-10 % from the first pass to the second, where the first pass estimated 13-37 %). With
    the whole 20 000, rat02's spheres get about 72 000 DOFs at their second pass and meet the goal at
    0.1-0.4 of it (the demo's jobs 3 720 s); with 12 000, about 49 000 DOFs and 0.15-0.57, every variant
    within the goal (2 440 s with every variant on meshes of its own, CHANGELOG.md). The passes
    after it are aimed by the change between passes and get ``max_tets``, which rat02's bar needs
    (75 615 DOFs at its third pass).
    """

    voi_goal_percent: float = 2.0
    bins_goal_pp: float = 1.0
    force_goal_percent: float | None = 2.0
    max_passes: int = 5
    max_wall_s: float = 3600.0
    h_min_mm: float = 0.1
    h_max_mm: float = 1.6
    max_shrink: float = 0.25
    max_growth: float = 1.0
    safety: float = 0.7
    grading: float = 0.4
    valid_shrink: float = 0.85
    voi_order: float = 2.0
    force_order: float = 1.75
    max_tets: int = 20000
    first_refinement_tets: int = 12000

    def __post_init__(self):
        if not 0 < self.h_min_mm <= self.h_max_mm:
            raise ValueError(
                f"AdaptSettings: need 0 < h_min_mm <= h_max_mm, got {self.h_min_mm}, {self.h_max_mm}"
            )
        if not 0 < self.max_shrink <= 1 <= self.max_growth:
            raise ValueError(
                f"AdaptSettings: need 0 < max_shrink <= 1 <= max_growth, got {self.max_shrink}, {self.max_growth}"
            )
        if (
            self.max_passes < 1
            or self.max_wall_s <= 0
            or not 0 < self.safety <= 1
            or self.grading <= 0
            or self.force_order <= 0
            or self.voi_order <= 0
            or not 0 < self.valid_shrink < 1
            or self.first_refinement_tets <= 0
        ):
            raise ValueError(
                "AdaptSettings: need max_passes >= 1, max_wall_s > 0, 0 < safety <= 1, grading > 0, "
                "force_order > 0, voi_order > 0, 0 < valid_shrink < 1, first_refinement_tets > 0"
            )


def element_sizes(mesh: TetMesh) -> np.ndarray:
    """The gmsh size each tetrahedron corresponds to (n_tets,) [mm]: its mean corner-edge length over
    :data:`GMSH_EDGE_RATIO`, so that a mesh asked for at 0.8 mm has sizes near 0.8 mm."""
    X = mesh.nodes_mm[mesh.tets[:, :4]]
    return (
        np.linalg.norm(X[:, _TET_EDGES[:, 1]] - X[:, _TET_EDGES[:, 0]], axis=2).mean(axis=1)
        / GMSH_EDGE_RATIO
    )


def _volumes(mesh: TetMesh) -> np.ndarray:
    X = mesh.nodes_mm[mesh.tets[:, :4]]
    return np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6.0


def estimated_tets(mesh: TetMesh, node_size_mm, *, current_mm=None) -> float:
    """Number of tetrahedra gmsh makes of ``mesh``'s domain meshed to the background size ``node_size_mm``
    (n_nodes,) [mm] at its corner nodes (:func:`node_sizes`, :class:`deeptissue.mesh.SizeField`): the
    integral of 1 / (:data:`GMSH_TET_VOLUME` h³) with h interpolated linearly in every element, as gmsh
    interpolates it, times :data:`GMSH_GRADED_EXCESS`. The graded sizes around a refined region count:
    a region refined to 0.2 mm brings a halo of elements growing by ``grading`` per mm.

    With ``current_mm`` (n_nodes,), the node sizes ``mesh`` itself was made to, an element none of whose
    corners changes size counts as itself: gmsh remeshes an unchanged region as it did (a coarse limb
    has 40 % more elements than the integral, its surface's share).
    """
    hn = np.asarray(node_size_mm, float)[mesh.tets[:, :4]]
    if not np.all(hn > 0):
        raise ValueError("estimated_tets: every corner node needs a size > 0")
    count = GMSH_GRADED_EXCESS * _volumes(mesh) * np.mean((hn @ _SIZE_N.T) ** -3.0, axis=1)
    count /= GMSH_TET_VOLUME
    if current_mm is not None:
        same = np.all(np.isclose(hn, np.asarray(current_mm, float)[mesh.tets[:, :4]]), axis=1)
        count[same] = 1.0
    return float(count.sum())


def target_sizes(
    h_mm, indicator, target_total, settings: AdaptSettings = AdaptSettings()
) -> np.ndarray:
    """New element sizes (n_tets,) [mm] from the current sizes ``h_mm`` and the indicator (n_tets,).

    Classic h-adaptation by equidistribution: each of the n elements with a non-zero indicator gets
    the share ``target_total / n`` of the goal, and ``h_new = h (share / η_e)^(1/p)`` with p = 2.
    The indicator is the volume whose class (below the threshold, or which bin) the recovered strain
    γ* and γh disagree on; within the region of one element it is the area of the threshold (or bin
    edge) surface times the band where they disagree, |γ* − γh| / |∇γ|. The strain of quadratic
    elements converges as h², so the band, and the region's indicator, shrink as h²: p = 2.
    Elements with a zero indicator keep their size (times ``max_growth``). The ratio h_new / h is
    clipped to [max_shrink, max_growth] per pass, and a changed size to [h_min_mm, h_max_mm]; an
    unchanged one stays as the mesher made it.
    """
    h = np.asarray(h_mm, float)
    eta = np.asarray(indicator, float)
    if h.shape != eta.shape:
        raise ValueError(f"target_sizes: h_mm {h.shape} and indicator {eta.shape} differ")
    if target_total <= 0:
        raise ValueError(f"target_sizes: target_total must be > 0, got {target_total}")
    st = settings
    ratio = np.full(h.shape, st.max_growth)
    on = eta > 0
    if on.any():
        ratio[on] = (target_total / on.sum() / eta[on]) ** 0.5
    ratio = np.clip(ratio, st.max_shrink, st.max_growth)
    out = h.copy()
    changed = ratio != 1.0
    out[changed] = np.clip(h[changed] * ratio[changed], st.h_min_mm, st.h_max_mm)
    return out


def node_sizes(
    mesh: TetMesh, tet_sizes_mm, *, grading: float = AdaptSettings.grading, current_mm=None
) -> np.ndarray:
    """Sizes at the corner nodes (n_nodes,) [mm; NaN at mid-edge nodes], limited so that they grow by
    at most ``grading`` mm per mm of distance along the mesh's edges (a small element's neighbours
    are refined too).

    Without ``current_mm`` a node takes the smallest size of the elements sharing it. With the
    elements' present sizes ``current_mm`` (n_tets,) it takes the volume-weighted mean of their
    present sizes, or the smallest new size of those that shrink if smaller: the smallest of the
    measured sizes would shrink every unchanged region a little at every pass, since the sizes of a
    gmsh mesh scatter about the size asked for.
    """
    s = np.asarray(tet_sizes_mm, float)
    corners = mesh.tets[:, :4]
    n_nodes = len(mesh.nodes_mm)
    out = np.full(n_nodes, np.inf)
    if current_mm is None:
        np.minimum.at(out, corners.ravel(), np.repeat(s, 4))
    else:
        cur = np.asarray(current_mm, float)
        X = mesh.nodes_mm[corners]
        w = np.repeat(np.abs(np.linalg.det(X[:, 1:] - X[:, :1])), 4)
        num = np.bincount(corners.ravel(), weights=w * np.repeat(cur, 4), minlength=n_nodes)
        den = np.bincount(corners.ravel(), weights=w, minlength=n_nodes)
        out = np.divide(num, den, out=np.full(n_nodes, np.inf), where=den > 0)
        shrink = s < cur
        np.minimum.at(out, corners[shrink].ravel(), np.repeat(s[shrink], 4))
    # out_i = min_j (out_j + grading × path length from j to i along the edges): the shortest path from a
    # source joined to every node j by an edge of length out_j
    edges = np.unique(np.sort(corners[:, _TET_EDGES].reshape(-1, 2), axis=1), axis=0)
    length = np.linalg.norm(mesh.nodes_mm[edges[:, 1]] - mesh.nodes_mm[edges[:, 0]], axis=1)
    seeded = np.flatnonzero(np.isfinite(out))
    rows = np.concatenate([edges[:, 0], edges[:, 1], np.full(len(seeded), n_nodes)])
    cols = np.concatenate([edges[:, 1], edges[:, 0], seeded])
    w = np.concatenate([grading * length, grading * length, out[seeded]])
    graph = coo_matrix((w, (rows, cols)), shape=(n_nodes + 1, n_nodes + 1)).tocsr()
    out = dijkstra(graph, directed=True, indices=n_nodes)[:n_nodes]
    out[~np.isfinite(out)] = np.nan
    return out


@dataclass(frozen=True)
class PassEstimate:
    """Estimated discretisation error of one solve (the estimator's answer to :func:`adapt`).

    ``indicator_mm3`` (n_tets,): the per-element indicator of the VOI and bins
    (:func:`deeptissue.errorest.element_indicator`); ``voi_indicator_mm3`` (n_tets,) or None: its
    part on different sides of the threshold (the rest is the bins'), so that only what misses its
    goal is refined; ``contact_tets`` (n_tets,) bool or None: the elements of the indenter's
    contact zone, refined while the force's estimate misses its goal.
    """

    voi_mm3: float
    voi_err_mm3: float
    bins_err_pp: float  # largest over the bins [pp]
    force_N: float
    indicator_mm3: np.ndarray
    contact_tets: np.ndarray | None = None
    bins_percent: dict = field(default_factory=dict)  # bin label -> % of the VOI
    voi_indicator_mm3: np.ndarray | None = None


@dataclass(frozen=True)
class AdaptPass:
    """One pass of :func:`adapt`: the mesh, the times [s] and the estimates.

    ``contact_shrink``: the contact zone's mean element size over the previous pass's (NaN on the first
    pass or without a contact zone). ``force_status`` says what ``force_err_percent`` is:
    ``'estimated'`` (the change from the previous pass), ``'held'`` (an earlier pass's estimate within
    the goal, :class:`AdaptSettings`), or why it is unknown: ``'first pass'``, ``'budget'`` or
    ``'h_min'`` (the element budget or the smallest size kept the contact zone from being refined
    enough), ``'not refined'`` (the contact zone did not shrink to ``valid_shrink``),
    ``'coarsened'`` (it grew past a held verdict's), ``'no goal'`` or ``'no solve'``. ``voi_status`` and
    ``bins_status`` say what ``voi_err_percent`` and ``bins_err_pp`` are: ``'estimated'`` (extrapolated
    from the previous pass), ``'held'`` or ``'recovered'`` (the recovered-strain estimate of this pass
    alone: on the first pass, where no element is marked or the region was not refined enough to
    extrapolate, and where the next pass would be almost the same mesh, :data:`SAME_MESH_GROWTH`);
    ``bins_err`` holds every bin's extrapolated or held estimate [pp] (empty when recovered).
    """

    index: int
    n_dofs: int
    n_tets: int
    converged: bool
    mesh_s: float
    solve_s: float
    estimate_s: float
    wall_s: float  # since the loop began, this pass included
    voi_mm3: float
    voi_err_percent: float
    bins_err_pp: float
    force_N: float
    force_err_percent: float  # NaN: no estimate (force_status says why)
    contact_shrink: float
    force_status: str
    h_min_mm: float  # smallest element of the mesh (gmsh size, :func:`element_sizes`)
    goal_met: bool
    bins_percent: dict = field(default_factory=dict)  # bin label -> % of the VOI
    voi_status: str = "recovered"
    bins_status: str = "recovered"
    bins_err: dict = field(default_factory=dict)  # bin label -> estimated error [pp]


@dataclass(frozen=True)
class AdaptResult:
    """The passes of :func:`adapt`, the last mesh, solution and estimate, and why the loop stopped
    (``'goal'``, ``'passes'``, ``'wall'`` or ``'not converged'``)."""

    passes: tuple
    mesh: TetMesh
    solution: object
    estimate: PassEstimate | None
    stop_reason: str

    def table(self) -> pd.DataFrame:
        """One row per pass: the fields of :class:`AdaptPass`, ``bins_percent`` and ``bins_err`` as
        ``bins_percent.<bin>`` and ``bins_err_pp.<bin>`` columns."""
        return pd.DataFrame(
            [
                {
                    **{
                        k: v
                        for k, v in p.__dict__.items()
                        if k not in ("bins_percent", "bins_err")
                    },
                    **{f"bins_percent.{b}": x for b, x in p.bins_percent.items()},
                    **{f"bins_err_pp.{b}": x for b, x in p.bins_err.items()},
                }
                for p in self.passes
            ]
        )

    @property
    def goal_met(self) -> bool:
        """Whether the last pass met every goal."""
        return bool(self.passes) and self.passes[-1].goal_met


def extrapolated_error(change: float, shrink: float, order: float) -> float:
    """The error of the finer of two solutions by Richardson extrapolation: with the region that decides a
    quantity refined by ``shrink`` (its mean element size over the coarser solution's) and an error
    ∝ h^``order``, the finer error is r = shrink^order times the coarser one, so it is
    ``change`` r / (1 − r), ``change`` the quantity's change between the two (same unit)."""
    r = shrink**order
    return change * r / (1.0 - r)


def _change(q, q0, relative: bool) -> np.ndarray:
    """The change between the values ``q`` and ``q0`` (arrays of one quantity, or of every bin), entry by
    entry: in % of the largest |q| if ``relative``, else in their unit."""
    q, q0 = np.atleast_1d(np.asarray(q, float)), np.atleast_1d(np.asarray(q0, float))
    d = np.abs(q - q0)
    if not relative:
        return d
    scale = float(np.max(np.abs(q))) if q.size else 0.0
    return 100.0 * d / scale if scale > 0 else np.where(d == 0, 0.0, np.inf)


@dataclass(frozen=True)
class _Tracked:
    """One quantity's values (one entry, or one per bin) and the mean element size [mm] of the region that
    decides it, at one pass (``previous``) or at the pass whose verdict holds (``held``, with that
    verdict's estimates ``err``)."""

    value: np.ndarray
    h_mm: float
    err: np.ndarray | None = None


def _extrapolate(value, h_mm, previous, held, order, settings, *, relative=True):
    """One quantity's estimates (an array like ``value``), their status and the shrink of its region.

    ``'estimated'``: the change from ``previous`` (:class:`_Tracked`) scaled by :func:`extrapolated_error`,
    valid where the region shrank to at most ``settings.valid_shrink`` (without a region to measure: the
    change itself); ``'held'``: the verdict ``held``, while the region has not grown past it, at least the
    change since; else NaN with ``'first pass'``, ``'not refined'`` or ``'coarsened'``."""
    vs = settings.valid_shrink
    nan = np.full(np.atleast_1d(value).shape, np.nan)
    if previous is None:
        return nan, "first pass", np.nan
    shrink = h_mm / previous.h_mm if np.isfinite(h_mm) and np.isfinite(previous.h_mm) else np.nan
    if not shrink > vs:  # shrunk enough, or no region to check
        change = _change(value, previous.value, relative)
        if not np.isfinite(shrink):
            return change, "estimated", shrink
        return extrapolated_error(change, shrink, order), "estimated", shrink
    if held is not None:
        if not h_mm > held.h_mm / vs:
            return np.maximum(held.err, _change(value, held.value, relative)), "held", shrink
        return nan, "coarsened", shrink
    return nan, "not refined", shrink


def _verdict(err, status, goal, value, h_mm, held):
    """The verdict in force after a pass: a new one where an estimate meets ``goal``, the old one while it
    holds and meets it, else None."""
    if status == "estimated" and np.max(err, initial=0.0) <= goal:
        return _Tracked(np.atleast_1d(np.asarray(value, float)), h_mm, err)
    return held if status == "held" and np.max(err, initial=0.0) <= goal else None


def _regions(est: PassEstimate) -> tuple[np.ndarray, np.ndarray]:
    """The elements that decide the VOI (its threshold indicator's, or the whole indicator's where the
    estimator does not split it) and the bins (the whole indicator's), as boolean masks (n_tets,)."""
    eta = np.asarray(est.indicator_mm3, float)
    voi = eta > 0 if est.voi_indicator_mm3 is None else np.asarray(est.voi_indicator_mm3) > 0
    return voi, eta > 0


def _region_h(h, mask) -> float:
    """The mean size [mm] of the elements of ``mask`` (NaN: none)."""
    return float(h[mask].mean()) if mask is not None and np.any(mask) else np.nan


@dataclass(frozen=True)
class _Estimates:
    """One pass's estimates as the loop judges them (:class:`AdaptPass` describes the fields)."""

    voi_pc: float
    voi_status: str
    bins_pp: dict
    bins_status: str
    force_pc: float
    force_status: str
    contact_shrink: float


def _pass_estimates(est: PassEstimate, h, track: dict, plan: str, st: AdaptSettings):
    """This pass's estimates of the VOI, the bins and the force (:class:`_Estimates`) from the estimator's
    ``est`` and the previous pass's and the verdicts' values in ``track`` (updated in place: keys
    ``'<quantity>'`` and ``'<quantity> held'``); ``plan`` why the last remeshing left the contact zone alone."""
    voi_region, bins_region = _regions(est)
    labels = list(est.bins_percent)
    regions = {
        "voi": (np.array([est.voi_mm3]), _region_h(h, voi_region), True),
        "bins": (
            np.array([est.bins_percent[k] for k in labels]),
            _region_h(h, bins_region),
            False,
        ),
        "force": (np.array([est.force_N]), _region_h(h, est.contact_tets), True),
    }
    out = {}
    for q, (value, h_q, relative) in regions.items():
        previous, held = track.get(q), track.get(f"{q} held")
        if q != "force" and not (
            np.isfinite(h_q)
            and previous is not None
            and np.isfinite(previous.h_mm)
            and len(previous.value) == len(value)
        ):
            # no marked region now or before (or other bins): judged by the recovered estimate alone
            track[q] = _Tracked(value, h_q)
            out[q] = (np.full(value.shape, np.nan), "recovered", np.nan)
            continue
        order = st.force_order if q == "force" else st.voi_order
        err, status, shrink = _extrapolate(
            value, h_q, previous, held, order, st, relative=relative
        )
        goal = {
            "voi": st.voi_goal_percent,
            "bins": st.bins_goal_pp,
            "force": st.force_goal_percent,
        }[q]
        if goal is not None:
            track[f"{q} held"] = _verdict(err, status, goal, value, h_q, held)
        track[q] = _Tracked(value, h_q)
        out[q] = (err, status, shrink)
    voi_pc, voi_status, _ = out["voi"]
    bins, bins_status, _ = out["bins"]
    if voi_status not in ("estimated", "held"):
        voi_pc, voi_status = [voi_error_percent(est.voi_mm3, est.voi_err_mm3)], "recovered"
    if bins_status not in ("estimated", "held") or not labels:
        bins, bins_status = np.full(len(labels), np.nan), "recovered"
    force_pc, force_status, shrink = out["force"]
    if st.force_goal_percent is None:
        force_pc, force_status = [np.nan], "no goal"
    elif force_status == "not refined" and plan:
        force_status = plan
    bins_pp = {k: float(b) for k, b in zip(labels, bins)}
    return _Estimates(
        float(voi_pc[0]),
        voi_status,
        bins_pp,
        bins_status,
        float(force_pc[0]),
        force_status,
        shrink,
    )


def adapt(
    build_mesh: Callable[[SizeField | None], TetMesh],
    solve: Callable[[TetMesh], object],
    estimate: Callable[[TetMesh, object], PassEstimate],
    settings: AdaptSettings = AdaptSettings(),
    *,
    initial: SizeField | None = None,
    given: Sequence[TetMesh] = (),
    log: Callable[[str], None] | None = None,
) -> AdaptResult:
    """Solve, estimate and remesh until the estimates meet the goals or the budget is spent.

    Parameters
    ----------
    build_mesh : callable
        ``build_mesh(size_field) -> TetMesh``; ``None`` asks for the mesher's own default sizes
        (the first pass, unless ``initial`` is given).
    solve : callable
        ``solve(mesh)`` -> an object with ``converged``, ``indenter_force_N`` and ``displacement_mm``
        (:class:`deeptissue.fem.solver.SolveResult`) of that mesh's own solve: a previous pass's solution
        carried to a new mesh folds its tets where the tissue is crushed between indenter and bone.
    estimate : callable
        ``estimate(mesh, solution) -> PassEstimate``.
    settings : AdaptSettings
        Goals, budget and remeshing limits.
    given : sequence of TetMesh
        The first passes' meshes (a base variant's, :func:`deeptissue.adapt_limb.adaptive_limb`); the
        loop meshes its own with ``build_mesh`` after them.
    log : callable or None
        Called with one line per pass.

    Returns
    -------
    AdaptResult
        A pass meets the goal when the estimated VOI error is at most ``voi_goal_percent`` of the VOI,
        the largest bin's at most ``bins_goal_pp`` and (unless ``force_goal_percent`` is None) the
        force's estimate (the change from the previous pass, or an earlier pass's held verdict,
        :class:`AdaptSettings`) at most ``force_goal_percent``. The loop stops there, after
        ``max_passes`` passes, or once ``max_wall_s`` has passed (``stop_reason`` 'wall', also for a solve
        that ended unconverged after it), or when a solve does not converge (the result then holds the
        last converged pass's mesh and solution).
    """
    st = settings
    t_start = time.perf_counter()
    passes, field_, last = [], initial, None
    # each quantity's previous values and verdict in force; why the last remeshing left the contact zone alone
    track, plan = {}, ""
    reason = "passes"
    for k in range(st.max_passes):
        t0 = time.perf_counter()
        mesh = given[k] if k < len(given) else build_mesh(field_)
        t1 = time.perf_counter()
        sol = solve(mesh)
        t2 = time.perf_counter()
        if (
            not sol.converged
        ):  # a solve stopped by the loop's budget (the solver's max_wall_s) spent it
            reason = "wall" if t2 - t_start >= st.max_wall_s else "not converged"
            passes.append(_unsolved_pass(k, mesh, (t1 - t0, t2 - t1, t2 - t_start)))
            break
        est = estimate(mesh, sol)
        t3 = time.perf_counter()
        h = element_sizes(mesh)
        e = _pass_estimates(est, h, track, plan, st)
        met, nxt, stuck = _met(e, est, st), None, ""
        wall_spent = time.perf_counter() - t_start >= st.max_wall_s
        if not (met or wall_spent or k + 1 == st.max_passes or k + 1 < len(given)):
            budget = min(st.first_refinement_tets, st.max_tets) if k == 0 else st.max_tets
            new_h, plan = _next_sizes(
                mesh, h, est, (e.voi_pc, _bins_max(e, est), e.force_pc), st, budget
            )
            nxt = node_sizes(mesh, new_h, grading=st.grading, current_mm=h)
            e, stuck = _judged_where_unrefinable(e, est, mesh, (h, new_h, nxt), st)
            met = _met(e, est, st)
        p = _solved_pass(k, mesh, h, (t1 - t0, t2 - t1, t3 - t2, t3 - t_start), est, e, met)
        passes.append(p)
        last = (mesh, sol, est)
        if log is not None:
            log(
                f"pass {k}: {p.n_dofs} DOFs, {p.solve_s:.1f} s solve, VOI {p.voi_mm3:.3f} mm3 +- {e.voi_pc:.2f} % "
                f"({e.voi_status}), bins +- {p.bins_err_pp:.2f} pp ({e.bins_status}), force {p.force_N:.5f} N "
                f"+- {e.force_pc:.2f} % ({e.force_status}), goal met: {met}"
            )
            if stuck:
                log(f"pass {k}: {stuck}")
        if met:
            reason = "goal"
            break
        if k + 1 == st.max_passes:
            break
        if wall_spent:
            reason = "wall"
            break
        if nxt is None:  # the next pass is given
            continue
        field_ = SizeField.from_mesh(mesh, nxt)
        if log is not None:
            log(f"pass {k + 1}: {NEXT_PASS}")
    mesh, sol, est = last if last is not None else (None, None, None)
    return AdaptResult(tuple(passes), mesh, sol, est, reason)


def _solved_pass(
    k: int, mesh: TetMesh, h, times_s: tuple, est: PassEstimate, e: _Estimates, met: bool
):
    """Pass ``k`` solved on ``mesh`` of element sizes ``h`` [mm]: its (mesh, solve, estimate, since the
    start) times [s], the estimator's ``est``, the estimates ``e`` as judged and whether they meet the
    goal."""
    return AdaptPass(
        k,
        3 * len(mesh.nodes_mm),
        int(mesh.n_tets),
        True,
        *times_s,
        est.voi_mm3,
        e.voi_pc,
        _bins_max(e, est),
        est.force_N,
        e.force_pc,
        e.contact_shrink,
        e.force_status,
        float(h.min()),
        met,
        dict(est.bins_percent),
        e.voi_status,
        e.bins_status,
        {} if e.bins_status == "recovered" else dict(e.bins_pp),
    )


def _bins_max(e: _Estimates, est: PassEstimate) -> float:
    """The largest bin's estimate [pp] of ``e``: the recovered one where the bins are judged by it."""
    if e.bins_status == "recovered":
        return float(est.bins_err_pp)
    return max(e.bins_pp.values(), default=0.0)


def _met(e: _Estimates, est: PassEstimate, st: AdaptSettings) -> bool:
    """Whether the estimates ``e`` meet every goal of ``st``."""
    verdict = goal_verdict(e.voi_pc, _bins_max(e, est), e.force_pc, e.force_status, st)
    return verdict["within_goal"]


def _judged_where_unrefinable(
    e: _Estimates, est: PassEstimate, mesh: TetMesh, sizes: tuple, st: AdaptSettings
) -> tuple[_Estimates, str]:
    """``e`` with the VOI's or the bins' estimate that misses its goal replaced by this pass's recovered
    estimate where the next pass's sizes make almost the same mesh (the element budget or ``h_min_mm``
    keep them there: at most :data:`SAME_MESH_GROWTH` times the elements, by :func:`estimated_tets` of
    the next node sizes) and leave the quantity's region above ``valid_shrink`` of its mean size: the
    next pass could not extrapolate it and would be judged by its recovered estimate on an almost
    unchanged mesh. ``sizes``: the present and the next element sizes (n_tets,) [mm] and the next node
    sizes (:func:`node_sizes`, the next pass's size field). Returns the estimates and what was judged
    anew and why ('' if nothing)."""
    h, new_h, nxt = sizes
    voi_region, bins_region = _regions(est)
    misses = {}
    if e.voi_status != "recovered" and not e.voi_pc <= st.voi_goal_percent:
        misses["VOI"] = voi_region
    if e.bins_status != "recovered" and not _bins_max(e, est) <= st.bins_goal_pp:
        misses["bins"] = bins_region
    misses = {q: m for q, m in misses.items() if m.any()}
    if not misses:
        return e, ""
    now = node_sizes(mesh, h, grading=st.grading, current_mm=h)
    # the expected count: the estimate is an upper one by gmsh's excess where sizes change
    growth = estimated_tets(mesh, nxt, current_mm=now) / (GMSH_GRADED_EXCESS * mesh.n_tets)
    shrink = {q: float(new_h[m].mean() / h[m].mean()) for q, m in misses.items()}
    stuck = [q for q, f in shrink.items() if f > st.valid_shrink]
    if growth > SAME_MESH_GROWTH or not stuck:
        return e, ""
    changes = {}
    if "VOI" in stuck:
        changes.update(
            voi_pc=voi_error_percent(est.voi_mm3, est.voi_err_mm3), voi_status="recovered"
        )
    if "bins" in stuck:
        changes.update(bins_pp={b: np.nan for b in e.bins_pp}, bins_status="recovered")
    regions = ", ".join(f"the {q} region to {shrink[q]:.2f}" for q in stuck)
    why = (
        f"the next sizes give {growth:.2f} times the elements and shrink {regions} of its size "
        f"(valid_shrink {st.valid_shrink:g}): judged by the recovered estimate"
    )
    return replace(e, **changes), why


def _unsolved_pass(k: int, mesh: TetMesh, times_s: tuple) -> AdaptPass:
    """Pass ``k`` whose solve did not converge on ``mesh``: its (mesh, solve, since the start) times [s]
    and no estimates."""
    mesh_s, solve_s, wall_s = times_s
    nan = np.nan
    return AdaptPass(
        k,
        3 * len(mesh.nodes_mm),
        int(mesh.n_tets),
        False,
        mesh_s,
        solve_s,
        0.0,
        wall_s,
        *(nan,) * 6,
        "no solve",
        float(element_sizes(mesh).min()),
        False,
        {},
        "no solve",
        "no solve",
    )


def goal_verdict(
    voi_err_percent: float,
    bins_err_pp: float,
    force_err_percent: float,
    force_status: str,
    settings: AdaptSettings = AdaptSettings(),
) -> dict:
    """Whether one solution's estimates meet the accuracy goal of ``settings``, and by how much they miss.

    ``voi_err_percent`` [%] and ``bins_err_pp`` (the largest bin's) [pp] are the estimates of the VOI and
    bins; ``force_err_percent`` [%] the force's (NaN: not known, ``force_status`` says why, as
    :class:`AdaptPass`'s). An unknown estimate does not meet its goal: a single mesh (the preview's) has
    none for the force. Returns the summary keys ``within_goal``; ``goal_ratio``, the largest estimate
    over its goal among the known ones (> 1: outside the goal by that factor; NaN if none is known);
    ``voi_err_percent``, ``bins_err_max_pp``, ``force_err_percent``, ``force_err_status``; and
    ``outside_goal``, the numbers that miss their goal and why ('' within the goal).
    """
    st = settings
    checks = [
        ("VOI", voi_err_percent, st.voi_goal_percent, "%"),
        ("bins", bins_err_pp, st.bins_goal_pp, "pp"),
    ]
    if st.force_goal_percent is not None:
        checks.append(("force", force_err_percent, st.force_goal_percent, "%"))
    ratios, missed = [], []
    for name, err, goal, unit in checks:
        if np.isnan(err):
            missed.append(f"{name} not estimated ({force_status})")
            continue
        ratios.append(err / goal)
        if not err <= goal:
            missed.append(f"{name} ±{err:.3g} {unit} > {goal:g} {unit}")
    return dict(
        within_goal=not missed,
        goal_ratio=float(max(ratios)) if ratios else np.nan,
        voi_err_percent=float(voi_err_percent),
        bins_err_max_pp=float(bins_err_pp),
        force_err_percent=float(force_err_percent),
        force_err_status=force_status,
        outside_goal="; ".join(missed),
    )


def voi_error_percent(voi_mm3: float, voi_err_mm3: float) -> float:
    """The VOI's estimated error over the VOI [%]: 0 where both are zero (no element near the threshold
    in either field: a scene strained below it everywhere has nothing to refine for the VOI), infinite
    where only the VOI is (a VOI may exist that the mesh does not resolve)."""
    if voi_mm3 > 0:
        return 100.0 * voi_err_mm3 / voi_mm3
    return 0.0 if voi_err_mm3 == 0 else np.inf


def _next_sizes(
    mesh: TetMesh, h, est: PassEstimate, errors: tuple, st: AdaptSettings, max_tets: int
) -> tuple[np.ndarray, str]:
    """The next pass's element sizes, and why the contact zone is not refined (``'budget'``, ``'h_min'``
    or ``''``): for the VOI and for the bins (``errors``: their estimates and the force's), each above
    ``safety`` of its goal, the elements of its indicator by :func:`target_sizes`, aiming its total at
    ``safety`` over its ratio of estimate to goal (one indicator and the worse ratio where the
    estimator does not split them), and each that misses its goal to at most ``valid_shrink`` of
    their size (``h_min_mm`` at least), so that the next pass extrapolates it; the contact zone shrunk by
    (safety goal / estimate)^(1/force_order) while the force misses its goal (by max_shrink^(1/2) while its
    estimate is not known), at most to ``valid_shrink``; then the refined sizes scaled up
    together until the estimated element count fits ``max_tets`` (this refinement's budget). A contact zone whose mean size would
    not shrink to ``valid_shrink`` is left to the VOI and bins (its change would not estimate
    the force)."""
    voi_pc, bins_pp, force_err = errors
    r_voi, r_bins = voi_pc / st.voi_goal_percent, bins_pp / st.bins_goal_pp
    eta = np.asarray(est.indicator_mm3, float)
    if est.voi_indicator_mm3 is None:
        parts = [(eta, max(r_voi, r_bins))]
    else:
        eta_voi = np.asarray(est.voi_indicator_mm3, float)
        parts = [(eta_voi, r_voi), (np.maximum(eta - eta_voi, 0.0), r_bins)]
    new_h = h.copy()
    for part, ratio in parts:
        total = float(part.sum())
        if total > 0 and ratio > st.safety:
            # an unbounded ratio (no VOI, a non-zero estimate) shrinks the indicator's elements as far as one pass may
            ratio = min(ratio, 1e12)
            target = target_sizes(h, part, st.safety * total / ratio, st)
            if ratio > 1:  # missing its goal: shrunk enough that the next pass extrapolates
                on = part > 0
                target[on] = np.minimum(
                    target[on], np.maximum(h[on] * st.valid_shrink, st.h_min_mm)
                )
            new_h = np.minimum(new_h, target)
    c = est.contact_tets
    if (
        st.force_goal_percent is None
        or c is None
        or not c.any()
        or force_err <= st.force_goal_percent
    ):
        return fit_budget(mesh, h, new_h, max_tets, grading=st.grading), ""
    f = (
        np.sqrt(st.max_shrink)
        if not np.isfinite(force_err)
        else np.clip(
            (st.safety * st.force_goal_percent / force_err) ** (1.0 / st.force_order),
            st.max_shrink,
            1.0,
        )
    )
    refined = new_h.copy()
    refined[c] = np.minimum(
        new_h[c], np.clip(h[c] * min(f, st.valid_shrink), st.h_min_mm, st.h_max_mm)
    )
    enough = st.valid_shrink * h[c].mean()
    if refined[c].mean() > enough:
        return fit_budget(mesh, h, new_h, max_tets, grading=st.grading), "h_min"
    fitted = fit_budget(mesh, h, refined, max_tets, grading=st.grading)
    if fitted[c].mean() > enough:
        return fit_budget(mesh, h, new_h, max_tets, grading=st.grading), "budget"
    return fitted, ""


def fit_budget(
    mesh: TetMesh, h_mm, new_h_mm, max_tets: float, *, grading: float = AdaptSettings.grading
) -> np.ndarray:
    """``new_h_mm`` (n_tets,) [mm] with every refined size (below the present sizes ``h_mm``) scaled by
    the smallest common factor λ >= 1, never past ``h_mm``, for which the mesh of its graded node sizes
    (:func:`node_sizes` with ``current_mm=h_mm``) has at most ``max_tets`` tetrahedra by
    :func:`estimated_tets`, the unchanged elements counted as they are (``new_h_mm`` itself if it fits;
    ``h_mm`` if even λ → ∞ does not)."""
    h, nh = np.asarray(h_mm, float), np.asarray(new_h_mm, float)

    def sized(lam):
        return np.where(nh < h, np.minimum(h, lam * nh), nh)

    now = node_sizes(mesh, h, grading=grading, current_mm=h)

    def count(lam):
        sizes = node_sizes(mesh, sized(lam), grading=grading, current_mm=h)
        return estimated_tets(mesh, sizes, current_mm=now)

    if count(1.0) <= max_tets:
        return nh
    lo, hi = 1.0, float(np.max(h / nh))
    if count(hi) > max_tets:
        return sized(hi)
    while hi / lo > 1.01:  # λ within 1 %: the count within about 3 %
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if count(mid) > max_tets else (lo, mid)
    return sized(hi)
