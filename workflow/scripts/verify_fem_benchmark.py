"""Glue of rule verify_fem_benchmark: wall time and DOFs of the reference indentation."""

import logging

from deeptissue.fem.material import Ogden
from deeptissue.fem.verification import write_benchmark

logging.basicConfig(filename=snakemake.log[0], level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
try:
    write_benchmark(Ogden.from_config(snakemake.params.material), benchmark_csv=snakemake.output.benchmark)
except Exception:
    logging.exception("verify_fem_benchmark failed")
    raise
