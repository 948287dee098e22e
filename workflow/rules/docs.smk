# Rules of the documentation: the configuration reference rendered from the schema.


rule config_docs:
    """docs/config.md rendered from the config schema: `snakemake --cores 1 config_docs` (not part of `all`)."""
    input:
        schema=workflow.source_path("../schemas/config.schema.yaml"),
    output:
        docs=str(Path(workflow.basedir) / "docs" / "config.md"),
    log:
        "results/logs/config_docs.log",
    conda:
        "../envs/deeptissue.yaml"
    shell:
        "python -m deeptissue.config {output.docs} --schema {input.schema} 2> {log}"
