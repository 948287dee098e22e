"""Solution-driven refinement of one limb variant: :func:`deeptissue.adapt.adapt` on an animal's model.

Each pass meshes the limb (:func:`deeptissue.model.build_model` with the variant's contact patch; the
first pass at the model's element size everywhere, the next ones from the background size field of the
previous pass), solves the bone rotation and the indentation on that mesh
(:func:`deeptissue.fem.solver.solve_bone_rotation`, :func:`deeptissue.study.solve_variant`; the cast
contacts the new mesh's skin facets, the indenter its patch) and estimates the discretisation error of
the VOI, its bins and the force (:func:`limb_estimate`). :func:`run_adaptive_variant` is the rule
``adapt_variant``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from .adapt import AdaptResult, AdaptSettings, PassEstimate, adapt
from .contours import Contours
from .errorest import voi_error_estimate
from .fem.cast import Cast as SolverCast
from .fem.indenters import Indenter
from .fem.material import Ogden
from .fem.solver import SolverSettings, solve_bone_rotation
from .fem.transfer import mapped_end_state
from .mesh import SizeField, TetMesh
from .model import Cast, ModelSettings, build_model
from .pose import Pose
from .strain import ElementStrain
from .study import StudySettings, accuracy_fields, solve_variant, variant_indenter
from .summary import SAMPLING_LEVELS, Summary

__all__ = [
    "LimbSolve",
    "adaptive_limb",
    "contact_tets",
    "limb_estimate",
    "limb_mesher",
    "limb_solver",
    "run_adaptive_variant",
]

log = logging.getLogger(__name__)


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
) -> Callable[[SizeField | None], TetMesh]:
    """``build_mesh(size_field) -> TetMesh`` of :func:`deeptissue.adapt.adapt` for one variant: the
    animal's limb (:func:`deeptissue.model.build_model`) with the facet sets ``bone``, ``skin`` (the
    cast's contact set), ``proximal``, ``distal``, ``patch_<variant>`` and ``patch``. Without a size
    field the mesh has the model's ``element_size_mm`` everywhere: the loop never coarsens, so it starts
    from the coarsest mesh and refines only where the estimate asks."""
    s = settings if isinstance(settings, ModelSettings) else ModelSettings.from_dict(settings)
    uniform = replace(s, refine_size_mm=s.element_size_mm)

    def build(size_field: SizeField | None) -> TetMesh:
        return build_model(
            contours,
            pose,
            variants=[variant],
            settings=uniform if size_field is None else s,
            animal=animal,
            cast=cast,
            size_field=size_field,
        ).mesh

    return build


def limb_solver(
    *,
    animal: str,
    variant: str,
    pose: Pose,
    cast: SolverCast | None,
    material: Ogden,
    settings: SolverSettings,
    study: StudySettings = StudySettings(),
    skin_contours_mm=None,
    bar_length_mm: float = 10.0,
    deadline_s: float | None = None,
) -> Callable[[TetMesh, tuple | None], LimbSolve]:
    """``solve(mesh, previous) -> LimbSolve`` of :func:`deeptissue.adapt.adapt`. The first pass solves the
    bone-rotation steps on the mesh (:func:`deeptissue.fem.solver.solve_bone_rotation`), then the variant
    from that state as the rule ``solve`` does (:func:`deeptissue.study.solve_variant`, which solves the
    rotation itself if those steps did not converge). A later pass starts from the previous pass's solution
    carried to its mesh (:func:`deeptissue.fem.transfer.mapped_end_state`, ``turned_from`` "previous pass")
    and solves the whole path only if that state folds tets or does not converge. ``deadline_s``
    (``time.perf_counter()`` seconds) ends every solve there, as the solver's ``max_wall_s`` (the smaller
    of the two): a pass that cannot finish within the loop's budget is stopped instead of running on.
    Other keywords as in :func:`deeptissue.study.solve_variant`."""
    indenter = variant_indenter(pose, variant, bar_length_mm=bar_length_mm)

    def solve(mesh: TetMesh, previous: tuple | None) -> LimbSolve:
        settings_ = settings
        if deadline_s is not None:
            left = max(deadline_s - time.perf_counter(), 1.0)
            settings_ = replace(settings, max_wall_s=min(settings.max_wall_s or np.inf, left))
        start = base = None
        if previous is None:
            _, start = solve_bone_rotation(
                mesh,
                material=material,
                bone_motion=pose.bone_motion,
                cast=cast,
                settings=settings_,
            )
        else:
            base = mapped_end_state(
                previous[0],
                previous[1].displacement_mm,
                mesh,
                indenter=indenter,
                bone_motion=pose.bone_motion,
                settings=settings_,
            )
        summary, u, strain = solve_variant(
            animal=animal,
            variant=variant,
            mesh=mesh,
            pose=pose,
            cast=cast,
            material=material,
            settings=settings_,
            study=study,
            skin_contours_mm=skin_contours_mm,
            bar_length_mm=bar_length_mm,
            start=start,
            base=base,
            base_variant="previous pass",
        )
        force = summary.indenter_force_N
        return LimbSolve(
            converged=summary.converged,
            indenter_force_N=np.nan if force is None else float(force),
            displacement_mm=u,
            summary=summary,
            strain=strain,
        )

    return solve


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
    *,
    animal: str,
    variant: str,
    contours: Contours,
    pose: Pose,
    cast: Cast,
    material: Ogden,
    solver_settings: SolverSettings,
    model_settings: ModelSettings | dict | None = None,
    study: StudySettings = StudySettings(),
    skin_contours_mm=None,
    bar_length_mm: float = 10.0,
    settings: AdaptSettings = AdaptSettings(),
    log_pass: Callable[[str], None] | None = None,
) -> AdaptResult:
    """One limb variant on adaptive meshes: :func:`deeptissue.adapt.adapt` with :func:`limb_mesher`,
    :func:`limb_solver` and :func:`limb_estimate` until the estimates meet the goals of ``settings`` or
    its budget is spent. ``cast`` is the model's cast (:func:`deeptissue.model.load_cast`), contacted by
    every pass's skin facets. Returns the AdaptResult (``solution``: the last converged pass's
    :class:`LimbSolve`)."""
    indenter = variant_indenter(pose, variant, bar_length_mm=bar_length_mm)
    deadline_s = time.perf_counter() + settings.max_wall_s
    return adapt(
        limb_mesher(contours, pose, variant, cast=cast, settings=model_settings, animal=animal),
        limb_solver(
            animal=animal,
            variant=variant,
            pose=pose,
            cast=SolverCast(cast.vertices_mm, cast.triangles),
            material=material,
            settings=solver_settings,
            study=study,
            skin_contours_mm=skin_contours_mm,
            bar_length_mm=bar_length_mm,
            deadline_s=deadline_s,
        ),
        lambda mesh, sol: limb_estimate(mesh, sol, indenter, study),
        settings,
        log=log_pass,
    )


def run_adaptive_variant(
    *,
    animal: str,
    variant: str,
    contours_path,
    pose_path,
    cast_path,
    during_contours_path,
    passes_csv,
    summary_path,
    model_cfg: dict | None,
    fem_cfg: dict,
    study_cfg: dict,
    vtu_path=None,
    settings: AdaptSettings = AdaptSettings(),
) -> AdaptResult | None:
    """Rule ``adapt_variant``: read the pre contours, pose, cast and during contours, run
    :func:`adaptive_limb` and write ``passes_csv`` (one row per pass, :meth:`deeptissue.adapt.AdaptResult.table`
    with animal, variant and stop_reason), ``summary_path`` (the last converged pass's summary, as
    the rule ``solve`` writes it, with ``adapt_passes``, ``adapt_stop_reason``, ``adapt_wall_s`` [s] and the last converged pass's
    verdict (:func:`deeptissue.study.accuracy_fields`, ``within_goal``); the failed pass's summary if none converged) and ``vtu_path`` (that pass's
    ``result.vtu``, :func:`deeptissue.summary.write_result_vtu`). A run that raises (its passes table then
    has no rows), or whose first pass does not converge, writes a summary with ``converged = False`` and
    the reason and the first pass's mesh undeformed, so that the study goes on without this variant (as
    rule ``solve`` does); returns None if it raised.

    ``model_cfg``, ``fem_cfg`` and ``study_cfg`` are the config sections ``model`` (with
    ``bar_length_mm``, as the rule ``mesh`` gets it), ``fem`` and ``study``.
    """
    import traceback

    from .contours import load_contours
    from .fem.solver import solver_settings_from_config
    from .io import atomic_path
    from .model import load_cast
    from .pose import load_pose
    from .strain import element_strain
    from .summary import failed_summary, qc_warnings_of, write_result_vtu, write_summary

    study = StudySettings.from_config(study_cfg)
    pose = load_pose(pose_path)
    contours, cast = load_contours(contours_path), load_cast(cast_path)

    def solver_log(line: str) -> None:
        log.info("%s/%s adaptive %s", animal, variant, line)

    try:
        result = adaptive_limb(
            animal=animal,
            variant=variant,
            contours=contours,
            pose=pose,
            cast=cast,
            material=Ogden(**fem_cfg.get("material", {})),
            solver_settings=solver_settings_from_config(fem_cfg.get("solver")),
            model_settings=model_cfg,
            study=study,
            skin_contours_mm=load_contours(during_contours_path).skin
            if during_contours_path
            else None,
            bar_length_mm=float(fem_cfg.get("bar_length_mm", 10.0)),
            settings=settings,
            log_pass=solver_log,
        )
    except Exception as exc:  # recorded, never lost: the study goes on without this variant
        log.error("%s/%s adaptive run failed:\n%s", animal, variant, traceback.format_exc())
        result, reason = None, f"{type(exc).__name__}: {exc}"
    if result is not None:
        table = result.table().assign(
            animal=animal, variant=variant, stop_reason=result.stop_reason
        )
    else:
        table = pd.DataFrame(dict(animal=[], variant=[], stop_reason=[]))
    table = table[
        ["animal", "variant", *[c for c in table.columns if c not in ("animal", "variant")]]
    ]
    Path(passes_csv).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(passes_csv) as tmp:
        table.to_csv(tmp, index=False)
    if result is not None and result.solution is not None:
        summary, mesh = result.solution.summary, result.mesh
        u, strain = result.solution.displacement_mm, result.solution.strain
    else:
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
        mesh = (
            limb_mesher(contours, pose, variant, cast=cast, settings=model_cfg, animal=animal)(
                None
            )
            if vtu_path
            else None
        )
        u = None if mesh is None else np.zeros_like(mesh.nodes_mm)
        strain = None if mesh is None else element_strain(mesh, u)
    # the last converged pass's verdict: its summary's VOI and bin estimates, the loop's force estimate
    solved = [p for p in result.passes if p.converged] if result is not None else []
    accuracy = accuracy_fields(
        summary,
        mesh="adaptive",
        force_err_percent=solved[-1].force_err_percent if solved else np.nan,
        force_status=solved[-1].force_status if solved else "no solve",
        goal=settings,
    )
    summary = replace(summary, extra={**summary.extra, **accuracy})
    if result is not None:
        summary = replace(
            summary,
            extra={
                **summary.extra,
                "adapt_passes": len(result.passes),
                "adapt_stop_reason": result.stop_reason,
                "adapt_wall_s": float(result.passes[-1].wall_s) if result.passes else None,
            },
        )
    if vtu_path is not None:
        write_result_vtu(
            vtu_path,
            mesh,
            u,
            strain,
            cell_data={"converged": np.full(mesh.n_tets, int(summary.converged))},
        )
    try:
        summary = replace(summary, qc_warnings=qc_warnings_of(pose_path))
    except (OSError, ValueError) as exc:
        log.warning("%s: QC warnings not read (%s)", pose_path, exc)
    write_summary(summary_path, summary)
    return result
