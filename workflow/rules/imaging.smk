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
    params:
        phantom=lambda wc: animal_cfg(wc.animal)["phantom"],
        n_points=config["segmentation"]["n_points"],
        start_angle_deg=config["segmentation"]["start_angle_deg"],
    log:
        "results/{animal}/logs/phantom.log",
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/phantom.py"


FINAL_OUTPUTS.extend(expand("results/{animal}/mri/truth.json", animal=PHANTOMS))
