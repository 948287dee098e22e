# Speed against error: one animal x a few variants solved at a ladder of discretisations,
# errors against the finest converged run, Pareto front and scaling. Target `convergence`, not in `all`.
import re

from deeptissue.config import ConfigError
from deeptissue.convergence import default_ladder

CONV = config["convergence"]
CONV_ANIMAL = CONV["animal"] or next((a for a in ANIMALS if has_during(a)), ANIMALS[0])
if CONV_ANIMAL not in ANIMALS or not has_during(CONV_ANIMAL):
    raise ConfigError(
        f"config key convergence.animal: {CONV_ANIMAL!r} is not a configured animal with a during scan {ANIMALS}"
    )
CONV_VARIANTS = list(CONV["variants"])
CONV_LADDER = default_ladder(CONV, model_cfg=config["model"], solver_cfg=config["fem"]["solver"])
CONV_SETTINGS = CONV_LADDER.names


wildcard_constraints:
    setting="|".join(re.escape(s) for s in CONV_SETTINGS),
    conv_variant="|".join(re.escape(v) for v in CONV_VARIANTS),


rule convergence_run:
    """One setting of the ladder: mesh, solve, post-process and a linear-elastic reference -> one row."""
    input:
        contours="results/{animal}/contours/pre.npz",
        pose="results/{animal}/pose.json",
        cast="results/{animal}/model/cast.npz",
    output:
        row="results/convergence/{animal}/{conv_variant}/{setting}.json",
    log:
        "results/convergence/logs/{animal}_{conv_variant}_{setting}.log",
    benchmark:
        "results/convergence/benchmarks/{animal}/{conv_variant}_{setting}.tsv"
    params:
        setting=lambda wc: CONV_LADDER.by_name(wc.setting).to_dict(),
        is_default=lambda wc: wc.setting == CONV_LADDER.default_name,
        model=config["model"],
        fem=config["fem"],
        study=config["study"],
        mesh_variants=CONV["mesh_variants"],  # null: the variant's study mesh (model.mesh_groups)
        linear_reference=CONV["linear_reference"],
    threads: 2  # one run at a time on a 2-core machine, so the timings do not compete
    resources:
        mem_mb=CONV["mem_mb"],
        runtime=CONV["runtime_min"],
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/convergence_run.py"


rule convergence_aggregate:
    """Every row and benchmark -> convergence.csv, the error-vs-time figure and summary.md."""
    input:
        rows=expand(
            "results/convergence/{animal}/{conv_variant}/{setting}.json",
            animal=[CONV_ANIMAL],
            conv_variant=CONV_VARIANTS,
            setting=CONV_SETTINGS,
        ),
        benchmarks=expand(
            "results/convergence/benchmarks/{animal}/{conv_variant}_{setting}.tsv",
            animal=[CONV_ANIMAL],
            conv_variant=CONV_VARIANTS,
            setting=CONV_SETTINGS,
        ),
    output:
        csv=report(
            "results/convergence/convergence.csv",
            caption="../report/convergence_csv.rst",
            category="Speed against error",
            subcategory=CONV_ANIMAL,
        ),
        png=report(
            "results/convergence/error_vs_time.png",
            caption="../report/convergence.rst",
            category="Speed against error",
            subcategory=CONV_ANIMAL,
        ),
        md="results/convergence/summary.md",
    params:
        default_name=CONV_LADDER.default_name,
        notes=list(CONV_LADDER.notes),
        goal=CONV["goal"],
        max_cost_ratio=CONV["max_cost_ratio"],
        size_measure=CONV["size_measure"],
    log:
        "results/convergence/logs/aggregate.log",
    resources:
        mem_mb=2000,
        runtime=15,
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/convergence_aggregate.py"


rule convergence:
    """Speed against error: `snakemake --cores 2 convergence` (not part of `all`)."""
    input:
        rules.convergence_aggregate.output,
