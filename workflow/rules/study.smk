# Rules of the study stage: one FE solve per animal x variant, then tables and figures of the whole study.
import re

from deeptissue.config import figure_animal
from deeptissue.variants import parse_variant

STUDY = config["study"]
# the study's tables and figures: a folder per study.name, so studies in one checkout keep their own
SUMMARY = f"results/summary/{STUDY_NAME}"
# the animals with a during scan are solved; pre-only animals are only segmented
STUDY_ANIMALS = [a for a in ANIMALS if has_during(a)]
# the solves of the study: each animal with its own variants (VARIANTS_OF: animals.<a>.variants or study.variants)
STUDY_RUNS = [(a, v) for a in STUDY_ANIMALS for v in VARIANTS_OF[a]]
FIGURE_ANIMAL = figure_animal(config)
# variants of the figure animal drawn in the section figures: sphere vs bar, and every sphere orientation
SECTION_VARIANTS = [
    v
    for v in (VARIANTS_OF[FIGURE_ANIMAL] if FIGURE_ANIMAL else [])
    if v == "bar" or parse_variant(v).indenter == "sphere"
]


STUDY_OUTPUTS = [
    f"{SUMMARY}/voi.csv",
    f"{SUMMARY}/bins.csv",
    f"{SUMMARY}/voi.png",
    f"{SUMMARY}/bins.png",
    f"{SUMMARY}/voi_change.png",
    f"{SUMMARY}/sections.png",
    f"{SUMMARY}/orientations.png",
]
# final targets of the study (tables and figures): part of the default target when an animal has a during scan
study_outputs = lambda: list(STUDY_OUTPUTS) if STUDY_ANIMALS else []
FINAL_OUTPUTS.extend(study_outputs())


rule aggregate:
    input:
        summaries=[variant_output(a, v, "summary.json") for a, v in STUDY_RUNS],
        results=[variant_output(FIGURE_ANIMAL, v, "result.vtu") for v in SECTION_VARIANTS],
        pose=f"results/{FIGURE_ANIMAL}/pose.json",
    output:
        voi_csv=report(
            f"{SUMMARY}/voi.csv",
            caption="../report/study_voi_csv.rst",
            category="Study",
            subcategory="Tables",
        ),
        bins_csv=report(
            f"{SUMMARY}/bins.csv",
            caption="../report/study_bins_csv.rst",
            category="Study",
            subcategory="Tables",
        ),
        voi_png=report(
            f"{SUMMARY}/voi.png",
            caption="../report/study_voi.rst",
            category="Study",
            subcategory="All animals",
        ),
        bins_png=report(
            f"{SUMMARY}/bins.png",
            caption="../report/study_bins.rst",
            category="Study",
            subcategory="All animals",
        ),
        voi_change_png=report(
            f"{SUMMARY}/voi_change.png",
            caption="../report/study_voi_change.rst",
            category="Study",
            subcategory="All animals",
        ),
        sections_png=report(
            f"{SUMMARY}/sections.png",
            caption="../report/study_sections.rst",
            category="Study",
            subcategory="Sections",
        ),
        orientations_png=report(
            f"{SUMMARY}/orientations.png",
            caption="../report/study_orientations.rst",
            category="Study",
            subcategory="Sections",
        ),
    log:
        f"{SUMMARY}/aggregate.log",
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        animals=STUDY_ANIMALS,
        variants={a: VARIANTS_OF[a] for a in STUDY_ANIMALS},
        section_variants=SECTION_VARIANTS,
        figure_animal=FIGURE_ANIMAL,
        strain_measure=STUDY["strain_measure"],
        threshold=STUDY["threshold"],
        bin_edges=STUDY["bin_edges"],
    script:
        "../scripts/aggregate.py"


wildcard_constraints:
    variant="|".join(re.escape(v) for v in ALL_VARIANTS),


rule bone_state:
    """The bone-rotation steps of one mesh (t 0 -> 3, before the indenter moves), solved once: every
    variant on the mesh starts from this state instead of solving them again (Stage 4).
    """
    input:
        mesh="results/{animal}/model/{group}/mesh.npz",
        cast="results/{animal}/model/cast.npz",
        pose="results/{animal}/pose.json",
    output:
        state="results/{animal}/model/{group}/bone_state.npz",
    log:
        "results/{animal}/logs/bone_state_{group}.log",
    benchmark:
        "results/{animal}/benchmarks/bone_state_{group}.tsv"
    priority: MODEL_PRIORITY
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        fem=config["fem"],
    script:
        "../scripts/bone_state.py"


rule solve:
    """One FE job: the animal's model and pose, one indenter variant -> summary.json and result.vtu.

    A variant that fails or does not converge still writes both files (converged: false, reason), so
    the study goes on and the animal is marked excluded by `aggregate`.
    """
    input:
        mesh=lambda wc: f"{mesh_of(wc.animal, wc.variant)}/mesh.npz",
        bone_state=lambda wc: f"{mesh_of(wc.animal, wc.variant)}/bone_state.npz",
        cast="results/{animal}/model/cast.npz",
        pose="results/{animal}/pose.json",
        during_contours="results/{animal}/contours/during.npz",
        base_state=lambda wc: base_state_of(wc.animal, wc.variant),
    output:
        summary="results/{animal}/{variant}/summary.json",
        vtu="results/{animal}/{variant}/result.vtu",
        end_state="results/{animal}/{variant}/end_state.npz",
    log:
        "results/{animal}/logs/solve_{variant}.log",
    benchmark:
        "results/{animal}/benchmarks/solve_{variant}.tsv"
    priority: solve_job_priority  # the longest solves first, so none runs alone at the end
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=4000,
        runtime=120,
    params:
        fem=config["fem"],
        study=STUDY,
        base_variant=lambda wc: turn_base_of(wc.animal, wc.variant),
    script:
        "../scripts/solve.py"


rule study:
    """The FE study of every configured animal and its variants: `snakemake --cores 2 study`."""
    input:
        study_outputs(),
