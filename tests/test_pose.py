"""Pose stage on synthetic inputs with known truth (tests/pose_synth.py builds them independently).

Truths: the capsule's axis/tip/depth used to draw the volume and the dimpled skin; the rigid motion
used to cut the moved bone at the slice planes; rigid-motion identities for the error measure.
"""

from pathlib import Path

import numpy as np
import pose_synth as ps
import pytest
import yaml

from deeptissue.bone_motion import BoneDistance, bone_centroid_mm, fit_bone_motion
from deeptissue.config import ConfigError, validate_config
from deeptissue.contours import Contours, save_contours
from deeptissue.fluid import inertia_axis
from deeptissue.pose import (
    Pose,
    PoseFiles,
    PoseOptions,
    estimate_pose,
    load_pose,
    pose_errors,
    run_pose,
    run_pose_accuracy,
)
from deeptissue.pose_error import PoseError
from deeptissue.rigid import BoneMotion, apply_rigid, rotation_matrix

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


def _scene(
    tilt,
    depth,
    *,
    blobs=(),
    rotation=(0, 0, 0),
    translation=(0, 0, 0),
    aim=(0.3, 0.0, 0.2),
    fluid=3.0,
    snr=None,
):
    """Synthetic during volume, pre/during contours and the true pose."""
    a = ps.axis_from_tilt(*tilt)
    entry = ps.circle_entry(a, aim_mm=aim)
    tip = entry + depth * a
    head = tip - 1.5 * a
    vol, A = ps.indenter_volume(head_mm=head, axis=a, blobs=blobs, fluid=fluid, subsamples=3)
    if snr:  # Rician noise, sigma = tissue intensity / snr
        rng = np.random.default_rng(12)
        vol = np.hypot(vol + rng.normal(0, 1 / snr, vol.shape), rng.normal(0, 1 / snr, vol.shape))
    bone_pre = ps.bone_stack()
    c = bone_centroid_mm(bone_pre)
    bone_dur = ps.bone_stack(rotation_deg=rotation, centre_mm=c, translation_mm=translation)
    pre = Contours(skin=ps.leg_skin(), bone=bone_pre)
    dur = Contours(skin=ps.leg_skin(head_mm=head, axis=a), bone=bone_dur)
    truth = Pose(
        indenter_axis=a,
        tip_start_mm=entry - a,
        tip_end_mm=tip,
        depth_mm=depth,
        bone_com_mm=c,
        bone_rotation_deg=rotation,
        bone_translation_mm=translation,
    )
    return vol, A, pre, dur, truth


@pytest.mark.slow
@pytest.mark.parametrize(
    "tilt, depth, snr",
    [
        ((0, 0), 1.0, None),
        ((25, 0), 1.0, None),
        ((0, 25), 3.0, 12),
        ((18, -18), 2.0, None),
        ((12, 4), 1.5, 12),
    ],
)
def test_pose_of_synthetic_indenter_within_tolerance(tilt, depth, snr):
    vol, A, pre, dur, truth = _scene(
        tilt, depth, rotation=(1.0, -0.5, 0.8), translation=(0.05, -0.10, 0.02), snr=snr
    )
    pose, _ = estimate_pose(
        vol, A, pre, dur, animal="synth", options=PoseOptions(bone_dof=6)
    )  # tapered bone
    err = pose_errors(pose, truth)
    assert err["axis_error_deg"] <= 1.0
    assert (
        err["tip_end_error_mm"] <= 0.1
    )  # measured <= 0.063 (axis 0.48 deg off at snr 12, partial volume)
    assert err["tip_start_error_mm"] <= 0.1
    assert err["depth_error_mm"] <= 0.05
    assert err["bone_rotation_error_deg"] <= 0.05
    assert err["bone_translation_error_mm"] <= 0.005
    assert pose.extra["tip_method"] == "head_sphere_fit"
    # the axis points from the indenter into the leg (the leg is centred on the z axis)
    assert pose.indenter_axis @ (np.zeros(3) - pose.indenter_com_mm) > 0


def test_deepest_vertex_fails_where_the_head_sphere_fit_does_not():
    """Oblique axis, shallow depth: the undeformed skin at the ROI rim lies deeper than the tip."""
    vol, A, pre, dur, truth = _scene((25, 0), 1.0)
    vertex, _ = estimate_pose(vol, A, pre, dur, options=PoseOptions(tip_method="vertex"))
    sphere, _ = estimate_pose(vol, A, pre, dur)
    assert pose_errors(vertex, truth)["tip_end_error_mm"] > 0.2
    assert pose_errors(sphere, truth)["tip_end_error_mm"] < 0.05


