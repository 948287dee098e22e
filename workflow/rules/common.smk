# Configuration validation, input functions and wildcard constraints shared by all rules.
from argparse import Namespace
from pathlib import Path

from deeptissue.config import animal_variants, has_during_scan, validate_config
from deeptissue.io import remove_stale_partials
from deeptissue.scanner import scan_kind
from deeptissue.variants import (
    adaptive_turns,
    mesh_group_of,
    mesh_groups,
    solve_priority,
    turn_base,
)

config = validate_config(
    config,
    workflow.source_path("../schemas/config.schema.yaml"),
    base_dir=Path(workflow.basedir),
    config_files=CONFIG_FILES,
)
# the study's name picks the folder of its tables (study.smk); it is no job's setting, so it is kept out of
# the jobs' params: renaming a study, or running one of the same settings under another name, redoes nothing
STUDY_NAME = config["study"].pop("name")

ANIMALS = list(config["animals"])
# the variants solved per animal: its own animals.<a>.variants, else study.variants
VARIANTS_OF = {a: animal_variants(config, a) for a in ANIMALS}
# every variant of some animal, in the order first named (study.variants, then the animals' own)
ALL_VARIANTS = list(dict.fromkeys(v for a in ANIMALS for v in VARIANTS_OF[a]))
# which of an animal's variants share a mesh (model.mesh_groups): {animal: {mesh name: variants}}
MESH_GROUPS = {a: mesh_groups(VARIANTS_OF[a], by=config["model"]["mesh_groups"]) for a in ANIMALS}
STATES = ["pre", "during"]


wildcard_constraints:
    animal="|".join(ANIMALS) if ANIMALS else "NO_ANIMAL",
    state="pre|during",


def animal_cfg(animal):
    return config["animals"][animal]


def is_phantom(animal):
    return "phantom" in animal_cfg(animal)


def has_during(animal):
    return has_during_scan(animal_cfg(animal))


def animal_states(animal):
    return STATES if has_during(animal) else ["pre"]


def turn_base_of(animal, variant):
    """The variant of the animal whose end state ``variant`` is turned from (study.turn_from_base), or None."""
    if not config["study"]["turn_from_base"]:
        return None
    return turn_base(variant, VARIANTS_OF[animal], MESH_GROUPS[animal])


def base_state_of(animal, variant):
    """The end state a turned variant starts from ([] if it is solved from the start)."""
    base = turn_base_of(animal, variant)
    return [] if base is None else f"results/{animal}/{base}/end_state.npz"


def adaptive_base_states_of(animal, variant):
    """The converged passes of the variant whose adaptive passes ``variant`` rides ([] if it meshes its own)."""
    base, _ = adaptive_turns(variant, VARIANTS_OF[animal], config["study"]["turn_from_base"])
    return [] if base is None else f"results/{animal}/adaptive/{base}/states"


# the (animal, variant) pairs others are turned from
TURN_BASES = {(a, turn_base_of(a, v)) for a in ANIMALS for v in VARIANTS_OF[a]} - {
    (a, None) for a in ANIMALS
}

# every rule upstream of a solve (convert, phantom, segment, pose, cast, mesh, bone_state) runs first, so each
# animal's model is ready before the solves fill the cores and the longest-first order of the solves holds
# across animals (solve_job_priority stays below it)
MODEL_PRIORITY = 100


def solve_job_priority(wildcards):
    """Longest solves first (bars, then deeper phantoms): deeptissue.variants.solve_priority; a variant that
    others are turned from (they wait for it) before the other variants of its shape, after the bars: the
    longest job, a bar, starts first, and the short turned variants end the study."""
    depth = animal_cfg(wildcards.animal).get("phantom", {}).get("depth_mm")
    return solve_priority(wildcards.variant, depth) + (
        5.0 if (wildcards.animal, wildcards.variant) in TURN_BASES else 0.0
    )


def variant_output(animal, variant, name):
    """A variant's summary.json or result.vtu: rule solve's on the model's mesh, or rule adapt_variant's
    on meshes refined from its own solution (study.mesh: adaptive)."""
    folder = f"adaptive/{variant}" if config["study"]["mesh"] == "adaptive" else variant
    return f"results/{animal}/{folder}/{name}"


def mesh_of(animal, variant):
    """The directory of the mesh a variant is solved on."""
    return f"results/{animal}/model/{mesh_group_of(variant, MESH_GROUPS[animal])}"


def is_converted(animal, state):
    """Whether a state's scan is scanner data (a DICOM series or a ParaVision scan) that rule convert turns into NIfTI."""
    cfg = animal_cfg(animal)
    return state in cfg and scan_kind(cfg[state], base_dir=workflow.basedir) != "nifti"


def scan_source(animal, state):
    """The files or folder a state's scan is read from: a ParaVision scan's parameter and data files (so
    that new scans in the study do not redo it; the study folder if they are missing, for deeptissue.scanner's
    message listing the scans that exist), a DICOM folder, or the NIfTI file."""
    spec = animal_cfg(animal)[state]
    if isinstance(spec, dict) and "bruker" in spec:
        scan = Path(spec["bruker"]) / str(spec["scan"])
        reco = scan / "pdata" / str(spec.get("reco", 1))
        files = [scan / "method", scan / "acqp", reco / "visu_pars", reco / "2dseq"]
        return [str(f) for f in files] if all(f.is_file() for f in files) else spec["bruker"]
    return spec.get("dicom") if isinstance(spec, dict) else spec


def mri_input(wildcards):
    """The NIfTI of one animal and state: the phantom's or the converted scanner data's output, or the configured file."""
    if is_phantom(wildcards.animal) or is_converted(wildcards.animal, wildcards.state):
        return f"results/{wildcards.animal}/mri/{wildcards.state}.nii.gz"
    return animal_cfg(wildcards.animal)[wildcards.state]


def segment_inputs(wildcards):
    """The image of the state, the pre image and contours a during scan needs, overrides and truth where they exist."""
    cfg = animal_cfg(wildcards.animal)
    inputs = {"image": mri_input(wildcards)}
    if wildcards.state == "during":
        inputs["reference"] = mri_input(Namespace(animal=wildcards.animal, state="pre"))
        # the pre tibia fills the during slices where it touches the indenter
        inputs["pre_contours"] = f"results/{wildcards.animal}/contours/pre.npz"
    if "overrides" in cfg:
        inputs["overrides"] = cfg["overrides"]
    if is_phantom(wildcards.animal):
        inputs["truth"] = f"results/{wildcards.animal}/mri/truth_{wildcards.state}.npz"
    return inputs


def checks_inputs(wildcards):
    """The checks of one animal: its segmentation's of each state and, with a during scan, the pose's."""
    a = wildcards.animal
    inputs = {
        f"segmentation_{s}": f"results/{a}/qc/segmentation_checks_{s}.csv"
        for s in animal_states(a)
    }
    if has_during(a):
        inputs["pose"] = f"results/{a}/qc/pose_checks.csv"
    return inputs


onstart:
    # the temporaries of outputs whose job was killed mid-write (SIGKILL: the out-of-memory killer); a rerun of
    # the job removes those of its own outputs, this removes those of outputs nothing will write again
    for partial in remove_stale_partials("results"):
        logger.info(f"removed {partial}: part of a file whose writing job was killed")


# Final targets of the study: each stage's rule file extends this list with its outputs.
FINAL_OUTPUTS = []
