"""The linear-solver benchmark (rule linear_solvers) times every backend on a tangent it solves exactly."""

import numpy as np

from deeptissue.fem.linsolve import available_backends
from deeptissue.fem.material import Ogden
from deeptissue.verification import linear_solvers as ls


def test_every_backend_is_timed_on_the_cylinder_tangent_and_solves_it(tmp_path, monkeypatch):
    monkeypatch.setattr(ls, "SCIPY_MAX_DOFS", 10**9)
    df = ls.linear_solver_rows(Ogden(), sizes_mm=(3.0,), repeats=1)
    assert list(df.columns) == ls.LINEAR_SOLVER_COLUMNS
    timed = df[df.note == ""]
    assert set(timed.backend) == set(available_backends())
    assert (timed.factor_solve_s > 0).all() and (timed.first_solve_s > 0).all()
    # a Cholesky of an SPD tangent (refined in double where the factor is single) to rounding
    assert (timed.backward_error < 1e-13).all()
    n = int(df.n_dofs.iloc[0])
    assert n % 3 == 0 and n > 1000
    ls.plot_linear_solvers(df, tmp_path / "ls.png")
    assert (tmp_path / "ls.png").stat().st_size > 1000


def test_scipy_is_left_out_above_its_size_with_the_reason(monkeypatch):
    monkeypatch.setattr(ls, "SCIPY_MAX_DOFS", 10)
    df = ls.linear_solver_rows(Ogden(), sizes_mm=(3.0,), backends=["scipy"], repeats=1)
    assert len(df) == 2 and df.factor_solve_s.isna().all()
    assert df.note.str.contains("not timed above 10 DOFs").all()


def test_the_tangent_holds_every_dof_but_the_core_and_is_positive_definite():
    from deeptissue.verification.shapes import cored_cylinder_mesh

    mesh = cored_cylinder_mesh(length_mm=20.0, radius_mm=6.0, core_radius_mm=1.5, h_mm=3.0)
    n_core = len(np.unique(mesh.facets["bone"].ravel()))
    U = ls.cylinder_tangent(Ogden(), 3.0)
    assert U.shape == (3 * (len(mesh.nodes_mm) - n_core),) * 2
    full = U + U.T
    full.setdiag(U.diagonal())
    x = np.random.default_rng(1).standard_normal(U.shape[0])
    assert float(x @ (full @ x)) > 0 and abs(full - full.T).max() == 0
