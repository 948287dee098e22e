"""Glue of rule convergence_run: one animal x variant x setting -> one row (JSON)."""

from deeptissue.convergence import Discretisation, RunJob, run_convergence_job
from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.linsolve import pin_reproducible
from deeptissue.io import script_log

with script_log(snakemake.log[0], "convergence_run"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    if snakemake.params.fem.get("reproducible"):
        pin_reproducible()  # before the first MKL call of this process
    job = RunJob(
        animal=snakemake.wildcards.animal,
        variant=snakemake.wildcards.conv_variant,
        setting=Discretisation.from_dict(dict(snakemake.params.setting)),
        mesh_variants=snakemake.params.mesh_variants or None,
        is_default=bool(snakemake.params.is_default),
        linear_reference=bool(snakemake.params.linear_reference),
    )
    run_convergence_job(
        job,
        contours_path=snakemake.input.contours,
        pose_path=snakemake.input.pose,
        cast_path=snakemake.input.cast,
        row_path=snakemake.output.row,
        model_cfg=dict(snakemake.params.model),
        fem_cfg=dict(snakemake.params.fem),
        study_cfg=dict(snakemake.params.study),
    )
