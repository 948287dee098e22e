# Scanner data in: each DICOM series or ParaVision scan given as an animal's pre/during becomes NIfTI once.

CONVERTED = [(a, s) for a in ANIMALS for s in STATES if is_converted(a, s)]


# a converted animal's scans come from this rule, a phantom's from rule phantom
ruleorder: convert > phantom


rule convert:
    """One DICOM series or ParaVision scan as NIfTI (RAS mm) with a JSON sidecar of its source and scanner settings."""
    input:
        source=lambda wc: scan_source(wc.animal, wc.state),
    output:
        nifti="results/{animal}/mri/{state}.nii.gz",
        sidecar=report(
            "results/{animal}/mri/{state}.json",
            caption="../report/convert.rst",
            category="Stage 0: scanner data",
            subcategory="{animal}",
        ),
    log:
        "results/{animal}/logs/convert_{state}.log",
    wildcard_constraints:
        animal="|".join(sorted({a for a, _ in CONVERTED})) or "NO_ANIMAL",
    priority: MODEL_PRIORITY
    conda:
        "../envs/deeptissue.yaml"
    params:
        spec=lambda wc: animal_cfg(wc.animal)[wc.state],
    script:
        "../scripts/convert.py"


FINAL_OUTPUTS.extend(f"results/{a}/mri/{s}.json" for a, s in CONVERTED)
