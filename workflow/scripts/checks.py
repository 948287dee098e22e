"""Glue: every check of one animal (segmentation of each state, pose with a during scan) in one checks.csv."""

import logging

from deeptissue.io import script_log
from deeptissue.segment_checks import merge_checks

with script_log(snakemake.log[0], "checks"):  # noqa: F821
    inp = snakemake.input  # noqa: F821
    n = merge_checks(
        snakemake.output.checks,  # noqa: F821
        segmentation={
            s: inp[f"segmentation_{s}"]
            for s in ("pre", "during")
            if f"segmentation_{s}" in inp.keys()
        },
        pose=inp.get("pose"),
    )
    logging.info("%s: %d checks", snakemake.output.checks, n)  # noqa: F821
