"""Glue of rule contact_variant: one study variant solved from the start with one contact formulation."""

from deeptissue.fem.cast import Cast
from deeptissue.fem.comparison import variant_row
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log, write_json
from deeptissue.mesh import load_tetmesh
from deeptissue.study import load_pose

with script_log(snakemake.log[0], "contact_variant"):
    w = snakemake.wildcards
    write_json(snakemake.output.row, variant_row(
        Ogden.from_config(snakemake.params.material), mesh=load_tetmesh(snakemake.input.mesh),
        pose=load_pose(snakemake.input.pose), cast=Cast.load(snakemake.input.cast), animal=w.animal,
        variant=w.variant, formulation=w.formulation, bar_length_mm=float(snakemake.params.bar_length_mm)))
