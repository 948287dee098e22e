# Rules of the imaging stage: digital phantom, skin/tibia segmentation, QC.

PHANTOMS = [a for a in ANIMALS if is_phantom(a)]


rule phantom:
    """Synthetic pre/during MRI of a phantom animal with its exact truth (pose and contours)."""
    output:
        pre="results/{animal}/mri/pre.nii.gz",
        during="results/{animal}/mri/during.nii.gz",
        truth="results/{animal}/mri/truth.json",
        truth_pre="results/{animal}/mri/truth_pre.npz",
        truth_during="results/{animal}/mri/truth_during.npz",
    log:
        "results/{animal}/logs/phantom.log",
    priority: MODEL_PRIORITY
    conda:
        "../envs/deeptissue.yaml"
    params:
        phantom=lambda wc: animal_cfg(wc.animal)["phantom"],
        n_points=config["segmentation"]["n_points"],
        start_angle_deg=config["segmentation"]["start_angle_deg"],
    script:
        "../scripts/phantom.py"


rule segment:
    """Skin, tibia and (where found) fibula contours of every slice of one state, their checks and a QC figure; a
    during scan after the pre one, whose tibia fills the slices where the bone touches the indenter. A run that
    fails names every failing slice and leaves its QC figure as segmentation_{state}_failed.png.
    """
    input:
        unpack(segment_inputs),
    output:
        contours="results/{animal}/contours/{state}.npz",
        qc=report(
            "results/{animal}/qc/segmentation_{state}.png",
            caption="../report/segmentation.rst",
            category="Stage 1: segmentation",
            subcategory="{animal}",
        ),
        # the segmentation checks of every animal, with or without an indenter (deeptissue.segment_checks)
        checks="results/{animal}/qc/segmentation_checks_{state}.csv",
    log:
        "results/{animal}/logs/segment_{state}.log",
    priority: MODEL_PRIORITY
    conda:
        "../envs/deeptissue.yaml"
    params:
        settings=lambda wc: {
            **config["segmentation"],
            **animal_cfg(wc.animal).get("segmentation", {}),
        },
        crop_mm=lambda wc: animal_cfg(wc.animal).get("crop_mm"),
        # a point inside the leg to segment, where the legs touch (none: the whole body inside crop_mm)
        leg_point_mm=lambda wc: animal_cfg(wc.animal).get("leg_point_mm"),
        # how the contrast fluid is found and the indenter's radius, for the during scan's indenter mask
        pose_options=config["pose"],
    script:
        "../scripts/segment.py"


rule checks:
    """Every check of one animal in one table: its segmentation's of each state and, with a during scan, the pose's."""
    input:
        unpack(checks_inputs),
    output:
        checks=report(
            "results/{animal}/qc/checks.csv",
            caption="../report/qc_checks.rst",
            category="QC checks",
            subcategory="{animal}",
        ),
    log:
        "results/{animal}/logs/checks.log",
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/checks.py"


rule segmentation_accuracy:
    """Distance of the segmented contours to the phantom's true contours, per slice and structure."""
    input:
        contours="results/{animal}/contours/{state}.npz",
        truth="results/{animal}/mri/truth_{state}.npz",
    output:
        csv="results/{animal}/qc/segmentation_accuracy_{state}.csv",
    log:
        "results/{animal}/logs/segmentation_accuracy_{state}.log",
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/segmentation_accuracy.py"


FINAL_OUTPUTS.extend(expand("results/{animal}/mri/truth.json", animal=PHANTOMS))
for _a in ANIMALS:
    FINAL_OUTPUTS.extend(
        expand(
            "results/{animal}/qc/segmentation_{state}.png",
            animal=_a,
            state=animal_states(_a),
        )
    )
    FINAL_OUTPUTS.extend(
        expand("results/{animal}/contours/{state}.npz", animal=_a, state=animal_states(_a))
    )
    FINAL_OUTPUTS.append(f"results/{_a}/qc/checks.csv")
FINAL_OUTPUTS.extend(
    expand(
        "results/{animal}/qc/segmentation_accuracy_{state}.csv",
        animal=PHANTOMS,
        state=STATES,
    )
)
