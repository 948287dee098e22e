"""Glue: segment skin, tibia and fibula on every slice of one state; write contours and the QC figure."""

from deeptissue.io import script_log
from deeptissue.segment import segment_files

with script_log(snakemake.log[0], "segment"):  # noqa: F821
    inp = snakemake.input
    segment_files(
        inp.image,
        contours_out=snakemake.output.contours,
        qc_out=snakemake.output.qc,
        animal=snakemake.wildcards.animal,
        state=snakemake.wildcards.state,
        settings=snakemake.params.settings,
        crop_mm=snakemake.params.crop_mm,
        leg_point_mm=snakemake.params.leg_point_mm,
        reference=inp.get("reference"),
        overrides=inp.get("overrides"),
        truth=inp.get("truth"),
        pre_contours=inp.get("pre_contours"),
        pose_options=dict(snakemake.params.pose_options),
    )
