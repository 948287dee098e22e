# deeptissue: MRI of an indentation experiment -> animal-specific FE models -> strained tissue volume.
# This file only wires: configuration, the rule files, and the final targets.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"


rule all:
    input:
        get_final_output(),
    default_target: True
