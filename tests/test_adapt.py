"""Solution-driven refinement: the size rule, the background size field, the loop, the cylinder scene."""

import time
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from deeptissue.adapt import (
    GMSH_GRADED_EXCESS,
    AdaptSettings,
    PassEstimate,
    adapt,
    element_sizes,
    estimated_tets,
    fit_budget,
    goal_verdict,
    node_sizes,
    target_sizes,
)
from deeptissue.fem.progress import NEXT_PASS
from deeptissue.mesh import GMSH_TET_VOLUME, SizeField, TetMesh
from deeptissue.verification.cylinder import CylinderMesh, cylinder_mesh

COARSE = CylinderMesh(element_size_mm=2.0, refine_size_mm=2.0)


@pytest.fixture(scope="module")
def coarse_cylinder():
    return cylinder_mesh(COARSE, order=1)


def _centroids(mesh):
    return mesh.nodes_mm[mesh.tets[:, :4]].mean(axis=1)


def _volumes(mesh):
    X = mesh.nodes_mm[mesh.tets[:, :4]]
    return np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6.0


def test_target_sizes_equidistribute_with_p2_and_stay_within_the_limits():
    st = AdaptSettings(h_min_mm=0.3, h_max_mm=1.6, max_shrink=0.1, max_growth=1.0)
    h = np.full(6, 1.0)
    eta = np.array([0.0, 1e-4, 0.01, 0.04, 0.09, 5.0])
    new = target_sizes(
        h, eta, target_total=0.05, settings=st
    )  # share 0.01 for each of the 5 non-zero elements
    assert new[0] == 1.0  # no indicator: the size stays
    assert new[1] == 1.0  # below its share: it would grow, and max_growth is 1
    assert new[2] == pytest.approx(1.0)  # exactly its share
    assert new[3] == pytest.approx(0.5)  # 4 shares: h (1/4)^(1/2)
    assert new[4] == pytest.approx(1 / 3)  # 9 shares
    assert new[5] == pytest.approx(0.3)  # 500 shares: 0.045, never below h_min
    assert np.all(np.diff(new[1:]) <= 0)  # a larger indicator never gets a larger element
    # a pass shrinks an element by at most max_shrink, and never grows one past h_max
    capped = target_sizes(
        np.full(3, 2.0), [0.0, 1.0, 100.0], 0.01, AdaptSettings(max_shrink=0.5, max_growth=2.0)
    )
    assert capped[0] == 1.6 and capped[2] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="differ"):
        target_sizes(h, eta[:3], 0.05)
    with pytest.raises(ValueError, match="h_min_mm"):
        AdaptSettings(h_min_mm=2.0, h_max_mm=1.0)


def test_estimated_tets_counts_gmsh_elements(coarse_cylinder):
    m0 = coarse_cylinder
    # uniform sizes: the volume over 0.21 h³, times the graded excess
    n = node_sizes(m0, np.full(m0.n_tets, 1.0))
    assert estimated_tets(m0, n) == pytest.approx(
        GMSH_GRADED_EXCESS * np.pi * 64 * 8 / (GMSH_TET_VOLUME * 1.0), rel=0.01
    )
    assert estimated_tets(m0, 0.5 * n) == pytest.approx(8 * estimated_tets(m0, n))
    # gmsh's own count: a uniform 1 mm cylinder, and the coarse mesh refined to 0.25 mm at the top centre
    # with its graded halo, which the element sizes alone leave out
    m = cylinder_mesh(CylinderMesh(element_size_mm=1.0, refine_size_mm=1.0), order=1)
    assert m.n_tets <= estimated_tets(m0, n) <= 1.25 * m.n_tets
    h = element_sizes(m0)
    near = np.linalg.norm(_centroids(m0) - [0, 0, 8.0], axis=1) < 1.5
    graded = node_sizes(m0, np.where(near, 0.25, h), grading=0.4, current_mm=h)
    remeshed = cylinder_mesh(COARSE, size_field=SizeField.from_mesh(m0, graded), order=1)
    assert estimated_tets(m0, graded) == pytest.approx(remeshed.n_tets, rel=0.15)
    ungraded = np.sum(_volumes(m0) / (GMSH_TET_VOLUME * np.where(near, 0.25, h) ** 3))
    assert ungraded < 0.75 * remeshed.n_tets  # what counting the element sizes alone would say
    # an element whose corner sizes stay as the mesh was made counts as itself
    now = node_sizes(m0, h, grading=0.4, current_mm=h)
    assert estimated_tets(m0, now, current_mm=now) == m0.n_tets
    with pytest.raises(ValueError, match="size > 0"):
        estimated_tets(m0, np.zeros(len(m0.nodes_mm)))


