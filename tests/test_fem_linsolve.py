"""FE core: the sparse symmetric solvers of the Newton tangent (PARDISO in mixed and double precision)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from deeptissue.fem.assembly import Assembler, as_material_law
from deeptissue.fem.linsolve import NotPositiveDefinite, PardisoSymmetric
from deeptissue.fem.material import Ogden
from deeptissue.fem.shapes import block_mesh


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
    m = block_mesh((4.0, 3.0, 2.0), h_mm=0.5)
    bottom = np.unique(m.facets["bottom"])
    fixed = np.zeros(3 * len(m.nodes_mm), bool)
    fixed[(3 * bottom[:, None] + np.arange(3)).ravel()] = True
    A = Assembler(m, as_material_law(Ogden()), constrained=fixed)
    _, _, data, _ = A.tangent(np.zeros(A.n_dofs))
    U = A.csr(data)
    b = np.random.default_rng(0).standard_normal(U.shape[0])
    return U, b


def test_mixed_precision_refines_to_the_double_precision_answer(elasticity):
    U, b = elasticity
    xd = PardisoSymmetric("double").solve(U, b)
    s = PardisoSymmetric("mixed")
    xm = s.solve(U, b)
    # one single-precision solve carries ~7 digits: the refinement steps are what make it exact
    assert s.refinements >= 1 and s.double_fallbacks == 0 and s.last_mode == 2
    assert _backward_error(U, xm, b) < 1e-14
    np.testing.assert_allclose(xm, xd, rtol=0, atol=1e-9 * np.abs(xd).max())
    # the factorisation is reused for a new matrix on the same pattern (values change, analysis kept)
    x2 = s.solve(U.multiply(2.0).tocsr(), b)
    np.testing.assert_allclose(x2, 0.5 * xd, rtol=0, atol=1e-9 * np.abs(xd).max())
    assert s.factorisations == 2
    s.close()


def test_an_ill_conditioned_matrix_falls_back_to_double_precision():
    # 1D Laplacian, fixed at one end: condition ~ 16 n^2 / pi^2 = 6.5e8, beyond single precision's 7 digits
    n = 20000
    main = np.full(n, 2.0)
    main[-1] = 1.0
    U = sp.diags([main, -np.ones(n - 1)], [0, 1], format="csr")
    b = np.ones(n)
    s = PardisoSymmetric("mixed")
    x = s.solve(U, b)
    assert s.double_fallbacks == 1
    assert _backward_error(U, x, b) < 1e-14
    exact = np.arange(1, n + 1) * (n + 0.5) - 0.5 * np.arange(1, n + 1) ** 2  # -x'' = 1, x(0) = 0, x'(n) ~ 0
    assert np.abs(x - exact).max() < 1e-6 * exact.max()


@pytest.mark.parametrize("precision", ["mixed", "double"])
def test_an_indefinite_matrix_is_refused_in_spd_mode_and_solved_by_ldlt(elasticity, precision):
    U, b = elasticity
    # shift the spectrum so that a few eigenvalues are negative
    K = _full(U)
    lam_min = sp.linalg.eigsh(K, k=1, sigma=0, which="LM", return_eigenvectors=False)[0]
    Ui = (U - 3.0 * lam_min * sp.eye(U.shape[0], format="csr")).tocsr()
    s = PardisoSymmetric(precision)
    with pytest.raises(NotPositiveDefinite):
        s.solve(Ui, b, spd_only=True)
    x = s.solve(Ui, b)
    assert s.last_mode == -2
    assert _backward_error(Ui, x, b) < 1e-12
    s.close()


def test_precision_is_validated():
    with pytest.raises(ValueError, match="precision 'single'"):
        PardisoSymmetric("single")


def test_reuse_solves_a_nearby_matrix_by_conjugate_gradients_on_the_last_factor(elasticity):
    U, b = elasticity
    s = PardisoSymmetric("mixed", reuse_iterations=20, reuse_rtol=1e-8)
    s.solve(U, b)
    assert s.factorisations == 1
    # a nearby matrix of the same pattern: two stiff "contact" springs switched on, the rest 2 % stiffer
    d = np.zeros(U.shape[0])
    d[np.random.default_rng(1).choice(U.shape[0], 2, replace=False)] = 10.0 * U.diagonal().max()
    U2 = _plus_diagonal(_on_pattern(U, 1.02 * U.data), d)
    x2 = s.solve(U2, b)
    assert (s.reused, s.factorisations, s.last_mode) == (1, 1, "cg")
    assert 1 <= s.cg_iterations <= 20
    K2 = _full(U2)
    assert np.linalg.norm(K2 @ x2 - b) <= 1e-8 * np.linalg.norm(b)
    # a matrix far from the factor's: the conjugate gradients give up and it is factorised (and exact)
    scale = np.exp(np.random.default_rng(2).uniform(-3, 3, U.shape[0]))
    rows = np.repeat(np.arange(U.shape[0]), np.diff(U.indptr))
    U3 = _on_pattern(U, U.data * scale[rows] * scale[U.indices])
    its = s.cg_iterations
    x3 = s.solve(U3, b)
    assert (s.reuse_failed, s.factorisations, s.last_mode) == (1, 2, 2)
    # given up after the third iteration, the first at which progress is judged: slower than geometric
    # progress to reuse_rtol in reuse_iterations iterations is not worth more conjugate gradients
    assert s.cg_iterations - its == 3
    assert _backward_error(U3, x3, b) < 1e-14
    s.close()


def test_reuse_finds_an_indefinite_matrix_without_a_failed_factorisation(elasticity):
    U, b = elasticity
    s = PardisoSymmetric("mixed", reuse_iterations=20)
    s.solve(U, b)
    # shift so that the first conjugate-gradient direction p0 = K^-1 b has negative curvature
    p0 = PardisoSymmetric("double").solve(U, b)
    c = 2.0 * float(p0 @ (_full(U) @ p0)) / float(p0 @ p0)
    Ui = _plus_diagonal(U, -c)
    with pytest.raises(NotPositiveDefinite, match="conjugate gradients"):
        s.solve(Ui, b, spd_only=True)
    assert (s.reuse_indefinite, s.factorisations) == (1, 1)
    x = s.solve(Ui, b)  # not spd_only: straight to the LDL^T factorisation in double precision
    assert s.last_mode == -2 and s.factorisations == 2
    assert _backward_error(Ui, x, b) < 1e-12
    # the SPD factor stays the preconditioner for the next matrix
    s.solve(U, b)
    assert s.last_mode == "cg" and s.factorisations == 2
    s.close()


def test_reuse_settings_are_validated():
    with pytest.raises(ValueError, match="reuse_iterations -1"):
        PardisoSymmetric("mixed", reuse_iterations=-1)
    with pytest.raises(ValueError, match="reuse_rtol 0"):
        PardisoSymmetric("mixed", reuse_iterations=5, reuse_rtol=0.0)


# --------------------------------------------------------------------------- reproducible mode
# MKL's mode is per process and fixed by its first computation, so each check runs in its own process,
# with two threads (the tests themselves run with one).

_ROOT = Path(__file__).resolve().parents[1]


def _run_two_threads(code: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(_ROOT / "src"), MKL_NUM_THREADS="2", OMP_NUM_THREADS="2")
    env.pop("MKL_CBWR", None)
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return p.stdout.strip().splitlines()[-1]


def test_pin_reproducible_is_refused_after_mkl_has_computed():
    out = _run_two_threads("""
        import numpy as np, scipy.sparse as sp
        from deeptissue.fem.linsolve import PardisoSymmetric, pin_reproducible
        PardisoSymmetric("double").solve(sp.identity(3, format="csr"), np.ones(3))
        try:
            pin_reproducible()
        except RuntimeError as e:
            print("refused:", e)
        """)
    assert out.startswith("refused:") and "before the first MKL computation" in out


@pytest.mark.slow
def test_pinned_factorisations_of_one_matrix_are_bitwise_identical():
    # a 3-D Laplacian of 17 576 dofs: large enough for PARDISO to factorise with both threads, where
    # unpinned repetitions of this loop give two or three different answers in twenty
    out = _run_two_threads("""
        import numpy as np, scipy.sparse as sp
        from deeptissue.fem.linsolve import PardisoSymmetric, pin_reproducible
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
                s = PardisoSymmetric(precision)
                answers.add((precision, s.solve(U, b).tobytes()))
                s.close()
        print(len(answers))
        """)
    assert out == "2"  # one answer per precision


@pytest.mark.slow
def test_two_reproducible_contact_solves_take_identical_newton_iterations():
    code = """
        import hashlib
        from deeptissue.fem.linsolve import pin_reproducible
        pin_reproducible()
        from deeptissue.fem.material import Ogden
        from deeptissue.fem.verification import _indent_limb, reference_limb
        r = _indent_limb(reference_limb(h_mm=2.5), Ogden(), kind="sphere", depth_mm=1.5)
        assert r.converged, r.reason
        print(r.increments, r.newton_iterations, hashlib.sha256(r.displacement_mm.tobytes()).hexdigest())
        """
    first, second = _run_two_threads(code), _run_two_threads(code)
    assert first == second  # increments, Newton iterations and the displacement field, bit for bit


def test_solve_indefinite_solves_a_saddle_point_system():
    from deeptissue.fem.linsolve import PardisoSymmetric

    rng = np.random.default_rng(4)
    A = rng.standard_normal((12, 12))
    K = A @ A.T + 12 * np.eye(12)  # SPD block
    G = rng.standard_normal((3, 12))  # three constraints
    M = np.block([[K, G.T], [G, np.zeros((3, 3))]])  # indefinite: Cholesky is impossible
    r, c = np.nonzero(np.triu(M))
    r, c = np.concatenate([r, np.arange(12, 15)]), np.concatenate([c, np.arange(12, 15)])  # the zero diagonal, stored
    U = sp.coo_matrix((M[r, c], (r, c)), shape=(15, 15)).tocsr()
    U.sort_indices()
    assert U.nnz == np.count_nonzero(np.triu(M)) + 3
    b = rng.standard_normal(15)
    s = PardisoSymmetric("double")
    try:
        x = s.solve_indefinite(U, b)
    finally:
        s.close()
    np.testing.assert_allclose(x, np.linalg.solve(M, b), rtol=1e-9, atol=1e-12)
    assert s.last_mode == -2 and s.factorisations == 1
