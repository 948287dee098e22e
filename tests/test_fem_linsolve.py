"""FE core: the sparse symmetric solvers of the Newton tangent (PARDISO, CHOLMOD or SuperLU; mixed and double
precision), each checked on every backend this machine has, and the choice of backend."""

import functools
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from deeptissue.fem.assembly import Assembler, as_material_law
from deeptissue.fem.linsolve import (
    BACKEND_ENV,
    NotPositiveDefinite,
    SymmetricSolver,
    available_backends,
    linear_backend,
)
from deeptissue.fem.material import Ogden
from deeptissue.verification.shapes import block_mesh

_ROOT = Path(__file__).resolve().parents[1]
HERE = available_backends()
needs_mkl = pytest.mark.skipif(
    linear_backend() != "pardiso", reason="MKL's reproducible mode: only with the PARDISO backend"
)


def _full(U):
    return (U + sp.triu(U, 1).T).tocsr()


def _on_pattern(U, data):
    """A matrix of U's sparsity pattern (explicit zeros kept, as the assembler's) with these values."""
    return sp.csr_matrix((data, U.indices, U.indptr), shape=U.shape)


def _plus_diagonal(U, d):
    data = U.data.copy()
    data[U.indptr[:-1]] += d  # sorted upper-triangle rows start at the diagonal
    return _on_pattern(U, data)


def _backward_error(U, x, b):
    K = _full(U)
    return np.abs(K @ x - b).max() / (abs(K).sum(axis=1).max() * np.abs(x).max() + np.abs(b).max())


@pytest.fixture(scope="module")
def elasticity():
    """Upper triangle of a P2 block's tangent at rest (bottom fixed: positive definite) and a load."""
    return _elasticity()


@functools.cache
def _elasticity():
    m = block_mesh((4.0, 3.0, 2.0), h_mm=0.5)
    bottom = np.unique(m.facets["bottom"])
    fixed = np.zeros(3 * len(m.nodes_mm), bool)
    fixed[(3 * bottom[:, None] + np.arange(3)).ravel()] = True
    A = Assembler(m, as_material_law(Ogden()), constrained=fixed)
    _, _, data, _ = A.tangent(np.zeros(A.n_dofs))
    U = A.csr(data)
    b = np.random.default_rng(0).standard_normal(U.shape[0])
    return U, b


@pytest.mark.parametrize("backend", HERE)
def test_mixed_precision_refines_to_the_double_precision_answer(elasticity, backend):
    U, b = elasticity
    xd = SymmetricSolver("double", backend=backend).solve(U, b)
    s = SymmetricSolver("mixed", backend=backend)
    xm = s.solve(U, b)
    # one single-precision solve carries ~7 digits: the refinement steps are what make it exact (CHOLMOD has
    # no single precision: its 'mixed' is one double-precision Cholesky)
    assert s.double_fallbacks == 0 and s.last_mode == 2
    assert s.refinements >= 1 if backend != "cholmod" else s.refinements == 0
    assert _backward_error(U, xm, b) < 1e-14
    np.testing.assert_allclose(xm, xd, rtol=0, atol=1e-9 * np.abs(xd).max())
    # the factorisation is reused for a new matrix on the same pattern (values change, analysis kept)
    x2 = s.solve(U.multiply(2.0).tocsr(), b)
    np.testing.assert_allclose(x2, 0.5 * xd, rtol=0, atol=1e-9 * np.abs(xd).max())
    assert s.factorisations == 2
    assert s.analyses == 1  # one pattern: analysed once
    s.close()


