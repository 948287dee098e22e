"""The study job (rule solve): files in, summary.json and result.vtu out, failures recorded."""

from dataclasses import replace

import numpy as np
import pytest

from deeptissue.mesh import save_tetmesh
from deeptissue.pose import Pose, save_pose
from deeptissue.study import SolvePaths, run_bone_state, run_solve, variant_indenter
from deeptissue.summary import read_result_vtu, read_summary
from deeptissue.verification.shapes import cored_cylinder_mesh

R, L = 5.0, 10.0  # cylinder radius and length [mm]
STUDY = {"threshold": 0.05, "bin_edges": [0.05, 0.1, 0.2]}


def _paths(model_dir, out_dir, name: str, **files) -> SolvePaths:
    """The solve job's files: the model's mesh and pose, outputs ``<name>.json`` and ``<name>.vtu``."""
    return SolvePaths(
        mesh=model_dir / "mesh.npz",
        pose=model_dir / "pose.json",
        summary=out_dir / f"{name}.json",
        vtu=out_dir / f"{name}.vtu",
        **files,
    )


@pytest.fixture(scope="module")
def model_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("model")
    mesh = cored_cylinder_mesh(
        length_mm=L,
        radius_mm=R,
        core_radius_mm=1.0,
        h_mm=2.0,
        refine_point_mm=(0.0, R, L / 2),
        refine_h_mm=0.4,
        refine_radius_mm=2.0,
    )
    save_tetmesh(d / "mesh.npz", mesh)
    depth = 0.4
    pose = Pose(
        indenter_axis=[0, -1, 0],
        tip_start_mm=[0, R + 1.0, L / 2],
        tip_end_mm=[0, R - depth, L / 2],
        depth_mm=depth,
        bone_com_mm=[0, 0, L / 2],
        bone_rotation_deg=[0.5, 0, 0],
        bone_translation_mm=[0, 0.02, 0],
    )
    save_pose(d / "pose.json", pose)
    return d, mesh


@pytest.mark.slow
def test_solve_job_writes_a_converged_summary_and_result(model_files, tmp_path):
    d, mesh = model_files
    s = run_solve(
        _paths(d, tmp_path, "summary"), animal="cyl", variant="sphere", fem_cfg={}, study_cfg=STUDY
    )
    assert s.converged, s.reason
    back = read_summary(tmp_path / "summary.json")
    assert back.converged and back.n_elements == mesh.n_tets
    assert back.indenter_force_N > 0
    # strains stay local: a shallow dent strains far less than the whole cylinder above 0.05
    total = np.pi * (R**2 - 1.0) * L
    assert 0 < back.voi_mm3 < 0.2 * total
    assert sum(back.bins_percent.values()) == pytest.approx(100.0)
    _, u, cells = read_result_vtu(tmp_path / "summary.vtu")
    # the skin under the tip moved inward by about the indentation depth
    top = np.argmin(np.linalg.norm(mesh.nodes_mm - [0, R, L / 2], axis=1))
    assert u[top, 1] == pytest.approx(-0.4, abs=0.08)
    assert np.all(cells["converged"] == 1)
    # one mesh: its own VOI and bin estimates, no force estimate, so never within the goal, and it says why
    x = back.extra
    assert x["mesh_kind"] == "fixed" and x["within_goal"] is False
    assert x["voi_err_percent"] == pytest.approx(100 * back.voi_err_mm3 / back.voi_mm3)
    assert x["bins_err_max_pp"] == pytest.approx(max(back.bins_err_pp.values()))
    assert x["goal_ratio"] == pytest.approx(max(x["voi_err_percent"] / 2.0, x["bins_err_max_pp"]))
    assert "force not estimated (one mesh)" in x["outside_goal"]
    assert np.isnan(x["force_err_percent"]) and x["force_err_status"] == "one mesh"


