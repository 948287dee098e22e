"""Glue of rule solve: one animal x variant -> summary.json and result.vtu."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.linsolve import pin_reproducible
from deeptissue.io import script_log
from deeptissue.study import SolvePaths, run_solve

with script_log(snakemake.log[0], "solve"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    if snakemake.params.fem.get("reproducible"):
        pin_reproducible()  # before the first MKL call of this process
    run_solve(
        SolvePaths(
            mesh=snakemake.input.mesh,
            pose=snakemake.input.pose,
            summary=snakemake.output.summary,
            vtu=snakemake.output.vtu,
            cast=snakemake.input.cast,
            during_contours=snakemake.input.during_contours,
            bone_state=snakemake.input.bone_state,
            end_state=snakemake.output.end_state,
            base_state=snakemake.input.base_state or None,
        ),
        animal=snakemake.wildcards.animal,
        variant=snakemake.wildcards.variant,
        fem_cfg=snakemake.params.fem,
        study_cfg=snakemake.params.study,
        base_variant=snakemake.params.base_variant,
    )
