"""Solution-driven refinement of one limb variant: :func:`deeptissue.adapt.adapt` on an animal's model.

Each pass meshes the limb (:func:`deeptissue.model.build_model` with the variant's contact patch; the
first pass at the model's element size everywhere, the next ones from the background size field of the
previous pass), solves the bone rotation and the indentation on that mesh
(:func:`deeptissue.fem.solver.solve_bone_rotation`, :func:`deeptissue.study.solve_variant`; the cast
contacts the new mesh's skin facets, the indenter its patch) and estimates the discretisation error of
the VOI, its bins and the force (:func:`limb_estimate`). Every pass solves the whole load path on its
own mesh: a previous pass's solution carried to a new mesh folds its tets where the tissue is crushed
between the indenter and the bone (:func:`deeptissue.adapt.adapt`).

A turned variant (``sphere_rx+15`` of ``sphere``, :func:`deeptissue.variants.turn_base`) rides its base
variant's passes: the base's meshes carry the turned variants' patches too, and each converged pass
writes its mesh and end state (:func:`pass_files`). The turned variant's first passes are those
meshes, each solved by turning the indenter from the base's end state on the same mesh
(:func:`deeptissue.fem.solver.solve_turned`, no state moves between meshes), and its own estimates
judge them; where they miss the goal, it meshes its own next passes and solves them from the start.
:func:`run_adaptive_variant` is the rule ``adapt_variant``.
"""

from __future__ import annotations

import itertools
import logging
import shutil
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from .adapt import AdaptPass, AdaptResult, AdaptSettings, PassEstimate, adapt
from .contours import Contours, load_contours
from .errorest import voi_error_estimate
from .fem.cast import Cast as SolverCast
from .fem.indenters import Indenter
from .fem.material import Ogden
from .fem.solver import EndState, SolverSettings, load_end_state, solve_bone_rotation
from .io import atomic_path
from .mesh import SizeField, TetMesh, load_tetmesh, save_tetmesh
from .model import Cast, ModelSettings, build_model, load_cast
from .pose import Pose, load_pose
from .strain import ElementStrain, element_strain
from .study import (
    FemPhysics,
    StudySettings,
    VariantJob,
    accuracy_fields,
    solve_variant,
    variant_indenter,
)
from .summary import (
    SAMPLING_LEVELS,
    Summary,
    failed_summary,
    qc_warnings_of,
    write_result_vtu,
    write_summary,
)
from .variants import adaptive_turns

