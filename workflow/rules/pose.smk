# Rules of the pose stage: indenter axis, travel and depth, tibia rigid motion.
from argparse import Namespace


rule pose:
    input:
        # the phantom's during scan, or the configured file (mri_input with state=during)
        during=lambda wildcards: mri_input(Namespace(animal=wildcards.animal, state="during")),
        pre=lambda wildcards: mri_input(Namespace(animal=wildcards.animal, state="pre")),
        pre_contours="results/{animal}/contours/pre.npz",
        during_contours="results/{animal}/contours/during.npz",
    output:
        pose="results/{animal}/pose.json",
        axis=report(
            "results/{animal}/qc/pose_axis.png",
            caption="../report/pose_axis.rst",
            category="pose",
            subcategory="{animal}",
        ),
        tip=report(
            "results/{animal}/qc/pose_tip.png",
            caption="../report/pose_tip.rst",
            category="pose",
            subcategory="{animal}",
        ),
        bone=report(
            "results/{animal}/qc/pose_bone.png",
            caption="../report/pose_bone.rst",
            category="pose",
            subcategory="{animal}",
        ),
        # read with the segmentation's checks in qc/checks.csv (rule checks)
        checks="results/{animal}/qc/pose_checks.csv",
    log:
        "results/{animal}/logs/pose.log",
    priority: MODEL_PRIORITY
    conda:
        "../envs/deeptissue.yaml"
    params:
        options=config["pose"],
        override=lambda wildcards: animal_cfg(wildcards.animal).get("pose_override", {}),
    script:
        "../scripts/pose.py"


rule pose_accuracy:
    input:
        pose="results/{animal}/pose.json",
        truth="results/{animal}/mri/truth.json",
    output:
        csv="results/{animal}/qc/pose_accuracy.csv",
    log:
        "results/{animal}/logs/pose_accuracy.log",
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/pose_accuracy.py"


FINAL_OUTPUTS.extend(f"results/{a}/pose.json" for a in ANIMALS if has_during(a))
FINAL_OUTPUTS.extend(f"results/{a}/qc/pose_accuracy.csv" for a in ANIMALS if is_phantom(a))