def test_node_sizes_take_the_smallest_element_and_grow_gently(coarse_cylinder):
    m = coarse_cylinder
    sizes = np.full(m.n_tets, 2.0)
    fine = np.argmin(np.linalg.norm(_centroids(m) - [0, 0, 8.0], axis=1))
    sizes[fine] = 0.3
    n = node_sizes(m, sizes, grading=0.4)
    assert np.allclose(n[m.tets[fine]], 0.3)
    edges = m.tets[:, [0, 0, 0, 1, 1, 2]], m.tets[:, [1, 2, 3, 2, 3, 3]]
    a, b = edges[0].ravel(), edges[1].ravel()
    length = np.linalg.norm(m.nodes_mm[a] - m.nodes_mm[b], axis=1)
    assert np.all(np.abs(n[a] - n[b]) <= 0.4 * length + 1e-12)
    assert n.max() == 2.0 and n.min() == 0.3
    # far from the fine element the element's own size comes back
    gap = np.linalg.norm(m.nodes_mm[:, None] - m.nodes_mm[m.tets[fine]][None], axis=2).min(axis=1)
    assert np.allclose(n[gap > 5.0], 2.0)  # 0.3 + 0.4 * 5 > 2
    assert np.all(n[gap < 2.0] < 0.3 + 0.4 * 2.0 + 1e-9) and (gap > 5.0).sum() > 10


def test_fit_budget_scales_the_refined_sizes_together_and_gmsh_keeps_to_it(coarse_cylinder):
    m0 = coarse_cylinder
    h = element_sizes(m0)
    d = np.linalg.norm(_centroids(m0) - [0, 0, 8.0], axis=1)
    new = np.where(d < 1.0, 0.15, np.where(d < 3.0, 0.4, h))
    assert np.array_equal(fit_budget(m0, h, new, 1e9), new)  # fits: unchanged

    def count(sizes):
        return estimated_tets(m0, node_sizes(m0, sizes, grading=0.4, current_mm=h))

    budget = 0.3 * count(new)
    fitted = fit_budget(m0, h, new, budget, grading=0.4)
    assert 0.95 * budget <= count(fitted) <= budget
    assert np.array_equal(fitted[new == h], h[new == h])  # unrefined sizes stay
    both = (d < 1.0) & (fitted < h)
    assert np.allclose(
        fitted[both] / new[both], fitted[both][0] / new[both][0]
    )  # one common factor
    assert np.all(fitted <= h)
    # gmsh honours the budget: its mesh of the fitted sizes has about the budget's tets, not more
    field = SizeField.from_mesh(m0, node_sizes(m0, fitted, grading=0.4, current_mm=h))
    assert (
        0.75 * budget <= cylinder_mesh(COARSE, size_field=field, order=1).n_tets <= 1.05 * budget
    )
    assert np.array_equal(fit_budget(m0, h, new, 1.0), h)  # cannot fit: no refinement at all


@pytest.mark.parametrize("method", ["view", "callback"])
def test_the_remesher_makes_small_elements_where_asked(coarse_cylinder, method, monkeypatch):
    import deeptissue.verification.cylinder as cylinder_module

    m0 = coarse_cylinder
    c = _centroids(m0)
    near_top = np.linalg.norm(c - [0, 0, 8.0], axis=1) < 2.0
    near_side = (
        np.linalg.norm(c - [8.0, 0, 4.0], axis=1) < 2.0
    )  # on the curved face: outside the old flat facets
    target = np.where(near_top | near_side, 0.5, 2.0)
    field = SizeField.from_mesh(m0, node_sizes(m0, target, grading=0.4))
    assert len(field.nodes_mm) == len(np.unique(m0.tets)) and field.tets.max() < len(
        field.nodes_mm
    )
    real = cylinder_module.set_background_size
    monkeypatch.setattr(
        cylinder_module, "set_background_size", lambda g, s: real(g, s, method=method)
    )
    m = cylinder_mesh(COARSE, size_field=field, order=1)
    h, cc = element_sizes(m), _centroids(m)
    top = np.linalg.norm(cc - [0, 0, 8.0], axis=1) < 1.5
    side = np.linalg.norm(cc - [8.0, 0, 4.0], axis=1) < 1.5
    far = (np.linalg.norm(cc - [0, 0, 8.0], axis=1) > 6.0) & (
        np.linalg.norm(cc - [8.0, 0, 4.0], axis=1) > 6.0
    )
    assert h[top].mean() == pytest.approx(0.5, rel=0.2)
    assert h[side].mean() == pytest.approx(0.5, rel=0.2)
    assert h[far].mean() > 1.5
    # the default mesh is unchanged by the new parameter
    assert cylinder_mesh(COARSE, order=1).n_tets == m0.n_tets


def _fake(mesh, errors_percent, *, forces=None, converged=None, meshes=None, vois=None):
    """A loop on a fixed mesh (or on meshes[k]) whose pass k reports errors_percent[k] for the VOI
    (vois[k] mm³, 1 mm³ without), the bins and the force forces[k]; the indicator is non-zero in the
    first element."""
    calls = {"fields": [], "k": -1}

    def build(field):
        calls["fields"].append(field)
        calls["k"] += 1
        return mesh if meshes is None else meshes[calls["k"]]

    def solve(m):
        k = calls["k"]
        ok = True if converged is None else converged[k]
        return SimpleNamespace(
            converged=ok,
            displacement_mm=np.zeros_like(m.nodes_mm),
            indenter_force_N=1.0 if forces is None else forces[k],
            k=k,
        )

    def estimate(m, sol):
        k = calls["k"]
        eta = np.zeros(m.n_tets)
        eta[0] = errors_percent[k] / 100
        voi = 1.0 if vois is None else vois[k]
        return PassEstimate(
            voi_mm3=voi,
            voi_err_mm3=voi * errors_percent[k] / 100,
            bins_err_pp=errors_percent[k] / 4,
            force_N=sol.indenter_force_N,
            indicator_mm3=eta,
        )

    return build, solve, estimate, calls


