"""Glue of rule pose_accuracy: errors of the estimated pose against the phantom truth."""

import logging
import sys

from deeptissue.pose import run_pose_accuracy

sys.stderr = open(snakemake.log[0], "w")  # noqa: F821
logging.basicConfig(stream=sys.stderr, level=logging.INFO)

rows = run_pose_accuracy(
    pose_json=snakemake.input.pose,  # noqa: F821
    truth_json=snakemake.input.truth,  # noqa: F821
    csv_path=snakemake.output.csv,  # noqa: F821
)
for row in rows:
    logging.info("%s", row)
