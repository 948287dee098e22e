"""The recovered-strain error estimate of the VOI and bins, and the cylinder scene's mesh."""

import numpy as np
import pytest
from study_meshes import box_tet10

from deeptissue.errorest import element_indicator, voi_error_estimate
from deeptissue.strain import gamma_at_points, voi_statistics


def _homogeneous(mesh, F):
    return mesh.nodes_mm @ (np.asarray(F) - np.eye(3)).T


def _simple_shear_gamma(s):
    """Green–Lagrange γmax of simple shear of amount s: (s/2) sqrt(1 + s²/4)."""
    return 0.5 * s * np.sqrt(1 + s * s / 4)


@pytest.mark.parametrize(
    "s", [0.3, 0.9]
)  # γ 0.15 (below the threshold), 0.49 (inside the bin 0.4-0.5)
def test_no_element_across_an_edge_gives_a_zero_estimate(s):
    m = box_tet10(np.linspace(0, 2, 3), np.linspace(0, 2, 3), np.linspace(0, 2, 3))
    F = np.eye(3)
    F[0, 2] = s
    u = _homogeneous(m, F)
    g, _, _ = gamma_at_points(m, u)
    assert np.allclose(g["green_lagrange"], _simple_shear_gamma(s))
    est = voi_error_estimate(m, u)
    assert est.voi_err_mm3 == 0
    assert not any(est.bins_err_pp.values()) and not np.any(est.indicator_mm3)


def _block(h_mm):
    from deeptissue.verification.shapes import block_mesh

    return block_mesh(
        (2.0, 2.0, 4.0),
        h_mm=h_mm,
        refine_point_mm=(1.0, 1.0, 2.0),
        refine_h_mm=h_mm,
        refine_radius_mm=10.0,
    )


K, P = (
    0.01,
    5,
)  # u_x = K z^P: simple shear of amount P K z^(P-1), γ from 0 at z = 0 to past every bin edge at z = 4


def _shear_field(mesh):
    u = np.zeros_like(mesh.nodes_mm)
    u[:, 0] = K * mesh.nodes_mm[:, 2] ** P
    return u


def _true_errors(mesh, u, g_h, v):
    """VOI [mm³] and largest bin [pp] error of γh against the exact γ at the same sample points."""
    from deeptissue.elements import tet10_shape_functions, tet_subdivision

    z = tet10_shape_functions(tet_subdivision(2)[0]) @ mesh.nodes_mm[mesh.tets][..., 2].T  # (q, m)
    exact = voi_statistics(_simple_shear_gamma(P * K * z.T ** (P - 1)).ravel(), v.ravel())
    h = voi_statistics(g_h.ravel(), v.ravel())
    return abs(h.voi_mm3 - exact.voi_mm3), max(
        abs(h.bins_percent[k] - exact.bins_percent[k]) for k in h.bins_percent
    )


def test_the_indicator_lives_where_gamma_crosses_an_edge_and_shrinks_with_the_mesh():
    err = []
    for h in (1.0, 0.7, 0.5):
        m = _block(h)
        u = _shear_field(m)
        eta = element_indicator(m, u)
        zc = m.nodes_mm[m.tets].mean(axis=1)[:, 2]
        assert eta.shape == (m.n_tets,) and np.all(eta >= 0)
        # γ < 0.02 below z = 1.2 (far from the threshold): no indicator there
        assert eta.sum() > 0 and np.all(eta[zc < 1.2] == 0)
        err.append(voi_error_estimate(m, u).voi_err_mm3)
    assert err[0] > err[1] > err[2] > 0


def test_the_threshold_part_of_the_indicator_sums_to_the_voi_estimate():
    m = _block(0.7)
    est = voi_error_estimate(m, _shear_field(m))
    assert est.threshold_indicator_mm3.sum() == pytest.approx(est.voi_err_mm3)
    assert np.all(est.threshold_indicator_mm3 <= est.indicator_mm3 + 1e-15)
    # the shear field crosses bin edges above the threshold: the bins add their own part
    assert est.indicator_mm3.sum() > est.threshold_indicator_mm3.sum() > 0


