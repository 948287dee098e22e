"""Glue of rule mesh: the tetrahedral mesh (quadratic by default) of one animal's limb with its facet sets and patches."""

from deeptissue.io import script_log
from deeptissue.model import MeshFiles, run_mesh

with script_log(snakemake.log[0], "mesh"):  # noqa: F821
    run_mesh(
        MeshFiles(
            contours_npz=snakemake.input.contours,  # noqa: F821
            pose_json=snakemake.input.pose,  # noqa: F821
            cast_npz=snakemake.input.cast,  # noqa: F821
            mesh_npz=snakemake.output.mesh,  # noqa: F821
            mesh_msh=snakemake.output.msh,  # noqa: F821
            mesh_vtu=snakemake.output.vtu,  # noqa: F821
            model_json=snakemake.output.model,  # noqa: F821
            qc_png=snakemake.output.qc,  # noqa: F821
        ),
        variants=list(snakemake.params.variants),  # noqa: F821
        settings=dict(snakemake.params.settings),  # noqa: F821
        animal=snakemake.wildcards.animal,  # noqa: F821
    )
