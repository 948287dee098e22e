"""One run of the ladder: mesh, solve and summarise one animal x variant at one setting, timed.

:func:`run_discretisation` meshes, solves and post-processes, times each part, and adds one
linear-elastic reference solve on the same mesh (:func:`linear_reference_solve`; ``cost_ratio``).
A :class:`RunJob` names the animal, variant and setting of a run. Its row has the columns
:data:`ROW_COLUMNS`; :func:`run_convergence_job` is rule ``convergence_run``.

Units: mm, N, s, MB (resident memory, 2**20 bytes).
"""

from __future__ import annotations

import logging
import resource
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .ladder import SUPPORTED_ELEMENT_ORDERS, Discretisation

log = logging.getLogger(__name__)

# keys of a row of run_discretisation, the columns of convergence.csv before the errors
ROW_COLUMNS = (
    "animal",
    "variant",
    "setting",
    "family",
    "element_order",
    "element_size_mm",
    "refine_size_mm",
    "tolerance",
    "rtol",
    "gap_tol_rel",
    "mesh_key",
    "is_default",
    "converged",
    "reason",
    "n_elements",
    "n_dofs",
    "increments",
    "newton_iterations",
    "gamma_sampling",
    "voi_mm3",
    "bins_percent",
    "voi_sampled_mm3",
    "bins_sampled_percent",
    "voi_centroid_mm3",
    "bins_centroid_percent",
    "voi_err_mm3",
    "bins_err_pp",
    "peak_gamma",
    "indenter_force_N",
    "mesh_s",
    "assembly_s",
    "linear_solve_s",
    "contact_s",
    "solver_other_s",
    "post_s",
    "solve_s",
    "wall_s",
    "linear_setup_s",
    "linear_assembly_s",
    "linear_factor_solve_s",
    "linear_wall_s",
    "cost_ratio",
    "start_rss_mb",
    "peak_rss_mb",
)


