"""Glue: distances of segmented to true contours (phantom), per slice and structure, as CSV."""
import logging
import sys

sys.stderr = open(snakemake.log[0], "w")
logging.basicConfig(stream=sys.stderr, level=logging.INFO)

from deeptissue.segment import write_accuracy

write_accuracy(snakemake.input.contours, snakemake.input.truth, snakemake.output.csv)
