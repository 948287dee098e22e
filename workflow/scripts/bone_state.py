"""Glue of rule bone_state: one mesh's bone-rotation steps, solved once for all its variants."""

from deeptissue.fem.heap import keep_freed_memory
from deeptissue.fem.linsolve import pin_reproducible
from deeptissue.io import script_log
from deeptissue.study import run_bone_state

with script_log(snakemake.log[0], "bone_state"):
    keep_freed_memory()  # this job's process keeps what it frees (deeptissue.fem.heap)
    if snakemake.params.fem.get("reproducible"):
        pin_reproducible()  # before the first MKL call of this process
    run_bone_state(
        mesh_path=snakemake.input.mesh,
        cast_path=snakemake.input.cast,
        pose_path=snakemake.input.pose,
        state_path=snakemake.output.state,
        fem_cfg=snakemake.params.fem,
    )
