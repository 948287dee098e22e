"""Glue of rule verify_summary: one row per check of the verification tables (written even if checks fail)."""

import logging

from deeptissue.io import script_log
from deeptissue.verification.scenes import VerificationCsvs, write_verification_summary

with script_log(snakemake.log[0], "verify_summary"):  # noqa: F821
    summary = write_verification_summary(
        VerificationCsvs(
            points=snakemake.input.points,  # noqa: F821
            hertz=snakemake.input.hertz,  # noqa: F821
            curve=snakemake.input.curve,  # noqa: F821
            locking=snakemake.input.locking,  # noqa: F821
            checks=snakemake.input.checks,  # noqa: F821
            hard=snakemake.input.hard,  # noqa: F821
            benchmark=snakemake.input.benchmark,  # noqa: F821
            cylinder_curve=snakemake.input.cylinder_curve,  # noqa: F821
            cylinder_voi=snakemake.input.cylinder_voi,  # noqa: F821
            cylinder_adaptive=snakemake.input.cylinder_adaptive,  # noqa: F821
        ),
        snakemake.output.summary,  # noqa: F821
    )
    logging.info("verification summary\n%s", summary.to_string(index=False))