def test_the_loop_stops_on_the_goal_and_refines_where_the_indicator_is(coarse_cylinder):
    m = coarse_cylinder
    build, solve, est, calls = _fake(
        m, [10.0, 5.0, 2.5, 1.5, 1.0], forces=[1.0, 1.1, 1.15, 1.16, 1.161]
    )
    r = adapt(build, solve, est, AdaptSettings(max_passes=5))
    # pass 3: VOI 1.5 %, bins 0.375 pp, force changed 0.9 % from pass 2
    assert r.stop_reason == "goal" and len(r.passes) == 4 and r.goal_met
    t = r.table()
    assert list(t["goal_met"]) == [False, False, False, True]
    assert np.isnan(t.loc[0, "force_err_percent"]) and t.loc[
        1, "force_err_percent"
    ] == pytest.approx(100 * 0.1 / 1.1)
    assert calls["fields"][0] is None  # the first pass on the mesher's own sizes
    f = calls["fields"][1]
    first = node_sizes(m, element_sizes(m))[m.tets[0, :4]]
    assert np.all(
        f.size_mm[np.searchsorted(np.unique(m.tets), m.tets[0, :4])] < first
    )  # the indicator's element
    far = np.linalg.norm(f.nodes_mm - m.nodes_mm[m.tets[0, :4]].mean(axis=0), axis=1) > 6.0
    h = element_sizes(m)
    unchanged = node_sizes(m, h, current_mm=h)[np.unique(m.tets)]
    assert far.sum() > 10 and np.allclose(
        f.size_mm[far], unchanged[far]
    )  # elsewhere the size stays
    # without a force goal the first pass within the VOI and bin goals ends the loop
    build, solve, est, _ = _fake(m, [10.0, 1.0, 1.0])
    assert len(adapt(build, solve, est, AdaptSettings(force_goal_percent=None)).passes) == 2


def test_only_the_quantity_that_misses_its_goal_is_refined(coarse_cylinder):
    m = coarse_cylinder
    far_apart = np.argmax(np.linalg.norm(_centroids(m) - _centroids(m)[0], axis=1))
    fields = []

    def estimate(
        mesh, sol
    ):  # the VOI (element 0) within its goal, the bins (element far_apart) not
        eta, voi = np.zeros(mesh.n_tets), np.zeros(mesh.n_tets)
        eta[0] = voi[0] = 0.01
        eta[far_apart] = 0.05
        return PassEstimate(
            voi_mm3=1.0,
            voi_err_mm3=0.01,
            bins_err_pp=3.0,
            force_N=1.0,
            indicator_mm3=eta,
            voi_indicator_mm3=voi,
        )

    adapt(
        lambda f: fields.append(f) or m,
        lambda mm: SimpleNamespace(
            converged=True, indenter_force_N=1.0, displacement_mm=np.zeros_like(mm.nodes_mm)
        ),
        estimate,
        AdaptSettings(max_passes=2, force_goal_percent=None),
    )
    h = element_sizes(m)
    before = node_sizes(m, h, current_mm=h)[np.unique(m.tets)]
    after = fields[1].size_mm
    index = np.searchsorted(np.unique(m.tets), m.tets[:, :4])
    assert np.all(after[index[far_apart]] < 0.8 * before[index[far_apart]])
    assert np.allclose(after[index[0]], before[index[0]])


def test_the_loop_stops_on_its_budget_and_on_a_failed_solve(coarse_cylinder):
    m = coarse_cylinder
    build, solve, est, _ = _fake(m, [10.0] * 5)
    lines = []
    r = adapt(build, solve, est, AdaptSettings(max_passes=3), log=lines.append)
    assert r.stop_reason == "passes" and len(r.passes) == 3 and not r.goal_met
    # each pass's line, and the line that says another pass is being meshed, but not after the last
    assert [ln.split(":")[0] for ln in lines] == ["pass 0", "pass 1", "pass 1", "pass 2", "pass 2"]
    assert lines[1] == lines[3].replace("2", "1") == f"pass 1: {NEXT_PASS}"
    build, solve, est, _ = _fake(m, [10.0] * 5)
    r = adapt(build, solve, est, AdaptSettings(max_wall_s=1e-9))
    assert r.stop_reason == "wall" and len(r.passes) == 1
    build, solve, est, _ = _fake(m, [10.0] * 5, converged=[True, False, True])
    r = adapt(build, solve, est)
    assert r.stop_reason == "not converged" and len(r.passes) == 2
    assert r.mesh is m and r.estimate.voi_err_mm3 == pytest.approx(0.1)  # the last converged pass
    # a solve that ends unconverged after the budget was spent (the solver's max_wall_s) stops on the budget
    build, solve, est, _ = _fake(m, [10.0] * 5, converged=[True, False, True])
    calls_made = []

    def slow(mesh):
        if calls_made:
            time.sleep(1.0)
        calls_made.append(mesh)
        return solve(mesh)

    r = adapt(build, slow, est, AdaptSettings(max_wall_s=0.8))
    assert r.stop_reason == "wall" and len(r.passes) == 2 and not r.passes[-1].converged


