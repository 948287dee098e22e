# Rules of the contact comparison (target `contact_comparison`, not part of `all`): the workflow's penalty
# solver and weighted-gap exact contact on the hard cases, one job per case and formulation.
import re

from deeptissue.fem.comparison import CASES, FORMULATIONS


rule contact_case:
    output:
        row="results/verification/contact/{formulation}/{case}.json",
    params:
        material=config["fem"]["material"],
    wildcard_constraints:
        formulation="|".join(FORMULATIONS),
        case="|".join(re.escape(c) for c in CASES),
    log:
        "results/logs/contact_{formulation}_{case}.log",
    resources:
        mem_mb=4000,
        runtime=30,
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/contact_case.py"


rule contact_comparison:
    """Both contact formulations on every hard case: a table and a figure of Newton iterations and wall time."""
    input:
        rows=expand("results/verification/contact/{formulation}/{case}.json", formulation=FORMULATIONS, case=list(CASES)),
    output:
        csv="results/verification/contact_comparison.csv",
        figure=report(
            "results/verification/contact_comparison.png",
            caption="../report/contact_comparison.rst",
            category="Verification",
            subcategory="solver",
        ),
    log:
        "results/logs/contact_comparison.log",
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/contact_comparison.py"
