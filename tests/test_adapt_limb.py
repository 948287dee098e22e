"""Adaptive meshes of one limb variant: the mesher with cast and patch, the contact zone, the rule's files."""

import json

import numpy as np
import pandas as pd
import pytest
from model_synth import leg_contours, leg_pose
from study_meshes import boundary_tri6, box_tet10

from deeptissue.adapt import AdaptSettings, element_sizes, node_sizes
from deeptissue.adapt_limb import (
    AdaptFiles,
    contact_tets,
    limb_mesher,
    load_pass_states,
    run_adaptive_variant,
)
from deeptissue.contours import save_contours
from deeptissue.fem.indenters import Indenter
from deeptissue.mesh import SizeField, TetMesh
from deeptissue.model import build_cast, build_model, save_cast
from deeptissue.pose import save_pose
from deeptissue.summary import read_result_vtu, read_summary

# a short phantom limb (12 slices, 11 x 8.6 mm across), the study's sizes but the quality gate's, which is
# the model stage's business
MODEL = dict(element_size_mm=1.6, refine_size_mm=0.8, min_scaled_jacobian=0.01)


@pytest.fixture(scope="module")
def limb():
    c = leg_contours(n_slices=12, z0_mm=-5.5)
    p = leg_pose(c, depth_mm=1.5)
    return c, p, build_cast(c, p, variants=["sphere"], settings=MODEL)


def _area_mm2(mesh: TetMesh, name: str) -> float:
    q = mesh.nodes_mm[mesh.facets[name][:, :3]]
    return float(
        0.5 * np.linalg.norm(np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), axis=1).sum()
    )


def _centroids(mesh: TetMesh) -> np.ndarray:
    return mesh.nodes_mm[mesh.tets[:, :4]].mean(axis=1)


def _files(d, name, base=None) -> AdaptFiles:
    return AdaptFiles(
        contours=d / "pre.npz",
        pose=d / "pose.json",
        cast=d / "cast.npz",
        during_contours=None,
        passes_csv=d / name / "passes.csv",
        summary=d / name / "summary.json",
        vtu=d / name / "result.vtu",
        base_states=None if base is None else d / base / "states",
        states=d / name / "states",
    )


def test_the_limb_mesher_puts_the_patch_and_the_cast_set_on_every_new_mesh(limb):
    c, p, cast = limb
    default = build_model(c, p, variants=["sphere"], settings=MODEL, cast=cast).mesh
    build = limb_mesher(c, p, "sphere", cast=cast, settings=MODEL)
    first = build(None)
    h = element_sizes(first)
    near = np.linalg.norm(_centroids(first) - p.tip_end_mm, axis=1) < 2.5
    refined = build(
        SizeField.from_mesh(first, node_sizes(first, np.where(near, 0.4, h), current_mm=h))
    )
    # the first pass: the model's element size everywhere (fewer elements than the default mesh, refined about the travel)
    assert first.n_tets < default.n_tets
    # ... the preview's fixed mesh (config/preview.yaml: refine_size_mm = element_size_mm), whatever variants it carries
    preview = build_model(
        c, p, variants=["sphere", "bar"], settings={**MODEL, "refine_size_mm": 1.6}, cast=cast
    ).mesh
    assert np.array_equal(preview.nodes_mm, first.nodes_mm)
    assert np.array_equal(preview.tets, first.tets)
    assert np.median(h) == pytest.approx(1.6, rel=0.2)
    for mesh in (first, refined):
        assert {"bone", "skin", "proximal", "distal", "patch", "patch_sphere"} <= set(mesh.facets)
        # the patch: the same 6 mm disc of skin about the final tip as on the default mesh
        assert _area_mm2(mesh, "patch_sphere") == pytest.approx(
            _area_mm2(default, "patch_sphere"), rel=0.1
        )
        assert _area_mm2(mesh, "patch_sphere") == pytest.approx(np.pi * 3.0**2, rel=0.25)
        patch_nodes = mesh.nodes_mm[np.unique(mesh.facets["patch_sphere"])]
        assert np.linalg.norm(patch_nodes - p.tip_end_mm, axis=1).max() < 3.0 + 1.6 + 1.5
        # the cast's contact set is the whole skin
        assert _area_mm2(mesh, "skin") == pytest.approx(_area_mm2(default, "skin"), rel=0.02)
    h_r = element_sizes(refined)
    assert h_r[np.linalg.norm(_centroids(refined) - p.tip_end_mm, axis=1) < 1.5].mean() < 0.7
    assert refined.n_tets > first.n_tets


