"""Ogden material point: stress and tangent against finite differences, small-strain elasticity,
rotations and the analytical homogeneous responses (principal-stretch form)."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from deeptissue.config import validate_config
from deeptissue.fem.material import (
    Ogden,
    ogden_energy,
    ogden_stress,
    ogden_stress_tangent,
    sym_eig3,
)
from deeptissue.verification import analytic
from deeptissue.verification.material import (
    FD_STEP_SECOND,
    FD_STEP_STRESS,
    TOL_FD,
    TOL_FD_SECOND,
    deformation_cases,
    fd_gradient,
    fd_hessian,
    homogeneous_responses,
    material_point_checks,
    random_rotations,
)

ROOT = Path(__file__).resolve().parents[1]
MAT = Ogden()
CASES = deformation_cases(np.random.default_rng(3))


def test_units_and_defaults():
    assert MAT.mu_mpa == pytest.approx(0.00365, rel=1e-15)
    assert MAT.bulk_mpa == pytest.approx(2.0 / 57.0, rel=1e-15)
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    validate_config(cfg, ROOT / "workflow" / "schemas" / "config.schema.yaml", base_dir=ROOT)
    assert Ogden.from_config(cfg["fem"]["material"]) == Ogden(
        mu_kpa=3.65, alpha=5.0, d_mm2_per_n=57.0
    )


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"mu_kpa": -1.0}, "mu_kpa"),
        ({"alpha": 0.0}, "alpha"),
        ({"d_mm2_per_n": 0.0}, "d_mm2_per_n"),
        ({"mu_kpa": float("nan")}, "mu_kpa"),
    ],
)
def test_bad_parameters_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        Ogden(**kw)


def test_bad_shape_is_refused():
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3, 3\)"):
        ogden_stress(np.eye(2), MAT)


def test_reference_state_is_stress_free_and_linear_elastic():
    W, P, A = ogden_stress_tangent(np.eye(3), MAT)
    assert W == 0.0
    assert np.all(P == 0.0)
    # small-strain isotropic elasticity written out with Lame constants: lambda = K - 2 mu / 3
    mu, K = 0.00365, 2.0 / 57.0
    lam = K - 2.0 * mu / 3.0
    d = np.eye(3)
    C = np.zeros((3, 3, 3, 3))
    for i, j, k, l in np.ndindex(3, 3, 3, 3):
        C[i, j, k, l] = lam * d[i, j] * d[k, l] + mu * (d[i, k] * d[j, l] + d[i, l] * d[j, k])
    np.testing.assert_allclose(A, C, rtol=0, atol=1e-13 * K)
    # small-strain shear modulus and bulk modulus read off the tangent
    assert A[0, 1, 0, 1] == pytest.approx(mu, rel=1e-13)
    assert (A[0, 0, 0, 0] + 2 * A[0, 0, 1, 1]) / 3 == pytest.approx(K, rel=1e-13)


@pytest.mark.parametrize("case", list(CASES))
def test_stress_and_tangent_match_finite_differences(case):
    F = CASES[case]
    W, P, A = ogden_stress_tangent(F, MAT)
    energy = lambda G: ogden_energy(G, MAT)  # noqa: E731
    stress = lambda G: ogden_stress(G, MAT)  # noqa: E731
    p_scale = max(np.abs(P).max(), MAT.mu_mpa)
    a_scale = np.abs(A).max()
    assert np.abs(P - fd_gradient(energy, F, FD_STEP_STRESS)).max() <= TOL_FD * p_scale
    assert np.abs(A - fd_gradient(stress, F, FD_STEP_STRESS)).max() <= TOL_FD * a_scale
    assert np.abs(A - fd_hessian(energy, F, FD_STEP_SECOND)).max() <= TOL_FD_SECOND * a_scale
    # major symmetry of the Hessian
    assert np.abs(A - A.transpose(0, 3, 4, 1, 2)).max() <= 1e-14 * a_scale
    assert np.all(np.isfinite(A))


def test_energy_matches_principal_stretch_form():
    F = np.concatenate(list(CASES.values()))
    sv = np.linalg.svd(F, compute_uv=False)
    expected = [analytic.principal_energy(*s, MAT) for s in sv]
    np.testing.assert_allclose(ogden_energy(F, MAT), expected, rtol=1e-12, atol=1e-14 * MAT.mu_mpa)


def test_objectivity_and_isotropy():
    rng = np.random.default_rng(11)
    F = CASES["random F"]
    Q = random_rotations(len(F), rng)
    W, P, A = ogden_stress_tangent(F, MAT)
    Wq, Pq, Aq = ogden_stress_tangent(Q @ F, MAT)
    np.testing.assert_allclose(Wq, W, rtol=1e-12)
    np.testing.assert_allclose(Pq, Q @ P, rtol=0, atol=1e-13 * np.abs(P).max())
    np.testing.assert_allclose(
        Aq, np.einsum("nia,nkb,naJbL->niJkL", Q, Q, A), rtol=0, atol=1e-13 * np.abs(A).max()
    )
    Wm, Pm, Am = ogden_stress_tangent(F @ Q, MAT)
    np.testing.assert_allclose(Wm, W, rtol=1e-12)
    np.testing.assert_allclose(Pm, P @ Q, rtol=0, atol=1e-13 * np.abs(P).max())
    np.testing.assert_allclose(
        Am, np.einsum("niMkN,nMJ,nNL->niJkL", A, Q, Q), rtol=0, atol=1e-13 * np.abs(A).max()
    )


def test_rigid_rotation_is_stress_free():
    Q = random_rotations(5, np.random.default_rng(5))
    W, P, _ = ogden_stress_tangent(Q, MAT)
    assert np.abs(W).max() <= 1e-14 * MAT.mu_mpa
    assert np.abs(P).max() <= 1e-13 * MAT.mu_mpa


def test_tangent_is_continuous_through_coalescence():
    """Stretches (a, a + d, b) for d -> 0: the tangent converges linearly to the one at d = 0."""
    R1, R2 = random_rotations(2, np.random.default_rng(9))
    a, b = 1.13, 0.84
    A0 = ogden_stress_tangent(R1 @ np.diag([a, a, b]) @ R2, MAT)[2]
    diffs = []
    for d in (1e-4, 1e-6, 1e-9, 1e-12):
        A = ogden_stress_tangent(R1 @ np.diag([a, a + d, b]) @ R2, MAT)[2]
        diffs.append(np.abs(A - A0).max() / np.abs(A0).max())
    # first-order convergence with a modest constant, down to rounding
    assert (
        diffs[0] < 10 * 1e-4 and diffs[1] < 10 * 1e-6 and diffs[2] < 10 * 1e-9 and diffs[3] < 1e-11
    )
    assert diffs[0] > 1e-6  # the tangent does depend on the split (the check can fail)


def test_batch_shapes_and_inverted_points():
    rng = np.random.default_rng(2)
    F = np.eye(3) + 0.2 * rng.standard_normal((2, 4, 3, 3))
    F[1, 2] = np.diag([1.0, 1.0, -1.0])  # inverted
    F[0, 3] = np.zeros((3, 3))  # degenerate
    W, P, A = ogden_stress_tangent(F, MAT)
    assert W.shape == (2, 4) and P.shape == (2, 4, 3, 3) and A.shape == (2, 4, 3, 3, 3, 3)
    bad = np.zeros((2, 4), bool)
    bad[1, 2] = bad[0, 3] = True
    assert np.all(np.isposinf(W[bad])) and np.all(np.isnan(P[bad])) and np.all(np.isnan(A[bad]))
    assert np.all(np.isfinite(W[~bad])) and np.all(np.isfinite(A[~bad]))
    np.testing.assert_allclose(ogden_energy(F, MAT), W, rtol=1e-14)
    # each point is independent of the others in the batch
    W1, P1, A1 = ogden_stress_tangent(F[0, 1], MAT)
    np.testing.assert_allclose(P1, P[0, 1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(A1, A[0, 1], rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    "spectrum",
    [
        [1.7, 0.9, 0.4],
        [1.0, 1.0, 1.0],
        [2.0, 2.0, 0.5],
        [1.0, 1.0 + 1e-9, 1.0 - 1e-9],
        [9.0, 0.09, 0.09 + 1e-12],
    ],
)
def test_jacobi_eigensolver_is_backward_stable(spectrum):
    """C V = V diag(c), V^T V = I to rounding; eigenvalues equal to the constructed spectrum."""
    R = random_rotations(200, np.random.default_rng(4))
    C = np.einsum("nia,a,nja->nij", R, np.array(spectrum), R)
    c, V = sym_eig3(C)
    scale = max(spectrum)
    assert np.abs(C @ V - V * c[:, None, :]).max() <= 1e-14 * scale
    assert np.abs(np.swapaxes(V, 1, 2) @ V - np.eye(3)).max() <= 1e-14
    np.testing.assert_allclose(
        np.sort(c, axis=1), np.broadcast_to(np.sort(spectrum), c.shape), rtol=0, atol=1e-14 * scale
    )
    np.testing.assert_array_equal(sym_eig3(C, vectors=False), c)


def test_chunked_evaluation_matches_pointwise():
    """Batches larger than the internal chunk give the same numbers as single points."""
    from deeptissue.fem import material as mat

    rng = np.random.default_rng(8)
    n = 2 * mat._CHUNK + 17
    F = np.eye(3) + 0.2 * rng.standard_normal((n, 3, 3))
    F[mat._CHUNK + 3] = -np.eye(3)  # an inverted point inside the second chunk
    W, P, A = ogden_stress_tangent(F, MAT)
    for i in (0, mat._CHUNK - 1, mat._CHUNK, mat._CHUNK + 4, n - 1):
        Wi, Pi, Ai = ogden_stress_tangent(F[i], MAT)
        assert Wi == pytest.approx(W[i], rel=1e-14)
        np.testing.assert_allclose(Pi, P[i], rtol=0, atol=1e-15)
        np.testing.assert_allclose(Ai, A[i], rtol=0, atol=1e-15)
    assert np.isposinf(W[mat._CHUNK + 3]) and np.isnan(A[mat._CHUNK + 3]).all()
    assert np.isfinite(A[mat._CHUNK + 2]).all() and np.isfinite(A[mat._CHUNK + 4]).all()


def test_lapack_fallback_for_unconverged_jacobi_gives_the_same_result(monkeypatch):
    """With one Jacobi sweep allowed, (almost) every point falls back to LAPACK eigh."""
    from deeptissue.fem import material as mat

    F = CASES["random F"]
    W, P, A = ogden_stress_tangent(F, MAT)
    c, V = sym_eig3(np.swapaxes(F, 1, 2) @ F)
    monkeypatch.setattr(mat, "_JACOBI_MAX_SWEEPS", 1)
    W1, P1, A1 = ogden_stress_tangent(F, MAT)
    C = np.swapaxes(F, 1, 2) @ F
    c1, V1 = sym_eig3(C)
    assert mat._jacobi(
        C[:, 0, 0], C[:, 1, 1], C[:, 2, 2], C[:, 0, 1], C[:, 0, 2], C[:, 1, 2], vectors=False
    )[2].all()
    np.testing.assert_allclose(W1, W, rtol=1e-13)
    np.testing.assert_allclose(P1, P, rtol=0, atol=1e-13 * np.abs(P).max())
    np.testing.assert_allclose(A1, A, rtol=0, atol=1e-13 * np.abs(A).max())
    np.testing.assert_allclose(np.sort(c1, axis=1), np.sort(c, axis=1), rtol=1e-13)


# ---- the analytical truth itself ---------------------------------------------------------------


def test_analytic_kirchhoff_is_the_derivative_of_the_analytic_energy():
    l = (1.3, 0.8, 1.05)
    h = 1e-5
    for a in range(3):
        up, dn = list(l), list(l)
        up[a] += h
        dn[a] -= h
        dW = (analytic.principal_energy(*up, MAT) - analytic.principal_energy(*dn, MAT)) / (2 * h)
        assert l[a] * dW == pytest.approx(analytic.principal_kirchhoff(*l, MAT)[a], rel=1e-7)


def test_analytic_uniaxial_small_strain_limit_is_linear_elasticity():
    mu, K = MAT.mu_mpa, MAT.bulk_mpa
    E = 9 * K * mu / (3 * K + mu)
    nu = (3 * K - 2 * mu) / (2 * (3 * K + mu))
    eps = 1e-6
    t, P = analytic.uniaxial(1 + eps, MAT)
    assert P == pytest.approx(E * eps, rel=1e-5)
    assert (1 - t) / eps == pytest.approx(nu, rel=1e-5)


def test_analytic_simple_shear_matches_spectral_reconstruction():
    """sigma = sum_a sigma_a n_a n_a with n_a eigenvectors of b = F F^T, as an independent route."""
    for g in (0.0, 0.3, 1.0, 2.5):
        F = np.eye(3)
        F[0, 1] = g
        b2, n = np.linalg.eigh(F @ F.T)
        tau = analytic.principal_kirchhoff(*np.sqrt(b2), MAT)
        sigma = (n * np.array(tau)) @ n.T
        np.testing.assert_allclose(analytic.simple_shear_cauchy(g, MAT), sigma, rtol=0, atol=1e-14)
    # small-shear limit: sigma_12 = mu gamma
    assert analytic.simple_shear_cauchy(1e-6, MAT)[0, 1] == pytest.approx(
        MAT.mu_mpa * 1e-6, rel=1e-9
    )


# ---- homogeneous responses of the model vs the truth ------------------------------------------


def test_homogeneous_responses_match_analytic():
    df = homogeneous_responses(MAT)
    assert set(df["case"]) == {"uniaxial", "equibiaxial", "simple_shear"}
    for (case, q), g in df.groupby(["case", "quantity"]):
        scale = max(np.abs(g["analytic"]).max(), 1.0)
        assert g["abs_error"].max() <= 1e-10 * scale, (case, q)
    uni = df[(df["case"] == "uniaxial") & (df["quantity"] == "nominal_stress_kpa")]
    # tension positive, compression negative, zero at stretch 1
    assert np.all(np.sign(uni["analytic"]) == np.sign(np.round(uni["x"] - 1.0, 12)))


@pytest.mark.parametrize(
    "material",
    [
        Ogden(),
        Ogden(mu_kpa=10.0, alpha=-2.5, d_mm2_per_n=1.0),
        Ogden(mu_kpa=1.0, alpha=2.0, d_mm2_per_n=500.0),
        Ogden(alpha=12.0),
    ],
    ids=["default", "negative-alpha", "neo-hookean-like", "stiffening"],
)
def test_all_material_point_checks_pass(material):
    df = material_point_checks(material, rng=np.random.default_rng(1))
    failed = df[~df["pass"]]
    assert failed.empty, failed.to_string()
    assert len(df) > 40