def test_the_force_estimate_needs_a_shrunk_contact_zone(coarse_cylinder):
    m = coarse_cylinder
    build, solve, est, _ = _fake(m, [1.0] * 4, forces=[1.0, 1.001, 1.001, 1.001])

    def with_contact(
        mesh, sol
    ):  # the contact zone: the first element, whose size the fake mesher never changes
        e = est(mesh, sol)
        c = np.zeros(mesh.n_tets, bool)
        c[0] = True
        return PassEstimate(e.voi_mm3, e.voi_err_mm3, e.bins_err_pp, e.force_N, e.indicator_mm3, c)

    r = adapt(build, solve, with_contact, AdaptSettings(max_passes=3))
    assert r.stop_reason == "passes" and np.isnan(r.table()["force_err_percent"]).all()
    assert list(r.table()["force_status"]) == ["first pass", "not refined", "not refined"]
    assert np.isnan(r.table().loc[0, "contact_shrink"]) and np.allclose(
        r.table()["contact_shrink"][1:], 1.0
    )


def _with_contact(estimate, contact):
    """The estimator ``estimate`` with the contact zone ``contact(mesh)`` (n_tets,) bool."""

    def est(mesh, sol):
        e = estimate(mesh, sol)
        return PassEstimate(
            e.voi_mm3, e.voi_err_mm3, e.bins_err_pp, e.force_N, e.indicator_mm3, contact(mesh)
        )

    return est


def test_a_force_within_its_goal_holds_while_the_voi_is_refined(coarse_cylinder):
    m = coarse_cylinder
    fine = TetMesh(
        0.5 * m.nodes_mm, m.tets, m.facets
    )  # every element half the size: the contact zone shrinks to 0.5
    far_apart = int(np.argmax(np.linalg.norm(_centroids(m) - _centroids(m)[0], axis=1)))

    def zone(mesh):
        c = np.zeros(mesh.n_tets, bool)
        c[far_apart] = True  # away from the VOI's indicator (element 0)
        return c

    def run(forces, meshes=(m, fine, fine, fine, fine)):
        # the VOI changes by 1/6 from pass 0 to 1: 1/6 r / (1 - r) = 5.6 % at r = 0.5^2, outside its goal
        build, solve, est, calls = _fake(
            m, [10.0, 5.0, 3.0, 1.5, 1.5], forces=forces, meshes=meshes, vois=[1.2] + [1.0] * 4
        )
        r = adapt(build, solve, _with_contact(est, zone), AdaptSettings(max_passes=5))
        return r, calls["fields"]

    def unchanged(mesh):  # the node sizes of a field that keeps every element's size
        h = element_sizes(mesh)
        return node_sizes(mesh, h, current_mm=h)[np.unique(mesh.tets)]

    # pass 1: the contact zone halved and the force changed by 0.99 %: an error of 0.99 % r / (1 - r),
    # r = 0.5^1.75 (Richardson with the force's order), within its goal; the VOI meets its goal at pass 3,
    # on meshes whose contact zone the loop no longer refines
    r, fields = run([1.0, 1.01, 1.012, 1.013, 1.013])
    t = r.table()
    assert r.stop_reason == "goal" and len(r.passes) == 4 and r.goal_met, t.to_string()
    assert list(t["force_status"]) == ["first pass", "estimated", "held", "held"]
    assert list(t["goal_met"]) == [False, False, False, True]
    assert np.isnan(t.loc[0, "force_err_percent"])
    r_half = 0.5**1.75
    # the verdict's, larger than the drift since
    assert np.allclose(t["force_err_percent"][1:], 100 * 0.01 / 1.01 * r_half / (1 - r_half))
    assert np.allclose(t["contact_shrink"][1:], [0.5, 1.0, 1.0])
    index = np.searchsorted(np.unique(m.tets), m.tets[far_apart, :4])
    assert np.all(
        fields[1].size_mm[index] < unchanged(m)[index]
    )  # the force unknown: its contact zone refined
    assert np.allclose(
        fields[2].size_mm[index], unchanged(fine)[index]
    )  # the force held: its contact zone not
    # a force that moves by more than its goal since the verdict revokes it, and the contact zone is refined again
    r, fields = run([1.0, 1.01, 1.05, 1.05, 1.05])
    t = r.table()
    assert t.loc[2, "force_status"] == "held" and t.loc[2, "force_err_percent"] == pytest.approx(
        100 * 0.04 / 1.05
    )
    assert (
        list(t["force_status"][3:]) == ["not refined", "not refined"] and r.stop_reason == "passes"
    )
    assert np.all(fields[3].size_mm[index] < unchanged(fine)[index])
    # a contact zone coarser than the verdict's (twice its size) ends it
    r, _ = run([1.0, 1.01, 1.012, 1.013, 1.013], meshes=(m, fine, m, m, m))
    assert list(r.table()["force_status"]) == [
        "first pass",
        "estimated",
        "coarsened",
        "not refined",
        "not refined",
    ]
    assert not r.goal_met


