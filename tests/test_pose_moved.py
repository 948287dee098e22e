"""The pose stage against a leg that moved in the cast between the scans, an oblique scan, and hand-given
quantities that no indentation gives.

Truths: the synthetic scene of tests/pose_synth.py (its during voxels moved by scipy.ndimage in
tests/moved_leg.py, its contours by the same millimetres), the digital phantoms' truth (tests/pose_phantom_cases.py),
and affines turned by a known angle.
"""

import csv
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from moved_leg import MOVES, move, shift_voxels
from test_pose import _scene

from deeptissue.contours import Contours, save_contours
from deeptissue.pose import (
    ACCURACY_TOLERANCES,
    MAX_SLICE_OBLIQUITY_DEG,
    LegGuard,
    Pose,
    PoseFiles,
    check_axial_slices,
    estimate_pose,
    pose_errors,
    register_leg,
    run_pose,
    slice_obliquity_deg,
)
from deeptissue.pose.checks import LIMITS
from deeptissue.pose.qc import travel_marks_mm
from deeptissue.pose_error import PoseError
from deeptissue.rigid import rotation_matrix

sys.path.insert(0, str(Path(__file__).parent))
PIXEL_MM = 0.1  # tests/pose_synth.py's grid


def _shifted_scene(pixels):
    """The synthetic scene with its during scan (voxels and contours) moved ``pixels`` (x, y)."""
    vol, A, pre, dur, truth = _scene(
        (8, -5), 2.0, rotation=(0.5, 0.5, -0.5), translation=(0.02, 0.03, 0.0)
    )
    d = np.array([pixels[0] * PIXEL_MM, pixels[1] * PIXEL_MM, 0.0])
    moved = Contours(skin=dur.skin + d, bone=dur.bone + d)
    return shift_voxels(vol, pixels), A, pre, moved, truth


@pytest.mark.parametrize("pixels", [(0, 0), (2, 0), (0, 5), (5, 0), (-3, 4)])
def test_a_leg_shifted_in_the_cast_is_corrected(pixels):
    vol, A, pre, dur, truth = _shifted_scene(pixels)
    pose, _ = estimate_pose(vol, A, pre, dur, animal="rat09")
    shift = np.hypot(*pixels) * PIXEL_MM
    assert pose.extra["leg_shift_mm"] == pytest.approx(shift, abs=0.002)
    np.testing.assert_allclose(
        pose.extra["leg_translation_mm"][:2], np.array(pixels) * PIXEL_MM, atol=0.002
    )
    assert pose.extra["leg_skin_residual_mm"] < LIMITS["leg_skin_residual_mm"].warn
    err = pose_errors(pose, truth)  # the unmoved scene's truth and test_pose's bounds
    assert err["axis_error_deg"] <= 1.0
    assert err["tip_end_error_mm"] <= 0.1 and err["tip_start_error_mm"] <= 0.1
    assert err["depth_error_mm"] <= 0.05
    assert err["bone_rotation_error_deg"] <= 0.05
    assert err["bone_translation_error_mm"] <= 0.005


def test_a_leg_shifted_20_pixels_is_refused_naming_the_shift_and_its_limit():
    vol, A, pre, dur, _ = _shifted_scene((0, 20))
    fail = LIMITS["leg_shift_mm"].fail
    with pytest.raises(
        PoseError,
        match=rf"animal rat09: leg_shift_mm 2(\.0+)? > {fail:g} \(the leg moved in the cast",
    ):
        estimate_pose(vol, A, pre, dur, animal="rat09")


def test_the_far_field_skin_measures_a_turn_about_the_leg():
    """An elliptic leg turned 3 deg about z: the registration gives the turn and the shift it implies."""
    th = np.radians(90.0) + 2 * np.pi * np.arange(120) / 120
    z = np.arange(20) - 9.5
    pre = np.stack(
        [np.column_stack([5.0 * np.cos(th), 4.2 * np.sin(th), np.full(120, zk)]) for zk in z]
    )
    R = rotation_matrix([0.0, 0.0, 3.0])
    centre = np.array([1.0, -0.5, 0.0])
    dur = (pre - centre) @ R.T + centre + [0.05, -0.02, 0.0]
    leg = register_leg(pre, dur, LegGuard(np.array([0.0, 20.0, 0.0]), 5.0))
    assert leg.rotation_deg == pytest.approx(3.0, abs=0.01)
    np.testing.assert_allclose(leg.to_pre(dur), pre, atol=0.002)
    assert leg.residual_mm < 0.002 and leg.residual_initial_mm > 0.05


