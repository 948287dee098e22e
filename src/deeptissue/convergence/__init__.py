"""Speed against error: animals and variants solved at a ladder of discretisations and on adaptive meshes.

The settings and the accuracy goal are in :mod:`.ladder`; one timed run (mesh, solve,
post-processing and a linear-elastic reference) in :mod:`.runs`; the errors against the finest
converged run, Richardson extrapolation, the Pareto front and the scaling fits in :mod:`.analysis`;
summary.md, the error-vs-time figure and rule ``convergence_aggregate`` in :mod:`.report`.

Units: mm, N, s, MB (resident memory, 2**20 bytes); percentages in %, bin errors in percentage
points (pp).
"""

from .analysis import (
    ADAPTIVE_FAMILY,
    ESTIMATES,
    Richardson,
    ScalingFit,
    adaptive_pass_errors,
    adaptive_rows,
    convergence_table,
    goal_error,
    pareto_mask,
    reference_rows,
    richardson_by_family,
    richardson_extrapolation,
    scaling_fit,
    scaling_fits,
    setting_table,
    size_measure,
)
from .ladder import (
    SUPPORTED_ELEMENT_ORDERS,
    AccuracyGoal,
    Discretisation,
    Ladder,
    default_ladder,
    setting_name,
)
from .report import (
    ConvergenceInputs,
    ConvergenceOutputs,
    aggregate_convergence,
    plot_error_vs_time,
    read_benchmark,
    summary_markdown,
    write_summary_md,
)
from .runs import (
    ROW_COLUMNS,
    RunJob,
    linear_reference_solve,
    run_convergence_job,
    run_discretisation,
)

__all__ = [
    # ladder
    "SUPPORTED_ELEMENT_ORDERS",
    "AccuracyGoal",
    "Discretisation",
    "Ladder",
    "default_ladder",
    "setting_name",
    # runs
    "ROW_COLUMNS",
    "linear_reference_solve",
    "RunJob",
    "run_convergence_job",
    "run_discretisation",
    # analysis
    "ADAPTIVE_FAMILY",
    "ESTIMATES",
    "Richardson",
    "ScalingFit",
    "adaptive_pass_errors",
    "adaptive_rows",
    "convergence_table",
    "goal_error",
    "pareto_mask",
    "reference_rows",
    "richardson_by_family",
    "richardson_extrapolation",
    "scaling_fit",
    "scaling_fits",
    "setting_table",
    "size_measure",
    # report
    "ConvergenceInputs",
    "ConvergenceOutputs",
    "aggregate_convergence",
    "plot_error_vs_time",
    "read_benchmark",
    "summary_markdown",
    "write_summary_md",
]