def test_contact_tets_are_the_elements_the_indenter_holds():
    mesh = box_tet10(np.linspace(-3, 3, 7), np.linspace(-3, 0, 4), np.linspace(-3, 3, 7))
    mesh = TetMesh(
        mesh.nodes_mm, mesh.tets, facets={"patch": boundary_tri6(mesh, lambda x: x[:, 1] > -1e-9)}
    )
    u = np.zeros_like(mesh.nodes_mm)
    # the nodes of the face y = 0 within the footprint of a 1.5 mm sphere 0.5 mm deep, pushed onto its surface
    r = np.linalg.norm(mesh.nodes_mm[:, [0, 2]], axis=1)
    dent = np.isclose(mesh.nodes_mm[:, 1], 0.0) & (r <= 1.12)
    u[dent, 1] = 1.0 - np.sqrt(1.5**2 - r[dent] ** 2)
    sphere = Indenter(kind="sphere", axis=(0, -1, 0), start_mm=(0, 1, 0), end_mm=(0, -0.5, 0))
    held = contact_tets(mesh, u, sphere)
    assert np.array_equal(held, dent[mesh.tets].any(axis=1))
    assert 0 < held.sum() < mesh.n_tets
    # a 10 mm bar along z touching the face at x = 2.5 mm holds a strip of elements there
    bar = Indenter(
        kind="bar", axis=(0, -1, 0), start_mm=(2.5, 1, 0), end_mm=(2.5, 0, 0), bar_length_mm=10.0
    )
    strip = contact_tets(mesh, np.zeros_like(u), bar)
    x = _centroids(mesh)
    assert strip.any() and np.all(np.abs(x[strip, 0] - 2.5) < 1.0) and np.all(x[strip, 1] > -1.0)
    assert set(np.round(x[strip, 2])) >= {-2.0, 0.0, 2.0}  # all along the bar