def test_inertia_axis_respects_voxel_size():
    """A 1 x 1 x 1 mm cube sampled as 10 x 10 x 1 voxels of 0.1 x 0.1 x 1 mm has isotropic inertia."""
    J = np.diag([0.1, 0.1, 1.0])
    ijk = np.argwhere(np.ones((10, 10, 1)))
    pts = ijk @ J.T
    _, _, moments = inertia_axis(pts, voxel_edges_mm=J)
    np.testing.assert_allclose(moments, 1 / 6, rtol=1e-12)  # (1^2 + 1^2) / 12 for a unit cube
    _, _, naive = inertia_axis(pts, voxel_edges_mm=np.zeros((3, 3)))
    assert (
        naive.max() - naive.min() > 0.05
    )  # without the voxel's own inertia the thick slice is lost


def test_fluid_found_among_noise_blobs_and_bright_tissue():
    blobs = [
        ((-9.0, -9.0, 3.0), 0.5, 3.0),
        ((9.0, 8.0, -4.0), 1.0, 3.0),  # noise outside the leg
        ((1.0, -1.5, 0.0), 2.0, 3.5),
    ]  # bright tissue inside the leg, bigger than the fluid column
    vol, A, pre, dur, truth = _scene((10, 5), 2.0, blobs=blobs)
    pose, _ = estimate_pose(vol, A, pre, dur, animal="rat09")
    err = pose_errors(pose, truth)
    assert err["axis_error_deg"] <= 1.0 and err["tip_end_error_mm"] <= 0.05
    assert (
        len(pose.extra["fluid_candidate_volumes_mm3"]) >= 2
    )  # a noise blob was a candidate, and lost


def test_no_fluid_is_a_clear_error():
    vol, A, pre, dur, _ = _scene((0, 0), 2.0, fluid=1.0)  # fluid as dark as tissue: nothing bright
    with pytest.raises(PoseError, match="animal rat09: no contrast fluid found"):
        estimate_pose(vol, A, pre, dur, animal="rat09")


def test_two_similar_components_are_ambiguous():
    vol, A, pre, dur, _ = _scene((0, 0), 2.0)
    vol[10:80, 30:50, 8:11] = 3.0  # a second fluid-like bar outside the leg, as big as the column
    with pytest.raises(
        PoseError, match="animal rat09: several candidate contrast-fluid components"
    ):
        estimate_pose(vol, A, pre, dur, animal="rat09")


def test_axis_missing_the_skin_is_a_clear_error():
    vol, A, pre, dur, _ = _scene((0, 0), 2.0)
    with pytest.raises(PoseError, match="animal rat09: the indenter axis does not meet"):
        estimate_pose(
            vol, A, pre, dur, animal="rat09", override={"indenter_axis": [1.0, 0.0, 0.0]}
        )


def test_unmatched_bone_slices_are_a_clear_error():
    vol, A, pre, dur, _ = _scene((0, 0), 2.0)
    short = Contours(skin=dur.skin[:-1], bone=dur.bone[:-1])
    with pytest.raises(
        PoseError,
        match="animal rat09: during bone contours cannot be matched.*19 slices during vs 20 pre",
    ):
        estimate_pose(vol, A, pre, short, animal="rat09")


def test_override_gets_past_an_unreadable_scan():
    vol, A, pre, dur, truth = _scene((0, 0), 2.0, fluid=1.0)  # no fluid visible
    short = Contours(skin=dur.skin[:-1], bone=dur.bone[:-1])  # bone cannot be matched either
    override = {
        "indenter_axis": truth.indenter_axis.tolist(),
        "tip_end_mm": truth.tip_end_mm.tolist(),
        "bone_rotation_deg": [0.5, 0.0, 0.0],
        "bone_translation_mm": [0.0, 0.1, 0.0],
    }
    pose, _ = estimate_pose(vol, A, pre, short, animal="rat09", override=override)
    np.testing.assert_allclose(pose.tip_end_mm, truth.tip_end_mm)
    np.testing.assert_allclose(pose.bone_rotation_deg, [0.5, 0, 0])
    # start and depth follow from the hand axis and tip against the undeformed skin
    assert pose_errors(pose, truth)["tip_start_error_mm"] < 0.01
    assert pose.depth_mm == pytest.approx(2.0, abs=0.01)
    assert pose.extra["overrides"] == sorted(override)


