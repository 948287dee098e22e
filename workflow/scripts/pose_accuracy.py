"""Glue of rule pose_accuracy: errors of the estimated pose against the phantom truth."""

import logging

from deeptissue.io import script_log
from deeptissue.pose import run_pose_accuracy

with script_log(snakemake.log[0], "pose_accuracy"):  # noqa: F821
    rows = run_pose_accuracy(
        pose_json=snakemake.input.pose,  # noqa: F821
        truth_json=snakemake.input.truth,  # noqa: F821
        csv_path=snakemake.output.csv,  # noqa: F821
    )
    for row in rows:
        logging.info("%s", row)
