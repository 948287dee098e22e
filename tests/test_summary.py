"""summary.json, failed runs, result.vtu and the skin agreement distance."""

import numpy as np
import pytest
from study_meshes import boundary_tri6, box_tet10

from deeptissue.mesh import TetMesh
from deeptissue.summary import (
    Summary,
    VoiSpec,
    deformed_surface,
    failed_summary,
    point_triangle_distance,
    read_result_vtu,
    read_summary,
    skin_agreement_mm,
    summarize_solution,
    surface_distance_mm,
    tri6_to_tri3,
    write_result_vtu,
    write_summary,
)


def test_point_triangle_distance_regions():
    a, b, c = np.array([0.0, 0, 0]), np.array([2.0, 0, 0]), np.array([0.0, 2, 0])
    cases = [
        ([0.5, 0.5, 0.7], 0.7),  # above the face
        ([-1.0, -1.0, 0.0], np.sqrt(2)),  # beyond vertex a
        ([3.0, -1.0, 1.0], np.sqrt(3)),  # beyond vertex b
        ([1.0, -2.0, 0.0], 2.0),  # beyond edge ab
        ([2.0, 2.0, 0.0], np.sqrt(2)),  # beyond the hypotenuse
        ([0.3, 0.3, 0.0], 0.0),  # in the face
    ]
    P = np.array([p for p, _ in cases])
    n = len(P)
    d = point_triangle_distance(P, np.tile(a, (n, 1)), np.tile(b, (n, 1)), np.tile(c, (n, 1)))
    np.testing.assert_allclose(d, [t for _, t in cases], atol=1e-14)


def test_point_triangle_distance_against_dense_sampling():
    rng = np.random.default_rng(3)
    n = 200
    P, A, B, C = (rng.normal(size=(n, 3)) for _ in range(4))
    d = point_triangle_distance(P, A, B, C)
    s = np.linspace(0, 1, 121)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    samples = (
        A[:, None] + u[None, :, None] * (B - A)[:, None] + v[None, :, None] * (C - A)[:, None]
    )
    brute = np.linalg.norm(samples - P[:, None], axis=2).min(axis=1)
    assert np.all(d <= brute + 1e-12)  # exact distance never exceeds any sample's
    spacing = (np.linalg.norm(B - A, axis=1) + np.linalg.norm(C - A, axis=1)) / 120
    assert np.all(
        brute - d <= spacing
    )  # the nearest sample is within one grid step of the closest point


def _cube_surface(h):
    corners = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))])
    return corners, tris


def test_surface_distance_to_a_cube_is_exact():
    h = 1.0
    V, T = _cube_surface(h)
    rng = np.random.default_rng(5)
    P = rng.uniform(-3, 3, size=(2000, 3))
    a = np.abs(P)
    outside = np.any(a > h, axis=1)
    truth = np.where(outside, np.linalg.norm(np.maximum(a - h, 0), axis=1), h - a.max(axis=1))
    np.testing.assert_allclose(surface_distance_mm(P, V, T), truth, atol=1e-12)


def test_skin_agreement_on_a_deformed_p2_face():
    m = box_tet10([0, 1, 2], [0, 1, 2, 3], [0, 1, 2])
    skin = boundary_tri6(m, lambda p: np.isclose(p[:, 0], 2.0))
    m = TetMesh(nodes_mm=m.nodes_mm, tets=m.tets, facets={"skin": skin})
    assert len(tri6_to_tri3(skin)) == 4 * len(skin)
    u = np.tile([0.3, -0.1, 0.2], (len(m.nodes_mm), 1))  # rigid translation of the whole block
    V, T = deformed_surface(m, u, facet="skin")
    # the deformed face is x = 2.3, y in [-0.1, 2.9], z in [0.2, 2.2]; points in front of it at offsets delta
    rng = np.random.default_rng(1)
    delta = rng.uniform(-0.5, 0.5, size=300)
    pts = np.column_stack([2.3 + delta, rng.uniform(0.0, 2.8, 300), rng.uniform(0.3, 2.1, 300)])
    mean, p95 = skin_agreement_mm(pts.reshape(3, 100, 3), V, T)
    assert mean == pytest.approx(np.abs(delta).mean(), abs=1e-12)
    assert p95 == pytest.approx(np.percentile(np.abs(delta), 95), abs=1e-12)
    # contour points beyond the model's ends (z outside [0.2, 2.2]) do not count
    beyond = np.array([[2.3, 1.0, 5.0], [2.3, 1.0, -3.0]])
    assert skin_agreement_mm(np.vstack([pts, beyond]), V, T) == pytest.approx(
        (mean, p95), abs=1e-12
    )
    assert skin_agreement_mm(np.vstack([pts, beyond]), V, T, clip_to_surface_z=False)[0] > mean
    with pytest.raises(ValueError, match="no contour points"):
        skin_agreement_mm(beyond, V, T)
    with pytest.raises(ValueError, match="no facet set 'cast'"):
        deformed_surface(m, u, facet="cast")


