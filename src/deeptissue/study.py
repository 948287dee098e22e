"""One study job: an animal's model, pose and one variant -> FE solution, strain statistics, files.

A variant that does not converge is returned by :func:`solve_variant` as a summary with
``converged = False`` and the reason; :func:`run_solve` records any error after the mesh is read
(reading the pose, cast or contours, setting up, solving) the same way, so the study goes on and the
aggregate step can mark the animal excluded.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .adapt import AdaptSettings, goal_verdict, voi_error_percent
from .contours import load_contours
from .fem.cast import Cast
from .fem.indenters import Indenter
from .fem.material import Ogden, ogden_energy
from .fem.solver import (
    BoneState,
    EndState,
    FacetSets,
    Scene,
    SolveResult,
    SolverSettings,
    end_state,
    load_bone_state,
    load_end_state,
    save_bone_state,
    save_end_state,
    solve_bone_rotation,
    solve_from,
    solver_settings_from_config,
)
from .io import save_npz
from .mesh import TetMesh, load_tetmesh
from .pose import Pose, load_pose
from .strain import DEFAULT_BIN_EDGES, ElementStrain, StrainError, element_strain
from .summary import (
    Summary,
    VoiSpec,
    failed_summary,
    qc_warnings_of,
    summarize_solution,
    write_result_vtu,
    write_summary,
)
from .variants import parse_variant, variant_travel

log = logging.getLogger(__name__)

__all__ = [
    "FemPhysics",
    "SolvePaths",
    "StudySettings",
    "VariantJob",
    "accuracy_fields",
    "run_bone_state",
    "run_solve",
    "solve_variant",
    "variant_indenter",
]


@dataclass(frozen=True)
class StudySettings:
    """Post-processing settings of the study (config ``study``). Which mesh a variant is solved on
    (``study.mesh``) picks the rule: ``solve`` on the model's mesh, ``adapt_variant`` on adaptive ones."""

    threshold: float = 0.3
    bin_edges: tuple = tuple(DEFAULT_BIN_EDGES)
    strain_measure: str = "green_lagrange"
    gamma_sampling: str = "points"  # 'points' (64 per element) or 'centroid' (the paper's), see summary.GAMMA_SAMPLINGS

    @classmethod
    def from_config(cls, study_cfg: dict | None) -> StudySettings:
        """From the config section ``study`` (defaults for missing keys)."""
        d = dict(study_cfg or {})
        return cls(
            threshold=float(d.get("threshold", 0.3)),
            bin_edges=tuple(d.get("bin_edges", DEFAULT_BIN_EDGES)),
            strain_measure=d.get("strain_measure", "green_lagrange"),
            gamma_sampling=d.get("gamma_sampling", "points"),
        )


def accuracy_fields(
    summary: Summary,
    *,
    mesh: str,
    force_err_percent: float = np.nan,
    force_status: str = "one mesh",
    goal: AdaptSettings = AdaptSettings(),
) -> dict:
    """The summary keys that say whether a variant's numbers are within the accuracy goal by their own
    estimates (:func:`deeptissue.adapt.goal_verdict`: ``within_goal``, ``goal_ratio``, ``outside_goal``
    and the estimates), and ``mesh_kind`` (``mesh``: 'fixed' or 'adaptive'). The VOI's and bins'
    estimates are the summary's (``voi_err_mm3``, ``bins_err_pp``); the force's is given (a single
    mesh has none: ``force_status`` 'one mesh'). A variant that did not converge is outside the goal."""
    if not summary.converged:
        return dict(
            mesh_kind=mesh, within_goal=False, goal_ratio=np.nan, outside_goal="not converged"
        )
    voi_pc = voi_error_percent(summary.voi_mm3, summary.voi_err_mm3)
    bins = max((summary.bins_err_pp or {}).values(), default=0.0)
    return dict(
        mesh_kind=mesh, **goal_verdict(voi_pc, bins, force_err_percent, force_status, goal)
    )