__all__ = [
    "AdaptFiles",
    "LimbJob",
    "LimbSolve",
    "adaptive_limb",
    "contact_tets",
    "limb_estimate",
    "limb_mesher",
    "limb_solver",
    "load_pass_states",
    "loop_estimates",
    "pass_files",
    "run_adaptive_variant",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LimbJob:
    """One limb variant to solve on adaptive meshes: the animal's pre contours, pose and model cast
    (:func:`deeptissue.model.load_cast`, contacted by every pass's skin facets), the tissue law, the
    solver's, model's and study's settings, the during scan's skin contour points [mm] (None: no skin
    agreement), the bar's length end to end [mm], the variants turned from this one (their patches are
    tagged on every pass's mesh, so that they ride its passes) and the variant this one is turned from
    (None: a base variant)."""

    animal: str
    variant: str
    contours: Contours
    pose: Pose
    cast: Cast
    material: Ogden
    solver: SolverSettings
    model: ModelSettings | dict | None = None
    study: StudySettings = StudySettings()
    skin_contours_mm: np.ndarray | None = None
    bar_length_mm: float = 10.0
    turned: tuple[str, ...] = ()
    base_variant: str | None = None

    def indenter(self) -> Indenter:
        """The variant's rigid indenter on this animal's pose."""
        return variant_indenter(self.pose, self.variant, bar_length_mm=self.bar_length_mm)


@dataclass(frozen=True)
class LimbSolve:
    """One pass's solve: what :func:`deeptissue.adapt.adapt` reads (``converged``, ``indenter_force_N`` [N],
    ``displacement_mm`` (n_nodes, 3)) and the variant's summary and centroid strain on that mesh."""

    converged: bool
    indenter_force_N: float
    displacement_mm: np.ndarray
    summary: Summary
    strain: ElementStrain


def limb_mesher(
    contours: Contours,
    pose: Pose,
    variant: str,
    *,
    cast: Cast,
    settings: ModelSettings | dict | None = None,
    animal: str = "?",
    turned: Sequence[str] = (),
) -> Callable[[SizeField | None], TetMesh]:
    """``build_mesh(size_field) -> TetMesh`` of :func:`deeptissue.adapt.adapt` for one variant: the
    animal's limb (:func:`deeptissue.model.build_model`) with the facet sets ``bone``, ``skin`` (the
    cast's contact set), ``proximal``, ``distal``, ``patch_<variant>``, ``patch_<t>`` of each variant
    ``t`` of ``turned`` (the patches are tagged on the finished mesh, which they do not change) and
    ``patch`` (their union). Without a size
    field the mesh has the model's ``element_size_mm`` everywhere: the loop never coarsens, so it starts
    from the coarsest mesh and refines only where the estimate asks."""
    s = settings if isinstance(settings, ModelSettings) else ModelSettings.from_dict(settings)
    uniform = replace(s, refine_size_mm=s.element_size_mm)

    def build(size_field: SizeField | None) -> TetMesh:
        return build_model(
            contours,
            pose,
            variants=[variant, *turned],
            settings=uniform if size_field is None else s,
            animal=animal,
            cast=cast,
            size_field=size_field,
        ).mesh

    return build


def limb_solver(
    job: LimbJob,
    *,
    deadline_s: float | None = None,
    base: Sequence[tuple[TetMesh, EndState]] = (),
    states_dir: str | Path | None = None,
) -> Callable[[TetMesh], LimbSolve]:
    """``solve(mesh) -> LimbSolve`` of :func:`deeptissue.adapt.adapt`. On a mesh of ``base`` (the base
    variant's passes, :func:`load_pass_states`) the variant is turned from the base's end state there
    (:func:`deeptissue.study.solve_variant` with ``base``; from the start if that does not converge).
    Every other pass solves the bone-rotation steps on its mesh
    (:func:`deeptissue.fem.solver.solve_bone_rotation`), then the variant from that state as the rule
    ``solve`` does (:func:`deeptissue.study.solve_variant`, which solves the rotation itself if those
    steps did not converge). ``deadline_s`` (``time.perf_counter()`` seconds) ends every solve there, as
    the solver's ``max_wall_s`` (the smaller of the two): a pass that cannot finish within the loop's
    budget is stopped instead of running on. ``states_dir``: where each converged pass's mesh and end
    state are written (:func:`pass_files`, the passes counted in the order solved)."""
    cast = SolverCast(job.cast.vertices_mm, job.cast.triangles)
    turn_from = {id(mesh): state for mesh, state in base}
    passes = itertools.count()  # adapt() solves each pass once, in order

    def solve(mesh: TetMesh) -> LimbSolve:
        k = next(passes)
        settings = job.solver
        if deadline_s is not None:
            left = max(deadline_s - time.perf_counter(), 1.0)
            settings = replace(settings, max_wall_s=min(settings.max_wall_s or np.inf, left))
        state, start = turn_from.get(id(mesh)), None
        if state is None:
            _, start = solve_bone_rotation(
                mesh,
                material=job.material,
                bone_motion=job.pose.bone_motion,
                cast=cast,
                settings=settings,
            )
        variant_job = VariantJob(
            animal=job.animal,
            variant=job.variant,
            pose=job.pose,
            material=job.material,
            settings=settings,
            cast=cast,
            study=job.study,
            skin_contours_mm=job.skin_contours_mm,
            bar_length_mm=job.bar_length_mm,
        )
        mesh_path, end_path = (None, None) if states_dir is None else pass_files(states_dir, k)
        summary, u, strain = solve_variant(
            variant_job,
            mesh,
            start=start,
            base=state,
            base_variant=job.base_variant,
            end_state_path=end_path,
        )
        if summary.converged and mesh_path is not None:
            save_tetmesh(mesh_path, mesh)
        force = summary.indenter_force_N
        return LimbSolve(
            converged=summary.converged,
            indenter_force_N=np.nan if force is None else float(force),
            displacement_mm=u,
            summary=summary,
            strain=strain,
        )

    return solve


def pass_files(states_dir: str | Path, k: int) -> tuple[Path, Path]:
    """The mesh file (:func:`deeptissue.mesh.save_tetmesh`) and the end-state file
    (:func:`deeptissue.fem.solver.save_end_state`) of converged pass ``k`` in ``states_dir``."""
    d = Path(states_dir)
    return d / f"pass{k}_mesh.npz", d / f"pass{k}_end_state.npz"


def load_pass_states(states_dir: str | Path) -> list[tuple[TetMesh, EndState]]:
    """The (mesh, end state) of each converged pass in ``states_dir`` (:func:`pass_files`), from pass 0 to
    the first pass without both files; ValueError naming the file that is not a mesh or an end state."""
    out = []
    while True:
        mesh_path, state_path = pass_files(states_dir, len(out))
        if not (mesh_path.is_file() and state_path.is_file()):
            return out
        out.append((load_tetmesh(mesh_path), load_end_state(state_path)))


def contact_tets(
    mesh: TetMesh,
    displacement_mm,
    indenter: Indenter,
    *,
    facet: str = "patch",
    tol_mm: float = 0.02,
) -> np.ndarray:
    """The elements (n_tets,) bool with a node of the ``facet`` set that ends within ``tol_mm`` of the
    indenter's surface at its final tip, or inside it: the contact zone that decides the indenter's
    force (a sphere's or a bar's). ``tol_mm`` 0.02 mm: about the solver's largest penetration, so a
    node the indenter holds counts and one a tenth of an element away does not."""
    nodes = np.unique(mesh.facets[facet])
    x = mesh.nodes_mm[nodes] + np.asarray(displacement_mm, float)[nodes]
    g, _, _ = indenter.gap(x, np.asarray(indenter.end_mm, float))
    touching = np.zeros(len(mesh.nodes_mm), bool)
    touching[nodes[g <= tol_mm]] = True
    return touching[mesh.tets].any(axis=1)


def limb_estimate(
    mesh: TetMesh, solution: LimbSolve, indenter: Indenter, study: StudySettings = StudySettings()
) -> PassEstimate:
    """``estimate(mesh, solution)`` of :func:`deeptissue.adapt.adapt`: the VOI and bins of the pass's
    summary, their recovered-strain error estimate as the summary computes it
    (:func:`deeptissue.errorest.voi_error_estimate` at the study's sampling), its per-element
    indicator, the force and the contact zone on the variant's patch (:func:`contact_tets`)."""
    s = solution.summary
    levels = SAMPLING_LEVELS if study.gamma_sampling == "points" else 0
    e = voi_error_estimate(
        mesh,
        solution.displacement_mm,
        threshold=study.threshold,
        bin_edges=study.bin_edges,
        strain_measure=study.strain_measure,
        levels=levels,
    )
    facet = s.extra.get("contact_set") or "patch"
    return PassEstimate(
        voi_mm3=float(s.voi_mm3),
        voi_err_mm3=e.voi_err_mm3,
        bins_err_pp=max(e.bins_err_pp.values()),
        force_N=solution.indenter_force_N,
        indicator_mm3=e.indicator_mm3,
        contact_tets=contact_tets(mesh, solution.displacement_mm, indenter, facet=facet),
        bins_percent=dict(s.bins_percent),
        voi_indicator_mm3=e.threshold_indicator_mm3,
    )


def adaptive_limb(
    job: LimbJob,
    settings: AdaptSettings = AdaptSettings(),
    *,
    base: Sequence[tuple[TetMesh, EndState]] = (),
    states_dir: str | Path | None = None,
    log_pass: Callable[[str], None] | None = None,
) -> AdaptResult:
    """One limb variant on adaptive meshes: :func:`deeptissue.adapt.adapt` with :func:`limb_mesher`,
    :func:`limb_solver` and :func:`limb_estimate` until the estimates meet the goals of ``settings`` or
    its budget is spent; its first passes are the meshes of ``base`` (the base variant's passes, on which
    this variant is turned from their end states) and every converged pass's mesh and end state go to
    ``states_dir`` (:func:`limb_solver`). Returns the AdaptResult (``solution``: the last converged
    pass's :class:`LimbSolve`)."""
    indenter = job.indenter()
    deadline_s = time.perf_counter() + settings.max_wall_s
    return adapt(
        limb_mesher(
            job.contours,
            job.pose,
            job.variant,
            cast=job.cast,
            settings=job.model,
            animal=job.animal,
            turned=job.turned,
        ),
        limb_solver(job, deadline_s=deadline_s, base=base, states_dir=states_dir),
        lambda mesh, sol: limb_estimate(mesh, sol, indenter, job.study),
        settings,
        given=[mesh for mesh, _ in base],
        log=log_pass,
    )


@dataclass(frozen=True)
class AdaptFiles:
    """The files of rule ``adapt_variant``: inputs ``contours`` (pre), ``pose``, ``cast``,
    ``during_contours`` (None: no skin agreement) and ``base_states`` (the folder of the base variant's
    converged passes, :func:`pass_files`; None: not a turned variant); outputs ``passes_csv``,
    ``summary``, ``vtu`` (None: not written) and ``states`` (the folder of this run's converged passes;
    None: not written)."""

    contours: str | Path
    pose: str | Path
    cast: str | Path
    during_contours: str | Path | None
    passes_csv: str | Path
    summary: str | Path
    vtu: str | Path | None = None
    base_states: str | Path | None = None
    states: str | Path | None = None


def run_adaptive_variant(
    *,
    animal: str,
    variant: str,
    files: AdaptFiles,
    model_cfg: dict | None,
    fem_cfg: dict,
    study_cfg: dict,
    settings: AdaptSettings = AdaptSettings(),
) -> AdaptResult | None:
    """Rule ``adapt_variant``: read the pre contours, pose, cast and during contours, run
    :func:`adaptive_limb` and write ``files.passes_csv`` (one row per pass,
    :meth:`deeptissue.adapt.AdaptResult.table` with animal, variant and stop_reason), ``files.summary``
    (the last converged pass's summary, as the rule ``solve`` writes it, its VOI and bin estimates the
    loop's (:func:`loop_estimates`), with ``adapt_passes``,
    ``adapt_stop_reason``, ``adapt_wall_s`` [s] and the last converged pass's verdict,
    :func:`deeptissue.study.accuracy_fields`; the failed pass's summary if none converged) and
    ``files.vtu`` (that pass's ``result.vtu``, :func:`deeptissue.summary.write_result_vtu`). A run that
    raises (its passes table then has no rows), or whose first pass does not converge, writes a summary
    with ``converged = False`` and the reason and the first pass's mesh undeformed, so that the study goes
    on without this variant (as rule ``solve`` does); returns None if it raised. ``files.states`` gets
    each converged pass's mesh and end state (:func:`pass_files`) where other variants ride this one's
    passes, and is left empty otherwise; a turned variant
    (:func:`deeptissue.variants.adaptive_turns`) rides the base's passes in ``files.base_states``.

    ``model_cfg``, ``fem_cfg`` and ``study_cfg`` are the config sections ``model`` (with
    ``bar_length_mm``, as the rule ``mesh`` gets it), ``fem`` and ``study`` (with the animal's
    ``variants``).
    """
    study = StudySettings.from_config(study_cfg)
    pose = load_pose(files.pose)
    contours, cast = load_contours(files.contours), load_cast(files.cast)
    base_variant, turned = adaptive_turns(
        variant, study_cfg.get("variants") or (), study_cfg.get("turn_from_base", True)
    )
    if files.states is not None:
        shutil.rmtree(files.states, ignore_errors=True)
        Path(files.states).mkdir(parents=True)
    reason = ""
    try:
        physics = FemPhysics.from_config(fem_cfg)
        job = LimbJob(
            animal=animal,
            variant=variant,
            contours=contours,
            pose=pose,
            cast=cast,
            material=physics.material,
            solver=physics.settings,
            model=model_cfg,
            study=study,
            skin_contours_mm=load_contours(files.during_contours).skin
            if files.during_contours
            else None,
            bar_length_mm=physics.bar_length_mm,
            turned=turned,
            base_variant=base_variant,
        )
        result = adaptive_limb(
            job,
            settings,
            base=_base_passes(files.base_states, base_variant, variant),
            states_dir=files.states if turned else None,  # only what a turned variant rides
            log_pass=lambda line: log.info("%s/%s adaptive %s", animal, variant, line),
        )
    except Exception as exc:  # recorded, never lost: the study goes on without this variant
        log.error("%s/%s adaptive run failed:\n%s", animal, variant, traceback.format_exc())
        result, reason = None, f"{type(exc).__name__}: {exc}"
    _write_passes(files.passes_csv, result, animal, variant)
    mesher = limb_mesher(contours, pose, variant, cast=cast, settings=model_cfg, animal=animal)
    summary, mesh, u, strain = _answer(
        result, reason, study, animal, variant, mesher if files.vtu is not None else None
    )
    solved = [p for p in result.passes if p.converged] if result is not None else []
    if solved:
        summary = loop_estimates(summary, solved[-1])
    # the last converged pass's verdict: the loop's VOI, bin and force estimates
    extra = accuracy_fields(
        summary,
        mesh="adaptive",
        force_err_percent=solved[-1].force_err_percent if solved else np.nan,
        force_status=solved[-1].force_status if solved else "no solve",
        goal=settings,
    )
    if result is not None:
        extra.update(
            adapt_passes=len(result.passes),
            adapt_stop_reason=result.stop_reason,
            adapt_wall_s=float(result.passes[-1].wall_s) if result.passes else None,
        )
    summary = replace(summary, extra={**summary.extra, **extra})
    if files.vtu is not None:
        write_result_vtu(
            files.vtu,
            mesh,
            u,
            strain,
            cell_data={"converged": np.full(mesh.n_tets, int(summary.converged))},
        )
    try:
        summary = replace(summary, qc_warnings=qc_warnings_of(files.pose))
    except (OSError, ValueError) as exc:
        log.warning("%s: QC warnings not read (%s)", files.pose, exc)
    write_summary(files.summary, summary)
    return result


def _base_passes(states_dir, base_variant, variant) -> list[tuple[TetMesh, EndState]]:
    """The base variant's converged passes in ``states_dir``; none without a base, or where its run
    converged on no pass or its meshes lack this variant's patch (a base run for other variants): this
    variant then meshes and solves its own passes from the start."""
    if states_dir is None or base_variant is None:
        return []
    passes = load_pass_states(states_dir)
    why = ""
    if not passes:
        why = f"{base_variant} converged on no adaptive pass"
    elif any(f"patch_{variant}" not in mesh.facets for mesh, _ in passes):
        why = f"the meshes of {base_variant} have no patch_{variant}"
    if why:
        log.warning("%s: %s: this variant is solved from the start", states_dir, why)
        return []
    return passes


def loop_estimates(summary: Summary, last: AdaptPass) -> Summary:
    """``summary`` (of the pass ``last``) with the loop's VOI and bin estimates where they come from the
    passes (``voi_status`` / ``bins_status`` 'estimated' or 'held': ``voi_err_mm3`` = VOI × ``voi_err_percent``,
    ``bins_err_pp`` = ``bins_err``) instead of its own recovered-strain ones, and the statuses in ``extra``
    (``voi_err_status``, ``bins_err_status``)."""
    changes = {}
    if last.voi_status != "recovered" and summary.voi_mm3 is not None:
        changes["voi_err_mm3"] = float(summary.voi_mm3) * last.voi_err_percent / 100.0
    if last.bins_status != "recovered" and last.bins_err:
        changes["bins_err_pp"] = dict(last.bins_err)
    extra = {
        **summary.extra,
        "voi_err_status": last.voi_status,
        "bins_err_status": last.bins_status,
    }
    return replace(summary, **changes, extra=extra)


def _write_passes(path, result: AdaptResult | None, animal: str, variant: str) -> None:
    """passes.csv: one row per pass with animal, variant and stop_reason (no rows if the run raised)."""
    if result is not None:
        table = result.table().assign(
            animal=animal, variant=variant, stop_reason=result.stop_reason
        )
    else:
        table = pd.DataFrame(dict(animal=[], variant=[], stop_reason=[]))
    table = table[
        ["animal", "variant", *[c for c in table.columns if c not in ("animal", "variant")]]
    ]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        table.to_csv(tmp, index=False)


def _answer(
    result: AdaptResult | None,
    reason: str,
    study: StudySettings,
    animal: str,
    variant: str,
    mesher: Callable[[SizeField | None], TetMesh] | None,
):
    """(summary, mesh, displacement, strain) of the run: its last converged pass, or a failed summary
    with the first pass's mesh (``mesher(None)``) undeformed (None for the mesh and fields without a
    mesher)."""
    if result is not None and result.solution is not None:
        sol = result.solution
        return sol.summary, result.mesh, sol.displacement_mm, sol.strain
    if result is not None:  # the first solve did not converge
        reason = f"adaptive pass 0: {result.stop_reason}"
        n_tets = result.passes[-1].n_tets if result.passes else None
    else:
        reason, n_tets = f"adaptive run: {reason}", None
    summary = failed_summary(
        animal=animal,
        variant=variant,
        reason=reason,
        strain_measure=study.strain_measure,
        threshold=study.threshold,
        gamma_sampling=study.gamma_sampling,
        n_elements=n_tets,
    )
    if mesher is None:
        return summary, None, None, None
    mesh = mesher(None)
    u = np.zeros_like(mesh.nodes_mm)
    return summary, mesh, u, element_strain(mesh, u)
