"""Glue of rule verify_cylinder: the cylinder scene on the default and the finest mesh."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.scenes import write_cylinder_verification

with script_log(snakemake.log[0], "verify_cylinder"):  # noqa: F821
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    write_cylinder_verification(
        Ogden.from_config(snakemake.params.material),  # noqa: F821
        curve_csv=snakemake.output.curve,
        voi_csv=snakemake.output.voi,
    )  # noqa: F821
