"""Glue of rule verify_material: material-point checks, homogeneous responses, speed (failures recorded, not raised)."""

from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.material import run_material_verification

with script_log(snakemake.log[0], "verify_material"):
    run_material_verification(
        Ogden.from_config(snakemake.params.material),
        point_csv=snakemake.output.points,
        homogeneous_csv=snakemake.output.homogeneous,
        figure_png=snakemake.output.figure,
        speed_csv=snakemake.output.speed,
        raise_on_failure=False,  # rule verify_summary judges the checks
    )
