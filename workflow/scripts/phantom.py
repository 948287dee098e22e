"""Glue: render one phantom animal (volumes, truth pose, truth contours)."""

import logging

from deeptissue.io import script_log
from deeptissue.phantom import PhantomSpec, write_phantom

with script_log(snakemake.log[0], "phantom"):  # noqa: F821
    ph = write_phantom(
        PhantomSpec.from_config(snakemake.params.phantom),
        pre_path=snakemake.output.pre,
        during_path=snakemake.output.during,
        truth_path=snakemake.output.truth,
        truth_pre_path=snakemake.output.truth_pre,
        truth_during_path=snakemake.output.truth_during,
        n_points=snakemake.params.n_points,
        start_angle_deg=snakemake.params.start_angle_deg,
    )
    logging.info("phantom %s: truth %s", snakemake.wildcards.animal, ph.truth.to_dict())
