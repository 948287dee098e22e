"""Glue of rule verify_material: material-point checks, homogeneous responses, speed."""

import logging

from deeptissue.fem.material import Ogden
from deeptissue.fem.material_checks import run_material_verification

logging.basicConfig(filename=snakemake.log[0], level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
try:
    run_material_verification(
        Ogden.from_config(snakemake.params.material),
        point_csv=snakemake.output.points,
        homogeneous_csv=snakemake.output.homogeneous,
        figure_png=snakemake.output.figure,
        speed_csv=snakemake.output.speed,
    )
except Exception:
    logging.exception("verify_material failed")
    raise
