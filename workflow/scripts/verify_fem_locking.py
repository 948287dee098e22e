"""Glue of rule verify_locking: Hertz force error of the displacement formulation as D -> 0."""

import logging

from deeptissue.fem.material import Ogden
from deeptissue.fem.verification import write_locking_check

logging.basicConfig(filename=snakemake.log[0], level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
try:
    write_locking_check(Ogden.from_config(snakemake.params.material), locking_csv=snakemake.output.locking)
except Exception:
    logging.exception("verify_locking failed")
    raise
