"""Glue of rule cast: the rigid cast of one animal from its pre skin contours and the indenter axis."""

from deeptissue.io import script_log
from deeptissue.model import run_cast

with script_log(snakemake.log[0], "cast"):  # noqa: F821
    run_cast(
        contours_npz=snakemake.input.contours,  # noqa: F821
        pose_json=snakemake.input.pose,  # noqa: F821
        cast_npz=snakemake.output.cast,  # noqa: F821
        variants=list(snakemake.params.variants),  # noqa: F821
        settings=dict(snakemake.params.settings),  # noqa: F821
        animal=snakemake.wildcards.animal,  # noqa: F821
    )
