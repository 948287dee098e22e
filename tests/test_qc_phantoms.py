"""The QC checks on whole phantoms through the rules' functions (segment_files, run_pose): good scans pass,
the wrong inputs of the issue are refused or flagged (about 30 s per phantom, all slow)."""

import csv
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from deeptissue.imaging import write_nifti
from deeptissue.io import read_json
from deeptissue.phantom import PhantomSpec, make_phantom
from deeptissue.pose import PoseFiles, run_pose
from deeptissue.pose_error import PoseError
from deeptissue.segment import SegmentJob, segment_files

# config/config.yaml's rat01 and rat02
RAT01 = PhantomSpec(
    seed=1,
    depth_mm=2.0,
    tilt_deg=(5.0, -3.0),
    bone_rotation_deg=(1.0, -0.5, 0.8),
    bone_translation_mm=(0.05, -0.10, 0.02),
    snr=20,
)
RAT02 = PhantomSpec(
    seed=2,
    depth_mm=2.5,
    tilt_deg=(-8.0, 6.0),
    bone_rotation_deg=(-1.5, 0.8, 0.3),
    bone_translation_mm=(-0.08, -0.12, 0.04),
    snr=15,
)


@cache
def _phantom(name):
    spec = {
        "rat01": RAT01,
        "rat02": RAT02,
        "tilt60": replace(RAT01, tilt_deg=(60.0, 0.0)),
        "slices5": replace(RAT01, n_slices=5),
    }[name]
    return make_phantom(spec)


def _run(tmp_path, pre_of, during_of, animal="ratQ"):
    """Write the pre scan of one phantom and the during scan of another, segment both, pose; the checks' rows."""
    pre_ph, dur_ph = _phantom(pre_of), _phantom(during_of)
    pre_nii, dur_nii = tmp_path / f"{pre_of}_pre.nii.gz", tmp_path / f"{during_of}_during.nii.gz"
    write_nifti(pre_nii, pre_ph.pre, pre_ph.affine)
    write_nifti(dur_nii, dur_ph.during, dur_ph.affine)
    c = {st: tmp_path / f"{st}.npz" for st in ("pre", "during")}
    segment_files(
        SegmentJob(
            image=pre_nii,
            contours_out=c["pre"],
            qc_out=tmp_path / "pre.png",
            animal=animal,
            state="pre",
            settings={},
        )
    )
    segment_files(
        SegmentJob(
            image=dur_nii,
            contours_out=c["during"],
            qc_out=tmp_path / "during.png",
            animal=animal,
            state="during",
            settings={},
            reference=pre_nii,
            pre_contours=c["pre"],
        )
    )
    out = dict(
        pose_json=tmp_path / "pose.json",
        axis_png=tmp_path / "a.png",
        tip_png=tmp_path / "t.png",
        bone_png=tmp_path / "b.png",
        checks_csv=tmp_path / "checks.csv",
    )
    error = None
    try:
        run_pose(
            PoseFiles(
                during_nifti=dur_nii,
                pre_nifti=pre_nii,
                pre_contours=c["pre"],
                during_contours=c["during"],
                **out,
            ),
            animal=animal,
        )
    except PoseError as exc:
        error = str(exc)
    with open(out["checks_csv"]) as fh:
        rows = {r["check"]: r for r in csv.DictReader(fh)}
    return rows, error, pre_nii, dur_nii


@pytest.mark.slow
def test_good_scan_passes_every_check(tmp_path):
    rows, error, *_ = _run(tmp_path, "rat01", "rat01")
    assert error is None
    assert all(r["status"] == "ok" for r in rows.values()), {
        k: r["value"] for k, r in rows.items()
    }
    assert read_json(tmp_path / "pose.json")["qc_warnings"] == []


@pytest.mark.slow
def test_pre_of_one_animal_with_during_of_another_is_refused(tmp_path):
    rows, error, pre_nii, dur_nii = _run(tmp_path, "rat01", "rat02")
    assert rows["bone_fit_rms_mm"]["status"] == "fail"
    assert "pre/during mismatch" in error and "ratQ" in error
    assert str(pre_nii) in error and str(dur_nii) in error
    assert f"bone_fit_rms_mm {float(rows['bone_fit_rms_mm']['value']):.4g} > 0.06" in error
    assert not (tmp_path / "pose.json").exists()


@pytest.mark.slow
def test_indenter_tilted_60_deg_out_of_the_slices_is_refused(tmp_path):
    """The fluid column crosses the slices so steeply that 3.4 mm of it remain: axis 5 deg, depth 0.16 mm off."""
    rows, error, *_ = _run(tmp_path, "tilt60", "tilt60")
    assert rows["fluid_column_length_mm"]["status"] == "fail" and "fluid_column_length_mm" in error
    assert float(rows["fluid_column_length_mm"]["value"]) < 5.0


@pytest.mark.slow
def test_five_slices_are_flagged(tmp_path):
    """On 5 slices the bone translation is 0.12 mm off: its standard error warns, and the warning is in pose.json."""
    rows, error, *_ = _run(tmp_path, "slices5", "slices5")
    assert error is None
    assert rows["bone_translation_sd_mm"]["status"] == "warn"
    warnings = read_json(tmp_path / "pose.json")["qc_warnings"]
    assert any(w.startswith("bone_translation_sd_mm") for w in warnings)
    truth = _phantom("slices5").truth
    pose = read_json(tmp_path / "pose.json")
    assert (
        np.linalg.norm(np.subtract(pose["bone_translation_mm"], truth.bone_translation_mm)) > 0.03
    )
