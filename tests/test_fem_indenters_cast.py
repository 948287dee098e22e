"""Analytical indenters and the triangulated cast: distances against geometry, gradients against FD."""

import numpy as np
import pytest

from deeptissue.fem.cast import Cast, closest_point_on_triangles
from deeptissue.fem.indenters import Indenter


def test_sphere_head_and_shaft_distances():
    ind = Indenter("sphere", axis=(0, 0, -1), radius_mm=1.5)
    tip = np.array([0.0, 0.0, 0.0])  # head centre at z = 1.5
    x = np.array([[0, 0, -0.2], [0, 0, 0.1], [3.0, 0, 1.5], [2.5, 0, 10.0], [0, 0, 1.5 + 1.5 + 0.3]])
    g, n, _ = ind.gap(x, tip)
    # below the tip; inside near the tip; beside the head; beside the shaft far up; on the axis above
    np.testing.assert_allclose(g, [0.2, -0.1, 1.5, 1.0, -1.5], atol=1e-12)
    np.testing.assert_allclose(n[0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(n[3], [1, 0, 0], atol=1e-12)


def test_bar_is_a_capsule_along_the_leg():
    ind = Indenter("bar", axis=(1, 0, 0), radius_mm=1.5, bar_length_mm=10.0)
    np.testing.assert_allclose(ind.bar_direction(), [0, 0, 1])
    tip = np.zeros(3)  # core segment x = -1.5, y = 0, z in [-3.5, 3.5]
    x = np.array([[0.5, 0, 3.0], [0.5, 0, -3.4], [-1.5, 0, 5.5], [-1.5, 0, -6.0], [-1.5, 2.0, 0.0]])
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
        assert d <= dmin + 1e-12 and d >= dmin - 0.02 * np.linalg.norm(b[i] - a[i]) - 0.02 * np.linalg.norm(c[i] - a[i])


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
    cast = _tube_cast()
    nrm = cast.normal[0]
    assert nrm @ (-cast.centroid[0] * [1, 1, 0]) > 0  # points toward the axis
    x = np.array([[2.0, 0, 5.0], [3.5, 0, 5.0], [0, 2.5, 4.0], [2.0, 0, 12.0]])
    g, n, _ = cast.gap(x)
    r_poly = 3.0 * np.cos(np.pi / 48)  # inscribed radius at a facet centre (x = 2, 3.5 lie on a vertex line)
    assert g[0] == pytest.approx(1.0, abs=3.0 - r_poly + 1e-9)
    assert g[1] < 0 and g[1] == pytest.approx(-0.5, abs=3.0 - r_poly + 1e-9)
    assert g[2] > 0
    assert g[3] == np.inf  # beyond the open end: no contact


def test_cast_gap_gradient_and_hessian_against_finite_differences():
    cast = _tube_cast(n=12, m=4)
    rng = np.random.default_rng(6)
    th = rng.uniform(0, 2 * np.pi, 300)
    rad = rng.uniform(2.4, 3.4, 300)
    x = np.stack([rad * np.cos(th), rad * np.sin(th), rng.uniform(2, 8, 300)], axis=1)
    g, n, H = cast.gap(x)
    keep = np.abs(g) > 0.05
    e = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = e
        gp, npl, _ = cast.gap(x + d)
        gm, nm, _ = cast.gap(x - d)
        np.testing.assert_allclose(((gp - gm) / (2 * e))[keep], n[keep, k], atol=1e-5)
        np.testing.assert_allclose(((npl - nm) / (2 * e))[keep], H[keep, :, k], atol=1e-3)
