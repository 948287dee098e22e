"""Config validation, result-file round trips and rigid-motion conventions."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from deeptissue.config import ConfigError, load_schema, validate_config
from deeptissue.contours import Contours, load_contours, save_contours
from deeptissue.pose import Pose, load_pose, save_pose
from deeptissue.rigid import apply_rigid, euler_xyz_deg, rotation_matrix

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


def _demo():
    return yaml.safe_load((ROOT / "config" / "config.yaml").read_text())


def test_demo_config_is_valid_and_gets_defaults():
    cfg = validate_config(_demo(), SCHEMA, base_dir=ROOT)
    assert cfg["segmentation"]["n_points"] == 100
    assert set(cfg["animals"]) == {"rat01", "rat02", "rat03"}


@pytest.mark.parametrize(
    "mutate, match",
    [
        (
            lambda c: c["animals"]["rat01"]["phantom"].update(depht_mm=2),
            r"animals\.rat01\.phantom: unknown key\(s\) \['depht_mm'\]",
        ),
        (
            lambda c: c["animals"]["rat01"]["phantom"].update(snr="high"),
            r"animals\.rat01\.phantom\.snr",
        ),
        (lambda c: c.update(segmentaton={}), r"unknown key\(s\) \['segmentaton'\]"),
        (
            lambda c: c["animals"].update(rat09={"pre": "nowhere/pre.nii.gz"}),
            r"animals\.rat09\.pre: file not found",
        ),
    ],
)
def test_bad_config_names_the_key(mutate, match):
    cfg = _demo()
    mutate(cfg)
    with pytest.raises(ConfigError, match=match) as info:
        validate_config(cfg, SCHEMA, base_dir=ROOT)
    assert "\n" not in str(info.value)


def test_contours_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    c = Contours(skin=rng.normal(size=(4, 10, 3)), bone=rng.normal(size=(4, 10, 3)))
    save_contours(tmp_path / "c.npz", c)
    back = load_contours(tmp_path / "c.npz")
    np.testing.assert_array_equal(back.skin, c.skin)
    np.testing.assert_array_equal(back.bone, c.bone)


def test_contours_reject_mismatched_slices():
    with pytest.raises(ValueError, match="skin has 4 slices but bone has 3"):
        Contours(skin=np.zeros((4, 10, 3)), bone=np.zeros((3, 10, 3)))


def test_pose_round_trip_and_validation(tmp_path):
    p = Pose(
        indenter_axis=[0, -1, 0],
        tip_start_mm=[0, 6, 10],
        tip_end_mm=[0, 3, 10],
        depth_mm=2.0,
        bone_com_mm=[1, -1, 10],
        bone_rotation_deg=[1, 0, 0],
        bone_translation_mm=[0, 0.1, 0],
        extra={"residual_mm": 0.01},
    )
    save_pose(tmp_path / "pose.json", p)
    back = load_pose(tmp_path / "pose.json")
    np.testing.assert_allclose(back.tip_end_mm, [0, 3, 10])
    assert back.extra == {"residual_mm": 0.01}
    assert back.travel_mm == pytest.approx(3.0)
    with pytest.raises(ValueError, match="indenter_axis: not a unit vector"):
        Pose(
            indenter_axis=[0, -2, 0],
            tip_start_mm=[0, 0, 0],
            tip_end_mm=[0, 0, 0],
            depth_mm=0,
            bone_com_mm=[0, 0, 0],
            bone_rotation_deg=[0, 0, 0],
            bone_translation_mm=[0, 0, 0],
        )


def test_rigid_motion_keeps_centre_and_distances():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(20, 3))
    c = np.array([1.0, 2.0, 3.0])
    moved = apply_rigid(pts, rotation_deg=[10, -20, 5], centre_mm=c, translation_mm=[0.5, 0, 0])
    d0 = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    d1 = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    np.testing.assert_allclose(d0, d1, atol=1e-12)
    np.testing.assert_allclose(
        apply_rigid(c, rotation_deg=[10, -20, 5], centre_mm=c, translation_mm=[0, 0, 0]), c
    )


def test_euler_steps_compose_to_the_rotation():
    rv = [12.0, -7.0, 30.0]
    a, b, c = np.radians(euler_xyz_deg(rv))
    Rx = rotation_matrix([np.degrees(a), 0, 0])
    Ry = rotation_matrix([0, np.degrees(b), 0])
    Rz = rotation_matrix([0, 0, np.degrees(c)])
    np.testing.assert_allclose(Rz @ Ry @ Rx, rotation_matrix(rv), atol=1e-12)


def test_variant_names():
    from deeptissue.variants import parse_variant, variant_travel

    v = parse_variant("sphere_rx+15")
    assert (v.indenter, v.turn_axis, v.turn_deg) == ("sphere", "x", 15.0)
    assert parse_variant("bar").turn_axis is None
    with pytest.raises(ValueError, match="variant 'cube'"):
        parse_variant("cube")
    axis, start, end = variant_travel(
        v, axis=[0, -1, 0], tip_start_mm=[0, 5, 0], tip_end_mm=[0, 2, 0]
    )
    # turning -y by +15 deg about x tilts it toward -z; the travel length is kept
    np.testing.assert_allclose(
        axis, [0, -np.cos(np.radians(15)), -np.sin(np.radians(15))], atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.norm(end - start), 3.0)


def test_mesh_groups_put_each_indenter_shape_on_its_own_mesh():
    from deeptissue.variants import mesh_group_of, mesh_groups

    six = ["sphere", "bar", "sphere_rx+15", "sphere_rx-15", "sphere_rz+15", "sphere_rz-15"]
    assert mesh_groups(six) == {"all": six}  # the default: one mesh per animal
    g = mesh_groups(six, by="indenter")
    assert g == {
        "sphere": ["sphere", "sphere_rx+15", "sphere_rx-15", "sphere_rz+15", "sphere_rz-15"],
        "bar": ["bar"],
    }
    assert mesh_group_of("sphere_rz-15", g) == "sphere" and mesh_group_of("bar", g) == "bar"
    assert mesh_groups(six, by="animal") == {"all": six}
    assert mesh_groups(["bar_rx+15", "bar"], by="indenter") == {"bar": ["bar_rx+15", "bar"]}
    with pytest.raises(ValueError, match="model.mesh_groups: 'variant'"):
        mesh_groups(six, by="variant")
    with pytest.raises(ValueError, match="variant 'cube'"):
        mesh_groups(["cube"], by="indenter")
    with pytest.raises(ValueError, match=r"'sphere_rx\+30' is in no mesh group"):
        mesh_group_of("sphere_rx+30", g)
    # the schema knows the key, its default and its values
    cfg = validate_config(_demo(), SCHEMA)
    assert cfg["model"]["mesh_groups"] == "animal"
    bad = _demo()
    bad["model"] = {**bad.get("model", {}), "mesh_groups": "variant"}
    with pytest.raises(ConfigError, match="mesh_groups"):
        validate_config(bad, SCHEMA)


def test_solve_priority_starts_bars_and_deeper_indentations_first():
    from deeptissue.variants import solve_priority

    assert solve_priority("bar") > solve_priority("sphere")
    assert solve_priority("bar_rx+15", 1.5) > solve_priority(
        "sphere_rz-15", 3.0
    )  # any bar before any sphere
    assert solve_priority("sphere", 2.5) > solve_priority("sphere", 2.0) > solve_priority("sphere")
    assert solve_priority("bar", 2.5) > solve_priority("bar", 1.5)
    with pytest.raises(ValueError, match="variant 'cube'"):
        solve_priority("cube")


def test_script_log_captures_logging_stderr_and_the_failure(tmp_path):
    import logging
    import sys

    from deeptissue.io import script_log

    log = tmp_path / "job.log"
    with pytest.raises(ValueError, match="bad input"):
        with script_log(log, "solve"):
            logging.getLogger("deeptissue.x").info("step 1 done")
            print("from a library", file=sys.stderr)
            raise ValueError("bad input")
    text = log.read_text()
    assert "step 1 done" in text and "from a library" in text
    assert "solve failed" in text and "ValueError: bad input" in text
    # the handler is removed again: later logging does not write to the closed file
    logging.getLogger("deeptissue.x").info("after")
    assert "after" not in log.read_text()


def test_schema_solver_defaults_are_the_solvers_own():
    # a study run from the config and a solve called from Python use the same settings
    from deeptissue.fem.solver import SolverSettings, solver_settings_from_config

    cfg = validate_config(_demo(), SCHEMA, base_dir=ROOT)
    solver_cfg = cfg["fem"]["solver"]
    assert {"newton", "increments", "contact", "max_wall_s"} <= set(solver_cfg)
    assert {"rtol", "max_iterations"} <= set(solver_cfg["newton"]) and "gap_tol_rel" in solver_cfg[
        "contact"
    ]
    assert solver_settings_from_config(solver_cfg) == SolverSettings()
    # at most 20 settings, every one described
    props = load_schema(SCHEMA)["properties"]["fem"]["properties"]["solver"]["properties"]
    leaves = [k for k, v in props.items() if "properties" not in v] + [
        f"{g}.{k}" for g, v in props.items() if "properties" in v for k in v["properties"]
    ]
    assert len(leaves) <= 20, leaves
    with pytest.raises(ValueError, match=r"fem.solver.newton: unknown keys \['rtoll'\]"):
        solver_settings_from_config({"newton": {"rtoll": 1e-6}})
    with pytest.raises(ValueError, match=r"fem.solver: unknown keys \['penalty_factor'\]"):
        solver_settings_from_config({"penalty_factor": 30})
