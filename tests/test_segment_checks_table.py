"""Every check of one animal in one table (deeptissue.segment_checks.merge_checks, rule checks): the segmentation's
of each state and, with a during scan, the pose's, each row as its stage wrote it."""

import csv

from deeptissue.pose.checks import Check
from deeptissue.pose.checks import write_checks as write_pose_checks
from deeptissue.segment_checks import CHECKS_COLUMNS, SegmentationCheck, merge_checks, write_checks


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


SEG = [
    SegmentationCheck("slices_left_out", -1, 2.0, 12.0),
    SegmentationCheck("slice_left_out", 0, 1.0, 0.0),  # a warning
    SegmentationCheck("tibia_area_step", 3, 0.04, 0.6),
    SegmentationCheck("tibia_fibula_ratio", 3, float("nan"), 1.0, below=True),
    SegmentationCheck("skin_to_mask_mm", 3, 0.02, 0.1),
]


def test_a_pre_only_animal_has_its_segmentation_checks_in_checks_csv(tmp_path):
    write_checks(tmp_path / "seg_pre.csv", SEG)
    n = merge_checks(tmp_path / "checks.csv", segmentation={"pre": tmp_path / "seg_pre.csv"})
    rows = _rows(tmp_path / "checks.csv")
    assert n == len(SEG) == len(rows)
    assert list(rows[0]) == list(CHECKS_COLUMNS)
    got = [(r["stage"], r["check"], r["slice"], r["status"]) for r in rows]
    assert got == [
        ("segmentation_pre", "slices_left_out", "-1", "ok"),
        ("segmentation_pre", "slice_left_out", "0", "warn"),
        ("segmentation_pre", "tibia_area_step", "3", "ok"),
        ("segmentation_pre", "tibia_fibula_ratio", "3", "n/a"),
        ("segmentation_pre", "skin_to_mask_mm", "3", "ok"),
    ]
    # a check that only warns has a warning limit; the others stop the rule at theirs
    assert (rows[1]["limit"], rows[1]["fail_limit"]) == ("0", "")
    assert (rows[2]["limit"], rows[2]["fail_limit"]) == ("", "0.6")
    assert rows[1]["action"].startswith("this slice at an end of the stack")
    assert not any(r["stage"] == "pose" for r in rows)


def test_an_animal_with_a_during_scan_has_both_states_and_the_pose(tmp_path):
    write_checks(tmp_path / "seg_pre.csv", SEG[2:])
    write_checks(tmp_path / "seg_during.csv", SEG[4:])
    pose = [
        Check("bone_fit_rms_mm", 0.04, 0.03, 0.06, "warn", "pre/during mismatch: check the scans"),
        Check("bone_slices_used", 1.0, 0.75, 0.5, "ok", ""),
    ]
    write_pose_checks(tmp_path / "pose_checks.csv", pose)
    merge_checks(
        tmp_path / "checks.csv",
        segmentation={"pre": tmp_path / "seg_pre.csv", "during": tmp_path / "seg_during.csv"},
        pose=tmp_path / "pose_checks.csv",
    )
    rows = _rows(tmp_path / "checks.csv")
    assert [(r["stage"], r["check"]) for r in rows] == [
        ("segmentation_pre", "tibia_area_step"),
        ("segmentation_pre", "tibia_fibula_ratio"),
        ("segmentation_pre", "skin_to_mask_mm"),
        ("segmentation_during", "skin_to_mask_mm"),
        ("pose", "bone_fit_rms_mm"),
        ("pose", "bone_slices_used"),
    ]
    fit = rows[4]
    assert (fit["slice"], fit["value"], fit["limit"], fit["fail_limit"], fit["status"]) == (
        "",
        "0.04",
        "0.03",
        "0.06",
        "warn",
    )
    assert fit["action"] == "pre/during mismatch: check the scans"