def test_a_refused_leg_writes_its_rows_and_names_both_scans(tmp_path, caplog):
    vol, A, pre, dur, _ = _shifted_scene((20, 0))
    files = _write(tmp_path, vol, A, pre, dur)
    with pytest.raises(PoseError) as exc:
        run_pose(files, options={}, animal="rat09")
    # the log, which Snakemake keeps when it removes a failed rule's outputs, has the row too
    assert f"rat09 check leg_shift_mm 2 > {LIMITS['leg_shift_mm'].fail:g} (fail)" in caplog.text
    msg = str(exc.value)
    assert "animal rat09" in msg and str(files.during_nifti) in msg and str(files.pre_nifti) in msg
    assert f"leg_shift_mm 2 > {LIMITS['leg_shift_mm'].fail:g}" in msg
    with open(files.checks_csv) as fh:
        rows = {r["check"]: r for r in csv.DictReader(fh)}
    assert rows["leg_shift_mm"]["status"] == "fail"
    assert float(rows["leg_shift_mm"]["value"]) == pytest.approx(2.0, abs=0.002)
    assert float(rows["leg_shift_mm"]["fail_limit"]) == LIMITS["leg_shift_mm"].fail
    assert rows["leg_skin_residual_mm"]["status"] == "ok"
    assert not files.pose_json.exists()
    # the same rows beside it, in a file Snakemake does not remove with the failed rule's outputs
    kept = files.checks_csv.with_name("checks_failed.csv")
    assert kept.read_text() == files.checks_csv.read_text()


def test_a_corrected_leg_warns_in_checks_and_pose_json(tmp_path):
    vol, A, pre, dur, _ = _shifted_scene((0, 5))
    files = _write(tmp_path, vol, A, pre, dur)
    stale = files.checks_csv.with_name("checks_failed.csv")
    stale.write_text("left by a refused run\n")
    pose = run_pose(files, options={}, animal="rat09")
    assert not stale.exists()  # a run that passes removes a refused run's rows
    with open(files.checks_csv) as fh:
        rows = {r["check"]: r for r in csv.DictReader(fh)}
    assert rows["leg_shift_mm"]["status"] == "warn"
    assert float(rows["leg_shift_mm"]["value"]) == pytest.approx(0.5, abs=0.002)
    assert float(rows["leg_skin_residual_mm"]["limit"]) == LIMITS["leg_skin_residual_mm"].warn
    assert any(w.startswith("leg_shift_mm 0.5") for w in pose.extra["qc_warnings"])


def _write(tmp_path, vol, A, pre, dur, *, pre_affine=None) -> PoseFiles:
    nib.save(nib.Nifti1Image(vol.astype(np.float32), A), tmp_path / "during.nii.gz")
    nib.save(
        nib.Nifti1Image(np.zeros((8, 8, 4), np.float32), A if pre_affine is None else pre_affine),
        tmp_path / "pre.nii.gz",
    )
    save_contours(tmp_path / "pre.npz", pre)
    save_contours(tmp_path / "during.npz", dur)
    return PoseFiles(
        during_nifti=tmp_path / "during.nii.gz",
        pre_nifti=tmp_path / "pre.nii.gz",
        pre_contours=tmp_path / "pre.npz",
        during_contours=tmp_path / "during.npz",
        pose_json=tmp_path / "pose.json",
        axis_png=tmp_path / "axis.png",
        tip_png=tmp_path / "tip.png",
        bone_png=tmp_path / "bone.png",
        checks_csv=tmp_path / "checks.csv",
    )


# ---- oblique slices ------------------------------------------------------------------------------


def _turned(A, degrees, axis="x"):
    R = np.eye(4)
    R[:3, :3] = rotation_matrix(
        {"x": [degrees, 0, 0], "y": [0, degrees, 0], "z": [0, 0, degrees]}[axis]
    )
    return R @ A


@pytest.mark.parametrize("degrees, axis", [(10, "x"), (30, "x"), (-7, "y"), (2, "x")])
def test_slice_obliquity_of_a_turned_affine(degrees, axis):
    A = np.diag([0.1, 0.1, 1.0, 1.0])
    assert slice_obliquity_deg(_turned(A, degrees, axis)) == pytest.approx(abs(degrees), abs=1e-9)
    assert slice_obliquity_deg(_turned(A, 40, "z")) == pytest.approx(
        0.0, abs=1e-9
    )  # in-plane turn
    with pytest.raises(
        PoseError,
        match=rf"rat09 during x.nii: the slices are oblique, {abs(degrees):.3g} deg "
        rf"from axial \(limit {MAX_SLICE_OBLIQUITY_DEG:g} deg\)",
    ):
        check_axial_slices(_turned(A, degrees, axis), where="rat09 during x.nii")
    check_axial_slices(_turned(A, 0.5, axis), where="rat09 during x.nii")  # within the tolerance


@pytest.mark.parametrize("which", ["during", "pre"])
def test_an_oblique_scan_is_refused_before_any_work(tmp_path, which):
    vol, A, pre, dur, _ = _scene((0, 0), 2.0)
    oblique = _turned(A, 10, "x")
    if which == "during":
        files = _write(tmp_path, vol, oblique, pre, dur, pre_affine=A)
    else:
        files = _write(tmp_path, vol, A, pre, dur, pre_affine=oblique)
    path = files.during_nifti if which == "during" else files.pre_nifti
    with pytest.raises(
        PoseError, match=rf"animal rat09: {which} scan {path}: the slices are oblique, 10 deg"
    ):
        run_pose(files, options={}, animal="rat09")
    assert not files.checks_csv.exists() and not files.pose_json.exists()