# ---- tibia ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "rotation, translation",
    [((3.0, 0.0, 0.0), (0.0, 0.0, 0.1)), ((-2.0, 2.0, 1.5), (-0.08, 0.10, -0.05))],
)
def test_bone_motion_surface_fit_recovers_truth(rotation, translation):
    pre = ps.bone_stack()
    c = bone_centroid_mm(pre)
    dur = ps.bone_stack(rotation_deg=rotation, centre_mm=c, translation_mm=translation)
    m = fit_bone_motion(pre, dur, dof=6)  # the synthetic bone tapers and bends: z shift observable
    assert np.linalg.norm(np.subtract(m.motion.rotation_deg, rotation)) < 0.01
    assert np.linalg.norm(np.subtract(m.motion.translation_mm, translation)) < 0.002
    # the centroid shift alone is biased: the slab cuts a different piece of the moved bone
    assert np.linalg.norm(m.com_shift_mm - translation) > 0.05
    # nearest-vertex distances between stacks at the same z planes are biased by through-plane motion
    v = fit_bone_motion(pre, dur, distance=BoneDistance("vertex"), dof=3)
    assert np.linalg.norm(np.subtract(v.motion.rotation_deg, rotation)) > 3 * np.linalg.norm(
        np.subtract(m.motion.rotation_deg, rotation)
    )
    assert v.rms_final_mm > 10 * m.rms_final_mm


def test_fibula_resolves_the_shift_along_a_prismatic_tibia():
    """A prism along z cannot show a shift along z; a fibula running obliquely to it, moved with it
    as one rigid body, can (its sections move across the slice by 0.3 mm per mm of shift)."""
    rot, tr = np.array([1.0, -0.5, 0.8]), np.array([0.03, -0.02, 0.12])
    pre_t = ps.bone_stack(body=ps.prism_body)
    c = bone_centroid_mm(pre_t)
    dur_t = ps.bone_stack(body=ps.prism_body, rotation_deg=rot, centre_mm=c, translation_mm=tr)
    pre_f = ps.bone_stack(body=ps.fibula_body)
    dur_f = ps.bone_stack(body=ps.fibula_body, rotation_deg=rot, centre_mm=c, translation_mm=tr)
    m = fit_bone_motion(pre_t, dur_t, fibula_pre_mm=pre_f, fibula_during_mm=dur_f, dof=6)
    assert m.fibula_slices == (20, 20)
    np.testing.assert_allclose(m.motion.centre_mm, c)  # the centre stays the tibia's
    assert np.linalg.norm(m.motion.rotation_deg - rot) < 0.01
    assert np.linalg.norm(m.motion.translation_mm - tr) < 0.002
    # the tibia alone leaves the shift along z where the centroid put it (a prism's centroid hardly moves)
    alone = fit_bone_motion(pre_t, dur_t, dof=6)
    assert alone.fibula_slices == (0, 0)
    assert abs(alone.motion.translation_mm[2] - tr[2]) > 0.05
    # slices without a fibula (NaN rows) are left out, and during sections the pre fibula does not
    # reach are not matched to its end: on 14 common slices the fibula still resolves z
    pre_gap, dur_gap = pre_f.copy(), dur_f.copy()
    pre_gap[:3], dur_gap[-3:] = np.nan, np.nan
    m = fit_bone_motion(pre_t, dur_t, fibula_pre_mm=pre_gap, fibula_during_mm=dur_gap, dof=6)
    assert m.fibula_slices == (17, 14)  # pre slices, common slices
    assert np.linalg.norm(m.motion.translation_mm - tr) < 0.003
    # with 0.005 mm of contour noise the shift along z stays well within the 0.03 mm tolerance
    rng = np.random.default_rng(8)
    noisy = [a + rng.normal(0, 0.005, a.shape) * [1, 1, 0] for a in (pre_t, dur_t, pre_f, dur_f)]
    m = fit_bone_motion(
        noisy[0], noisy[1], fibula_pre_mm=noisy[2], fibula_during_mm=noisy[3], dof=6
    )
    assert np.linalg.norm(m.motion.translation_mm - tr) < 0.015