@pytest.mark.slow
def test_variants_start_from_the_bone_state_job_with_the_same_answer(model_files, tmp_path):
    # rule bone_state solves the bone rotation once per mesh; rule solve starts each variant from it
    d, mesh = model_files
    state = run_bone_state(
        mesh_path=d / "mesh.npz",
        cast_path=None,
        pose_path=d / "pose.json",
        state_path=tmp_path / "bone_state.npz",
        fem_cfg={},
    )
    assert state is not None and state.history and all(h.step < 4 for h in state.history)
    common = dict(animal="cyl", variant="sphere", fem_cfg={}, study_cfg=STUDY)
    own = run_solve(_paths(d, tmp_path, "own"), **common)
    shared = run_solve(
        _paths(d, tmp_path, "shared", bone_state=tmp_path / "bone_state.npz"), **common
    )
    assert (
        shared.converged
        and shared.extra["started_from_bone_state"]
        and not own.extra["started_from_bone_state"]
    )
    assert (
        shared.newton_iterations == own.newton_iterations and shared.increments == own.increments
    )
    assert shared.voi_mm3 == pytest.approx(own.voi_mm3, rel=1e-9)
    assert shared.indenter_force_N == pytest.approx(own.indenter_force_N, rel=1e-8)
    # a bone-state job that fails says why in its file; the variants then solve the rotation themselves
    bad = tmp_path / "pose_bad.json"
    bad.write_text("{not json")
    assert (
        run_bone_state(
            mesh_path=d / "mesh.npz",
            cast_path=None,
            pose_path=bad,
            state_path=tmp_path / "failed_state.npz",
            fem_cfg={},
        )
        is None
    )
    alone = run_solve(
        _paths(d, tmp_path, "alone", bone_state=tmp_path / "failed_state.npz"), **common
    )
    assert alone.converged and not alone.extra["started_from_bone_state"]
    assert alone.newton_iterations == own.newton_iterations
    # a file that is not a bone state: the variant is recorded as failed, naming the file
    (tmp_path / "junk.npz").write_text("junk")
    junk = run_solve(_paths(d, tmp_path, "junk", bone_state=tmp_path / "junk.npz"), **common)
    assert not junk.converged and "junk.npz: not a bone-state file" in junk.reason


@pytest.mark.slow
def test_turned_variant_job_starts_from_the_base_end_state(model_files, tmp_path):
    # rule solve of 'sphere' writes its end state; 'sphere_rz+15' turns the indenter from it (study.turn_from_base)
    d, mesh = model_files
    common = dict(animal="cyl", fem_cfg={}, study_cfg=STUDY)
    base = run_solve(
        _paths(d, tmp_path, "b", end_state=tmp_path / "sphere_end.npz"), variant="sphere", **common
    )
    assert base.converged and (tmp_path / "sphere_end.npz").exists()
    own = run_solve(_paths(d, tmp_path, "own"), variant="sphere_rz+15", **common)
    turned = run_solve(
        _paths(d, tmp_path, "t", base_state=tmp_path / "sphere_end.npz"),
        variant="sphere_rz+15",
        base_variant="sphere",
        **common,
    )
    assert own.converged and turned.converged
    assert turned.extra["turned_from"] == "sphere" and own.extra["turned_from"] is None
    assert turned.newton_iterations < own.newton_iterations
    assert turned.indenter_force_N == pytest.approx(own.indenter_force_N, rel=5e-3)
    assert turned.voi_mm3 == pytest.approx(own.voi_mm3, rel=2e-2)
    assert read_summary(tmp_path / "t.json").extra["turned_from"] == "sphere"
    # a base that failed leaves a file saying why: the turned variant is solved from the start
    bad = tmp_path / "pose_bad.json"
    bad.write_text("{not json")
    failed = run_solve(
        replace(_paths(d, tmp_path, "f", end_state=tmp_path / "failed_end.npz"), pose=bad),
        variant="sphere",
        **common,
    )
    assert not failed.converged and (tmp_path / "failed_end.npz").exists()
    alone = run_solve(
        _paths(d, tmp_path, "a", base_state=tmp_path / "failed_end.npz"),
        variant="sphere_rz+15",
        base_variant="sphere",
        **common,
    )
    assert alone.converged and alone.extra["turned_from"] is None
    assert alone.newton_iterations == own.newton_iterations
    # a file that is not an end state: recorded as failed, naming the file
    (tmp_path / "junk.npz").write_text("junk")
    junk = run_solve(
        _paths(d, tmp_path, "j", base_state=tmp_path / "junk.npz"),
        variant="sphere_rz+15",
        base_variant="sphere",
        **common,
    )
    assert not junk.converged and "junk.npz: not an end-state file" in junk.reason


def test_turn_base_is_the_unturned_variant_of_the_same_shape_on_the_same_mesh():
    from deeptissue.variants import mesh_groups, turn_base

    variants = ["sphere", "bar", "sphere_rx+15", "bar_rz-10", "sphere_ry+0"]
    assert turn_base("sphere_rx+15", variants) == "sphere"
    assert turn_base("bar_rz-10", variants) == "bar"
    assert turn_base("sphere", variants) is None and turn_base("bar", variants) is None
    assert turn_base("sphere_ry+0", variants) is None  # no turn
    assert turn_base("sphere_rx+15", ["bar", "sphere_rx+15"]) is None  # its base is not solved
    assert turn_base("sphere_rx+15", variants, mesh_groups(variants, by="indenter")) == "sphere"
    split = {"a": ["sphere", "bar"], "b": ["sphere_rx+15", "bar_rz-10", "sphere_ry+0"]}
    assert turn_base("sphere_rx+15", variants, split) is None  # not on its base's mesh