@pytest.mark.parametrize("backend", [b for b in HERE if b != "cholmod"])
def test_an_ill_conditioned_matrix_falls_back_to_double_precision(backend):
    # 1D Laplacian, fixed at one end: condition ~ 16 n^2 / pi^2 = 6.5e8, beyond single precision's 7 digits
    n = 20000
    main = np.full(n, 2.0)
    main[-1] = 1.0
    U = sp.diags([main, -np.ones(n - 1)], [0, 1], format="csr")
    b = np.ones(n)
    s = SymmetricSolver("mixed", backend=backend)
    x = s.solve(U, b)
    assert s.double_fallbacks == 1
    assert _backward_error(U, x, b) < 1e-14
    exact = (
        np.arange(1, n + 1) * (n + 0.5) - 0.5 * np.arange(1, n + 1) ** 2
    )  # -x'' = 1, x(0) = 0, x'(n) ~ 0
    assert np.abs(x - exact).max() < 1e-6 * exact.max()


@pytest.mark.parametrize("backend", HERE)
@pytest.mark.parametrize("precision", ["mixed", "double"])
def test_an_indefinite_matrix_is_refused_in_spd_mode_and_solved_by_ldlt(
    elasticity, precision, backend
):
    U, b = elasticity
    # shift the spectrum so that a few eigenvalues are negative
    K = _full(U)
    lam_min = sp.linalg.eigsh(K, k=1, sigma=0, which="LM", return_eigenvectors=False)[0]
    Ui = (U - 3.0 * lam_min * sp.eye(U.shape[0], format="csr")).tocsr()
    s = SymmetricSolver(precision, backend=backend)
    with pytest.raises(NotPositiveDefinite):
        s.solve(Ui, b, spd_only=True)
    x = s.solve(Ui, b)
    assert s.last_mode == -2
    assert _backward_error(Ui, x, b) < 1e-12
    s.close()


def test_precision_is_validated():
    with pytest.raises(ValueError, match="precision 'single'"):
        SymmetricSolver("single")


def _saddle(U, G):
    """The full saddle-point matrix [[K, -G^T], [G, 0]] of K = U + triu(U, 1)^T (unsymmetric sign convention
    of solve_constrained: K x - G^T lam = r, G x = s)."""
    return sp.bmat([[_full(U), -G.T], [G, None]]).tocsc()


def _constraints(n, m, seed):
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(m), 6)
    cols = rng.choice(n, 6 * m)
    return sp.csr_matrix((rng.standard_normal(6 * m), (rows, cols)), shape=(m, n))


@functools.cache
def _saddle_case(shift: float):
    """A constrained elasticity problem (:func:`elasticity` with 40 random constraints) and its answer by
    SuperLU on the full saddle-point matrix, computed once for every backend: (Uk, G, rho, A, b, s, ref)."""
    U, b = _elasticity()
    n, m = U.shape[0], 40
    G = _constraints(n, m, 3)
    rho = 1e3 * np.median(U.diagonal()) / np.asarray(G.multiply(G).sum(axis=1)).ravel()
    if shift:
        # K indefinite in directions the constraints fix (K - c P^T P with P a subset of G's rows, c ten times
        # the stiffness there); the augmented matrix stays positive definite: one single-precision factor
        P = G[:5]
        c = 1e-2 * float(np.min(rho[:5]))
        Uk = (U - shift * c * sp.triu(P.T @ P)).tocsr()
    else:
        Uk = U
    Uk.sort_indices()
    A = (Uk + sp.triu(G.T @ sp.diags(rho) @ G)).tocsr()
    A.sort_indices()
    s_ = np.random.default_rng(4).standard_normal(m) * 1e-2
    ref = sp.linalg.spsolve(_saddle(Uk, G), np.concatenate([b, s_]))
    return Uk, G, rho, A, b, s_, ref


@pytest.mark.parametrize("backend", HERE)
@pytest.mark.parametrize("shift", [0.0, 1.0], ids=["spd", "indefinite-off-the-constraints"])
def test_solve_constrained_solves_the_saddle_point_system(shift, backend):
    Uk, G, rho, A, b, s_, ref = _saddle_case(shift)
    n = Uk.shape[0]
    solver = SymmetricSolver(backend=backend)
    x, lam = solver.solve_constrained(A, G, rho, b, s_)
    assert np.allclose(x, ref[:n], rtol=0, atol=1e-9 * np.abs(ref[:n]).max())
    assert np.allclose(lam, ref[n:], rtol=0, atol=1e-9 * np.abs(ref[n:]).max())
    # one Cholesky factorisation (single precision where the backend has it), a handful of corrections
    assert (solver.factorisations, solver.double_fallbacks, solver.last_mode) == (1, 0, 2)
    assert solver.refinements <= 8
    solver.close()


