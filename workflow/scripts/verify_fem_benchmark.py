"""Glue of rule verify_fem_benchmark: wall time and DOFs of the reference indentation."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.scenes import write_benchmark

with script_log(snakemake.log[0], "verify_fem_benchmark"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    write_benchmark(
        Ogden.from_config(snakemake.params.material), benchmark_csv=snakemake.output.benchmark
    )
