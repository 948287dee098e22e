"""Glue of rule solve: one animal x variant -> summary.json and result.vtu."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.linsolve import pin_reproducible
from deeptissue.io import script_log
from deeptissue.study import run_solve

with script_log(snakemake.log[0], "solve"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    if snakemake.params.fem.get("reproducible"):
        pin_reproducible()  # before the first MKL call of this process
    run_solve(
        animal=snakemake.wildcards.animal,
        variant=snakemake.wildcards.variant,
        mesh_path=snakemake.input.mesh,
        bone_state_path=snakemake.input.bone_state,
        end_state_path=snakemake.output.end_state,
        base_state_path=snakemake.input.base_state or None,
        base_variant=snakemake.params.base_variant,
        cast_path=snakemake.input.cast,
        pose_path=snakemake.input.pose,
        during_contours_path=snakemake.input.during_contours,
        summary_path=snakemake.output.summary,
        vtu_path=snakemake.output.vtu,
        fem_cfg=snakemake.params.fem,
        study_cfg=snakemake.params.study,
    )