def test_bone_dof_auto_uses_the_fibula_or_falls_back(caplog):
    """bone_dof 'auto': 6 with a fibula in both states; without one, 5 and a log line saying why."""
    import logging

    vol, A, pre, dur, truth = _scene(
        (0, 0), 2.0, rotation=(0.5, 0.0, 0.3), translation=(0.02, 0.0, 0.1)
    )
    with caplog.at_level(logging.INFO, logger="deeptissue.pose"):
        pose, _ = estimate_pose(vol, A, pre, dur, animal="rat09")
    assert pose.extra["bone_dof"] == 5 and pose.extra["bone_fibula_slices"] == [0, 0]
    assert "animal rat09: bone_dof auto -> 5: no usable fibula contours" in caplog.text
    # the same scene with a fibula that moved with the bone: 6 DOF, the shift along z resolved
    c = bone_centroid_mm(pre.bone)
    fib_pre = ps.bone_stack(body=ps.fibula_body)
    fib_dur = ps.bone_stack(
        body=ps.fibula_body,
        rotation_deg=truth.bone_rotation_deg,
        centre_mm=c,
        translation_mm=truth.bone_translation_mm,
    )
    pre_f = Contours(skin=pre.skin, bone=pre.bone, fibula=fib_pre)
    dur_f = Contours(skin=dur.skin, bone=dur.bone, fibula=fib_dur)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="deeptissue.pose"):
        pose, _ = estimate_pose(vol, A, pre_f, dur_f, animal="rat09")
    assert pose.extra["bone_dof"] == 6 and pose.extra["bone_fibula_slices"] == [20, 20]
    assert "bone_dof auto -> 6: tibia and fibula fitted together" in caplog.text
    assert pose_errors(pose, truth)["bone_translation_error_mm"] < 0.002
    # a fibula on too few slices of one state is not used
    few = fib_dur.copy()
    few[2:] = np.nan  # 2 slices
    pose, _ = estimate_pose(
        vol, A, pre_f, Contours(skin=dur.skin, bone=dur.bone, fibula=few), animal="rat09"
    )
    assert pose.extra["bone_dof"] == 5
    with pytest.raises(ValueError, match="bone_dof must be 3, 5, 6 or 'auto'"):
        estimate_pose(vol, A, pre_f, dur_f, animal="rat09", options=PoseOptions(bone_dof=4))


def test_zero_bone_rotation_comes_back_as_zero_with_noise():
    """0.01 mm contour noise on a ~2 mm bone: no spurious rotation beyond the noise (measured 0.13 deg)."""
    rng = np.random.default_rng(5)
    pre = ps.bone_stack() + rng.normal(0, 0.01, (20, 100, 3)) * [1, 1, 0]
    dur = ps.bone_stack() + rng.normal(0, 0.01, (20, 100, 3)) * [1, 1, 0]
    m = fit_bone_motion(pre, dur)
    assert np.linalg.norm(m.motion.rotation_deg) < 0.2
    assert np.linalg.norm(m.motion.translation_mm) < 0.01


def test_pose_errors_compare_motions_not_parameters():
    """The same motion expressed about another centre has zero error (t' = t + (R - I)(c' - c))."""
    rot, c, t = (
        np.array([2.0, -1.0, 0.5]),
        np.array([0.5, -1.0, 0.0]),
        np.array([0.05, 0.02, -0.03]),
    )
    c2 = c + [0.4, -0.3, 1.0]
    t2 = t + (rotation_matrix(rot) - np.eye(3)) @ (c2 - c)
    pts = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_allclose(
        apply_rigid(pts, rotation_deg=rot, centre_mm=c, translation_mm=t),
        apply_rigid(pts, rotation_deg=rot, centre_mm=c2, translation_mm=t2),
        atol=1e-12,
    )
    base = dict(
        indenter_axis=[0, -1, 0],
        tip_start_mm=[0, 6, 0],
        tip_end_mm=[0, 3, 0],
        depth_mm=2.0,
        bone_rotation_deg=rot,
    )
    e = pose_errors(
        Pose(**base, bone_com_mm=c2, bone_translation_mm=t2),
        Pose(**base, bone_com_mm=c, bone_translation_mm=t),
    )
    assert e["bone_translation_error_mm"] < 1e-12 and e["bone_rotation_error_deg"] < 1e-9


