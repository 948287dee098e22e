"""Glue: distances of segmented to true contours (phantom), per slice and structure, as CSV."""

from deeptissue.io import script_log
from deeptissue.segment_accuracy import write_accuracy

with script_log(snakemake.log[0], "segmentation_accuracy"):  # noqa: F821
    write_accuracy(snakemake.input.contours, snakemake.input.truth, snakemake.output.csv)