@pytest.mark.slow
def test_two_adaptive_passes_on_a_phantom_limb_refine_under_the_indenter(limb, tmp_path):
    c, p, cast = limb
    save_contours(tmp_path / "pre.npz", c)
    save_pose(tmp_path / "pose.json", p)
    save_cast(tmp_path / "cast.npz", cast)
    study = {"threshold": 0.3, "variants": ["sphere", "sphere_rz+15", "sphere_rx+15"]}
    result = run_adaptive_variant(
        animal="leg",
        variant="sphere",
        files=_files(tmp_path, "a"),
        model_cfg=MODEL,
        fem_cfg={},
        study_cfg=study,
        settings=AdaptSettings(max_passes=2, max_tets=2200),
    )
    t = pd.read_csv(tmp_path / "a/passes.csv")
    assert len(t) == 2 and t["converged"].all(), t.to_string()
    assert set(t["animal"]) == {"leg"} and set(t["variant"]) == {"sphere"}
    assert t.loc[1, "n_dofs"] > t.loc[0, "n_dofs"]
    # the budget, graded sizes counted: gmsh's count stays within 10 % of it (the surface's share)
    assert 0.7 * 2200 <= t.loc[1, "n_tets"] <= 1.1 * 2200, t.to_string()
    assert t.loc[1, "h_min_mm"] < 0.8 * t.loc[0, "h_min_mm"]
    # the refinement is where the VOI is decided: under the indenter
    mesh = result.mesh
    h, d = element_sizes(mesh), np.linalg.norm(_centroids(mesh) - p.tip_end_mm, axis=1)
    assert h[d < 2.0].mean() < 0.75 * h[d > 5.0].mean()
    # the summary is the last pass's, in the fixed mesh's format, with the loop's facts
    s = read_summary(tmp_path / "a/summary.json")
    assert s.converged and s.n_dofs == t.loc[1, "n_dofs"] and s.n_elements == mesh.n_tets
    assert s.voi_mm3 == pytest.approx(t.loc[1, "voi_mm3"]) and s.voi_mm3 > 0
    assert 100 * s.voi_err_mm3 / s.voi_mm3 == pytest.approx(t.loc[1, "voi_err_percent"])
    assert max(s.bins_err_pp.values()) == pytest.approx(t.loc[1, "bins_err_pp"])
    assert s.indenter_force_N == pytest.approx(t.loc[1, "force_N"]) and s.indenter_force_N > 0
    assert s.extra["contact_set"] == "patch_sphere"
    d = json.loads((tmp_path / "a/summary.json").read_text())
    assert d["adapt_passes"] == 2 and d["adapt_stop_reason"] in ("passes", "goal")
    assert d["adapt_wall_s"] == pytest.approx(t.loc[1, "wall_s"])
    # the verdict of the last pass, as the loop judged it: the same estimates, the same goal
    assert d["mesh_kind"] == "adaptive" and d["within_goal"] == bool(t.loc[1, "goal_met"])
    assert d["force_err_status"] == t.loc[1, "force_status"]
    assert d["voi_err_percent"] == pytest.approx(t.loc[1, "voi_err_percent"])
    assert d["within_goal"] == (d["outside_goal"] == "")
    # the result for ParaView and the study's sections: the last pass's mesh, displacement and strain
    vtu_mesh, u, cells = read_result_vtu(tmp_path / "a/result.vtu")
    assert vtu_mesh.n_tets == mesh.n_tets and np.allclose(u, result.solution.displacement_mm)
    assert (
        np.allclose(cells["gamma_gl"], result.solution.strain.gamma_gl)
        and cells["converged"].all()
    )
    # every converged pass's mesh (with the patches of the variants turned from this one) and end state
    passes = load_pass_states(tmp_path / "a/states")
    assert [m.n_tets for m, _ in passes] == list(t["n_tets"])
    assert {"patch_sphere", "patch_sphere_rz+15", "patch_sphere_rx+15"} <= set(passes[1][0].facets)
    assert np.allclose(passes[1][1].displacement_mm, result.solution.displacement_mm.ravel())
    # a turned variant rides those passes: the same meshes, each turned from the sphere's end state there
    run_adaptive_variant(
        animal="leg",
        variant="sphere_rz+15",
        files=_files(tmp_path, "t", base="a"),
        model_cfg=MODEL,
        fem_cfg={},
        study_cfg=study,
        settings=AdaptSettings(max_passes=2, max_tets=2200),
    )
    rode = pd.read_csv(tmp_path / "t/passes.csv")
    assert list(rode["n_tets"]) == list(t["n_tets"]) and rode["converged"].all()
    d = json.loads((tmp_path / "t/summary.json").read_text())
    assert d["turned_from"] == "sphere" and d["contact_set"] == "patch_sphere_rz+15"
    assert d["indenter_force_N"] > 0 and d["voi_mm3"] > 0
    assert not any((tmp_path / "t/states").iterdir())  # no variant rides a turned one's passes
    # a base that converged on no pass: the turned variant meshes and solves its own from the start
    (tmp_path / "empty/states").mkdir(parents=True)
    run_adaptive_variant(
        animal="leg",
        variant="sphere_rx+15",
        files=_files(tmp_path, "x", base="empty"),
        model_cfg=MODEL,
        fem_cfg={},
        study_cfg=study,
        settings=AdaptSettings(max_passes=1),
    )
    d = json.loads((tmp_path / "x/summary.json").read_text())
    assert d["converged"] and d["turned_from"] is None and d["adapt_passes"] == 1