def test_a_contact_zone_the_budget_cannot_refine_is_left_alone_and_said_so(coarse_cylinder):
    m = coarse_cylinder
    lowest, order = int(np.argmin(_centroids(m)[:, 2])), np.arange(m.n_tets)
    order[[0, lowest]] = [lowest, 0]
    mesh = TetMesh(
        m.nodes_mm, m.tets[order], m.facets
    )  # _fake's indicator (element 0) at the bottom
    top = _centroids(mesh)[:, 2] > 6.0  # the contact zone: a quarter of the cylinder
    h = element_sizes(mesh)
    # room for the VOI's element, not for a quarter of the cylinder
    budget = 1.05 * estimated_tets(mesh, node_sizes(mesh, h, current_mm=h))
    build, solve, est, calls = _fake(mesh, [10.0] * 3, forces=[1.0, 1.1, 1.2])
    r = adapt(
        build,
        solve,
        _with_contact(est, lambda mm: top),
        AdaptSettings(max_passes=3, max_tets=int(budget)),
    )
    t = r.table()
    assert (
        list(t["force_status"]) == ["first pass", "budget", "budget"]
        and np.isnan(t["force_err_percent"]).all()
    )
    corners = np.unique(mesh.tets)
    unchanged = node_sizes(mesh, h, current_mm=h)[corners]
    f = calls["fields"][1]
    on_top = np.isin(corners, mesh.tets[top, :4])
    assert on_top.sum() > 10 and np.allclose(
        f.size_mm[on_top], unchanged[on_top]
    )  # no useless refinement on top
    bottom = np.searchsorted(corners, mesh.tets[0, :4])
    assert np.all(f.size_mm[bottom] < unchanged[bottom])  # the budget went to the VOI
    # a contact zone already at h_min cannot shrink either
    hc = float(h[top].max())
    build, solve, est, _ = _fake(mesh, [10.0] * 2, forces=[1.0, 1.1])
    r = adapt(
        build,
        solve,
        _with_contact(est, lambda mm: top),
        AdaptSettings(max_passes=2, h_min_mm=hc, h_max_mm=hc),
    )
    assert list(r.table()["force_status"]) == ["first pass", "h_min"]


def test_contact_tets_are_the_elements_under_the_sphere(coarse_cylinder):
    from deeptissue.verification.cylinder import _indenter, contact_tets

    m = coarse_cylinder
    ind = _indenter(
        0.5, 8.0
    )  # the sphere's cap 0.5 mm into the undeformed top: radius sqrt(1.5² - 1²)
    c = contact_tets(m, np.zeros_like(m.nodes_mm), ind, tol_mm=0.0)
    top = np.unique(m.facets["patch"])
    inside = top[np.hypot(m.nodes_mm[top, 0], m.nodes_mm[top, 1]) <= np.sqrt(1.5**2 - 1.0**2)]
    assert len(inside) >= 1
    assert np.array_equal(c, np.isin(m.tets, inside).any(axis=1))


def test_adaptive_comparison_errors_against_the_reference(tmp_path):
    from deeptissue.verification.cylinder import adaptive_comparison, plot_adaptive

    voi = pd.DataFrame(
        dict(
            mesh=["a", "ref"],
            depth_mm=[2.0, 2.0],
            n_dofs=[10, 100],
            voi_mm3=[10.5, 10.0],
            voi_err_mm3=[1.0, 0.1],
            **{
                "bins_percent.x": [60.0, 58.0],
                "bins_percent.y": [40.0, 42.0],
                "bins_err_pp.x": [3.0, 0.2],
                "bins_err_pp.y": [1.0, 0.2],
            },
        )
    )
    curve = pd.DataFrame(
        dict(
            mesh=["a", "ref", "a", "ref"],
            depth_mm=[2.0, 2.0, 0.5, 0.5],
            force_N=[1.01, 1.0, 0.2, 0.1],
            wall_s=[5.0, 50.0, 2.0, 20.0],
        )
    )
    passes = pd.DataFrame(
        dict(
            depth_mm=[2.0, 0.5],
            index=[1, 2],
            n_dofs=[20, 30],
            wall_s=[12.0, 9.0],
            voi_mm3=[9.9, 0.0],
            voi_err_percent=[1.5, 0.0],
            bins_err_pp=[0.5, 0.0],
            force_N=[0.998, 0.1003],
            force_err_percent=[0.3, 0.4],
            goal_met=[True, True],
            **{"bins_percent.x": [58.5, 0.0], "bins_percent.y": [41.5, 0.0]},
        )
    )
    t = adaptive_comparison(passes, voi, curve)
    # a depth of the force-depth curve without a VOI row: the force's true error only
    shallow = t[t["depth_mm"] == 0.5].iloc[0]
    assert shallow["kind"] == "adaptive" and shallow["true_force_percent"] == pytest.approx(0.3)
    assert np.isnan(shallow["true_voi_percent"]) and np.isnan(shallow["true_bins_pp"])
    plot_adaptive(t, tmp_path / "with_shallow.png")
    t = t[t["depth_mm"] == 2.0].set_index("kind")
    assert len(t) == 2  # the reference itself is no row
    assert t.loc["fixed", "true_voi_percent"] == pytest.approx(5.0)
    assert (
        t.loc["fixed", "true_bins_pp"] == pytest.approx(2.0)
        and t.loc["fixed", "est_bins_pp"] == 3.0
    )
    assert (
        t.loc["fixed", "true_force_percent"] == pytest.approx(1.0)
        and t.loc["fixed", "wall_s"] == 5.0
    )
    assert t.loc["adaptive", "true_voi_percent"] == pytest.approx(-1.0)
    assert t.loc["adaptive", "true_bins_pp"] == pytest.approx(0.5)
    assert t.loc["adaptive", "true_force_percent"] == pytest.approx(-0.2)
    assert t.loc["adaptive", "est_voi_percent"] == 1.5 and t.loc["adaptive", "pass_index"] == 1
    plot_adaptive(t.reset_index(), tmp_path / "adaptive.png")
    assert (tmp_path / "adaptive.png").read_bytes()[:4] == b"\x89PNG"


