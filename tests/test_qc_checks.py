"""QC checks of the imaging estimates (deeptissue.pose.checks): status against the limits, the table, the
message that stops the rule, and the warnings carried into summary.json."""

import csv
from dataclasses import replace

import numpy as np
import pytest

from deeptissue.contours import Contours
from deeptissue.io import write_json
from deeptissue.pose import Pose
from deeptissue.pose.checks import (
    LIMITS,
    evaluate_checks,
    failed_message,
    tibia_steps,
    warnings_of,
    write_checks,
)
from deeptissue.summary import Summary, qc_warnings_of


def _stack(centres, radius=0.9, n=40):
    """Circular tibia sections (radius mm) centred at ``centres`` (n_slices, 2), slices 1 mm apart."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    out = []
    for k, (cx, cy) in enumerate(centres):
        r = radius[k] if np.ndim(radius) else radius
        out.append(
            np.column_stack([cx + r * np.cos(th), cy + r * np.sin(th), np.full(n, float(k))])
        )
    return np.stack(out)


def _contours(centres, radius=0.9):
    bone = _stack(centres, radius)
    return Contours(skin=_stack(centres, 5.0), bone=bone)


def _pose(**extra):
    base = dict(
        bone_rms_final_mm=0.01,
        bone_slices_used=[10, 10],
        axis_inertia_vs_cylinder_deg=0.3,
        fluid_column_length_mm=9.0,
        bone_fit_sd=[0.003, 0.003, 0.005, 0.0003, 0.0003],
        leg_shift_mm=0.001,
        leg_rotation_deg=-0.02,
        leg_skin_residual_mm=0.011,
    )
    base.update(extra)
    return Pose(
        indenter_axis=[0, -1, 0],
        tip_start_mm=[0, 5, 0],
        tip_end_mm=[0, 3, 0],
        depth_mm=2.0,
        bone_com_mm=[0, 0, 4.5],
        bone_rotation_deg=[0, 0, 0],
        bone_translation_mm=[0, 0, 0],
        extra=base,
    )


STRAIGHT = [(0.02 * k, -0.01 * k) for k in range(10)]


def test_tibia_steps_of_a_drifting_shaft_and_a_swap():
    jump, area = tibia_steps(_contours(STRAIGHT))
    assert np.isclose(jump, np.hypot(0.02, 0.01)) and np.isclose(area, 0.0, atol=1e-9)
    swapped = list(STRAIGHT)
    swapped[6] = (3.5, -1.5)  # the fibula, 3.8 mm away, taken for the tibia on one slice
    radius = np.full(10, 0.9)
    radius[6] = 0.42
    jump, area = tibia_steps(_contours(swapped, radius))
    assert jump > 3.0 and np.isclose(area, 2 * np.log(0.9 / 0.42), rtol=1e-3)


def test_good_estimates_pass_every_check():
    c = _contours(STRAIGHT)
    checks = evaluate_checks(_pose(), c, c)
    assert {ch.name for ch in checks} == set(LIMITS)
    assert all(ch.status == "ok" and ch.action == "" for ch in checks), checks
    assert (
        warnings_of(checks) == []
        and failed_message(checks, animal="rat9", pre_file="a", during_file="b") is None
    )


def test_mismatch_fails_naming_animal_files_and_number():
    c = _contours(STRAIGHT)
    checks = evaluate_checks(_pose(bone_rms_final_mm=0.19), c, c)
    msg = failed_message(
        checks,
        animal="rat9",
        pre_file="scans/rat9_pre.nii.gz",
        during_file="scans/rat7_during.nii.gz",
    )
    assert (
        "animal rat9" in msg
        and "scans/rat9_pre.nii.gz" in msg
        and "scans/rat7_during.nii.gz" in msg
    )
    assert "pre/during mismatch" in msg
    assert f"bone_fit_rms_mm 0.19 > {LIMITS['bone_fit_rms_mm'].fail:.4g}" in msg


def test_warning_between_the_limits_and_below_limits():
    c = _contours(STRAIGHT)
    lim = LIMITS["axis_inertia_vs_cylinder_deg"]
    checks = evaluate_checks(
        _pose(axis_inertia_vs_cylinder_deg=(lim.warn + lim.fail) / 2, bone_slices_used=[6, 10]),
        c,
        c,
    )
    by = {ch.name: ch for ch in checks}
    assert by["axis_inertia_vs_cylinder_deg"].status == "warn"
    assert (
        by["bone_slices_used"].status == "warn"
    )  # 0.6 of the slices: below the 0.75 warning, above 0.5
    assert (
        by["bone_slices_used"].describe()
        == f"bone_slices_used 0.6 < {LIMITS['bone_slices_used'].warn:.4g}"
    )
    assert (
        len(warnings_of(checks)) == 2
        and failed_message(checks, animal="a", pre_file="p", during_file="d") is None
    )


def test_steep_indenter_fails_and_an_unrefined_axis_warns():
    c = _contours(STRAIGHT)
    checks = evaluate_checks(
        _pose(fluid_column_length_mm=3.4, axis_inertia_vs_cylinder_deg=float("nan")), c, c
    )
    by = {ch.name: ch for ch in checks}
    assert by["fluid_column_length_mm"].status == "fail"
    assert by["axis_inertia_vs_cylinder_deg"].status == "warn"
    assert (
        by["axis_inertia_vs_cylinder_deg"].describe()
        == "axis_inertia_vs_cylinder_deg not measured"
    )
    msg = failed_message(checks, animal="ratX", pre_file="p.nii", during_file="d.nii")
    assert f"fluid_column_length_mm 3.4 < {LIMITS['fluid_column_length_mm'].fail:.4g}" in msg


def test_few_slices_warn_through_the_fit_errors():
    c = _contours(STRAIGHT)
    checks = evaluate_checks(
        _pose(bone_fit_sd=[0.0137, 0.0137, 0.0063, 0.0004, 0.0006, 0.0158]), c, c
    )
    assert [ch.name for ch in checks if ch.status != "ok"] == ["bone_translation_sd_mm"]


def test_swapped_bone_fails():
    pre = _contours(STRAIGHT)
    swapped = list(STRAIGHT)
    swapped[6] = (3.5, -1.5)
    checks = evaluate_checks(_pose(), pre, _contours(swapped))
    failed = [ch.name for ch in checks if ch.status == "fail"]
    assert failed == ["tibia_centroid_jump_during_mm_per_mm"]


def test_hand_given_bone_motion_has_no_fit_checks():
    c = _contours(STRAIGHT)
    p = _pose()
    p = replace(p, extra={"overrides": ["bone_rotation_deg", "bone_translation_mm"]})
    names = {ch.name for ch in evaluate_checks(p, c, c)}
    assert "bone_fit_rms_mm" not in names and "tibia_centroid_jump_pre_mm_per_mm" in names


def test_checks_csv_and_warnings_into_the_summary(tmp_path):
    c = _contours(STRAIGHT)
    checks = evaluate_checks(_pose(axis_inertia_vs_cylinder_deg=3.0), c, c)
    write_checks(tmp_path / "checks.csv", checks)
    with open(tmp_path / "checks.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["check", "value", "limit", "fail_limit", "status", "action"]
    row = [r for r in rows if r["check"] == "axis_inertia_vs_cylinder_deg"][0]
    assert row["status"] == "warn" and float(row["value"]) == 3.0 and row["action"]
    pose = _pose(qc_warnings=warnings_of(checks))
    write_json(tmp_path / "pose.json", pose.to_dict())
    text = qc_warnings_of(tmp_path / "pose.json")
    assert (
        text
        == f"axis_inertia_vs_cylinder_deg 3 > {LIMITS['axis_inertia_vs_cylinder_deg'].warn:.4g}"
    )
    s = Summary(animal="a", variant="sphere", converged=True, qc_warnings=text)
    assert Summary.from_dict(s.to_dict()).qc_warnings == text
    write_json(tmp_path / "pose2.json", _pose().to_dict())
    assert qc_warnings_of(tmp_path / "pose2.json") is None


@pytest.mark.parametrize("name", sorted(LIMITS))
def test_limits_are_ordered(name):
    lim = LIMITS[name]
    assert (lim.fail < lim.warn) if lim.below else (lim.fail > lim.warn)
    assert lim.action
