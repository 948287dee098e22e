"""Strain post-processing against closed-form answers (shape functions, volumes, γmax, VOI bins)."""

from math import factorial

import gmsh
import numpy as np
import pytest

from deeptissue.mesh import TetMesh
from deeptissue.rigid import rotation_matrix
from deeptissue.strain import (
    StrainError,
    bin_labels,
    deformation_gradient_at_centroids,
    element_strain,
    element_volumes_mm3,
    green_lagrange,
    max_shear,
    principal_log_stretches,
    principal_values,
    tet10_shape_functions,
    tet10_shape_gradients,
    tet_quadrature,
    voi_statistics,
)
from study_meshes import box_tet10, centroids

REF_TET = np.array(
    [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1],
     [0.5, 0, 0], [0.5, 0.5, 0], [0, 0.5, 0], [0, 0, 0.5], [0, 0.5, 0.5], [0.5, 0, 0.5]], float
)


def test_shape_functions_and_gradients_match_gmsh_tetrahedron10():
    rng = np.random.default_rng(0)
    pts = np.vstack([[0.25, 0.25, 0.25], rng.dirichlet(np.ones(4), size=5)[:, 1:]])
    gmsh.initialize(interruptible=False)
    try:
        _, val, _ = gmsh.model.mesh.getBasisFunctions(11, pts.ravel().tolist(), "Lagrange")
        _, grad, _ = gmsh.model.mesh.getBasisFunctions(11, pts.ravel().tolist(), "GradLagrange")
    finally:
        gmsh.finalize()
    np.testing.assert_allclose(tet10_shape_functions(pts), np.reshape(val, (len(pts), 10)), atol=1e-12)
    np.testing.assert_allclose(tet10_shape_gradients(pts), np.reshape(grad, (len(pts), 10, 3)), atol=1e-12)
    # Kronecker property at the gmsh reference nodes
    np.testing.assert_allclose(tet10_shape_functions(REF_TET), np.eye(10), atol=1e-14)


@pytest.mark.parametrize("a,b,c", [(0, 0, 0), (1, 0, 0), (2, 1, 0), (1, 1, 1), (0, 3, 0), (0, 1, 2)])
def test_quadrature_integrates_cubic_monomials_exactly(a, b, c):
    x, w = tet_quadrature(3)
    exact = factorial(a) * factorial(b) * factorial(c) / factorial(a + b + c + 3)
    assert np.sum(w * x[:, 0] ** a * x[:, 1] ** b * x[:, 2] ** c) == pytest.approx(exact, rel=1e-13)


def test_curved_element_volume_integrates_det_j():
    # x -> (x + a y^2, y + b z^2, z + c x^2) is quadratic, so the 10-node element represents it exactly;
    # det J = 1 + 8abc xyz, integral over the unit tet = 1/6 + 8abc/720
    a, b, c = 0.5, 0.4, 0.7
    x, y, z = REF_TET.T
    nodes = np.column_stack([x + a * y**2, y + b * z**2, z + c * x**2])
    m = TetMesh(nodes_mm=nodes, tets=np.arange(10)[None])
    assert element_volumes_mm3(m)[0] == pytest.approx(1 / 6 + a * b * c / 90, rel=1e-13)
    assert m.volumes_mm3()[0] != pytest.approx(1 / 6 + a * b * c / 90, rel=1e-3)  # corners alone miss it


def test_box_volumes_sum_to_the_box():
    m = box_tet10([0, 0.5, 2.0], [0, 1.0, 1.5, 3.0], [-1, 0.25, 1])
    vol = element_volumes_mm3(m)
    assert np.all(vol > 0)
    assert vol.sum() == pytest.approx(2.0 * 3.0 * 2.0, rel=1e-13)
    np.testing.assert_allclose(vol, m.volumes_mm3(), rtol=1e-12)


def test_centroid_gradient_of_a_quadratic_field_is_exact():
    m = box_tet10([0, 0.7, 1.5], [0, 0.6, 1.3], [0, 0.8, 1.6])
    A = np.array([[0.1, -0.2, 0.05], [0.3, 0.0, -0.1], [0.02, 0.07, 0.2]])
    q = np.array([0.05, -0.03, 0.08])

    def u(X):  # u = A X + q * (x y, y z, z x)
        x, y, z = X.T
        return X @ A.T + q * np.column_stack([x * y, y * z, z * x])

    def grad(X):
        x, y, z = X.T
        G = np.broadcast_to(A, (len(X), 3, 3)).copy()
        G[:, 0, 0] += q[0] * y; G[:, 0, 1] += q[0] * x
        G[:, 1, 1] += q[1] * z; G[:, 1, 2] += q[1] * y
        G[:, 2, 2] += q[2] * x; G[:, 2, 0] += q[2] * z
        return G

    F = deformation_gradient_at_centroids(m, u(m.nodes_mm))
    np.testing.assert_allclose(F, np.eye(3) + grad(centroids(m)), atol=1e-13)


