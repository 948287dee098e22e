"""How fast each linear-solver backend factorises the FE tangent on this machine: rule ``linear_solvers``.

A Newton iteration's cost is mostly one sparse Cholesky factorisation (docs/performance.md), and its speed
varies between machines and backends more than any other cost. The matrices here are the linear-elastic
tangents of the cored cylinder (:func:`deeptissue.verification.shapes.cored_cylinder_mesh`: quadratic tets,
the core's nodes fixed, a limb's size) on a ladder of element sizes. Every backend this machine has
(:func:`deeptissue.fem.linsolve.available_backends`) solves each in both precisions of
:class:`deeptissue.fem.linsolve.SymmetricSolver`: the first solve analyses the pattern, factorises and
solves; the second, on the same pattern with other values, factorises and solves, as a Newton iteration
does. The best of ``repeats`` second solves is the row's ``factor_solve_s``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import pandas as pd

from ..fem.assembly import Assembler, as_material_law
from ..fem.linsolve import PRECISIONS, SymmetricSolver, available_backends, backward_error
from ..fem.skmesh import straighten_invalid
from .shapes import cored_cylinder_mesh

__all__ = [
    "LINEAR_SOLVER_COLUMNS",
    "SCIPY_MAX_DOFS",
    "cylinder_tangent",
    "linear_solver_rows",
    "plot_linear_solvers",
]

LINEAR_SOLVER_COLUMNS = [
    "backend",
    "precision",
    "h_mm",
    "n_dofs",
    "nnz_upper",
    "first_solve_s",
    "factor_solve_s",
    "backward_error",
    "note",
]
# SciPy's SuperLU is an order of magnitude slower than the Cholesky backends on these matrices (minutes at
# 90 k DOFs): it is timed up to this size only
SCIPY_MAX_DOFS = 30_000


def cylinder_tangent(material, h_mm: float):
    """The upper triangle (CSR) of the linear-elastic tangent of the cored cylinder (20 mm long, radius 6 mm,
    core 1.5 mm) at element size ``h_mm``, the core's nodes fixed (curved tets with a non-positive Jacobian
    straightened, as the solver does)."""
    mesh = cored_cylinder_mesh(length_mm=20.0, radius_mm=6.0, core_radius_mm=1.5, h_mm=h_mm)
    mesh, _ = straighten_invalid(mesh)
    core = np.unique(mesh.facets["bone"].ravel())
    fixed = np.zeros(mesh.nodes_mm.size, bool)
    fixed[(3 * core[:, None] + np.arange(3)).ravel()] = True
    asm = Assembler(mesh, as_material_law(material), constrained=fixed)
    _, _, data, _ = asm.tangent(np.zeros(mesh.nodes_mm.size))
    return asm.csr(data)


def _timed(backend: str, precision: str, U, repeats: int) -> tuple[float, float, float]:
    """(first solve [s], best later factorise-and-solve [s], its backward error) of one backend."""
    rng = np.random.default_rng(0)
    b = rng.standard_normal(U.shape[0])
    solver = SymmetricSolver(precision, backend=backend)
    try:
        t0 = time.perf_counter()
        solver.solve(U, b, spd_only=True)
        first = time.perf_counter() - t0
        best, err = np.inf, np.nan
        for k in range(repeats):
            # same pattern, other values: a Newton iteration's case
            V = U.copy()
            V.data = V.data * (1.0 + 0.01 * (k + 1))
            t0 = time.perf_counter()
            x = solver.solve(V, b, spd_only=True)
            dt = time.perf_counter() - t0
            if dt < best:
                best, err = dt, backward_error(V, x, b)
        return first, best, err
    finally:
        solver.close()


def linear_solver_rows(
    material,
    *,
    sizes_mm: Sequence[float] = (1.6, 1.2, 1.0, 0.8),
    backends: Sequence[str] | None = None,
    repeats: int = 2,
) -> pd.DataFrame:
    """One row per backend x precision x element size (:data:`LINEAR_SOLVER_COLUMNS`): the times and the
    backward error of the solves described in the module docstring. ``backends``: default every one this
    machine has; SciPy's only up to :data:`SCIPY_MAX_DOFS` (a row with the reason beyond)."""
    backends = list(available_backends() if backends is None else backends)
    rows = []
    for h in sizes_mm:
        U = cylinder_tangent(material, h)
        n = U.shape[0]
        for backend in backends:
            for precision in PRECISIONS:
                row = dict(backend=backend, precision=precision, h_mm=h, n_dofs=n, nnz_upper=U.nnz)
                if backend == "scipy" and n > SCIPY_MAX_DOFS:
                    rows.append({**row, "note": f"not timed above {SCIPY_MAX_DOFS} DOFs"})
                    continue
                if backend == "cholmod" and precision == "mixed":
                    rows.append(
                        {**row, "note": "no single precision: 'mixed' is the 'double' row"}
                    )
                    continue
                first, again, err = _timed(backend, precision, U, repeats)
                rows.append(
                    {
                        **row,
                        "first_solve_s": first,
                        "factor_solve_s": again,
                        "backward_error": err,
                        "note": "",
                    }
                )
    return pd.DataFrame(rows, columns=LINEAR_SOLVER_COLUMNS)


def plot_linear_solvers(df: pd.DataFrame, path) -> None:
    """Factorise-and-solve time against DOFs, log-log, one line per backend and precision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    timed = df.dropna(subset=["factor_solve_s"])
    for (backend, precision), g in timed.groupby(["backend", "precision"]):
        ax.loglog(g.n_dofs, g.factor_solve_s, "o-", label=f"{backend}, {precision}")
    ax.set_xlabel("free DOFs of the tangent")
    ax.set_ylabel("factorise and solve [s], one thread")
    ax.set_title("Linear solvers on the cored cylinder's tangent")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
