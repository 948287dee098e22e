# deeptissue: MRI of an indentation experiment -> animal-specific FE models -> strained tissue volume.
# This file only wires: configuration, the rule files, and the final targets.
from snakemake.utils import min_version

from deeptissue.config import check_config_files

min_version("9.0")


# paths are relative to the repository, wherever snakemake is started (`-s ../Snakefile` from workflow/ writes
# the same results/), unless --directory names another working directory
workdir: workflow.basedir


# the demo study, unless a config file is given on the command line (`--configfile config/paper.yaml`):
# then that file alone is the configuration (its animals are not merged with the demo's)
CONFIG_FILES = [str(f) for f in workflow.overwrite_configfiles] or ["config/config.yaml"]
# YAML syntax errors (file, line, column), keys given twice and unquoted numeric animal names
check_config_files(CONFIG_FILES)
if not workflow.overwrite_configfiles:

    configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/convert.smk"
include: "workflow/rules/imaging.smk"
include: "workflow/rules/pose.smk"
include: "workflow/rules/model.smk"
include: "workflow/rules/material.smk"
include: "workflow/rules/fem.smk"
include: "workflow/rules/study.smk"
include: "workflow/rules/findings.smk"
include: "workflow/rules/convergence.smk"
include: "workflow/rules/adapt.smk"
include: "workflow/rules/docs.smk"


rule all:
    default_target: True
    input:
        FINAL_OUTPUTS,
