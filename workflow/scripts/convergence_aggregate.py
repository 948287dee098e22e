"""Glue of rule convergence_aggregate: rows, benchmarks, adaptive runs and the cylinder scene -> convergence.csv,
error_vs_time.png, summary.md."""

from deeptissue.convergence import ConvergenceInputs, ConvergenceOutputs, aggregate_convergence
from deeptissue.io import script_log

with script_log(snakemake.log[0], "convergence_aggregate"):
    aggregate_convergence(
        ConvergenceInputs(
            row_paths=list(snakemake.input.rows),
            benchmark_paths=list(snakemake.input.benchmarks),
            adaptive_paths=list(snakemake.input.adaptive),
            cylinder_path=snakemake.input.cylinder,
        ),
        ConvergenceOutputs(
            csv_path=snakemake.output.csv,
            png_path=snakemake.output.png,
            md_path=snakemake.output.md,
        ),
        default_name=snakemake.params.default_name,
        goal=dict(snakemake.params.goal),
        notes=list(snakemake.params.notes),
        max_cost_ratio=float(snakemake.params.max_cost_ratio),
        measure=snakemake.params.size_measure,
    )
