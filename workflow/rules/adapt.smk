# Solution-driven refinement of single limb variants: mesh, solve, estimate the VOI, bins and force
# error, remesh where the estimate says, until the goals are met or the budget is spent
# (deeptissue.adapt_limb, deeptissue.adapt.AdaptSettings' goals and budget). Target `adaptive`, not in `all`.

# the demo's sphere runs at 2.0 mm (rat01) and 1.5 mm (rat03); in a study without those animals, its first one
ADAPTIVE_ANIMALS = [a for a in ("rat01", "rat03") if a in STUDY_ANIMALS] or STUDY_ANIMALS[:1]
ADAPTIVE_VARIANT = "sphere" if "sphere" in VARIANTS else VARIANTS[0]


rule adapt_variant:
    """One animal x variant on adaptive meshes: every pass meshes the limb with the variant's patch,
    solves the bone rotation and the indentation with the cast, and estimates the errors."""
    input:
        contours="results/{animal}/contours/pre.npz",
        pose="results/{animal}/pose.json",
        cast="results/{animal}/model/cast.npz",
        during_contours="results/{animal}/contours/during.npz",
    output:
        passes="results/{animal}/adaptive/{variant}/passes.csv",
        summary="results/{animal}/adaptive/{variant}/summary.json",
    log:
        "results/{animal}/logs/adapt_{variant}.log",
    benchmark:
        "results/{animal}/benchmarks/adapt_{variant}.tsv"
    params:
        model=dict(config["model"], bar_length_mm=float(config.get("fem", {}).get("bar_length_mm", 10.0))),
        fem=config["fem"],
        study=STUDY,
    resources:
        mem_mb=4000,  # 1.7 GB at the budget's 20 000 tetrahedra (rat01, sphere)
        runtime=120,  # AdaptSettings.max_wall_s (an hour) and one more pass
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/adapt_variant.py"


rule adaptive_aggregate:
    input:
        passes=expand(
            "results/{animal}/adaptive/{variant}/passes.csv", animal=ADAPTIVE_ANIMALS, variant=[ADAPTIVE_VARIANT]
        ),
        fixed=expand("results/{animal}/{variant}/summary.json", animal=ADAPTIVE_ANIMALS, variant=[ADAPTIVE_VARIANT]),
    output:
        passes=report(
            "results/adaptive/passes.csv",
            caption="../report/adaptive_csv.rst",
            category="Adaptive meshes",
            subcategory="Tables",
        ),
        figure=report(
            "results/adaptive/error_vs_time.png",
            caption="../report/adaptive.rst",
            category="Adaptive meshes",
            subcategory="Figures",
        ),
    log:
        "results/adaptive/aggregate.log",
    resources:
        mem_mb=1000,
        runtime=10,
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/adaptive_aggregate.py"


rule adaptive:
    """Adaptive meshes of the demo's sphere variants against the fixed mesh: `snakemake --cores 1 adaptive`
    (not part of `all`)."""
    input:
        rules.adaptive_aggregate.output,
