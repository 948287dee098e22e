"""Glue of rule solve: one animal x variant -> summary.json and result.vtu."""

import contextlib
import logging

from deeptissue.study import run_solve

with open(snakemake.log[0], "w") as log, contextlib.redirect_stderr(log):
    logging.basicConfig(stream=log, level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    run_solve(
        animal=snakemake.wildcards.animal,
        variant=snakemake.wildcards.variant,
        mesh_path=snakemake.input.mesh,
        cast_path=snakemake.input.cast,
        pose_path=snakemake.input.pose,
        during_contours_path=snakemake.input.during_contours,
        summary_path=snakemake.output.summary,
        vtu_path=snakemake.output.vtu,
        fem_cfg=snakemake.params.fem,
        study_cfg=snakemake.params.study,
    )
