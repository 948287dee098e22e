"""Glue of rule verify_cylinder_adaptive: the cylinder scene on adaptive meshes against the fixed ones."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.cylinder import write_adaptive_cylinder

with script_log(snakemake.log[0], "verify_cylinder_adaptive"):  # noqa: F821
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    write_adaptive_cylinder(
        Ogden.from_config(snakemake.params.material),  # noqa: F821
        voi_csv=snakemake.input.voi,
        curve_csv=snakemake.input.curve,  # noqa: F821
        out_csv=snakemake.output.table,
        figure_png=snakemake.output.figure,
    )  # noqa: F821