@pytest.mark.parametrize("backend", HERE)
def test_solve_constrained_without_constraints_is_a_plain_solve(elasticity, backend):
    U, b = elasticity
    G = sp.csr_matrix((0, U.shape[0]))
    x, lam = SymmetricSolver(backend=backend).solve_constrained(U, G, np.zeros(0), b, np.zeros(0))
    assert lam.shape == (0,)
    assert _backward_error(U, x, b) < 1e-13


@pytest.mark.parametrize("backend", HERE)
def test_solve_constrained_falls_back_to_an_indefinite_factorisation(elasticity, backend):
    U, b = elasticity
    n = U.shape[0]
    G = _constraints(n, 10, 5)
    rho = 1e3 * np.median(U.diagonal()) / np.asarray(G.multiply(G).sum(axis=1)).ravel()
    # an augmented matrix with a negative eigenvalue off the constraints: Cholesky fails, Bunch-Kaufman solves it
    p0 = SymmetricSolver("double", backend=backend).solve(U, b)
    Ui = _plus_diagonal(U, -2.0 * float(p0 @ (_full(U) @ p0)) / float(p0 @ p0))
    A = (Ui + sp.triu(G.T @ sp.diags(rho) @ G)).tocsr()
    A.sort_indices()
    solver = SymmetricSolver(backend=backend)
    x, lam = solver.solve_constrained(A, G, rho, b, np.zeros(10))
    ref = sp.linalg.spsolve(_saddle(Ui, G), np.concatenate([b, np.zeros(10)]))
    assert solver.last_mode == -2
    assert np.allclose(x, ref[:n], rtol=0, atol=1e-8 * np.abs(ref[:n]).max())


# --------------------------------------------------------------------------- choice of backend


def test_the_environment_variable_names_the_backend(monkeypatch):
    monkeypatch.setenv(BACKEND_ENV, "scipy")
    assert linear_backend() == "scipy" and SymmetricSolver().backend == "scipy"
    monkeypatch.setenv(BACKEND_ENV, "umfpack")
    with pytest.raises(ValueError, match=f"{BACKEND_ENV}='umfpack'"):
        SymmetricSolver()
    monkeypatch.delenv(BACKEND_ENV)
    assert linear_backend() == HERE[0] and "scipy" in HERE


def test_without_mkl_the_solver_chooses_another_backend_and_solves():
    # pypardiso (and with it MKL) made unimportable, as on a machine that is not x86-64
    env = dict(os.environ, PYTHONPATH=str(_ROOT / "src"))
    env.pop(BACKEND_ENV, None)
    code = """
        import sys
        sys.modules["pypardiso"] = None
        import numpy as np, scipy.sparse as sp
        from deeptissue.fem.linsolve import SymmetricSolver, available_backends, linear_backend
        assert "pardiso" not in available_backends()
        U = sp.triu(sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(50, 50))).tocsr()
        x = SymmetricSolver().solve(U, np.ones(50))
        k = np.arange(1, 51)
        print(linear_backend(), np.abs(x - k * (51 - k) / 2).max())
        """
    p = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True
    )
    assert p.returncode == 0, p.stderr[-3000:]
    backend, err = p.stdout.split()
    assert backend in ("cholmod", "scipy") and float(err) < 1e-10  # -x'' = 1, x(0) = x(51) = 0


