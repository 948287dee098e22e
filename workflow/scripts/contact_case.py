"""Glue of rule contact_case: one hard case solved with one contact formulation."""

from deeptissue.fem.comparison import comparison_row
from deeptissue.fem.material import Ogden
from deeptissue.io import script_log, write_json

with script_log(snakemake.log[0], "contact_case"):
    write_json(snakemake.output.row, comparison_row(Ogden.from_config(snakemake.params.material),
                                                    snakemake.wildcards.case, snakemake.wildcards.formulation))
