"""Glue of rule findings: voi.csv, bins.csv and the sphere's and bar's result.vtu -> findings.csv, .md, figures."""

from deeptissue.findings import FindingsJob, write_findings
from deeptissue.io import script_log

with script_log(snakemake.log[0], "findings"):
    runs = [tuple(r) for r in snakemake.params.runs]
    write_findings(
        FindingsJob(
            voi_csv=snakemake.input.voi,
            bins_csv=snakemake.input.bins,
            outputs={k: snakemake.output[k] for k in snakemake.output.keys()},
            study=snakemake.params.study,
            results=dict(zip(runs, snakemake.input.results)),
            poses={a: p for (a, _), p in zip(runs, snakemake.input.poses)},
            strain_measure=snakemake.params.strain_measure,
            threshold=snakemake.params.threshold,
            bar_length_mm=snakemake.params.bar_length_mm,
        )
    )
