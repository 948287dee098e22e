"""Glue of rule verify_hertz_curve: sphere force-depth curve to depth 2 R and the Hertz plot."""

import logging

from deeptissue.fem.material import Ogden
from deeptissue.fem.verification import write_hertz_curve

logging.basicConfig(filename=snakemake.log[0], level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
try:
    write_hertz_curve(Ogden.from_config(snakemake.params.material), hertz_csv=snakemake.input.hertz,
                      curve_csv=snakemake.output.curve, figure_png=snakemake.output.figure)
except Exception:
    logging.exception("verify_hertz_curve failed")
    raise