@pytest.mark.parametrize("h", [1.0, 0.7, 0.5])
def test_the_true_error_of_a_known_field_is_within_twice_the_estimate(h):
    """u_x = K z^P on a block: γh of the quadratic elements against the exact γ at the same points."""
    m = _block(h)
    u = _shear_field(m)
    g, v, _ = gamma_at_points(m, u)
    true_voi, true_bins = _true_errors(m, u, g["green_lagrange"], v)
    est = voi_error_estimate(m, u, sampled=(g["green_lagrange"], v))
    assert true_voi <= 2 * est.voi_err_mm3 and true_bins <= 2 * max(est.bins_err_pp.values())
    assert est.voi_err_mm3 < 10 * max(true_voi, 0.01)  # and not uselessly large


def test_cylinder_mesh_sets_volume_and_refinement():
    from deeptissue.strain import element_volumes_mm3
    from deeptissue.verification.cylinder import CylinderMesh, cylinder_mesh

    m = cylinder_mesh(
        CylinderMesh(
            element_size_mm=3.0,
            refine_size_mm=1.0,
            refine_radius_mm=2.0,
            refine_transition_mm=1.0,
            refine_depth_mm=2.0,
        ),
        radius_mm=8.0,
        height_mm=8.0,
    )
    assert {"bone", "patch", "side", "skin"} <= set(m.facets)
    z = m.nodes_mm[:, 2]
    r = np.hypot(m.nodes_mm[:, 0], m.nodes_mm[:, 1])
    assert np.allclose(z[m.facets["bone"]], 0.0) and np.allclose(z[m.facets["patch"]], 8.0)
    assert np.allclose(
        r[m.facets["side"]], 8.0, atol=1e-6
    )  # curved P2 facets: mid-edge nodes on the cylinder
    assert len(m.facets["skin"]) == len(m.facets["patch"]) + len(m.facets["side"])
    assert element_volumes_mm3(m).sum() == pytest.approx(np.pi * 64 * 8, rel=1e-4)
    # finer under the indenter (top centre) than at the bottom rim
    edge = np.linalg.norm(m.nodes_mm[m.tets[:, 1]] - m.nodes_mm[m.tets[:, 0]], axis=1)
    c = m.nodes_mm[m.tets[:, :4]].mean(axis=1)
    top = np.hypot(c[:, 0], c[:, 1]) ** 2 + (c[:, 2] - 8.0) ** 2 < 1.5**2
    rim = (np.hypot(c[:, 0], c[:, 1]) > 5.0) & (c[:, 2] < 3.0)
    assert edge[top].mean() < 0.6 * edge[rim].mean()


def _layered_shear(m, k_low=0.5, k_high=0.7):
    """u_x with slope k_low for y < 1 and k_high above: γ 0.258 below, 0.371 above, a kink at y = 1."""
    y = m.nodes_mm[:, 1]
    ux = k_low * np.clip(y, 0, 1) + k_high * np.clip(y - 1, 0, 1)
    return np.column_stack([ux, np.zeros_like(y), np.zeros_like(y)])


