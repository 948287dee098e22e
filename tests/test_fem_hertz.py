"""Hertz verification of the FE core on a mesh refined under the sphere (analytical truth: Hertz)."""

import numpy as np
import pytest

from deeptissue.fem.material import Ogden
from deeptissue.verification.scenes import hertz_curve
from deeptissue.verification.shapes import block_mesh

LAW = Ogden()


def _hertz_N(law, radius_mm, depth_mm):
    # independent of the code under test: small-strain moduli from mu and K = 2 / D of the Ogden law
    K, mu = 2.0 / law.d_mm2_per_n, law.mu_kpa * 1e-3
    E = 9 * K * mu / (3 * K + mu)
    nu = (3 * K - 2 * mu) / (2 * (3 * K + mu))
    return 4.0 / 3.0 * E / (1 - nu**2) * np.sqrt(radius_mm) * depth_mm**1.5


def _facet_edges_near(m, name, centre_mm, radius_mm):
    f = m.facets[name][:, :3]
    p = m.nodes_mm
    sel = np.linalg.norm(p[f].mean(axis=1)[:, :2] - np.asarray(centre_mm)[:2], axis=1) < radius_mm
    e = np.linalg.norm(p[f[:, 1]] - p[f[:, 0]], axis=1)
    return e[sel]


def test_size_field_refines_the_facets_under_the_point():
    # a small refinement ball on a large block is found: the facets under it are ~refine_h_mm, not the
    # block's ~2.4 mm (gmsh samples the size field only at the vertices of the mesh it refines)
    m = block_mesh(
        (20.0, 20.0, 10.0),
        h_mm=2.5,
        refine_point_mm=(10.0, 10.0, 10.0),
        refine_h_mm=0.1,
        refine_radius_mm=0.4,
        refine_growth=0.5,
    )
    e = _facet_edges_near(m, "top", (10.0, 10.0), 0.4)
    assert len(e) > 20
    assert e.max() < 0.15


@pytest.mark.slow
def test_sphere_force_within_3_percent_of_hertz_at_small_depth():
    R, d = 1.5, 0.06  # d = 0.04 R
    df = hertz_curve(LAW, radius_mm=R, max_depth_mm=d, max_increment=1.0)
    assert df.attrs["converged"], df.attrs["reason"]
    last = df.iloc[-1]
    assert last.depth_mm == pytest.approx(d, abs=1e-9)
    assert last.force_N == pytest.approx(_hertz_N(LAW, R, d), rel=0.03)
