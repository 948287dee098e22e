"""Glue of rule adaptive_aggregate: every adaptive run's passes and the fixed mesh's solves -> table and figure."""

from deeptissue.adapt_limb import write_adaptive_study
from deeptissue.io import script_log

with script_log(snakemake.log[0], "adaptive_aggregate"):  # noqa: F821
    write_adaptive_study(list(snakemake.input.passes), list(snakemake.input.fixed),  # noqa: F821
                         out_csv=snakemake.output.passes, figure_png=snakemake.output.figure)  # noqa: F821
