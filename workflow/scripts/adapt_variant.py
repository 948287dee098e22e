"""Glue of rule adapt_variant: one animal x variant on adaptive meshes -> passes.csv, summary.json, result.vtu."""

from deeptissue.adapt_limb import AdaptFiles, run_adaptive_variant
from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.linsolve import pin_reproducible
from deeptissue.io import script_log

with script_log(snakemake.log[0], "adapt_variant"):  # noqa: F821
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    if snakemake.params.fem.get("reproducible"):  # noqa: F821
        pin_reproducible()  # before the first MKL call of this process
    run_adaptive_variant(
        animal=snakemake.wildcards.animal,  # noqa: F821
        variant=snakemake.wildcards.variant,  # noqa: F821
        files=AdaptFiles(
            contours=snakemake.input.contours,  # noqa: F821
            pose=snakemake.input.pose,  # noqa: F821
            cast=snakemake.input.cast,  # noqa: F821
            during_contours=snakemake.input.during_contours,  # noqa: F821
            passes_csv=snakemake.output.passes,  # noqa: F821
            summary=snakemake.output.summary,  # noqa: F821
            vtu=snakemake.output.vtu,  # noqa: F821
            base_states=snakemake.input.base_states or None,  # noqa: F821
            states=snakemake.output.states,  # noqa: F821
        ),
        model_cfg=snakemake.params.model,  # noqa: F821
        fem_cfg=snakemake.params.fem,  # noqa: F821
        study_cfg=snakemake.params.study,  # noqa: F821
    )
