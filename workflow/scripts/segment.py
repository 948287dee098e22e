"""Glue: segment skin and tibia on every slice of one state; write contours and the QC figure."""
import logging
import sys

sys.stderr = open(snakemake.log[0], "w")
logging.basicConfig(stream=sys.stderr, level=logging.INFO)

from deeptissue.segment import segment_files

inp = snakemake.input
segment_files(
    inp.image,
    contours_out=snakemake.output.contours,
    qc_out=snakemake.output.qc,
    animal=snakemake.wildcards.animal,
    state=snakemake.wildcards.state,
    settings=snakemake.params.settings,
    crop_mm=snakemake.params.crop_mm,
    reference=inp.get("reference"),
    overrides=inp.get("overrides"),
    truth=inp.get("truth"),
)
