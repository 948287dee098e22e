# Rules of the contact comparison (target `contact_comparison`, not part of `all`): the workflow's penalty
# solver and weighted-gap exact contact on the hard cases and on the demo's costliest variants, one job per
# case and formulation.
import re

from deeptissue.fem.comparison import CASES, DEMO_VARIANTS, FORMULATIONS

# the demo variants of this configuration (animal_variant)
CONTACT_VARIANTS = [c for c in DEMO_VARIANTS if c.split("_", 1)[0] in STUDY_ANIMALS and c.split("_", 1)[1] in VARIANTS]


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


rule contact_variant:
    input:
        mesh=lambda wc: f"{mesh_of(wc.animal, wc.variant)}/mesh.npz",
        cast="results/{animal}/model/cast.npz",
        pose="results/{animal}/pose.json",
    output:
        row="results/verification/contact/{formulation}/{animal}_{variant}.json",
    params:
        material=config["fem"]["material"],
        bar_length_mm=config["fem"]["bar_length_mm"],
    wildcard_constraints:
        formulation="|".join(FORMULATIONS),
        animal="|".join(re.escape(a) for a in STUDY_ANIMALS) if STUDY_ANIMALS else "NO_ANIMAL",
        variant="|".join(re.escape(v) for v in VARIANTS),
    log:
        "results/logs/contact_{formulation}_{animal}_{variant}.log",
    resources:
        mem_mb=4000,
        runtime=60,
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/contact_variant.py"


rule contact_comparison:
    """Both contact formulations on every hard case and the demo's costliest variants: a table and a figure of
    Newton iterations and wall time."""
    input:
        rows=expand("results/verification/contact/{formulation}/{case}.json", formulation=FORMULATIONS,
                    case=list(CASES) + CONTACT_VARIANTS),
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
