"""Glue of rule aggregate: every summary.json -> results/summary/<study.name>/ tables and figures."""

from deeptissue.io import script_log
from deeptissue.report import AggregateJob, aggregate_study

with script_log(snakemake.log[0], "aggregate"):
    aggregate_study(
        AggregateJob(
            summary_paths=list(snakemake.input.summaries),
            animals=snakemake.params.animals,
            variants=snakemake.params.variants,
            outputs={k: snakemake.output[k] for k in snakemake.output.keys()},
            figure_animal=snakemake.params.figure_animal,
            figure_results=dict(zip(snakemake.params.section_variants, snakemake.input.results)),
            pose_path=snakemake.input.pose,
            strain_measure=snakemake.params.strain_measure,
            threshold=snakemake.params.threshold,
            bin_edges=snakemake.params.bin_edges,
        )
    )
