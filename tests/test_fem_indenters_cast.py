"""Analytical indenters and the triangulated cast: distances against geometry, gradients against FD."""

import numpy as np
import pytest

from deeptissue.fem.cast import Cast, closest_point_on_triangles
from deeptissue.fem.indenters import Indenter


def test_sphere_head_and_shaft_distances():
    ind = Indenter("sphere", axis=(0, 0, -1), radius_mm=1.5)
    tip = np.array([0.0, 0.0, 0.0])  # head centre at z = 1.5
    x = np.array(
        [[0, 0, -0.2], [0, 0, 0.1], [3.0, 0, 1.5], [2.5, 0, 10.0], [0, 0, 1.5 + 1.5 + 0.3]]
    )
    g, n, _ = ind.gap(x, tip)
    # below the tip; inside near the tip; beside the head; beside the shaft far up; on the axis above
    np.testing.assert_allclose(g, [0.2, -0.1, 1.5, 1.0, -1.5], atol=1e-12)
    np.testing.assert_allclose(n[0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(n[3], [1, 0, 0], atol=1e-12)


def test_bar_is_a_capsule_along_the_leg():
    ind = Indenter("bar", axis=(1, 0, 0), radius_mm=1.5, bar_length_mm=10.0)
    np.testing.assert_allclose(ind.bar_direction(), [0, 0, 1])
    tip = np.zeros(3)  # core segment x = -1.5, y = 0, z in [-3.5, 3.5]
    x = np.array(
        [[0.5, 0, 3.0], [0.5, 0, -3.4], [-1.5, 0, 5.5], [-1.5, 0, -6.0], [-1.5, 2.0, 0.0]]
    )
    g, _, _ = ind.gap(x, tip)
    np.testing.assert_allclose(g, [0.5, 0.5, 0.5, 1.0, 0.5], atol=1e-12)


@pytest.mark.parametrize("kind", ["sphere", "bar"])
def test_normal_and_hessian_are_derivatives_of_the_gap(kind):
    ind = Indenter(kind, axis=(0.3, -0.2, -1.0), radius_mm=1.5, bar_length_mm=8.0)
    tip = np.array([0.1, 0.2, 0.3])
    x = np.random.default_rng(3).uniform(-4, 4, (200, 3))
    g, n, H = ind.gap(x, tip)
    e = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = e
        gp, npl, _ = ind.gap(x + d, tip)
        gm, nm, _ = ind.gap(x - d, tip)
        np.testing.assert_allclose((gp - gm) / (2 * e), n[:, k], atol=1e-6)
        np.testing.assert_allclose((npl - nm) / (2 * e), H[:, :, k], atol=1e-4)


def test_closest_point_on_triangles_against_dense_sampling():
    rng = np.random.default_rng(4)
    a, b, c = (rng.standard_normal((50, 3)) for _ in range(3))
    p = 2 * rng.standard_normal((50, 3))
    q, _ = closest_point_on_triangles(p, a, b, c)
    s = np.linspace(0, 1, 201)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    for i in range(50):
        pts = a[i] + u[:, None] * (b[i] - a[i]) + v[:, None] * (c[i] - a[i])
        dmin = np.min(np.linalg.norm(pts - p[i], axis=1))
        d = np.linalg.norm(q[i] - p[i])
        assert d <= dmin + 1e-12 and d >= dmin - 0.02 * np.linalg.norm(
            b[i] - a[i]
        ) - 0.02 * np.linalg.norm(c[i] - a[i])


def _tube_cast(radius=3.0, length=10.0, n=48, m=10):
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    z = np.linspace(0, length, m)
    v = np.array([[radius * np.cos(a), radius * np.sin(a), zz] for zz in z for a in th])
    tris = []
    for j in range(m - 1):
        for i in range(n):
            a, b = j * n + i, j * n + (i + 1) % n
            c, d = a + n, b + n
            tris += [[a, c, b], [b, c, d]]  # normals inward (toward the axis)
    return Cast(v, np.array(tris))


def test_cast_signed_distance_toward_the_leg_and_free_ends():
    cast = _tube_cast(
        m=41
    )  # 0.25 mm rows: no vertex within the weights' support of the points 0.5-1 mm off
    nrm = cast.normal[0]
    assert nrm @ (-cast.centroid[0] * [1, 1, 0]) > 0  # points toward the axis
    x = np.array([[2.0, 0, 5.0], [3.5, 0, 5.0], [0, 2.5, 4.0], [2.0, 0, 12.0]])
    g, n, _ = cast.gap(x)
    r_poly = 3.0 * np.cos(
        np.pi / 48
    )  # inscribed radius at a facet centre (x = 2, 3.5 lie on a vertex line)
    assert g[0] == pytest.approx(1.0, abs=3.0 - r_poly + 1e-9)
    assert g[1] < 0 and g[1] == pytest.approx(-0.5, abs=3.0 - r_poly + 1e-9)
    assert g[2] > 0
    assert g[3] == np.inf  # beyond the open end: no contact


def test_cast_gap_is_smooth_across_facet_edges_with_its_exact_derivatives():
    cast = _tube_cast(n=24, m=6)
    # points on the polygon either side of a vertex line (a facet edge at angle 0): the facets' distance
    # has a gradient that jumps there by 15 deg, the cast's gap does not
    eps = 1e-6
    r0 = 3.0 * np.cos(np.pi / 24) / np.cos(np.pi / 24 - eps)
    x = np.array([[r0 * np.cos(s * eps), r0 * np.sin(s * eps), 5.0] for s in (-1.0, 1.0)])
    g, n, H = cast.gap(x)
    assert np.linalg.norm(n[0] - n[1]) < 1e-4
    np.testing.assert_allclose(
        n[0] / np.linalg.norm(n[0]), [-1.0, 0.0, 0.0], atol=1e-5
    )  # toward the axis
    # near the surface the gap is the distance to the tube to within the facets' sagitta (edge^2 / (2 R))
    rng = np.random.default_rng(6)
    th = rng.uniform(0, 2 * np.pi, 300)
    rad = rng.uniform(2.9, 3.1, 300)
    x = np.stack([rad * np.cos(th), rad * np.sin(th), rng.uniform(2, 8, 300)], axis=1)
    g, n, H = cast.gap(x)
    edge = 2 * np.pi * 3.0 / 24
    np.testing.assert_allclose(g, 3.0 - rad, atol=edge**2 / (2 * 3.0))
    # the returned normal is the gap's gradient (finite differences): a consistent linearisation
    e = 1e-6
    grad = np.stack(
        [(cast.gap(x + e * d)[0] - cast.gap(x - e * d)[0]) / (2 * e) for d in np.eye(3)], axis=1
    )
    np.testing.assert_allclose(n, grad, atol=1e-6)
    hess = np.stack(
        [(cast.gap(x + e * d)[1] - cast.gap(x - e * d)[1]) / (2 * e) for d in np.eye(3)], axis=2
    )
    np.testing.assert_allclose(H, hess, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=0.05)


def test_cast_gap_weighs_every_vertex_of_its_support_and_skips_the_hessian_on_request():
    # 0.05 mm rows under 0.8 mm edges around: the support (1.2 x the longest edge) holds 60-100 vertices, more
    # than the 16 queried first
    cast = _tube_cast(n=24, m=201)
    rng = np.random.default_rng(7)
    th = rng.uniform(0, 2 * np.pi, 50)
    rad = rng.uniform(2.9, 3.1, 50)
    x = np.stack([rad * np.cos(th), rad * np.sin(th), rng.uniform(2, 8, 50)], axis=1)
    g, n, H = cast.gap(x)
    d = x[:, None, :] - cast.v[None]
    s = np.sum(d**2, axis=2) / cast.radius_mm**2
    w = np.where(s < 1, (1 - s) ** 4, 0.0)
    assert np.all(np.count_nonzero(w, axis=1) > 16)
    g_all = np.sum(w * np.einsum("nvi,vi->nv", d, cast.vertex_normal), axis=1) / w.sum(axis=1)
    np.testing.assert_allclose(g, g_all, rtol=1e-12, atol=1e-12)
    g2, n2, H2 = cast.gap(x, hessian=False)
    assert H2 is None and H.shape == (50, 3, 3)
    np.testing.assert_array_equal(g2, g)
    np.testing.assert_array_equal(n2, n)


def test_a_cast_with_a_hole_has_a_finite_gap_beside_the_hole_without_warnings():
    # a window cut out of a tube (its inner vertices then belong to no triangle: they have no normal) next to a
    # point 0.1 mm inside the tube: the gap is the tube's, 0.1 mm to within the facets' sagitta, as on the
    # whole tube, and the vertices without a triangle take no part
    whole = _tube_cast(n=48, m=21)
    c = whole.v[whole.t].mean(axis=1)
    window = np.linalg.norm(c - [3.0, 0.0, 5.0], axis=1) < 1.2
    th = np.radians([30.0, 60.0, 180.0])  # the window reaches 23 deg
    x = np.stack([2.9 * np.cos(th), 2.9 * np.sin(th), np.full(3, 5.0)], axis=1)
    with np.errstate(all="raise"):
        holed = Cast(whole.v, whole.t[~window])
        g, n, H = holed.gap(x)
    assert np.all(np.isfinite(n)) and np.all(np.isfinite(H))
    # 2.9 mm from the axis of a 3 mm tube, to within the sagitta of its 0.39 mm facets (0.026 mm)
    np.testing.assert_allclose(g, 0.1, atol=0.026)
    np.testing.assert_allclose(g[2], whole.gap(x[2:])[0][0], atol=1e-12)  # far from the window
    # over the window itself there is no cast
    assert np.isinf(holed.gap(np.array([[2.9, 0.0, 5.0]]))[0][0])