def test_bone_motion_of_a_pose_moves_points_as_pose_json_says():
    """x -> R (x - bone_com_mm) + bone_com_mm + bone_translation_mm, R from the rotation vector (scipy)."""
    from scipy.spatial.transform import Rotation

    rot, c, t = (
        np.array([2.0, -1.0, 0.5]),
        np.array([0.5, -1.0, 4.0]),
        np.array([0.05, 0.02, -0.03]),
    )
    pose = Pose(
        indenter_axis=[0, -1, 0],
        tip_start_mm=[0, 6, 0],
        tip_end_mm=[0, 3, 0],
        depth_mm=2.0,
        bone_com_mm=c,
        bone_rotation_deg=rot,
        bone_translation_mm=t,
    )
    motion = pose.bone_motion
    assert motion == BoneMotion(
        rotation_deg=tuple(rot), centre_mm=tuple(c), translation_mm=tuple(t)
    )
    assert all(
        type(x) is float for x in motion.rotation_deg + motion.centre_mm + motion.translation_mm
    )
    pts = np.random.default_rng(1).normal(size=(4, 5, 3))
    R = Rotation.from_rotvec(np.radians(rot)).as_matrix()
    np.testing.assert_allclose(
        motion.apply(pts), np.einsum("ij,abj->abi", R, pts - c) + c + t, atol=1e-12
    )
    np.testing.assert_allclose(BoneMotion().apply(pts), pts)
    with pytest.raises(ValueError, match=r"BoneMotion\.centre_mm: expected 3 numbers"):
        BoneMotion(centre_mm=(1.0, 2.0))


# ---- files, rule glue and config -----------------------------------------------------------------


def test_run_pose_writes_pose_figures_and_accuracy(tmp_path):
    import nibabel as nib

    vol, A, pre, dur, truth = _scene(
        (8, -5), 2.0, rotation=(0.5, 0.5, -0.5), translation=(0.02, 0.03, 0.0)
    )
    nib.save(nib.Nifti1Image(vol.astype(np.float32), A), tmp_path / "during.nii.gz")
    save_contours(tmp_path / "pre.npz", pre)
    save_contours(tmp_path / "during.npz", dur)
    out = {k: tmp_path / f"{k}.png" for k in ("axis", "tip", "bone")}
    run_pose(
        PoseFiles(
            during_nifti=tmp_path / "during.nii.gz",
            pre_contours=tmp_path / "pre.npz",
            during_contours=tmp_path / "during.npz",
            pose_json=tmp_path / "pose.json",
            axis_png=out["axis"],
            tip_png=out["tip"],
            bone_png=out["bone"],
        ),
        options={},
        animal="synth",
    )
    assert all(p.stat().st_size > 10_000 for p in out.values())
    pose = load_pose(tmp_path / "pose.json")
    assert pose_errors(pose, truth)["tip_end_error_mm"] < 0.05
    (tmp_path / "truth.json").write_text(__import__("json").dumps(truth.to_dict()))
    rows = run_pose_accuracy(
        pose_json=tmp_path / "pose.json",
        truth_json=tmp_path / "truth.json",
        csv_path=tmp_path / "acc.csv",
    )
    assert {r["quantity"] for r in rows} >= {
        "axis_error_deg",
        "depth_error_mm",
        "bone_rotation_error_deg",
    }
    assert all(r["within_tolerance"] in (True, "") for r in rows)
    assert (
        (tmp_path / "acc.csv").read_text().startswith("quantity,error,tolerance,within_tolerance")
    )


def test_pose_config_and_override_schema():
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    cfg["animals"]["rat01"]["pose_override"] = {
        "indenter_axis": [0, -1, 0],
        "tip_end_mm": [0, 3, 0],
    }
    out = validate_config(cfg, SCHEMA, base_dir=ROOT)
    assert out["pose"]["roi_diameter_mm"] == 5.0 and out["pose"]["fluid_threshold"] is None
    assert PoseOptions.from_config(out["pose"]) == PoseOptions()
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    cfg["animals"]["rat01"]["pose_override"] = {"tip_end": [0, 3, 0]}
    with pytest.raises(
        ConfigError, match=r"animals\.rat01\.pose_override: unknown key\(s\) \['tip_end'\]"
    ):
        validate_config(cfg, SCHEMA, base_dir=ROOT)
