"""Glue of rule verify_locking: Hertz force error of the displacement formulation as D -> 0."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.scenes import write_locking_check

with script_log(snakemake.log[0], "verify_fem_locking"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    write_locking_check(
        Ogden.from_config(snakemake.params.material), locking_csv=snakemake.output.locking
    )