def _homogeneous(m, F):
    return m.nodes_mm @ (np.asarray(F) - np.eye(3)).T


@pytest.mark.parametrize("k", [0.1, 0.6, 1.5])
def test_simple_shear_closed_form(k):
    m = box_tet10([0, 1, 2], [0, 1], [0, 0.5, 1])
    F = np.array([[1, k, 0], [0, 1, 0], [0, 0, 1.0]])
    s = element_strain(m, _homogeneous(m, F))
    root = np.sqrt(k * k + 4)
    np.testing.assert_allclose(s.principal_gl, np.tile([(k * k + k * root) / 4, 0, (k * k - k * root) / 4], (m.n_tets, 1)), atol=1e-13)
    np.testing.assert_allclose(s.gamma_gl, k * root / 4, rtol=1e-12)
    # principal stretches of simple shear: (sqrt(k^2+4) ± k)/2, so (ln λ1 - ln λ3)/2 = asinh(k/2)
    np.testing.assert_allclose(s.gamma_log, np.arcsinh(k / 2), rtol=1e-12)
    np.testing.assert_allclose(s.principal_log[:, 1], 0.0, atol=1e-13)


def test_rigid_motion_has_no_strain():
    m = box_tet10([0, 1, 2], [0, 1, 2], [0, 1])
    R = rotation_matrix([40.0, -70.0, 25.0])
    u = (m.nodes_mm - 1.0) @ R.T + 1.0 + np.array([3.0, -2.0, 0.5]) - m.nodes_mm
    s = element_strain(m, u)
    np.testing.assert_allclose(s.F, np.broadcast_to(R, s.F.shape), atol=1e-13)
    np.testing.assert_allclose(s.principal_gl, 0.0, atol=1e-13)
    np.testing.assert_allclose(s.principal_log, 0.0, atol=1e-13)
    np.testing.assert_allclose(s.gamma_gl, 0.0, atol=1e-13)


@pytest.mark.parametrize(
    "F,expected_principal_gl",
    [
        (np.diag([1.3, 1.0, 1.0]), [(1.69 - 1) / 2, 0, 0]),  # E2 = E3
        (np.diag([0.8, 1.2, 1.2]), [(1.44 - 1) / 2, (1.44 - 1) / 2, (0.64 - 1) / 2]),  # E1 = E2
        (1.1 * np.eye(3), [0.105, 0.105, 0.105]),  # all equal: no shear
    ],
)
def test_repeated_principal_values(F, expected_principal_gl):
    m = box_tet10([0, 1], [0, 1], [0, 1])
    R = rotation_matrix([10.0, 20.0, -30.0])  # rotate the stretch axes away from the grid
    Fr = R @ F @ R.T
    s = element_strain(m, _homogeneous(m, Fr))
    e = np.array(expected_principal_gl)
    np.testing.assert_allclose(s.principal_gl, np.tile(e, (m.n_tets, 1)), atol=1e-13)
    np.testing.assert_allclose(s.gamma_gl, (e[0] - e[2]) / 2, atol=1e-13)
    lam = np.sort(np.linalg.svd(F, compute_uv=False))[::-1]
    np.testing.assert_allclose(s.gamma_log, (np.log(lam[0]) - np.log(lam[2])) / 2, atol=1e-13)


