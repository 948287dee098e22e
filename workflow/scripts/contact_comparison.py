"""Glue of rule contact_comparison: the rows of every case and formulation -> CSV and figure."""

import pandas as pd

from deeptissue.fem.comparison import plot_comparison
from deeptissue.io import atomic_path, read_json, script_log

with script_log(snakemake.log[0], "contact_comparison"):
    df = pd.DataFrame([read_json(p) for p in snakemake.input.rows])
    with atomic_path(snakemake.output.csv) as tmp:
        df.to_csv(tmp, index=False)
    plot_comparison(df, snakemake.output.figure)