def _layered_shear(m, bounds, ks):
    y = m.nodes_mm[:, 1]
    ux = np.zeros_like(y)
    for lo, hi, k in zip(bounds[:-1], bounds[1:], ks):
        ux += k * np.clip(y - lo, 0, hi - lo)
    return np.column_stack([ux, np.zeros_like(y), np.zeros_like(y)])


def test_summarize_solution_and_json_round_trip(tmp_path):
    bounds = np.array([0.0, 1.0, 2.0])
    ks = np.array(
        [0.5, 0.7]
    )  # γ_GL = k sqrt(k²+4)/4: 0.2577, 0.3707; γ_log = asinh(k/2): 0.2475, 0.3428
    m = box_tet10([0, 1], bounds, [0, 1])
    u = _layered_shear(m, bounds, ks)
    s, strain = summarize_solution(
        m,
        u,
        animal="rat01",
        variant="sphere",
        indenter_force_N=0.12,
        n_dofs=99,
        increments=4,
        newton_iterations=17,
        wall_s=1.5,
        contact_nodes=12,
    )
    assert s.converged and s.reason is None
    assert s.voi_mm3 == pytest.approx(1.0, rel=1e-12)
    assert s.bins_percent["0.3-0.4"] == pytest.approx(100.0)
    assert s.below_threshold_percent == pytest.approx(50.0)
    assert s.peak_gamma == pytest.approx(0.7 * np.sqrt(0.49 + 4) / 4, rel=1e-12)
    assert s.voi_by_measure_mm3 == pytest.approx({"green_lagrange": 1.0, "log": 1.0})
    assert s.peak_gamma_by_measure["log"] == pytest.approx(np.arcsinh(0.35), rel=1e-12)
    assert s.n_elements == m.n_tets and s.newton_iterations == 17
    assert s.extra == {"contact_nodes": 12, "sampling_centroid_elements": 0}

    # skin agreement inside summarize_solution: the x = 1 face, sheared into x = 1 + u_x(y)
    skin = boundary_tri6(m, lambda p: np.isclose(p[:, 0], 1.0))
    ms = TetMesh(nodes_mm=m.nodes_mm, tets=m.tets, facets={"skin": skin})
    pts = []
    for y0, k, f0 in [(0.5, 0.5, 0.25), (1.5, 0.7, 0.5 + 0.35)]:  # u_x at y0 = f0, slope k
        for z0 in (0.3, 0.6):
            pts.append([1.0 + f0 + 0.1, y0, z0])
    s_skin, _ = summarize_solution(
        ms, u, animal="rat01", variant="sphere", skin_contours_mm=np.array(pts)
    )
    d = np.repeat(0.1 / np.sqrt(1 + ks**2), 2)
    assert s_skin.skin_mean_mm == pytest.approx(d.mean(), rel=1e-12)
    assert s_skin.skin_p95_mm == pytest.approx(np.percentile(d, 95), rel=1e-12)

    s_log, _ = summarize_solution(
        m,
        u,
        animal="rat01",
        variant="sphere",
        voi=VoiSpec(strain_measure="log", threshold=0.25, bin_edges=(0.25, 0.3, 0.5)),
    )
    assert s_log.voi_mm3 == pytest.approx(1.0)  # only the k = 0.7 layer has γ_log > 0.25
    assert s_log.bins_percent == pytest.approx({"0.25-0.3": 0.0, "0.3-0.5": 100.0, ">0.5": 0.0})

    write_summary(tmp_path / "summary.json", s)
    back = read_summary(tmp_path / "summary.json")
    assert back == s
    assert back.to_dict()["contact_nodes"] == 12

    write_result_vtu(tmp_path / "result.vtu", m, u, strain)
    mr, ur, cd = read_result_vtu(tmp_path / "result.vtu")
    np.testing.assert_array_equal(mr.tets, m.tets)
    np.testing.assert_allclose(ur, u)
    np.testing.assert_allclose(cd["gamma_gl"], strain.gamma_gl)
    np.testing.assert_allclose(cd["volume_mm3"].sum(), 2.0, rtol=1e-12)


