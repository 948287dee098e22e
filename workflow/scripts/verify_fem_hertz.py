"""Glue of rule verify_hertz: sphere into a block against Hertz to depth 0.1 R."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.scenes import write_hertz_verification

with script_log(snakemake.log[0], "verify_fem_hertz"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    write_hertz_verification(
        Ogden.from_config(snakemake.params.material), hertz_csv=snakemake.output.hertz
    )
