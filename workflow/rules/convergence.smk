# Speed against error: animals x variants solved at a ladder of discretisations and on adaptive meshes
# (rule adapt_variant), and the cylinder scene of `verify` on fixed and adaptive meshes; errors against the
# finest converged run, Pareto front and scaling. Target `convergence`, not in `all`.
import re

from deeptissue.config import convergence_animals
from deeptissue.convergence import default_ladder

CONV = config["convergence"]
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
    conda:
        "../envs/deeptissue.yaml"
    threads: 2  # one run at a time on a 2-core machine, so the timings do not compete
    resources:
        mem_mb=CONV["mem_mb"],
        runtime=CONV["runtime_min"],
    params:
        setting=lambda wc: CONV_LADDER.by_name(wc.setting).to_dict(),
        is_default=lambda wc: wc.setting == CONV_LADDER.default_name,
        model=config["model"],
        fem=config["fem"],
        # with the animal's variants, whose study meshes (model.mesh_groups) a null mesh_variants takes
        study=lambda wc: dict(config["study"], variants=VARIANTS_OF[wc.animal]),
        mesh_variants=CONV["mesh_variants"],  # null: the variant's study mesh (model.mesh_groups)
        linear_reference=CONV["linear_reference"],
    script:
        "../scripts/convergence_run.py"


rule convergence_aggregate:
    """Every row, benchmark and adaptive run -> convergence.csv, the error-vs-time figure and summary.md."""
    input:
        # convergence_animals(required=True) inside the input functions: a study without a during scan keeps its
        # other targets, and only `convergence` stops with a ConfigError
        rows=lambda wc: expand(
            "results/convergence/{animal}/{conv_variant}/{setting}.json",
            animal=convergence_animals(config, required=True),
            conv_variant=CONV_VARIANTS,
            setting=CONV_SETTINGS,
        ),
        benchmarks=lambda wc: expand(
            "results/convergence/benchmarks/{animal}/{conv_variant}_{setting}.tsv",
            animal=convergence_animals(config, required=True),
            conv_variant=CONV_VARIANTS,
            setting=CONV_SETTINGS,
        ),
        # rule adapt_variant's runs of each animal's study variants (VARIANTS_OF) among convergence.variants
        adaptive=lambda wc: [
            f"results/{a}/adaptive/{v}/passes.csv"
            for a in convergence_animals(config, required=True)
            for v in CONV_VARIANTS
            if v in VARIANTS_OF[a]
        ],
        cylinder=rules.verify_cylinder_adaptive.output.table,
    output:
        csv=report(
            "results/convergence/convergence.csv",
            caption="../report/convergence_csv.rst",
            category="Speed against error",
            subcategory="Ladder",
        ),
        png=report(
            "results/convergence/error_vs_time.png",
            caption="../report/convergence.rst",
            category="Speed against error",
            subcategory="Ladder",
        ),
        md="results/convergence/summary.md",
    log:
        "results/convergence/logs/aggregate.log",
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=2000,
        runtime=15,
    params:
        default_name=CONV_LADDER.default_name,
        notes=list(CONV_LADDER.notes),
        goal=CONV["goal"],
        max_cost_ratio=CONV["max_cost_ratio"],
        size_measure=CONV["size_measure"],
    script:
        "../scripts/convergence_aggregate.py"


rule convergence:
    """Speed against error: `snakemake --cores 2 convergence` (not part of `all`)."""
    input:
        rules.convergence_aggregate.output,
