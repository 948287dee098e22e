"""Strain post-processing against closed-form answers (shape functions, volumes, γmax, VOI bins)."""

from math import factorial

import gmsh
import numpy as np
import pytest
from study_meshes import box_tet10, centroids

from deeptissue.elements import (
    tet10_shape_functions,
    tet10_shape_gradients,
    tet_quadrature,
    tet_subdivision,
)
from deeptissue.mesh import TetMesh
from deeptissue.rigid import rotation_matrix
from deeptissue.strain import (
    StrainError,
    bin_labels,
    deformation_gradient_at_centroids,
    element_strain,
    element_volumes_mm3,
    gamma_at_points,
    green_lagrange,
    max_shear,
    principal_log_stretches,
    principal_values,
    voi_statistics,
)

REF_TET = np.array(
    [
        [0, 0, 0],
        [1, 0, 0],
        [0, 1, 0],
        [0, 0, 1],
        [0.5, 0, 0],
        [0.5, 0.5, 0],
        [0, 0.5, 0],
        [0, 0, 0.5],
        [0, 0.5, 0.5],
        [0.5, 0, 0.5],
    ],
    float,
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
    np.testing.assert_allclose(
        tet10_shape_functions(pts), np.reshape(val, (len(pts), 10)), atol=1e-12
    )
    np.testing.assert_allclose(
        tet10_shape_gradients(pts), np.reshape(grad, (len(pts), 10, 3)), atol=1e-12
    )
    # Kronecker property at the gmsh reference nodes
    np.testing.assert_allclose(tet10_shape_functions(REF_TET), np.eye(10), atol=1e-14)


@pytest.mark.parametrize(
    "a,b,c", [(0, 0, 0), (1, 0, 0), (2, 1, 0), (1, 1, 1), (0, 3, 0), (0, 1, 2)]
)
def test_quadrature_integrates_cubic_monomials_exactly(a, b, c):
    x, w = tet_quadrature(3)
    exact = factorial(a) * factorial(b) * factorial(c) / factorial(a + b + c + 3)
    assert np.sum(w * x[:, 0] ** a * x[:, 1] ** b * x[:, 2] ** c) == pytest.approx(
        exact, rel=1e-13
    )


def test_curved_element_volume_integrates_det_j():
    # x -> (x + a y^2, y + b z^2, z + c x^2) is quadratic, so the 10-node element represents it exactly;
    # det J = 1 + 8abc xyz, integral over the unit tet = 1/6 + 8abc/720
    a, b, c = 0.5, 0.4, 0.7
    x, y, z = REF_TET.T
    nodes = np.column_stack([x + a * y**2, y + b * z**2, z + c * x**2])
    m = TetMesh(nodes_mm=nodes, tets=np.arange(10)[None])
    assert element_volumes_mm3(m)[0] == pytest.approx(1 / 6 + a * b * c / 90, rel=1e-13)
    assert m.volumes_mm3()[0] != pytest.approx(
        1 / 6 + a * b * c / 90, rel=1e-3
    )  # corners alone miss it


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
        G[:, 0, 0] += q[0] * y
        G[:, 0, 1] += q[0] * x
        G[:, 1, 1] += q[1] * z
        G[:, 1, 2] += q[1] * y
        G[:, 2, 2] += q[2] * x
        G[:, 2, 0] += q[2] * z
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
    np.testing.assert_allclose(
        s.principal_gl,
        np.tile([(k * k + k * root) / 4, 0, (k * k - k * root) / 4], (m.n_tets, 1)),
        atol=1e-13,
    )
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
    expected = {
        "0.3-0.4": 10.0,
        "0.4-0.5": 0.0,
        "0.5-0.6": 30.0,
        "0.6-0.7": 0.0,
        "0.7-0.8": 0.0,
        "0.8-0.9": 0.0,
        "0.9-1.0": 40.0,
        ">1.0": 20.0,
    }
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

    custom = voi_statistics(
        np.array([0.25, 0.6]), np.array([1.0, 3.0]), threshold=0.2, bin_edges=(0.2, 0.5)
    )
    assert custom.bins_percent == {"0.2-0.5": 25.0, ">0.5": 75.0}

    with pytest.raises(ValueError, match="first edge must be the threshold"):
        voi_statistics(g, v, threshold=0.25)
    with pytest.raises(ValueError, match="strictly increasing"):
        voi_statistics(g, v, bin_edges=(0.3, 0.5, 0.4))
    with pytest.raises(ValueError, match="volume_mm3 has"):
        voi_statistics(g, v[:3])


def test_bin_labels():
    assert bin_labels(np.arange(3, 11) / 10) == [
        "0.3-0.4",
        "0.4-0.5",
        "0.5-0.6",
        "0.6-0.7",
        "0.7-0.8",
        "0.8-0.9",
        "0.9-1.0",
        ">1.0",
    ]
    assert bin_labels([0.25, 1, 2]) == ["0.25-1.0", "1.0-2.0", ">2.0"]


def test_tet_subdivision_is_a_midpoint_rule_on_equal_sub_tetrahedra():
    for levels, n in ((0, 1), (1, 8), (2, 64)):
        p, w = tet_subdivision(levels)
        assert p.shape == (n, 3) and np.allclose(w, 1 / 6 / n)
        assert np.all(p > 0) and np.all(
            p.sum(axis=1) < 1
        )  # strictly inside the reference tetrahedron
        np.testing.assert_allclose(
            w @ p, np.full(3, 1 / 24), rtol=1e-13
        )  # ∫ξ = 1/24: linear functions exact
    assert (
        len({tuple(x) for x in np.round(tet_subdivision(2)[0], 12)}) == 64
    )  # no two sub-tets alike
    with pytest.raises(ValueError, match="levels"):
        tet_subdivision(-1)


def _slab_volume(k, t):
    """Volume of the unit cube where γ_GL = s sqrt(s² + 4)/4 > t for s = k y: s_t² = sqrt(4 + 16 t²) − 2."""
    return 1.0 - np.sqrt(np.sqrt(4 + 16 * t**2) - 2) / k


@pytest.mark.slow
def test_gamma_sampled_at_points_measures_the_volume_above_a_threshold_inside_elements():
    """u_x = k y²/2 is exact in P2: simple shear of amount s = k y, γ_GL = s sqrt(s² + 4)/4 grows with y.
    On a mesh one element thick in y the volume with γ > t is the slab y > y_t; the 64 points per
    element find it, the centroids can only count whole elements."""
    k, t = 1.0, 0.3
    m = box_tet10([0, 1], [0, 1], [0, 0.5, 1])
    y = m.nodes_mm[:, 1]
    u = np.column_stack([0.5 * k * y**2, np.zeros_like(y), np.zeros_like(y)])
    exact = _slab_volume(k, t)
    gam, vol, n_folded = gamma_at_points(m, u, levels=2, strain_measures=("green_lagrange", "log"))
    assert n_folded == 0
    assert vol.shape == gam["green_lagrange"].shape == (m.n_tets, 64)
    np.testing.assert_allclose(vol.sum(axis=1), element_volumes_mm3(m), rtol=1e-12)
    # at every point γ is the closed form of the point's y
    pts, _ = tet_subdivision(2)
    L = np.column_stack(
        [1 - pts.sum(axis=1), pts]
    )  # barycentric; y of a straight tet is linear in them
    yq = np.einsum("qa,ma->mq", L, m.nodes_mm[m.tets[:, :4], 1])
    np.testing.assert_allclose(
        gam["green_lagrange"], k * yq * np.sqrt((k * yq) ** 2 + 4) / 4, atol=1e-12
    )
    np.testing.assert_allclose(gam["log"], np.arcsinh(k * yq / 2), atol=1e-12)
    sampled = voi_statistics(
        gam["green_lagrange"].ravel(), vol.ravel(), threshold=t, bin_edges=(t, 0.5)
    )
    assert sampled.voi_mm3 == pytest.approx(exact, rel=0.02)  # -1.6 %
    gamma_from_centroids = element_strain(m, u).gamma_gl
    centroid = voi_statistics(
        gamma_from_centroids, element_volumes_mm3(m), threshold=t, bin_edges=(t, 0.5)
    )
    assert abs(centroid.voi_mm3 - exact) > 5 * abs(sampled.voi_mm3 - exact)  # -21 %
    # 32 768 points per element: within 1 % of the slab for other shears and thresholds too
    for k, t in ((1.0, 0.3), (1.0, 0.2), (0.8, 0.3)):
        u = np.column_stack([0.5 * k * y**2, np.zeros_like(y), np.zeros_like(y)])
        g, v, _ = gamma_at_points(m, u, levels=5)
        fine = voi_statistics(
            g["green_lagrange"].ravel(), v.ravel(), threshold=t, bin_edges=(t, 0.5)
        )
        assert fine.voi_mm3 == pytest.approx(_slab_volume(k, t), rel=0.01)
    with pytest.raises(ValueError, match="strain_measure"):
        gamma_at_points(m, u, strain_measures=("cauchy",))


def test_a_curved_element_that_folds_inside_is_sampled_at_its_centroid():
    corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    mids = np.array(
        [
            (corners[a] + corners[b]) / 2
            for a, b in ((0, 1), (1, 2), (0, 2), (0, 3), (2, 3), (1, 3))
        ]
    )
    mids[0, 0] = (
        0.15  # edge (0, 1)'s mid node pulled toward corner 0: dx/dξ = 4·0.15 − 1 < 0 near that corner
    )
    m = TetMesh(nodes_mm=np.vstack([corners, mids]), tets=np.arange(10)[None])
    u = 0.1 * m.nodes_mm[:, [1, 0, 2]]  # a linear field: F constant
    gam, vol, n_folded = gamma_at_points(m, u)
    assert n_folded == 1
    np.testing.assert_allclose(vol, element_volumes_mm3(m)[0] / 64, rtol=1e-12)
    np.testing.assert_allclose(gam["green_lagrange"], element_strain(m, u).gamma_gl[0], rtol=1e-12)


def test_an_element_inverted_between_its_quadrature_points_is_sampled_at_its_centroid():
    """A P2 displacement that inverts the element near one corner only (det F <= 0 there) but not at
    the centroid: the log strain has no value at those points, so the element counts at its centroid."""
    corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    mids = np.array(
        [
            (corners[a] + corners[b]) / 2
            for a, b in ((0, 1), (1, 2), (0, 2), (0, 3), (2, 3), (1, 3))
        ]
    )
    m = TetMesh(nodes_mm=np.vstack([corners, mids]), tets=np.arange(10)[None])
    u = np.zeros((10, 3))
    u[
        4, 0
    ] = -0.35  # mid node of edge (0, 1) pulled back: ∂u_x/∂x = 4·(−0.35) at corner 0, −1.4 < −1
    F_c = deformation_gradient_at_centroids(m, u)
    assert np.linalg.det(F_c)[0] > 0
    gam, vol, n = gamma_at_points(m, u, strain_measures=("green_lagrange", "log"))
    assert n == 1
    np.testing.assert_allclose(vol, 1 / 6 / 64, rtol=1e-12)
    s = element_strain(m, u)
    np.testing.assert_allclose(gam["log"], s.gamma_log[0], rtol=1e-12)
    np.testing.assert_allclose(gam["green_lagrange"], s.gamma_gl[0], rtol=1e-12)