def test_pardiso_named_where_there_is_no_mkl_is_refused(monkeypatch):
    import deeptissue.fem.linsolve as linsolve

    monkeypatch.setitem(linsolve._WORKS, "pardiso", lambda: False)  # as on a machine without MKL
    monkeypatch.setenv(BACKEND_ENV, "pardiso")
    with pytest.raises(RuntimeError, match="not usable here"):
        linear_backend()
    monkeypatch.delenv(BACKEND_ENV)
    assert linear_backend() in ("cholmod", "scipy")


# --------------------------------------------------------------------------- reproducible mode
# MKL's mode is per process and fixed by its first computation, so each check runs in its own process,
# with two threads (the tests themselves run with one).


def _run_two_threads(code: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(_ROOT / "src"), MKL_NUM_THREADS="2", OMP_NUM_THREADS="2")
    env.pop("MKL_CBWR", None)
    p = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert p.returncode == 0, p.stderr[-3000:]
    return p.stdout.strip().splitlines()[-1]


@needs_mkl
def test_pin_reproducible_is_refused_after_mkl_has_computed():
    out = _run_two_threads("""
        import numpy as np, scipy.sparse as sp
        from deeptissue.fem.linsolve import SymmetricSolver, pin_reproducible
        SymmetricSolver("double").solve(sp.identity(3, format="csr"), np.ones(3))
        try:
            pin_reproducible()
        except RuntimeError as e:
            print("refused:", e)
        """)
    assert out.startswith("refused:") and "before the first MKL computation" in out


@needs_mkl
@pytest.mark.slow
def test_pinned_factorisations_of_one_matrix_are_bitwise_identical():
    # a 3-D Laplacian of 17 576 dofs: large enough for PARDISO to factorise with both threads, where
    # unpinned repetitions of this loop give two or three different answers in twenty
    out = _run_two_threads("""
        import numpy as np, scipy.sparse as sp
        from deeptissue.fem.linsolve import SymmetricSolver, pin_reproducible
        pin_reproducible()
        n = 26
        T, I = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n)), sp.identity(n)
        K = sp.kron(sp.kron(T, I), I) + sp.kron(sp.kron(I, T), I) + sp.kron(sp.kron(I, I), T)
        rng = np.random.default_rng(0)
        U = sp.triu(K + sp.diags(1e-3 * rng.random(n**3))).tocsr()
        U.sort_indices()
        b = rng.random(n**3)
        answers = set()
        for precision in ("mixed", "double"):
            for _ in range(6):
                s = SymmetricSolver(precision)
                answers.add((precision, s.solve(U, b).tobytes()))
                s.close()
        print(len(answers))
        """)
    assert out == "2"  # one answer per precision


@needs_mkl
@pytest.mark.slow
def test_two_reproducible_contact_solves_take_identical_newton_iterations():
    code = """
        import hashlib
        from deeptissue.fem.linsolve import pin_reproducible
        pin_reproducible()
        from deeptissue.fem.material import Ogden
        from deeptissue.verification.scenes import _indent_limb, reference_limb
        r = _indent_limb(reference_limb(h_mm=2.5), Ogden(), kind="sphere", depth_mm=1.5)
        assert r.converged, r.reason
        print(r.increments, r.newton_iterations, hashlib.sha256(r.displacement_mm.tobytes()).hexdigest())
        """
    first, second = _run_two_threads(code), _run_two_threads(code)
    assert first == second  # increments, Newton iterations and the displacement field, bit for bit


def test_the_mkl_library_is_named_to_pypardiso_from_the_environment(monkeypatch):
    # pypardiso otherwise searches every folder under the environment's lib (0.5 s in each solve job)
    import deeptissue.fem.linsolve as linsolve

    if "pardiso" not in linsolve.available_backends():
        pytest.skip("no MKL PARDISO here")
    monkeypatch.delenv("PYPARDISO_MKL_RT", raising=False)
    lib = linsolve._mkl_rt.__wrapped__()
    path = os.environ["PYPARDISO_MKL_RT"]
    assert os.path.dirname(path) == os.path.join(sys.prefix, "lib") and lib._name == path
