"""Glue of rule verify: fail, naming them, if any check of the verification summary has status 'fail'."""

import sys

import pandas as pd

from deeptissue.io import script_log
from deeptissue.verification.scenes import failed_checks

with script_log(snakemake.log[0], "verify"):  # noqa: F821
    summary_csv = snakemake.input.summary  # noqa: F821
    failed = failed_checks(pd.read_csv(summary_csv))
    if failed:
        message = (
            f"{len(failed)} verification check(s) failed (see {summary_csv}):\n  "
            + "\n  ".join(failed)
        )
        print(message, file=sys.__stderr__)  # on the console as well as in the log
        raise RuntimeError(message)
