"""Glue of rule verify_hertz: sphere into a block against Hertz to depth 0.1 R."""

import logging

from deeptissue.fem.material import Ogden
from deeptissue.fem.verification import write_hertz_verification

logging.basicConfig(filename=snakemake.log[0], level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
try:
    write_hertz_verification(Ogden.from_config(snakemake.params.material), hertz_csv=snakemake.output.hertz)
except Exception:
    logging.exception("verify_hertz failed")
    raise