def test_a_strain_jump_across_the_threshold_is_estimated_in_the_summary_and_voi_csv(tmp_path):
    from deeptissue.report import summary_tables
    from deeptissue.summary import VoiSpec, read_summary, summarize_solution, write_summary

    m = box_tet10([0, 1], [0, 0.5, 1, 1.5, 2], [0, 1])
    u = _layered_shear(m)
    s, _ = summarize_solution(m, u, animal="a", variant="sphere")
    assert s.voi_mm3 == pytest.approx(1.0)
    # the recovered field averages 0.258 and 0.371 at the kink (0.31 > 0.3): part of the lower layer moves
    # into the VOI, only in the elements next to y = 1
    assert 0 < s.voi_err_mm3 < 0.5 and s.bins_err_pp["0.3-0.4"] == pytest.approx(
        0, abs=1e-9
    )  # the same bin
    eta = element_indicator(m, u)
    yc = m.nodes_mm[m.tets].mean(axis=1)[:, 1]
    assert np.all(eta[np.abs(yc - 1) > 0.5] == 0) and eta[
        np.abs(yc - 1) < 0.5
    ].sum() == pytest.approx(s.voi_err_mm3)
    write_summary(tmp_path / "summary.json", s)
    assert read_summary(tmp_path / "summary.json") == s
    voi, _ = summary_tables([s], animals=["a"], variants=["sphere"])
    assert (
        voi.loc[0, "voi_err_mm3"] == s.voi_err_mm3
        and voi.loc[0, "bins_err_pp.0.3-0.4"] == s.bins_err_pp["0.3-0.4"]
    )
    assert {f"bins_err_pp.{k}" for k in s.bins_percent} <= set(voi.columns)
    # centroid sampling: the estimate of the centroid numbers (one point per element)
    c, _ = summarize_solution(
        m, u, animal="a", variant="sphere", voi=VoiSpec(gamma_sampling="centroid")
    )
    assert c.voi_err_mm3 >= 0 and set(c.bins_err_pp) == set(s.bins_percent)


def test_cylinder_scene_on_a_coarse_mesh_gives_the_curve_and_the_estimated_voi():
    from deeptissue.fem.material import Ogden
    from deeptissue.verification.cylinder import CylinderMesh, CylinderScene, cylinder_scene

    coarse = CylinderMesh(
        element_size_mm=4.0,
        refine_size_mm=2.0,
        refine_radius_mm=2.0,
        refine_transition_mm=1.0,
        refine_depth_mm=3.0,
    )
    curve, voi = cylinder_scene(
        Ogden(),
        coarse,
        curve_depths_mm=[0.25],
        voi_depths_mm=[0.5],
        scene=CylinderScene(threshold=0.05, bin_edges=(0.05, 0.1, 0.2)),
    )
    assert list(curve["depth_mm"]) == [0.25, 0.5] and curve["converged"].all()
    assert 0 < curve["force_N"].iloc[0] < curve["force_N"].iloc[1]
    assert curve.attrs["mesh"] == "4 / 2 mm" and curve.attrs["n_dofs"] > 0
    row = voi.iloc[0]
    assert row["voi_mm3"] > 0 and row["voi_err_mm3"] > 0
    assert sum(row[f"bins_percent.{b}"] for b in ("0.05-0.1", "0.1-0.2", ">0.2")) == pytest.approx(
        100
    )
    assert {"bins_err_pp.0.05-0.1", "bins_err_pp.>0.2"} <= set(voi.columns)


def test_effectivity_table_divides_the_estimate_by_the_true_error_against_the_finest():
    import pandas as pd

    from deeptissue.verification.cylinder import effectivity_table

    base = {
        "bins_percent.0.3-0.4": 70.0,
        "bins_percent.>1.0": 30.0,
        "bins_err_pp.0.3-0.4": 1.0,
        "bins_err_pp.>1.0": 2.0,
    }
    voi = pd.DataFrame(
        [
            dict(base, mesh="fine", n_dofs=100, depth_mm=2.0, voi_mm3=10.0, voi_err_mm3=0.1),
            dict(
                base,
                mesh="coarse",
                n_dofs=10,
                depth_mm=2.0,
                voi_mm3=10.4,
                voi_err_mm3=0.8,
                **{"bins_percent.0.3-0.4": 71.0, "bins_percent.>1.0": 29.0},
            ),
        ]
    )
    t = effectivity_table(voi)
    assert len(t) == 1 and t.loc[0, "mesh"] == "coarse"
    assert t.loc[0, "true_voi_percent"] == pytest.approx(4.0) and t.loc[
        0, "true_bins_pp"
    ] == pytest.approx(1.0)
    assert t.loc[0, "voi"] == pytest.approx(2.0)
    assert t.loc[0, "bins"] == pytest.approx(2.0)  # the largest bin estimate