def _rss_mb() -> float:
    """Peak resident set size of this process so far [MB] (Linux: ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def linear_reference_solve(
    mesh, *, material, solver_settings, load_set: str = "patch", direction=(0.0, 0.0, -1.0)
) -> dict:
    """One linear-elastic solve on ``mesh``: the tangent at u = 0 assembled once, factorised once.

    The bone facets are fixed; a total force of 1 N along
    ``direction`` is spread over the nodes of ``load_set``. Timed as the nonlinear solve is: set-up
    (skfem basis, sparsity pattern: ``linear_setup_s``), assembly (``linear_assembly_s``),
    factorisation + solve by PARDISO's Cholesky in mixed precision, the fastest linear solve of the
    tangent (``linear_factor_solve_s``, symbolic analysis included). Returns the times [s] and the largest displacement [mm].
    """
    from ..fem.assembly import Assembler, as_material_law
    from ..fem.linsolve import SymmetricSolver
    from ..fem.skmesh import straighten_invalid

    s = solver_settings
    t0 = time.perf_counter()
    mesh, _ = straighten_invalid(mesh, order=s.quadrature_order)
    n = len(mesh.nodes_mm)
    constrained = np.zeros(3 * n, bool)
    bone = np.unique(mesh.facets["bone"])
    constrained[(3 * bone[:, None] + np.arange(3)).ravel()] = True
    asm = Assembler(
        mesh, as_material_law(material), constrained=constrained, intorder=s.quadrature_order
    )
    t1 = time.perf_counter()
    _, _, data, _ = asm.tangent(np.zeros(3 * n))
    t2 = time.perf_counter()
    loaded = np.unique(mesh.facets[load_set if load_set in mesh.facets else "skin"])
    loaded = loaded[~constrained[3 * loaded]]
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    rhs = np.zeros(3 * n)
    rhs[(3 * loaded[:, None] + np.arange(3)).ravel()] = np.tile(
        d / max(len(loaded), 1), len(loaded)
    )
    solver = SymmetricSolver("mixed")
    try:
        x = solver.solve(asm.csr(data), rhs[asm.free])
    finally:
        solver.close()
    t3 = time.perf_counter()
    return dict(
        linear_setup_s=t1 - t0,
        linear_assembly_s=t2 - t1,
        linear_factor_solve_s=t3 - t2,
        linear_wall_s=t3 - t0,
        linear_max_displacement_mm=float(np.max(np.abs(x))) if len(x) else 0.0,
    )


@dataclass(frozen=True)
class RunJob:
    """One run of the ladder: the animal x variant solved at ``setting``, and what the run records.

    ``mesh_variants``: variants whose travel the mesh is refined around; None: those sharing the
    variant's study mesh (``model.mesh_groups`` of ``study.variants``), so the mesh is the study's
    mesh; the solved variant is always included. ``linear_reference``: also time one linear-elastic
    solve on the same mesh (:func:`linear_reference_solve`). ``is_default``: recorded in the row, the
    setting is the configured default.
    """

    animal: str
    variant: str
    setting: Discretisation
    mesh_variants: Sequence[str] | None = None
    is_default: bool = False
    linear_reference: bool = True


def _blank_row(job: RunJob, start_rss_mb: float) -> dict:
    """A row with the keys :data:`ROW_COLUMNS`: the job and its setting filled in, not converged."""
    s = job.setting
    row: dict = {k: None for k in ROW_COLUMNS}
    row.update(
        animal=job.animal,
        variant=job.variant,
        setting=s.name,
        family=s.family,
        element_order=s.element_order,
        element_size_mm=s.element_size_mm,
        refine_size_mm=s.refine_size_mm,
        tolerance=s.tolerance,
        rtol=s.rtol,
        gap_tol_rel=s.gap_tol_rel,
        mesh_key=s.mesh_key,
        is_default=bool(job.is_default),
        converged=False,
        start_rss_mb=start_rss_mb,
    )
    return row


def _mesh_variants(job: RunJob, model_cfg: dict | None, study_cfg: dict) -> list:
    """The variants the mesh is refined around (:attr:`RunJob.mesh_variants`), the solved one included."""
    from ..model import ModelSettings
    from ..variants import mesh_groups

    if job.mesh_variants:
        variants = list(job.mesh_variants)
    else:  # the variants of the variant's study mesh
        groups = mesh_groups(
            study_cfg.get("variants") or [job.variant],
            by=(model_cfg or {}).get("mesh_groups", ModelSettings.mesh_groups),
        )
        variants = next((list(m) for m in groups.values() if job.variant in m), [])
    if job.variant not in variants:
        variants.append(job.variant)
    return variants


def _solution_columns(summary, run_s: float) -> dict:
    """The row's columns from the solve's summary; ``run_s``: solve + post-processing wall time [s]."""
    d = summary.to_dict()
    solve_s = float(d.get("solver_wall_s") or 0.0)
    parts = {k: float(d.get(k) or 0.0) for k in ("assembly_s", "linear_solve_s", "contact_s")}
    return dict(
        converged=bool(summary.converged),
        reason=summary.reason,
        n_dofs=d.get("n_dofs"),
        increments=d.get("increments"),
        newton_iterations=d.get("newton_iterations"),
        voi_mm3=summary.voi_mm3,
        bins_percent=summary.bins_percent,
        gamma_sampling=summary.gamma_sampling,
        voi_sampled_mm3=summary.voi_sampled_mm3,
        bins_sampled_percent=summary.bins_sampled_percent,
        voi_centroid_mm3=summary.voi_centroid_mm3,
        bins_centroid_percent=summary.bins_centroid_percent,
        voi_err_mm3=summary.voi_err_mm3,
        bins_err_pp=summary.bins_err_pp,
        peak_gamma=summary.peak_gamma,
        indenter_force_N=summary.indenter_force_N,
        solve_s=solve_s,
        solver_other_s=max(solve_s - sum(parts.values()), 0.0),
        post_s=max(run_s - solve_s, 0.0),
        **parts,
    )


def _add_linear_reference(
    row: dict, job: RunJob, mesh, *, pose, material, settings, bar_mm
) -> None:
    """Time the linear-elastic reference on ``mesh`` into ``row`` (``linear_*``, ``cost_ratio``); a
    failure is logged and recorded as ``linear_error``."""
    from ..study import variant_indenter

    variant = job.variant
    axis = variant_indenter(pose, variant, bar_length_mm=bar_mm).axis
    patch = f"patch_{variant}" if f"patch_{variant}" in mesh.facets else "patch"
    try:
        lin = linear_reference_solve(
            mesh, material=material, solver_settings=settings, load_set=patch, direction=axis
        )
        row.update({k: v for k, v in lin.items() if k in ROW_COLUMNS})
        row["cost_ratio"] = (
            row["solve_s"] / lin["linear_wall_s"] if lin["linear_wall_s"] > 0 else None
        )
    except Exception as exc:
        log.exception(
            "%s/%s/%s: linear reference solve failed", job.animal, variant, job.setting.name
        )
        row["linear_error"] = f"{type(exc).__name__}: {exc}"


def _log_row(row: dict) -> None:
    """One log line of a solved row: convergence, size, solve and linear-reference times, memory."""
    log.info(
        "%s/%s/%s: converged %s, %s tets, %s dofs, solve %.1f s, linear %.2f s, peak %.0f MB",
        row["animal"],
        row["variant"],
        row["setting"],
        row["converged"],
        row["n_elements"],
        row["n_dofs"],
        row["solve_s"],
        row["linear_wall_s"] or float("nan"),
        row["peak_rss_mb"],
    )


def run_discretisation(
    job: RunJob,
    *,
    contours,
    pose,
    cast=None,
    model_cfg: dict | None = None,
    fem_cfg: dict | None = None,
    study_cfg: dict | None = None,
) -> dict:
    """Mesh, solve and summarise one animal x variant at one setting, timing each part.

    Parameters
    ----------
    job : RunJob
        The animal, the variant (``study.variants``) and the setting solved; the setting's sizes,
        element order and tolerances override those of ``model_cfg`` and ``fem_cfg``.
    contours : deeptissue.contours.Contours
        The pre-state contours.
    pose : deeptissue.pose.Pose
        The animal's pose.
    cast : deeptissue.model.Cast or None or False
        The cast; None: built here, outside the timing; False: built for the mesh only, no cast
        contact in the solve.
    model_cfg, fem_cfg, study_cfg : dict, optional
        The config sections ``model``, ``fem`` and ``study``.

    Returns
    -------
    dict
        One row with the keys :data:`ROW_COLUMNS`: times [s] of meshing (``mesh_s``), the solver's
        assembly, linear solves and contact and the rest (``solver_other_s``), post-processing
        (``post_s``), the solver's wall time (``solve_s``), all of it (``wall_s``), the linear-elastic
        reference (``linear_*``) and ``cost_ratio = solve_s / linear_wall_s``; peak resident memory
        of the process (``peak_rss_mb``; ``start_rss_mb`` before meshing) [MB]. A failed mesh or solve
        gives a row with ``converged`` false and the reason (never raises for those).

    Raises
    ------
    ValueError
        If the setting's element order is not supported.
    """
    from ..fem.cast import Cast as FemCast
    from ..model import build_cast, build_model
    from ..study import FemPhysics, StudySettings, VariantJob, solve_variant

    animal, variant, setting = job.animal, job.variant, job.setting
    if setting.element_order not in SUPPORTED_ELEMENT_ORDERS:
        raise ValueError(
            f"setting {setting.name}: element order {setting.element_order} is not supported by the mesh/FE "
            f"code (supported: {list(SUPPORTED_ELEMENT_ORDERS)})"
        )
    fem_cfg = dict(fem_cfg or {})
    study_cfg = dict(study_cfg or {})
    row = _blank_row(job, _rss_mb())
    variants = _mesh_variants(job, model_cfg, study_cfg)
    msettings = setting.model_settings(model_cfg)
    physics = FemPhysics.from_config(
        fem_cfg, solver_cfg=setting.solver_config(fem_cfg.get("solver"))
    )
    msettings.setdefault("bar_length_mm", physics.bar_length_mm)
    use_cast = cast is not False
    if (
        cast is None or cast is False
    ):  # the cast does not depend on the element size: built untimed
        cast = build_cast(contours, pose, variants=variants, settings=msettings, animal=animal)
    t0 = time.perf_counter()
    try:
        model = build_model(
            contours, pose, variants=variants, settings=msettings, animal=animal, cast=cast
        )
    except Exception as exc:  # a mesh that fails the quality gate is a result of this setting
        log.error("%s/%s/%s: meshing failed: %s", animal, variant, setting.name, exc)
        row.update(
            reason=f"meshing failed: {type(exc).__name__}: {exc}",
            mesh_s=time.perf_counter() - t0,
            peak_rss_mb=_rss_mb(),
        )
        return row
    mesh = model.mesh
    row["mesh_s"] = time.perf_counter() - t0
    row["n_elements"] = int(mesh.n_tets)
    study = StudySettings.from_config(study_cfg)
    fem_cast = None if not use_cast else FemCast(model.cast.vertices_mm, model.cast.triangles)
    t1 = time.perf_counter()
    try:
        summary, _, _ = solve_variant(
            VariantJob(
                animal=animal,
                variant=variant,
                pose=pose,
                material=physics.material,
                settings=physics.settings,
                cast=fem_cast,
                study=study,
                bar_length_mm=physics.bar_length_mm,
            ),
            mesh,
        )
    except Exception as exc:  # set-up errors of the solver: recorded, the ladder goes on
        log.exception("%s/%s/%s: solve failed", animal, variant, setting.name)
        row.update(reason=f"{type(exc).__name__}: {exc}", peak_rss_mb=_rss_mb())
        return row
    run_s = time.perf_counter() - t1  # solve + post-processing (strain, VOI, bins)
    row.update(_solution_columns(summary, run_s))
    row["wall_s"] = row["mesh_s"] + run_s
    if job.linear_reference:
        _add_linear_reference(
            row,
            job,
            mesh,
            pose=pose,
            material=physics.material,
            settings=physics.settings,
            bar_mm=physics.bar_length_mm,
        )
    row["peak_rss_mb"] = _rss_mb()
    _log_row(row)
    return row


def run_convergence_job(
    job: RunJob,
    *,
    contours_path,
    pose_path,
    cast_path,
    row_path,
    model_cfg: dict,
    fem_cfg: dict,
    study_cfg: dict,
) -> dict:
    """Rule ``convergence_run``: read the animal's pre contours, pose and cast, run
    :func:`run_discretisation` on ``job`` and write the row to ``row_path`` as JSON; returns the row."""
    from ..contours import load_contours
    from ..io import write_json
    from ..model import load_cast
    from ..pose import load_pose

    row = run_discretisation(
        job,
        contours=load_contours(contours_path),
        pose=load_pose(pose_path),
        cast=load_cast(cast_path) if cast_path else None,
        model_cfg=model_cfg,
        fem_cfg=fem_cfg,
        study_cfg=study_cfg,
    )
    write_json(row_path, row)
    return row