def variant_indenter(
    pose: Pose, variant_name: str, *, radius_mm: float = 1.5, bar_length_mm: float = 10.0
) -> Indenter:
    """The rigid indenter of a variant: shape from the name, axis turned about the final tip.

    Parameters
    ----------
    pose : Pose
        Estimated indenter axis and tip travel [mm].
    variant_name : str
        :func:`deeptissue.variants.parse_variant` name.
    radius_mm : float
        Head, shaft and bar radius [mm] (1.5: the 3 mm indenter).
    bar_length_mm : float
        Bar length end to end [mm] (config ``fem.bar_length_mm``).

    Returns
    -------
    Indenter
        Tip travelling from the variant's start to its end tip [mm].
    """
    v = parse_variant(variant_name)
    axis, start, end = variant_travel(
        v, axis=pose.indenter_axis, tip_start_mm=pose.tip_start_mm, tip_end_mm=pose.tip_end_mm
    )
    return Indenter(
        kind=v.indenter,
        axis=tuple(axis),
        start_mm=tuple(start),
        end_mm=tuple(end),
        radius_mm=radius_mm,
        bar_length_mm=bar_length_mm,
    )


@dataclass(frozen=True)
class FemPhysics:
    """The config section ``fem`` read once for every solve: the tissue law, the solver's settings and the
    bar's length end to end [mm] (10: ``fem.bar_length_mm``'s default, the paper's oblong indenter)."""

    material: Ogden
    settings: SolverSettings
    bar_length_mm: float = 10.0

    @classmethod
    def from_config(cls, fem_cfg: dict | None, *, solver_cfg: dict | None = None) -> FemPhysics:
        """From the config section ``fem`` (defaults for missing keys); ``solver_cfg`` in place of its
        ``solver`` section where a run sets its own (a convergence setting's tolerances)."""
        d = dict(fem_cfg or {})
        return cls(
            material=Ogden(**d.get("material", {})),
            settings=solver_settings_from_config(
                d.get("solver") if solver_cfg is None else solver_cfg
            ),
            bar_length_mm=float(d.get("bar_length_mm", cls.bar_length_mm)),
        )


@dataclass(frozen=True)
class VariantJob:
    """What one variant's solve needs besides its mesh: the run, the indenter's travel, the physics and
    the summary's settings.

    Attributes
    ----------
    animal, variant : str
        The run; ``variant`` is a :func:`deeptissue.variants.parse_variant` name.
    pose : Pose
        Indenter travel and bone motion [mm, deg].
    material : Ogden
        Tissue law.
    settings : SolverSettings
        Solver settings (the indenter's contact set is the variant's patch).
    cast : Cast or None
        Rigid cast (None: no cast contact).
    study : StudySettings
        Threshold, bins, strain measure and sampling of the summary.
    skin_contours_mm : (..., 3) array_like or None
        During-scan skin contour points [mm] for the skin agreement (None: no comparison).
    bar_length_mm : float
        Bar length end to end [mm] (10: config ``fem.bar_length_mm``'s default).
    """

    animal: str
    variant: str
    pose: Pose
    material: Ogden
    settings: SolverSettings
    cast: Cast | None = None
    study: StudySettings = StudySettings()
    skin_contours_mm: np.ndarray | None = None
    bar_length_mm: float = 10.0