@pytest.fixture(scope="module")
def adaptive_2mm():
    from deeptissue.fem.material import Ogden
    from deeptissue.verification.cylinder import adaptive_cylinder

    return adaptive_cylinder(Ogden(), 2.0)


@pytest.mark.slow
def test_adaptive_cylinder_at_2mm_meets_the_goal_by_its_own_estimate(adaptive_2mm):
    r = adaptive_2mm
    t = r.table()
    assert r.stop_reason == "goal" and r.goal_met, t.to_string()
    last = t.iloc[-1]
    assert (
        last["voi_err_percent"] <= 2.0
        and last["bins_err_pp"] <= 1.0
        and last["force_err_percent"] <= 2.0
    )
    assert np.all(np.diff(t["n_dofs"]) > 0) and np.all(
        np.diff(t["voi_err_percent"]) < 0
    )  # each pass finer, closer
    # from the second pass on the VOI and bins are extrapolated from the change since the previous pass
    assert t.loc[0, "voi_status"] == "recovered" and set(t["voi_status"][1:]) <= {
        "estimated",
        "held",
    }
    # no runaway refinement: 30 537 DOFs measured (pass 1), fewer than the fixed 1.6 / 0.6 mm mesh
    # (35 244 DOFs), the coarsest fixed mesh that meets the goal against the reference
    assert last["n_dofs"] < 35244, t.to_string()


def test_the_limb_mesher_follows_a_background_size():
    from dataclasses import replace

    from model_synth import leg_contours

    from deeptissue.mesh import MeshSpec, mesh_limb

    c = leg_contours(n_slices=8, z0_mm=-3.5)
    spec = MeshSpec(
        element_size_mm=1.6, order=1, min_scaled_jacobian=0.01
    )  # the sizes, not the gate
    m0, _ = mesh_limb(c.skin, c.bone, spec, animal="r")
    spot = c.skin[4, 0]  # a skin point at mid-length: where an indenter would press
    near = np.linalg.norm(_centroids(m0) - spot, axis=1) < 2.0
    sizes = node_sizes(
        m0, np.where(near, 0.5, element_sizes(m0)), grading=0.4, current_mm=element_sizes(m0)
    )
    m, _ = mesh_limb(
        c.skin, c.bone, replace(spec, size_field=SizeField.from_mesh(m0, sizes)), animal="r"
    )
    # the element budget's count, graded halo included, is gmsh's on a limb too
    assert estimated_tets(m0, sizes) == pytest.approx(m.n_tets, rel=0.2)
    h, d = element_sizes(m), np.linalg.norm(_centroids(m) - spot, axis=1)
    h0, d0 = element_sizes(m0), np.linalg.norm(_centroids(m0) - spot, axis=1)
    assert h[d < 1.0].mean() == pytest.approx(0.5, rel=0.25)
    assert h[d > 6.0].mean() == pytest.approx(h0[d0 > 6.0].mean(), rel=0.15)
    assert m.n_tets > m0.n_tets


def test_a_scene_without_a_voi_meets_the_voi_goal_only_if_its_estimate_agrees(coarse_cylinder):
    m = coarse_cylinder

    def run(voi_err_mm3):
        def estimate(mesh, sol):
            eta = np.zeros(mesh.n_tets)
            eta[0] = voi_err_mm3
            return PassEstimate(
                voi_mm3=0.0,
                voi_err_mm3=voi_err_mm3,
                bins_err_pp=0.0,
                force_N=1.0,
                indicator_mm3=eta,
            )

        return adapt(
            lambda f: m,
            lambda mm: SimpleNamespace(
                converged=True, indenter_force_N=1.0, displacement_mm=np.zeros_like(mm.nodes_mm)
            ),
            estimate,
            AdaptSettings(max_passes=2, force_goal_percent=None),
        )

    # strained below the threshold everywhere in both fields: nothing to refine for the VOI
    r = run(0.0)
    assert r.stop_reason == "goal" and len(r.passes) == 1 and r.passes[0].voi_err_percent == 0.0
    # no VOI in the solution, but the recovered field crosses the threshold: a VOI the mesh may not resolve
    r = run(0.01)
    assert r.stop_reason == "passes" and np.isinf(r.passes[0].voi_err_percent)