def test_gamma_sampling_chooses_the_reported_voi_and_both_are_kept():
    """u_x = y²/2 (exact in P2): γ grows inside each element, so points and centroids differ."""
    m = box_tet10([0, 1], [0, 0.5, 1], [0, 1])
    y = m.nodes_mm[:, 1]
    u = np.column_stack([0.5 * y**2, np.zeros_like(y), np.zeros_like(y)])
    w = np.full(m.n_tets, 2.0)  # energy density [MPa]
    pts, _ = summarize_solution(m, u, animal="a", variant="sphere", energy_density_mpa=w)
    cen, _ = summarize_solution(
        m,
        u,
        animal="a",
        variant="sphere",
        voi=VoiSpec(gamma_sampling="centroid"),
        energy_density_mpa=w,
    )
    assert pts.gamma_sampling == "points" and cen.gamma_sampling == "centroid"
    assert (
        pts.voi_sampled_mm3 == cen.voi_sampled_mm3 and pts.voi_centroid_mm3 == cen.voi_centroid_mm3
    )
    assert pts.voi_mm3 == pts.voi_sampled_mm3 and cen.voi_mm3 == cen.voi_centroid_mm3
    assert pts.voi_sampled_mm3 != pytest.approx(pts.voi_centroid_mm3, rel=0.01)
    assert (
        pts.bins_percent == pts.bins_sampled_percent
        and cen.bins_percent == cen.bins_centroid_percent
    )
    # the VOI energy follows the sampling: density 2 MPa times that VOI
    assert pts.strain_energy_mJ == pytest.approx(
        2.0 * pts.voi_mm3
    ) and cen.strain_energy_mJ == pytest.approx(2.0 * cen.voi_mm3)
    assert pts.below_threshold_percent == pytest.approx(100 * (1 - pts.voi_mm3))  # unit cube
    assert pts.voi_by_measure_mm3["green_lagrange"] == pts.voi_mm3
    assert cen.peak_gamma == pts.peak_gamma  # always the largest centroid value
    with pytest.raises(ValueError, match="gamma_sampling"):
        summarize_solution(m, u, animal="a", variant="sphere", voi=VoiSpec(gamma_sampling="nodes"))


def test_result_vtu_uses_vtk_node_order(tmp_path):
    import meshio

    m = box_tet10([0, 1], [0, 1], [0, 1])
    s, strain = summarize_solution(m, np.zeros_like(m.nodes_mm), animal="a", variant="bar")
    write_result_vtu(tmp_path / "r.vtu", m, np.zeros_like(m.nodes_mm), strain)
    cells = meshio.read(tmp_path / "r.vtu").get_cells_type("tetra10")
    p = m.nodes_mm[cells]
    # VTK_QUADRATIC_TETRA: mid-edge nodes 4..9 on edges (0,1), (1,2), (2,0), (0,3), (1,3), (2,3)
    for k, (a, b) in enumerate([(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]):
        np.testing.assert_allclose(p[:, 4 + k], 0.5 * (p[:, a] + p[:, b]))


def test_failed_run_is_recorded_not_lost(tmp_path):
    f = failed_summary(
        animal="rat02",
        variant="sphere_rx+15",
        reason="increment cut below 1e-4 at step 3",
        n_elements=5000,
        increments=7,
        wall_s=120.0,
        last_residual=3e-2,
    )
    write_summary(tmp_path / "s.json", f)
    back = read_summary(tmp_path / "s.json")
    assert back.converged is False and back.reason.startswith("increment cut")
    assert (
        back.voi_mm3 is None and back.n_elements == 5000 and back.extra == {"last_residual": 3e-2}
    )
    # a summary written without animal/variant keys takes them from its path
    (tmp_path / "ratZ" / "bar").mkdir(parents=True)
    (tmp_path / "ratZ" / "bar" / "summary.json").write_text('{"converged": true, "voi_mm3": 1.5}')
    z = read_summary(tmp_path / "ratZ" / "bar" / "summary.json")
    assert (z.animal, z.variant, z.voi_mm3) == ("ratZ", "bar", 1.5)
    (tmp_path / "ratZ" / "bar" / "summary.json").write_text('{"converged": "yes"}')
    with pytest.raises(ValueError, match="ratZ/bar/summary.json.*converged must be true or false"):
        read_summary(tmp_path / "ratZ" / "bar" / "summary.json")
    with pytest.raises(ValueError, match="needs a reason"):
        Summary(animal="a", variant="sphere", converged=False)
    with pytest.raises(ValueError, match="missing key"):
        Summary.from_dict({"animal": "a"})
    with pytest.raises(ValueError, match="strain_measure"):
        Summary(animal="a", variant="sphere", converged=True, strain_measure="hencky")
