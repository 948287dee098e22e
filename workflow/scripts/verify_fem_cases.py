"""Glue of rule verify_fem_cases: patch tests, rigid bone motion, hard convergence cases."""

import logging

from deeptissue.fem.material import Ogden
from deeptissue.fem.verification import write_case_verification

logging.basicConfig(filename=snakemake.log[0], level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
try:
    write_case_verification(Ogden.from_config(snakemake.params.material), checks_csv=snakemake.output.checks,
                            hard_csv=snakemake.output.hard)
except Exception:
    logging.exception("verify_fem_cases failed")
    raise
