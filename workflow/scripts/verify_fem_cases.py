"""Glue of rule verify_fem_cases: patch tests, rigid bone motion, hard convergence cases."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.scenes import write_case_verification

with script_log(snakemake.log[0], "verify_fem_cases"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    write_case_verification(
        Ogden.from_config(snakemake.params.material),
        checks_csv=snakemake.output.checks,
        hard_csv=snakemake.output.hard,
    )
