"""Glue of rule verify_hertz_curve: sphere force-depth curve to depth 2 R and the Hertz plot."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.scenes import write_hertz_curve

with script_log(snakemake.log[0], "verify_fem_hertz_curve"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    write_hertz_curve(
        Ogden.from_config(snakemake.params.material),
        hertz_csv=snakemake.input.hertz,
        curve_csv=snakemake.output.curve,
        figure_png=snakemake.output.figure,
    )
