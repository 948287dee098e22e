# deeptissue: MRI of an indentation experiment -> animal-specific FE models -> strained tissue volume.
# This file only wires: configuration, the rule files, and the final targets.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/imaging.smk"
include: "workflow/rules/pose.smk"
include: "workflow/rules/model.smk"
include: "workflow/rules/material.smk"
include: "workflow/rules/fem.smk"
include: "workflow/rules/study.smk"
include: "workflow/rules/convergence.smk"


rule all:
    input:
        FINAL_OUTPUTS,
    default_target: True