def test_batched_helpers_agree_with_definitions():
    F = np.array([[[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]] * 2)
    E = green_lagrange(F)
    np.testing.assert_allclose(E[0], 0.5 * (F[0].T @ F[0] - np.eye(3)))
    p = principal_values(E)
    assert np.all(np.diff(p, axis=-1) <= 0)
    assert max_shear(p).shape == (2,)


def test_inverted_element_and_bad_shape_are_refused():
    m = box_tet10([0, 1], [0, 1], [0, 1])
    with pytest.raises(StrainError, match="inverted"):
        element_strain(m, _homogeneous(m, np.diag([-1.0, 1.0, 1.0])))
    with pytest.raises(StrainError, match="expected shape"):
        element_strain(m, np.zeros((3, 3)))
    with pytest.raises(StrainError, match="inverted"):
        principal_log_stretches(np.diag([1.0, -1.0, 1.0]))


def _shear_for_gamma(gamma):
    """Simple-shear amount k with Green–Lagrange γmax = k sqrt(k^2+4)/4 = gamma."""
    return np.sqrt(np.sqrt(4 + 16 * gamma**2) - 2)


def test_voi_bins_of_a_layered_shear_field_are_exact():
    # slabs in y with their own simple-shear amount: u_x = ∫ k(y) dy is continuous and piecewise
    # linear, so every element of a slab has exactly the slab's γ; slab volumes are thickness × 1 × 1
    bounds = np.array([0.0, 0.5, 0.75, 1.5, 2.5, 3.0])
    gammas = np.array([0.1, 0.35, 0.55, 0.95, 1.2])
    ks = _shear_for_gamma(gammas)
    ys = np.unique(np.concatenate([bounds, [0.25, 2.0]]))
    m = box_tet10([0, 0.5, 1], ys, [0, 1])
    y = m.nodes_mm[:, 1]
    ux = np.zeros_like(y)
    for lo, hi, k in zip(bounds[:-1], bounds[1:], ks):
        ux += k * np.clip(y - lo, 0, hi - lo)
    u = np.column_stack([ux, np.zeros_like(y), np.zeros_like(y)])
    s = element_strain(m, u)
    slab = np.searchsorted(bounds, centroids(m)[:, 1]) - 1
    np.testing.assert_allclose(s.gamma_gl, gammas[slab], rtol=1e-12)

    energy_density = np.array([1.0, 2.0, 3.0, 4.0, 5.0])[slab]  # MPa
    st = voi_statistics(s.gamma_gl, s.volume_mm3, threshold=0.3, energy_density_mpa=energy_density)
    assert st.voi_mm3 == pytest.approx(2.5, rel=1e-12)
    assert st.total_mm3 == pytest.approx(3.0, rel=1e-12)
    expected = {"0.3-0.4": 10.0, "0.4-0.5": 0.0, "0.5-0.6": 30.0, "0.6-0.7": 0.0, "0.7-0.8": 0.0,
                "0.8-0.9": 0.0, "0.9-1.0": 40.0, ">1.0": 20.0}
    assert list(st.bins_percent) == list(expected)
    for key, val in expected.items():
        assert st.bins_percent[key] == pytest.approx(val, abs=1e-10)
    assert st.below_threshold_percent == pytest.approx(100 * 0.5 / 3.0, rel=1e-12)
    assert st.peak_gamma == pytest.approx(1.2, rel=1e-12)
    assert st.strain_energy_mJ == pytest.approx(2 * 0.25 + 3 * 0.75 + 4 * 1.0 + 5 * 0.5, rel=1e-12)


def test_voi_statistics_edges_empty_voi_and_errors():
    g = np.array([0.3, 0.4, 0.4000001, 1.0, 1.0000001, 0.0])
    v = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    st = voi_statistics(g, v)
    assert st.voi_mm3 == pytest.approx(14.0)  # γ = 0.3 exactly is not above the threshold
    assert st.bins_percent["0.3-0.4"] == pytest.approx(100 * 2 / 14)
    assert st.bins_percent["0.4-0.5"] == pytest.approx(100 * 3 / 14)
    assert st.bins_percent["0.9-1.0"] == pytest.approx(100 * 4 / 14)
    assert st.bins_percent[">1.0"] == pytest.approx(100 * 5 / 14)
    assert st.below_threshold_percent == pytest.approx(100 * 7 / 21)
    assert st.strain_energy_mJ is None

    empty = voi_statistics(np.array([0.1, 0.2]), np.array([1.0, 1.0]))
    assert empty.voi_mm3 == 0.0 and empty.below_threshold_percent == 100.0
    assert all(p == 0.0 for p in empty.bins_percent.values())

    custom = voi_statistics(np.array([0.25, 0.6]), np.array([1.0, 3.0]), threshold=0.2, bin_edges=(0.2, 0.5))
    assert custom.bins_percent == {"0.2-0.5": 25.0, ">0.5": 75.0}

    with pytest.raises(ValueError, match="first edge must be the threshold"):
        voi_statistics(g, v, threshold=0.25)
    with pytest.raises(ValueError, match="strictly increasing"):
        voi_statistics(g, v, bin_edges=(0.3, 0.5, 0.4))
    with pytest.raises(ValueError, match="volume_mm3 has"):
        voi_statistics(g, v[:3])


def test_bin_labels():
    assert bin_labels(np.arange(3, 11) / 10) == ["0.3-0.4", "0.4-0.5", "0.5-0.6", "0.6-0.7", "0.7-0.8", "0.8-0.9", "0.9-1.0", ">1.0"]
    assert bin_labels([0.25, 1, 2]) == ["0.25-1.0", "1.0-2.0", ">2.0"]