def test_on_adaptive_meshes_a_turned_variant_rides_its_base_whatever_the_mesh_groups():
    from deeptissue.variants import adaptive_turns

    variants = ["sphere", "bar", "sphere_rx+15", "sphere_rz-15", "bar_rz-10"]
    assert adaptive_turns("sphere", variants) == (None, ("sphere_rx+15", "sphere_rz-15"))
    assert adaptive_turns("bar", variants) == (None, ("bar_rz-10",))
    assert adaptive_turns("sphere_rx+15", variants) == ("sphere", ())
    assert adaptive_turns("sphere_rx+15", ["bar", "sphere_rx+15"]) == (None, ())
    assert adaptive_turns("sphere", variants, turn_from_base=False) == (None, ())
    assert adaptive_turns("sphere_rz-15", variants, turn_from_base=False) == (None, ())


def test_failed_job_is_recorded_with_its_reason(model_files, tmp_path):
    d, mesh = model_files
    bad = tmp_path / "pose.json"
    bad.write_text("{not json")
    s = run_solve(
        replace(_paths(d, tmp_path, "summary"), pose=bad),
        animal="cyl",
        variant="bar",
        fem_cfg={},
        study_cfg={},
    )
    assert not s.converged
    back = read_summary(tmp_path / "summary.json")
    assert not back.converged and "pose.json" in back.reason and "not valid JSON" in back.reason
    assert back.extra["within_goal"] is False and back.extra["outside_goal"] == "not converged"
    _, u, cells = read_result_vtu(tmp_path / "summary.vtu")
    assert np.all(u == 0) and np.all(cells["converged"] == 0)


def test_variant_indenter_turns_about_the_final_tip(model_files):
    d, _ = model_files
    from deeptissue.pose import load_pose

    pose = load_pose(d / "pose.json")
    ind = variant_indenter(pose, "sphere_rz+15")
    np.testing.assert_allclose(ind.end_mm, pose.tip_end_mm)
    assert np.degrees(np.arccos(np.dot(ind.unit_axis, pose.indenter_axis))) == pytest.approx(15.0)
    assert np.linalg.norm(np.subtract(ind.end_mm, ind.start_mm)) == pytest.approx(pose.travel_mm)
    assert variant_indenter(pose, "bar").kind == "bar"


def test_an_unconverged_solve_keeps_its_reason_when_its_last_state_has_no_strain(
    model_files, tmp_path, monkeypatch
):
    """A last state inverted at an element's centroid (one the solver admitted between its quadrature points) has no strain:
    the summary keeps the solver's reason, load and iterations, and result.vtu shows the undeformed mesh."""
    import deeptissue.study as study
    from deeptissue.fem.solver import SolveResult

    d, mesh = model_files
    u = np.zeros_like(mesh.nodes_mm)
    X = mesh.nodes_mm[mesh.tets[0]]
    n = np.cross(X[2] - X[1], X[3] - X[1])
    n /= np.linalg.norm(n)
    u[mesh.tets[0]] = (
        -2.0 * ((X - X[1]) @ n)[:, None] * n
    )  # the element mirrored through its face 1-2-3
    z3 = np.zeros(3)
    folded = SolveResult(
        converged=False,
        reason="wall-time budget of 600 s spent at t = 3.9854",
        displacement_mm=u,
        deformation_gradient=np.tile(np.eye(3), (mesh.n_tets, 1, 1)),
        history=(),
        indenter_force_N=0.37,
        force_on_tissue_N=z3,
        cast_force_N=z3,
        max_penetration_mm=0.3,
        max_penetration_rel=0.4,
        strain_energy_mJ=1.0,
        n_dofs=u.size,
        n_free_dofs=u.size,
        increments=29,
        newton_iterations=382,
        load_reached=3.9854,
        wall_s=600.0,
        assembly_s=0.0,
        linear_solve_s=0.0,
        contact_s=0.0,
    )
    monkeypatch.setattr(study, "solve_from", lambda *a, **k: folded)
    s = run_solve(
        _paths(d, tmp_path, "s"), animal="cyl", variant="sphere", fem_cfg={}, study_cfg=STUDY
    )
    back = read_summary(tmp_path / "s.json")
    assert not back.converged and back.reason.startswith(
        "wall-time budget of 600 s spent at t = 3.9854; "
    )
    assert "inverted" in back.reason and "undeformed" in back.reason
    assert (
        back.newton_iterations == 382
        and back.extra["load_reached"] == pytest.approx(3.9854)
        and s.increments == 29
    )
    _, u_vtu, cells = read_result_vtu(tmp_path / "s.vtu")
    assert np.all(u_vtu == 0) and np.all(cells["converged"] == 0)
