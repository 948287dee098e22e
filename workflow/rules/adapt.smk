# Solution-driven refinement of single limb variants: mesh, solve, estimate the VOI, bins and force
# error, remesh where the estimate says, until the goals are met or the budget is spent
# (deeptissue.adapt_limb, deeptissue.adapt.AdaptSettings' goals and budget). The study's tables read it for
# every variant with study.mesh: adaptive (the default); the target `convergence` runs it on its animals and variants and
# measures it against the ladder; any one: results/{animal}/adaptive/{variant}/.


rule adapt_variant:
    """One animal x variant on adaptive meshes: every pass meshes the limb with the variant's patch,
    solves the bone rotation and the indentation with the cast, and estimates the errors; a turned
    variant's first passes are its base's meshes, turned from the base's end states.
    """
    input:
        contours="results/{animal}/contours/pre.npz",
        pose="results/{animal}/pose.json",
        cast="results/{animal}/model/cast.npz",
        during_contours="results/{animal}/contours/during.npz",
        # a turned variant rides its base's passes, turned from their end states on the same meshes
        base_states=lambda wc: adaptive_base_states_of(wc.animal, wc.variant),
    output:
        passes="results/{animal}/adaptive/{variant}/passes.csv",
        summary="results/{animal}/adaptive/{variant}/summary.json",
        vtu="results/{animal}/adaptive/{variant}/result.vtu",
        states=directory("results/{animal}/adaptive/{variant}/states"),
    log:
        "results/{animal}/logs/adapt_{variant}.log",
    benchmark:
        "results/{animal}/benchmarks/adapt_{variant}.tsv"
    priority: solve_job_priority  # the longest first, as the study's solves
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=4000,  # AdaptSettings.max_tets: 20 000 tetrahedra (about 90 000 DOFs), gmsh's count graded
        runtime=120,  # AdaptSettings.max_wall_s (an hour) and one more pass
    params:
        model=dict(
            config["model"],
            bar_length_mm=float(config.get("fem", {}).get("bar_length_mm", 10.0)),
        ),
        fem=config["fem"],
        study=lambda wc: dict(STUDY, variants=VARIANTS_OF[wc.animal]),
    script:
        "../scripts/adapt_variant.py"
