# Rules of the model stage: rigid cast, limb mesh with contact patches.
# The model settings get the FE section's bar length (if set) for the bar's contact patch.
# One cast per animal (its hole clears every variant of the animal); one mesh per group of the animal's
# variants (model.mesh_groups: by default one mesh "all" per animal; "indenter": one per indenter shape,
# refined only where that indenter goes).
import re


wildcard_constraints:
    group="|".join(re.escape(g) for g in dict.fromkeys(g for a in ANIMALS for g in MESH_GROUPS[a])),


rule cast:
    input:
        contours="results/{animal}/contours/pre.npz",
        pose="results/{animal}/pose.json",
    output:
        cast="results/{animal}/model/cast.npz",
    log:
        "results/{animal}/logs/cast.log",
    priority: MODEL_PRIORITY
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        settings=dict(
            config["model"],
            bar_length_mm=float(config.get("fem", {}).get("bar_length_mm", 10.0)),
        ),
        variants=lambda wc: VARIANTS_OF[wc.animal],
    script:
        "../scripts/cast.py"


rule mesh:
    input:
        contours="results/{animal}/contours/pre.npz",
        pose="results/{animal}/pose.json",
        cast="results/{animal}/model/cast.npz",
    output:
        mesh="results/{animal}/model/{group}/mesh.npz",
        msh="results/{animal}/model/{group}/mesh.msh",
        vtu="results/{animal}/model/{group}/mesh.vtu",
        model="results/{animal}/model/{group}/model.json",
        qc=report(
            "results/{animal}/qc/model_{group}.png",
            caption="../report/model.rst",
            category="model",
            subcategory="{animal}",
        ),
    log:
        "results/{animal}/logs/mesh_{group}.log",
    benchmark:
        "results/{animal}/benchmarks/mesh_{group}.tsv"
    priority: MODEL_PRIORITY
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=2000,
        runtime=15,
    params:
        settings=dict(
            config["model"],
            bar_length_mm=float(config.get("fem", {}).get("bar_length_mm", 10.0)),
        ),
        variants=lambda wc: MESH_GROUPS[wc.animal][wc.group],
    script:
        "../scripts/mesh.py"


# Final targets (animals with a during scan, i.e. a pose), once the rules making the inputs exist.
if {"segment", "pose"} <= {r.name for r in workflow.rules}:
    FINAL_OUTPUTS.extend(f"results/{a}/model/cast.npz" for a in ANIMALS if has_during(a))
    FINAL_OUTPUTS.extend(
        f"results/{a}/model/{g}/{f}"
        for a in ANIMALS
        if has_during(a)
        for g in MESH_GROUPS[a]
        for f in ("mesh.npz", "mesh.msh", "mesh.vtu", "model.json")
    )
    FINAL_OUTPUTS.extend(
        f"results/{a}/qc/model_{g}.png" for a in ANIMALS if has_during(a) for g in MESH_GROUPS[a]
    )