def solve_variant(
    job: VariantJob,
    mesh: TetMesh,
    *,
    start: BoneState | None = None,
    base: EndState | None = None,
    base_variant: str | None = None,
    end_state_path=None,
):
    """Solve one variant and summarise it.

    For a solve that did not converge the summary says why, and the displacement is the last
    converged state (so its strain field can still be looked at, never counted). Exceptions of
    the set-up or solver are not caught here (:func:`run_solve` records them).

    Parameters
    ----------
    job : VariantJob
        The run, pose, cast, material, solver and study settings.
    mesh : TetMesh
        Reference mesh [mm] with facet sets ``bone``, ``skin`` and ``patch_<variant>`` (or ``patch``).
    start : BoneState or None
        The mesh's shared bone-rotation state (:func:`run_bone_state`); None: solved here.
    base : EndState or None
        The converged end state of ``base_variant`` on this mesh, whose indenter this variant's
        turns about the same final tip (:func:`deeptissue.variants.turn_base`): the variant is solved
        by turning the indenter from there (:func:`deeptissue.fem.solver.solve_turned`), and from
        ``start`` as usual if that fails (the times and iterations of both are reported).
    base_variant : str or None
        Name of the variant ``base`` belongs to (reported as ``turned_from``).
    end_state_path : str or Path or None
        Where to write the converged end state (:func:`deeptissue.fem.solver.save_end_state`), the
        start of the variants turned from this one; a solve that does not converge writes nothing.

    Returns
    -------
    summary : Summary
        :func:`deeptissue.summary.summarize_solution` or :func:`deeptissue.summary.failed_summary`,
        with the solver's costs and contact diagnostics.
    displacement_mm : (n_nodes, 3) ndarray
        Nodal displacement [mm]: the last converged state if not converged (zero if that state has no strain:
        an element inverted at its centroid, between the solver's quadrature points).
    strain : ElementStrain
        Centroid strain of that displacement.
    """
    t0 = time.perf_counter()
    indenter = variant_indenter(job.pose, job.variant, bar_length_mm=job.bar_length_mm)
    set_name = f"patch_{job.variant}" if f"patch_{job.variant}" in mesh.facets else "patch"
    scene = Scene(
        job.material,
        indenter,
        bone_motion=job.pose.bone_motion,
        cast=job.cast,
        sets=FacetSets(indenter=set_name),
    )
    result = solve_from(mesh, scene, base=base, start=start, settings=job.settings)
    info = _solve_info(
        result,
        contact_set=set_name,
        turned_from=base_variant if result.extra.get("turned") else None,
        wall_s=time.perf_counter() - t0,
    )
    if not result.converged:
        return _unconverged(job, mesh, result, info)
    if end_state_path is not None:
        state = end_state(
            result,
            mesh,
            indenter=indenter,
            bone_motion=job.pose.bone_motion,
            settings=job.settings,
        )
        save_end_state(end_state_path, state)
    summary, strain = summarize_solution(
        mesh,
        result.displacement_mm,
        animal=job.animal,
        variant=job.variant,
        voi=VoiSpec(
            strain_measure=job.study.strain_measure,
            threshold=job.study.threshold,
            bin_edges=job.study.bin_edges,
            gamma_sampling=job.study.gamma_sampling,
        ),
        energy_density_mpa=ogden_energy(result.deformation_gradient, job.material),
        skin_contours_mm=job.skin_contours_mm,
        **info,
    )
    return summary, result.displacement_mm, strain


def _solve_info(
    result: SolveResult, *, contact_set: str, turned_from: str | None, wall_s: float
) -> dict:
    """The solver's costs and contact diagnostics that every variant's summary carries: ``wall_s`` [s]
    is the whole solve's, set-up included; ``turned_from`` the base variant if the turn was used."""
    return dict(
        indenter_force_N=result.indenter_force_N,
        n_dofs=result.n_dofs,
        increments=result.increments,
        newton_iterations=result.newton_iterations,
        wall_s=wall_s,
        solver_wall_s=result.wall_s,
        assembly_s=result.assembly_s,
        linear_solve_s=result.linear_solve_s,
        contact_s=result.contact_s,
        max_penetration_mm=result.max_penetration_mm,
        max_penetration_rel=result.max_penetration_rel,
        load_reached=result.load_reached,
        contact_set=contact_set,
        active_set_changes=result.extra.get("active_set_changes"),
        bone_clearance_mm=result.extra.get("bone_clearance_mm"),
        started_from_bone_state=result.extra.get("started_from_bone_state", False),
        turned_from=turned_from,
        turn_failed=result.extra.get("turn_failed"),
    )


def _unconverged(job: VariantJob, mesh: TetMesh, result: SolveResult, info: dict):
    """The summary, displacement and strain of a solve that did not converge: the solver's reason and
    its last converged state, or the undeformed mesh if that state has no strain."""
    log.warning("%s/%s did not converge: %s", job.animal, job.variant, result.reason)
    u, reason = result.displacement_mm, result.reason
    try:
        strain = element_strain(mesh, u)
    except StrainError as exc:
        # the solver admits a state by its quadrature points; one folded between them has no strain to
        # show, and the solver's reason, load and costs must not be lost to it
        u = np.zeros_like(mesh.nodes_mm)
        strain = element_strain(mesh, u)
        reason = (
            f"{reason}; its last state has no strain ({exc}): result.vtu shows the undeformed mesh"
        )
    summary = failed_summary(
        animal=job.animal,
        variant=job.variant,
        reason=reason,
        strain_measure=job.study.strain_measure,
        threshold=job.study.threshold,
        gamma_sampling=job.study.gamma_sampling,
        n_elements=int(mesh.n_tets),
        **info,
    )
    return summary, u, strain