def test_a_turned_variant_rides_only_base_passes_that_carry_its_patch(tmp_path):
    from deeptissue.adapt_limb import _base_passes, pass_files
    from deeptissue.fem.solver import EndState, SolverSettings, save_end_state
    from deeptissue.mesh import save_tetmesh
    from deeptissue.rigid import BoneMotion

    box = box_tet10(np.linspace(0, 2, 3), np.linspace(0, 2, 3), np.linspace(0, 2, 3))
    top = boundary_tri6(box, lambda x: x[:, 2] > 2 - 1e-9)
    sphere = Indenter(kind="sphere", axis=(0, 0, -1), start_mm=(1, 1, 3), end_mm=(1, 1, 1.8))
    state = EndState(np.zeros(box.nodes_mm.size), {}, sphere, BoneMotion(), SolverSettings())
    for k, facets in enumerate(({"patch_sphere_rz+15": top}, {"patch_sphere": top})):
        mesh_path, state_path = pass_files(tmp_path, k)
        save_tetmesh(mesh_path, TetMesh(box.nodes_mm, box.tets, facets=facets))
        save_end_state(state_path, state)
    assert len(load_pass_states(tmp_path)) == 2
    # pass 1 lacks the patch: the base was meshed for other variants, so no pass is ridden
    assert _base_passes(tmp_path, "sphere", "sphere_rz+15") == []
    pass_files(tmp_path, 1)[0].unlink()  # pass 1 incomplete: the passes end before it
    assert len(_base_passes(tmp_path, "sphere", "sphere_rz+15")) == 1
    assert _base_passes(tmp_path, None, "sphere_rz+15") == []
    # a file that is not an end state is refused with its name
    pass_files(tmp_path, 0)[1].write_text("no state")
    with pytest.raises(ValueError, match="pass0_end_state.npz"):
        load_pass_states(tmp_path)


def test_a_failed_adaptive_run_is_recorded_and_the_study_goes_on(limb, tmp_path):
    c, p, cast = limb
    save_contours(tmp_path / "pre.npz", c)
    save_pose(tmp_path / "pose.json", p)
    save_cast(tmp_path / "cast.npz", cast)
    out = tmp_path / "a"
    result = run_adaptive_variant(
        animal="leg",
        variant="sphere",
        files=_files(tmp_path, "a"),
        model_cfg=MODEL,
        fem_cfg={"material": {"mu_kpa": 3.65, "no_such_parameter": 1.0}},
        study_cfg={"threshold": 0.3},
    )
    assert result is None
    s = read_summary(out / "summary.json")
    assert (
        not s.converged
        and "no_such_parameter" in s.reason
        and s.reason.startswith("adaptive run: TypeError")
    )
    assert len(pd.read_csv(out / "passes.csv")) == 0
    assert s.extra["within_goal"] is False and s.extra["outside_goal"] == "not converged"
    # the first pass's mesh, undeformed, flagged as not converged
    mesh, u, cells = read_result_vtu(out / "result.vtu")
    assert mesh.n_tets > 0 and not u.any() and not cells["converged"].any()


def test_the_summary_takes_the_loops_extrapolated_estimates_and_keeps_its_own_otherwise():
    from dataclasses import replace

    from deeptissue.adapt import AdaptPass
    from deeptissue.adapt_limb import loop_estimates
    from deeptissue.summary import Summary

    s = Summary(
        animal="a",
        variant="bar",
        converged=True,
        voi_mm3=20.0,
        bins_percent={"0.3-0.4": 60.0, "0.4-0.5": 40.0},
        voi_err_mm3=2.0,
        bins_err_pp={"0.3-0.4": 3.0, "0.4-0.5": 3.0},
    )
    nan = float("nan")
    p = AdaptPass(
        *(1, 100, 30, True, 1.0, 1.0, 1.0, 3.0, 20.0, 1.5, 0.4, 1.0, nan, nan, "no goal", 0.1),
        goal_met=True,
        voi_status="estimated",
        bins_status="held",
        bins_err={"0.3-0.4": 0.4, "0.4-0.5": 0.2},
    )
    out = loop_estimates(s, p)
    assert out.voi_err_mm3 == pytest.approx(0.3)  # 1.5 % of 20 mm³
    assert out.bins_err_pp == {"0.3-0.4": 0.4, "0.4-0.5": 0.2}
    assert out.extra == {"voi_err_status": "estimated", "bins_err_status": "held"}
    # the first pass (recovered): the summary's own estimates
    first = loop_estimates(s, replace(p, voi_status="recovered", bins_status="recovered"))
    assert first.voi_err_mm3 == 2.0 and first.bins_err_pp == s.bins_err_pp