def test_goal_verdict_says_which_number_misses_its_goal_and_by_how_much():
    st = AdaptSettings()  # VOI 2 %, bins 1 pp, force 2 %
    ok = goal_verdict(1.9, 0.5, 1.0, "estimated", st)
    assert (
        ok["within_goal"] and ok["outside_goal"] == "" and ok["goal_ratio"] == pytest.approx(0.95)
    )
    off = goal_verdict(8.0, 1.5, 1.0, "estimated", st)
    assert not off["within_goal"] and off["goal_ratio"] == pytest.approx(4.0)
    assert off["outside_goal"] == "VOI ±8 % > 2 %; bins ±1.5 pp > 1 pp"
    # an unknown force estimate misses its goal, with the reason; the known ones still give the ratio
    one = goal_verdict(1.0, 0.2, np.nan, "one mesh", st)
    assert not one["within_goal"] and one["outside_goal"] == "force not estimated (one mesh)"
    assert one["goal_ratio"] == pytest.approx(0.5)
    assert goal_verdict(1.0, 0.2, np.nan, "no goal", AdaptSettings(force_goal_percent=None))[
        "within_goal"
    ]
    assert goal_verdict(np.inf, 0.0, 1.0, "estimated", st)["goal_ratio"] == np.inf


def test_from_the_second_pass_the_voi_and_bins_are_extrapolated_with_their_order(coarse_cylinder):
    """VOI = 10 + 4 h² mm³ and bins 50 ± 2 h² %, h the size of the indicator's element: on meshes
    halved pass by pass, Richardson with order 2 gives the true error 4 h² (2 h²) exactly."""
    m = coarse_cylinder
    meshes = [TetMesh(f * m.nodes_mm, m.tets, m.facets) for f in (1.0, 0.5, 0.25)]
    truth = []

    def estimate(mesh, sol):
        h = element_sizes(mesh)[0]
        eta = np.zeros(mesh.n_tets)
        eta[0] = 1.0  # the recovered estimate: 10 % of the VOI, 5 pp, far off
        truth.append((4 * h * h, 2 * h * h))
        return PassEstimate(
            voi_mm3=10 + 4 * h * h,
            voi_err_mm3=0.1 * (10 + 4 * h * h),
            bins_err_pp=5.0,
            force_N=1.0,
            indicator_mm3=eta,
            bins_percent={"a": 50 + 2 * h * h, "b": 50 - 2 * h * h},
            voi_indicator_mm3=eta,
        )

    k = iter(range(3))
    r = adapt(
        lambda f: meshes[next(k)],
        lambda mm: SimpleNamespace(
            converged=True, indenter_force_N=1.0, displacement_mm=np.zeros_like(mm.nodes_mm)
        ),
        estimate,
        AdaptSettings(max_passes=3, force_goal_percent=None, voi_goal_percent=1e-6),
    )
    t = r.table()
    assert list(t["voi_status"]) == ["recovered", "estimated", "estimated"]
    assert t.loc[0, "voi_err_percent"] == pytest.approx(10.0) and t.loc[0, "bins_err_pp"] == 5.0
    for i in (1, 2):
        voi_err, bin_err = truth[i]
        assert t.loc[i, "voi_err_percent"] == pytest.approx(100 * voi_err / t.loc[i, "voi_mm3"])
        assert t.loc[i, "bins_err_pp.a"] == pytest.approx(bin_err)
        assert t.loc[i, "bins_err_pp.b"] == pytest.approx(bin_err)
        assert t.loc[i, "bins_err_pp"] == pytest.approx(bin_err)
    # the same estimates with order 1 are three times as large at a halving: r / (1 - r) = 1, not 1/3
    k = iter(range(3))
    truth.clear()
    r1 = adapt(
        lambda f: meshes[next(k)],
        lambda mm: SimpleNamespace(
            converged=True, indenter_force_N=1.0, displacement_mm=np.zeros_like(mm.nodes_mm)
        ),
        estimate,
        AdaptSettings(max_passes=2, force_goal_percent=None, voi_goal_percent=1e-6, voi_order=1.0),
    )
    assert r1.table().loc[1, "voi_err_percent"] == pytest.approx(3 * t.loc[1, "voi_err_percent"])