def run_bone_state(
    *, mesh_path, cast_path, pose_path, state_path, fem_cfg: dict
) -> BoneState | None:
    """Rule ``bone_state``: the bone-rotation steps of one mesh, solved once for all its variants.

    The steps are :func:`deeptissue.fem.solver.solve_bone_rotation`. If they do not converge (or the
    set-up fails) the file says so (an array ``failed`` with the reason) and every variant solves
    them itself; nothing is lost. Never raises for a failed solve.

    Parameters
    ----------
    mesh_path, cast_path, pose_path : str or Path
        Model mesh (:func:`deeptissue.mesh.load_tetmesh`), cast (``cast.npz``; falsy: no cast) and pose.
    state_path : str or Path
        Output ``bone_state.npz`` (:func:`deeptissue.fem.solver.save_bone_state`).
    fem_cfg : dict
        Config section ``fem`` (``material``, ``solver``).

    Returns
    -------
    BoneState or None
        The state written, None if the rotation was not solved.
    """
    state, why = None, ""
    try:
        mesh = load_tetmesh(mesh_path)
        pose = load_pose(pose_path)
        cast = Cast.load(cast_path) if cast_path else None
        physics = FemPhysics.from_config(fem_cfg)
        r, state = solve_bone_rotation(
            mesh,
            material=physics.material,
            bone_motion=pose.bone_motion,
            cast=cast,
            settings=physics.settings,
        )
        why = r.reason
    except Exception as exc:  # the variants then solve the rotation themselves
        log.error("bone state of %s failed:\n%s", mesh_path, traceback.format_exc())
        why = f"{type(exc).__name__}: {exc}"
    if state is None:
        log.warning(
            "%s: bone rotation not solved once for all variants (%s): each variant solves it",
            mesh_path,
            why,
        )
        save_npz(state_path, failed=np.array(why or "not converged"))
        return None
    log.info(
        "bone rotation of %s: %d increments, %d Newton iterations, %.1f s",
        mesh_path,
        len(state.history),
        state.newton_iterations,
        state.wall_s,
    )
    save_bone_state(state_path, state)
    return state


def _failed_marker(path, what: str) -> str | None:
    """Why the job that writes ``path`` failed (its file says so), or None if the file holds a state."""
    try:
        with np.load(path) as d:
            return str(d["failed"]) if "failed" in d else None
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not {what} file ({exc})") from exc


def _load_start(path) -> BoneState | None:
    """The shared bone state of ``path``, None if that solve failed (its file says why)."""
    if (failed := _failed_marker(path, "a bone-state")) is not None:
        log.warning(
            "%s: the shared bone rotation failed (%s): solving it for this variant", path, failed
        )
        return None
    return load_bone_state(path)


def _load_base(path, base_variant) -> EndState | None:
    """The end state of the base variant in ``path``, None if that solve did not converge (its file says why)."""
    if (failed := _failed_marker(path, "an end-state")) is not None:
        log.warning(
            "%s: %s did not converge (%s): solving this variant from the start",
            path,
            base_variant,
            failed,
        )
        return None
    return load_end_state(path)


@dataclass(frozen=True)
class SolvePaths:
    """The files of rule ``solve`` (each a str or Path).

    Attributes
    ----------
    mesh, pose : str or Path
        Model mesh (:func:`deeptissue.mesh.load_tetmesh`) and pose (:func:`deeptissue.pose.load_pose`).
    summary, vtu : str or Path
        Outputs (:func:`deeptissue.summary.write_summary`, :func:`deeptissue.summary.write_result_vtu`
        with cell data ``converged``).
    cast : str or Path or None
        The cast (``cast.npz``; falsy: no cast).
    during_contours : str or Path or None
        During-scan contours, whose skin is compared with the deformed model (falsy: no comparison).
    bone_state : str or Path or None
        The mesh's shared bone state (:func:`run_bone_state`); a file that records a failure means
        this variant solves the rotation itself.
    end_state : str or Path or None
        Output: the converged end state (the start of the variants turned from this one), or, after
        a failure, a file saying why.
    base_state : str or Path or None
        The end state of the base variant (:func:`deeptissue.variants.turn_base`), the start of this one.
    """

    mesh: str | Path
    pose: str | Path
    summary: str | Path
    vtu: str | Path
    cast: str | Path | None = None
    during_contours: str | Path | None = None
    bone_state: str | Path | None = None
    end_state: str | Path | None = None
    base_state: str | Path | None = None


