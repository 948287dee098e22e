"""Glue of rule verify_summary: one row per check of the verification tables (written even if checks fail)."""

import logging

from deeptissue.io import script_log
from deeptissue.verification.scenes import write_verification_summary

with script_log(snakemake.log[0], "verify_summary"):  # noqa: F821
    summary = write_verification_summary(
        point_csv=snakemake.input.points,  # noqa: F821
        hertz_csv=snakemake.input.hertz,  # noqa: F821
        curve_csv=snakemake.input.curve,  # noqa: F821
        locking_csv=snakemake.input.locking,  # noqa: F821
        checks_csv=snakemake.input.checks,  # noqa: F821
        hard_csv=snakemake.input.hard,  # noqa: F821
        benchmark_csv=snakemake.input.benchmark,  # noqa: F821
        cylinder_curve_csv=snakemake.input.cylinder_curve,  # noqa: F821
        cylinder_voi_csv=snakemake.input.cylinder_voi,  # noqa: F821
        cylinder_adaptive_csv=snakemake.input.cylinder_adaptive,  # noqa: F821
        summary_csv=snakemake.output.summary,  # noqa: F821
    )
    logging.info("verification summary\n%s", summary.to_string(index=False))