def test_a_region_the_budget_cannot_refine_is_judged_by_its_recovered_estimate(
    coarse_cylinder,
):
    """Bins 50 ± 20 h² % on meshes halved from pass 0 to 1: pass 1's extrapolated estimate misses the
    goal by far, its recovered estimate (0.5 pp) meets it. Where the budget leaves the next pass's sizes
    as they are, the next pass could only be judged by its recovered estimate on the same mesh: pass 1
    is judged by its own, and the loop stops there."""
    m = coarse_cylinder
    meshes = [TetMesh(f * m.nodes_mm, m.tets, m.facets) for f in (1.0, 0.5, 0.5)]
    recovered_pp = iter([5.0, 0.5, 0.5])

    def estimate(mesh, sol):
        h = element_sizes(mesh)[0]
        eta = np.zeros(mesh.n_tets)
        eta[0] = 1.0
        return PassEstimate(
            voi_mm3=10.0,
            voi_err_mm3=0.01,
            bins_err_pp=next(recovered_pp),
            force_N=1.0,
            indicator_mm3=eta,
            bins_percent={"a": 50 + 20 * h * h, "b": 50 - 20 * h * h},
            voi_indicator_mm3=np.zeros(mesh.n_tets),
        )

    def run(max_tets):
        k = iter(range(3))
        lines = []
        r = adapt(
            lambda f: meshes[next(k)],
            lambda mm: SimpleNamespace(
                converged=True, indenter_force_N=1.0, displacement_mm=np.zeros_like(mm.nodes_mm)
            ),
            estimate,
            AdaptSettings(max_passes=3, force_goal_percent=None, max_tets=max_tets),
            log=lines.append,
        )
        return r, r.table(), lines

    r, t, lines = run(max_tets=1)  # no room for a single element more
    assert r.stop_reason == "goal" and len(r.passes) == 2, t.to_string()
    assert list(t["bins_status"]) == ["recovered", "recovered"]
    assert t.loc[1, "bins_err_pp"] == 0.5 and "bins_err_pp.a" not in t
    assert any("0.83 times the elements and shrink the bins region to 1.00" in ln for ln in lines)
    # with room to refine, pass 1 keeps its extrapolated estimate and the loop goes on
    recovered_pp = iter([5.0, 0.5, 0.5])
    r, t, _ = run(max_tets=10**6)
    assert t.loc[1, "bins_status"] == "estimated" and t.loc[1, "bins_err_pp"] > 1.0
    assert len(r.passes) == 3 and not t.loc[1, "goal_met"]


def test_a_voi_region_that_misses_its_goal_is_refined_enough_to_extrapolate(coarse_cylinder):
    m = coarse_cylinder
    h = element_sizes(m)
    eta = np.zeros(m.n_tets)
    eta[:40] = 1e-3  # just above the goal: the size rule alone would shrink these by 2 % only
    est = PassEstimate(
        voi_mm3=1.0,
        voi_err_mm3=0.0209,
        bins_err_pp=0.0,
        force_N=1.0,
        indicator_mm3=eta,
        voi_indicator_mm3=eta,
    )
    from deeptissue.adapt import _next_sizes

    st = AdaptSettings(force_goal_percent=None, max_tets=10**6)
    new_h, _ = _next_sizes(m, h, est, (2.09, 0.0, np.nan), st, st.max_tets)
    assert np.all(new_h[:40] <= st.valid_shrink * h[:40] + 1e-12)
    assert np.allclose(new_h[40:], h[40:])


def test_given_meshes_are_the_first_passes_and_the_loop_meshes_its_own_after_them(coarse_cylinder):
    # a turned variant's first passes are its base's meshes: solved and judged as they are, never meshed
    # again; where they miss the goal, the loop meshes its next pass from its own estimate
    m = coarse_cylinder
    given = [m, TetMesh(m.nodes_mm.copy(), m.tets.copy(), facets=dict(m.facets))]

    def run(errors_percent):
        built, solved, errors = [], [], iter(errors_percent)

        def build(field):
            built.append(field)
            return m

        def solve(mesh):
            solved.append(mesh)
            return SimpleNamespace(
                converged=True, displacement_mm=np.zeros_like(mesh.nodes_mm), indenter_force_N=1.0
            )

        def estimate(mesh, sol):
            e = next(errors)
            eta = np.zeros(mesh.n_tets)
            eta[0] = e / 100
            return PassEstimate(
                voi_mm3=1.0, voi_err_mm3=e / 100, bins_err_pp=e / 4, force_N=1.0, indicator_mm3=eta
            )

        st = AdaptSettings(max_passes=4, force_goal_percent=None)
        return adapt(build, solve, estimate, st, given=given), built, solved

    r, built, solved = run([10.0, 1.0])
    assert r.goal_met and len(r.passes) == 2 and built == []
    assert solved[0] is given[0] and solved[1] is given[1]
    r, built, solved = run([10.0, 10.0, 1.0])
    assert r.goal_met and len(r.passes) == 3 and all(a is b for a, b in zip(solved, given))
    assert (
        len(built) == 1 and built[0] is not None
    )  # its own refined sizes, not the mesher's default


def test_the_first_refinement_has_the_smaller_budget(coarse_cylinder, monkeypatch):
    # the first refinement is aimed by the recovered estimate (several times the true error): it gets
    # first_refinement_tets, or max_tets where that is smaller; every later one gets max_tets
    import deeptissue.adapt as adapt_module

    budgets = []
    real = adapt_module.fit_budget

    def recording(mesh, h, new_h, max_tets, **kw):
        budgets.append(max_tets)
        return real(mesh, h, new_h, max_tets, **kw)

    monkeypatch.setattr(adapt_module, "fit_budget", recording)
    build, solve, est, _ = _fake(coarse_cylinder, [10.0] * 3)
    adapt(
        build, solve, est, AdaptSettings(max_passes=3, max_tets=9000, first_refinement_tets=3000)
    )
    assert budgets and budgets[0] == 3000 and set(budgets[1:]) == {9000}
    budgets.clear()
    build, solve, est, _ = _fake(coarse_cylinder, [10.0] * 2)
    adapt(
        build, solve, est, AdaptSettings(max_passes=2, max_tets=2000, first_refinement_tets=3000)
    )
    assert set(budgets) == {2000}
    with pytest.raises(ValueError, match="first_refinement_tets"):
        AdaptSettings(first_refinement_tets=0)