def run_solve(
    paths: SolvePaths,
    *,
    animal: str,
    variant: str,
    fem_cfg: dict,
    study_cfg: dict,
    base_variant: str | None = None,
) -> Summary:
    """Rule ``solve``: read the model files, solve, write ``summary.json`` and ``result.vtu``.

    Once the mesh is read, both files are always written: a failure (set-up error or no convergence)
    gives a summary with ``converged = False`` and the reason, and a VTU of the last converged state
    (or the undeformed mesh when nothing was solved).

    Parameters
    ----------
    paths : SolvePaths
        The files read and written.
    animal, variant : str
        The run.
    fem_cfg : dict
        Config section ``fem`` (``material``, ``solver``, ``bar_length_mm``).
    study_cfg : dict
        Config section ``study`` (:class:`StudySettings`).
    base_variant : str or None
        The name of the variant whose end state is ``paths.base_state``.

    Returns
    -------
    Summary
        What was written to ``paths.summary``.
    """
    if paths.end_state is not None:
        Path(paths.end_state).unlink(missing_ok=True)
    study = StudySettings.from_config(study_cfg)
    mesh = load_tetmesh(paths.mesh)
    try:
        job = _read_job(paths, animal=animal, variant=variant, fem_cfg=fem_cfg, study=study)
        summary, u, strain = solve_variant(
            job,
            mesh,
            start=_load_start(paths.bone_state) if paths.bone_state else None,
            base=_load_base(paths.base_state, base_variant) if paths.base_state else None,
            base_variant=base_variant,
            end_state_path=paths.end_state,
        )
    except Exception as exc:  # recorded, never lost: the study goes on without this variant
        log.error("%s/%s failed:\n%s", animal, variant, traceback.format_exc())
        summary = failed_summary(
            animal=animal,
            variant=variant,
            reason=f"{type(exc).__name__}: {exc}",
            strain_measure=study.strain_measure,
            threshold=study.threshold,
            gamma_sampling=study.gamma_sampling,
            n_elements=int(mesh.n_tets),
        )
        u = np.zeros_like(mesh.nodes_mm)
        strain = element_strain(mesh, u)
    return _write_solve_outputs(paths, mesh, summary, u, strain)


def _read_job(
    paths: SolvePaths, *, animal: str, variant: str, fem_cfg: dict, study: StudySettings
) -> VariantJob:
    """The variant's job from its pose, cast and during contours files and the config section ``fem``."""
    pose = load_pose(paths.pose)
    cast = Cast.load(paths.cast) if paths.cast else None
    skin = load_contours(paths.during_contours).skin if paths.during_contours else None
    physics = FemPhysics.from_config(fem_cfg)
    return VariantJob(
        animal=animal,
        variant=variant,
        pose=pose,
        material=physics.material,
        settings=physics.settings,
        cast=cast,
        study=study,
        skin_contours_mm=skin,
        bar_length_mm=physics.bar_length_mm,
    )


def _write_solve_outputs(
    paths: SolvePaths, mesh: TetMesh, summary: Summary, u: np.ndarray, strain: ElementStrain
) -> Summary:
    """Write the outputs of rule ``solve``: a failure marker for a missing end state, ``result.vtu`` and the
    summary with its accuracy fields and the animal's QC warnings (which travel with every variant's numbers).
    Returns the summary written."""
    summary = replace(summary, extra={**summary.extra, **accuracy_fields(summary, mesh="fixed")})
    if paths.end_state is not None and not Path(paths.end_state).exists():
        save_npz(paths.end_state, failed=np.array(summary.reason or "not converged"))
    write_result_vtu(
        paths.vtu,
        mesh,
        u,
        strain,
        cell_data={"converged": np.full(mesh.n_tets, int(summary.converged))},
    )
    try:
        summary = replace(summary, qc_warnings=qc_warnings_of(paths.pose))
    except (OSError, ValueError) as exc:
        log.warning("%s: QC warnings not read (%s)", paths.pose, exc)
    write_summary(paths.summary, summary)
    return summary
