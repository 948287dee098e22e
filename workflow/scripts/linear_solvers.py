"""Glue of rule linear_solvers: the backends' factorisation times on the cored cylinder's tangent."""

from deeptissue.fem.material import Ogden
from deeptissue.io import script_log
from deeptissue.verification.linear_solvers import linear_solver_rows, plot_linear_solvers

with script_log(snakemake.log[0], "linear_solvers"):  # noqa: F821
    table = linear_solver_rows(Ogden.from_config(snakemake.params.material))  # noqa: F821
    table.to_csv(snakemake.output.table, index=False)  # noqa: F821
    plot_linear_solvers(table, snakemake.output.figure)  # noqa: F821
