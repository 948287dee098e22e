"""Glue of rule pose: estimate the indenter pose and tibia motion of one animal."""

import logging

from deeptissue.io import script_log
from deeptissue.pose import PoseFiles, run_pose

with script_log(snakemake.log[0], "pose"):  # noqa: F821
    pose = run_pose(
        PoseFiles(
            during_nifti=snakemake.input.during,  # noqa: F821
            pre_nifti=snakemake.input.pre,  # noqa: F821
            pre_contours=snakemake.input.pre_contours,  # noqa: F821
            during_contours=snakemake.input.during_contours,  # noqa: F821
            pose_json=snakemake.output.pose,  # noqa: F821
            axis_png=snakemake.output.axis,  # noqa: F821
            tip_png=snakemake.output.tip,  # noqa: F821
            bone_png=snakemake.output.bone,  # noqa: F821
            checks_csv=snakemake.output.checks,  # noqa: F821
        ),
        options=dict(snakemake.params.options),  # noqa: F821
        override=dict(snakemake.params.override),  # noqa: F821
        animal=snakemake.wildcards.animal,  # noqa: F821
    )
    logging.info("pose of %s: %s", snakemake.wildcards.animal, pose.to_dict())  # noqa: F821