# ---- hand-given quantities ----------------------------------------------------------------------


@pytest.mark.parametrize("axis", [[0, 0, 0], [float("nan"), -1, 0], [0, float("inf"), 0]])
def test_a_zero_or_non_finite_axis_override_is_refused_naming_the_key(axis):
    vol, A, pre, dur, _ = _scene((0, 0), 2.0)
    with pytest.raises(
        PoseError,
        match=r"animal rat09: pose_override\.indenter_axis .*(zero length|3 finite numbers)",
    ):
        estimate_pose(vol, A, pre, dur, animal="rat09", override={"indenter_axis": axis})


def test_a_tip_outside_the_leg_is_refused_naming_the_key():
    vol, A, pre, dur, truth = _scene((0, 0), 2.0)
    outside = (truth.tip_end_mm - 30.0 * truth.indenter_axis).tolist()  # 30 mm out along the axis
    with pytest.raises(
        PoseError,
        match=r"animal rat09: pose_override\.tip_end_mm .* lies outside the leg of the during scan \(3[0-9.]* mm from",
    ):
        estimate_pose(
            vol,
            A,
            pre,
            dur,
            animal="rat09",
            override={"indenter_axis": truth.indenter_axis.tolist(), "tip_end_mm": outside},
        )
    deep = (truth.tip_end_mm + 6.0 * truth.indenter_axis).tolist()  # past the leg's centre
    with pytest.raises(PoseError, match=r"pose_override\.tip_end_mm .*deeper|leg's radius"):
        estimate_pose(vol, A, pre, dur, animal="rat09", override={"tip_end_mm": deep})


def test_a_non_finite_depth_is_refused_by_the_pose_itself():
    with pytest.raises(ValueError, match=r"pose\.depth_mm: expected a finite number, got nan"):
        Pose(
            indenter_axis=[0, -1, 0],
            tip_start_mm=[0, 5, 0],
            tip_end_mm=[0, 3, 0],
            depth_mm=float("nan"),
            bone_com_mm=[0, 0, 0],
            bone_rotation_deg=[0, 0, 0],
            bone_translation_mm=[0, 0, 0],
        )


def test_the_tip_figure_draws_the_depth_between_skin_and_tip():
    vol, A, pre, dur, truth = _scene((8, -5), 2.0)
    pose, _ = estimate_pose(vol, A, pre, dur)
    marks = travel_marks_mm(pose)
    assert marks["end"] - marks["skin"] == pytest.approx(pose.depth_mm, abs=1e-9)
    assert marks["skin"] - marks["start"] == pytest.approx(
        1.0, abs=1e-9
    )  # start_backoff_mm above the skin
    assert marks["end"] == pytest.approx(truth.depth_mm, abs=0.05)


# ---- the digital phantoms, moved ----------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, move_name",
    [("rat01", m) for m in MOVES if m != "tilt3"]
    + [("rat02", "tilt3"), ("tilt25x-shallow", "y5")],
)
def test_moved_phantom_is_corrected_or_refused(name, move_name, tmp_path_factory):
    """Phantoms of the demo config (tests/pose_phantom_cases.py), segmented as the workflow does, their during
    scan moved: corrected within the unmoved case's accuracy tolerances, or refused by a leg check with its
    number and limit (a shift of 20 pixels, 1.95 mm; a tilt of 3 deg out of the slices)."""
    from pose_phantom_cases import segmented_contours

    from deeptissue.imaging import Volume
    from deeptissue.segment import segment_volume

    cache = tmp_path_factory.getbasetemp() / "phantoms"
    truth, during, affine, pre, _ = segmented_contours(name, supersample=4, cache=cache)
    moved = move(during, affine, move_name)
    dur, _ = segment_volume(Volume(moved, affine), state="during")
    kind, amount = MOVES[move_name]
    if move_name.endswith("20") or kind == "tilt":
        check = "leg_shift_mm" if kind == "shift" else "leg_skin_residual_mm"
        with pytest.raises(
            PoseError, match=rf"animal {name}: {check} [0-9.]+ > {LIMITS[check].fail:g} \("
        ) as exc:
            estimate_pose(moved, affine, pre, dur, animal=name)
        rows = {c.name: c for c in exc.value.checks}
        assert rows[check].status == "fail" and rows[check].fail_limit == LIMITS[check].fail
        return
    pose, _ = estimate_pose(moved, affine, pre, dur, animal=name)
    err = pose_errors(pose, truth)
    for key, tol in ACCURACY_TOLERANCES.items():
        assert err[key] <= tol, (key, err[key])
    if kind == "shift":
        assert pose.extra["leg_shift_mm"] == pytest.approx(
            np.hypot(*amount) * affine[0, 0], abs=0.005
        )
    else:
        assert pose.extra["leg_rotation_deg"] == pytest.approx(amount, abs=0.15)
    assert pose.extra["leg_skin_residual_mm"] <= LIMITS["leg_skin_residual_mm"].warn
