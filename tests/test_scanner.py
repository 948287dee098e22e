"""Scanner data in: a phantom written as DICOM in every orientation comes back with the same voxels and world mm.

The truth is the phantom's own voxels and affine (quantised as DICOM stores them); the series is
written with pydicom (tests/scanner_synth.py) and read back through dcm2niix by
:func:`deeptissue.scanner.read_dicom`. Comparison is in world coordinates: both volumes are brought
to the closest canonical (RAS) voxel order, then voxels and the world positions of the corners must
agree to 0.01 mm.
"""

import json
import shutil
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from scanner_synth import (
    quantised,
    reorder,
    rotated,
    write_enhanced,
    write_paravision,
    write_series,
)

from deeptissue.config import ConfigError, validate_config
from deeptissue.imaging import ImagingError, load_nifti
from deeptissue.phantom import PhantomSpec, make_phantom
from deeptissue.scanner import (
    dicom_series,
    read_bruker,
    read_dicom,
    read_scan,
    scan_kind,
    write_scan,
)

WORLD_TOL_MM = 0.01


@pytest.fixture(scope="module")
def ph():
    return make_phantom(PhantomSpec(n_pixels=40, n_slices=8, fov_mm=25.0, supersample=2, seed=3))


def _canonical(data, affine):
    img = nib.as_closest_canonical(
        nib.Nifti1Image(np.asarray(data, np.float32), np.asarray(affine, float))
    )
    return np.asarray(img.dataobj, np.float32), img.affine


def assert_same_geometry(data0, affine0, data1, affine1):
    """Same voxels (to float32 rounding of the DICOM slope) at the same world positions (<= 0.01 mm)."""
    c0, a0 = _canonical(data0, affine0)
    c1, a1 = _canonical(data1, affine1)
    assert c0.shape == c1.shape
    np.testing.assert_allclose(c1, c0, rtol=0, atol=1e-5 * float(np.abs(c0).max()))
    corners = (
        np.array(np.meshgrid(*[[0, n - 1] for n in c0.shape], indexing="ij")).reshape(3, -1).T
    )
    w0 = corners @ a0[:3, :3].T + a0[:3, 3]
    w1 = corners @ a1[:3, :3].T + a1[:3, 3]
    assert np.abs(w0 - w1).max() <= WORLD_TOL_MM


# (voxel axis permutation, flips, rotation of the acquisition deg, DICOM PatientPosition)
ORIENTATIONS = {
    "axial_head_first": ((0, 1, 2), (False, False, False), None, "HFS"),
    "axial_feet_first": ((0, 1, 2), (True, False, True), None, "FFS"),
    "axial_prone": ((0, 1, 2), (True, True, False), None, "HFP"),
    "coronal": ((0, 2, 1), (False, False, False), None, "HFS"),
    "coronal_feet_first": ((0, 2, 1), (True, True, True), None, "FFS"),
    "sagittal": ((1, 2, 0), (False, True, False), None, "HFS"),
    "sagittal_feet_first_prone": ((2, 1, 0), (False, True, True), None, "FFP"),
    "oblique": ((0, 1, 2), (False, False, False), (12.0, -20.0, 7.0), "HFS"),
    "oblique_coronal_feet_first": ((2, 0, 1), (True, False, False), (-8.0, 15.0, 30.0), "FFS"),
}


def assert_read_back(ph, affine, aff, vol, *, axial):
    """A converted stack (vol) of the phantom written with voxel-to-world ``aff`` (the phantom's ``affine``
    reordered): the same voxels at the same world positions; the slice axis stays the third voxel axis
    (later stages read slices as data[:, :, k]); an axial stack comes back ordered and flipped toward
    +x, +y, +z world, as the phantom's own array."""
    assert_same_geometry(quantised(ph.pre), affine, vol.data, vol.affine)
    normal_in, normal_out = (
        aff[:3, 2] / np.linalg.norm(aff[:3, 2]),
        vol.affine[:3, 2] / np.linalg.norm(vol.affine[:3, 2]),
    )
    assert abs(abs(normal_in @ normal_out) - 1.0) < 1e-6
    if axial:
        np.testing.assert_allclose(
            vol.data, quantised(ph.pre), rtol=0, atol=1e-5 * float(ph.pre.max())
        )
        np.testing.assert_allclose(vol.affine, ph.affine, atol=1e-5)


@pytest.mark.parametrize("name", sorted(ORIENTATIONS))
def test_dicom_geometry_round_trip(ph, tmp_path, name):
    perm, flip, rot, position = ORIENTATIONS[name]
    affine = ph.affine if rot is None else rotated(ph.affine, rot)
    data, aff = reorder(ph.pre, affine, perm=perm, flip=flip)
    # the reordered voxels are the phantom's at the same world positions (checks the writer's helper)
    assert_same_geometry(ph.pre, affine, data, aff)
    write_series(tmp_path / "dcm", data, aff, patient_position=position)
    vol, meta = read_dicom(tmp_path / "dcm", animal="rat")
    assert_read_back(ph, affine, aff, vol, axial=perm == (0, 1, 2) and rot is None)
    assert all(vol.affine[np.argmax(np.abs(vol.affine[:3, a])), a] > 0 for a in range(3))
    assert meta["converter"] == "dcm2niix" and meta["patient_position"] == position
    assert (
        meta["field_strength_t"] == 7.0
        and meta["echo_time_ms"] == 12.0
        and meta["repetition_time_ms"] == 2500.0
    )


def test_dicom_files_in_shuffled_order(ph, tmp_path):
    """Slice order on disk (file names, instance numbers) does not decide the geometry: positions do."""
    write_series(tmp_path / "dcm", ph.pre, ph.affine, slices=[3, 0, 7, 5, 1, 6, 2, 4])
    vol, _ = read_dicom(tmp_path / "dcm")
    assert_same_geometry(quantised(ph.pre), ph.affine, vol.data, vol.affine)


def test_scan_kinds_and_sidecar(ph, tmp_path):
    write_series(tmp_path / "scans" / "pre", ph.pre, ph.affine)
    assert scan_kind("scans/pre", base_dir=tmp_path) == "dicom"
    assert scan_kind({"dicom": "scans", "series": 1}) == "dicom"
    assert scan_kind({"bruker": "study", "scan": 5}) == "bruker"
    assert scan_kind("pre.nii.gz", base_dir=tmp_path) == "nifti"
    vol, meta = read_scan("scans/pre", base_dir=tmp_path, animal="rat")
    write_scan(vol, meta, tmp_path / "out" / "pre.nii.gz", tmp_path / "out" / "pre.json")
    back = load_nifti(tmp_path / "out" / "pre.nii.gz")
    assert_same_geometry(quantised(ph.pre), ph.affine, back.data, back.affine)
    side = json.loads((tmp_path / "out" / "pre.json").read_text())
    assert side["kind"] == "dicom" and side["shape"] == [40, 40, 8]
    assert side["orientation"] == "RAS"
    # an axial series reads back as the very array and affine of its NIfTI twin
    np.testing.assert_allclose(
        back.data, quantised(ph.pre), rtol=0, atol=1e-5 * float(ph.pre.max())
    )
    np.testing.assert_allclose(back.affine, ph.affine, atol=1e-5)
    np.testing.assert_allclose(side["voxel_mm"], [25 / 40, 25 / 40, 1.0])
    # a NIfTI entry reads as before, with the same sidecar keys
    vol2, meta2 = read_scan("out/pre.nii.gz", base_dir=tmp_path)
    np.testing.assert_array_equal(vol2.data, back.data)
    assert meta2["kind"] == "nifti" and set(meta) >= set(meta2) - {"converter_version"}


# --- refusals, each naming the folder ---


def test_refuses_several_series_and_picks_one(ph, tmp_path):
    write_series(tmp_path / "d", ph.pre, ph.affine, series_number=3, description="T2 RARE pre")
    write_series(
        tmp_path / "d", ph.during, ph.affine, series_number=4, description="T2 RARE during"
    )
    with pytest.raises(
        ImagingError,
        match=r"animal rat, folder .*d: 2 DICOM series \(series 3 'T2 RARE pre' \(8 files\); "
        r"series 4 'T2 RARE during' \(8 files\)\); pick one with .*series",
    ):
        read_dicom(tmp_path / "d", animal="rat")
    assert [r["series"] for r in dicom_series(tmp_path / "d")] == [3, 4]
    vol, meta = read_dicom(tmp_path / "d", series=4)
    assert_same_geometry(quantised(ph.during), ph.affine, vol.data, vol.affine)
    assert meta["series_description"] == "T2 RARE during"
    vol, _ = read_dicom(tmp_path / "d", series="T2 RARE pre")
    assert_same_geometry(quantised(ph.pre), ph.affine, vol.data, vol.affine)
    with pytest.raises(ImagingError, match=r"folder .*d: no DICOM series match series 9"):
        read_dicom(tmp_path / "d", series=9)


def test_refuses_missing_slice(ph, tmp_path):
    write_series(tmp_path / "d", ph.pre, ph.affine, slices=[0, 1, 2, 4, 5, 6, 7])
    with pytest.raises(
        ImagingError,
        match=r"folder .*d: 1 slice\(s\) missing: slice gap 2.0000 mm .* others are 1.0000 mm",
    ):
        read_dicom(tmp_path / "d", animal="rat")


def test_refuses_uneven_slices(ph, tmp_path):
    aff = ph.affine.copy()
    write_series(tmp_path / "d", ph.pre[:, :, :4], aff)
    aff2 = aff.copy()
    aff2[2, 3] += 4 * aff[2, 2] + 0.3  # the second half 0.3 mm further on
    write_series(
        tmp_path / "d", ph.pre[:, :, 4:], aff2, series_uid=None, instance_start=5, name="B"
    )
    # written as two series: join them into one (same series UID) to make one uneven stack
    import pydicom

    uid = pydicom.dcmread(sorted((tmp_path / "d").glob("IM*"))[0]).SeriesInstanceUID
    for p in sorted((tmp_path / "d").glob("B*")):
        ds = pydicom.dcmread(p)
        ds.SeriesInstanceUID = uid
        ds.save_as(p)
    with pytest.raises(
        ImagingError, match=r"folder .*d: unevenly spaced slices: slice gap 1.3000 mm"
    ):
        read_dicom(tmp_path / "d")


def test_refuses_tilted_stack_and_mixed_orientations(ph, tmp_path):
    sheared = ph.affine.copy()
    sheared[0, 2] = (
        0.2  # each slice 0.2 mm further along x: a gantry-tilted stack, not a box of voxels
    )
    write_series(tmp_path / "tilt", ph.pre, sheared)
    with pytest.raises(
        ImagingError,
        match=r"folder .*tilt: slices shifted in-plane from one to the next \(a tilted stack\)",
    ):
        read_dicom(tmp_path / "tilt")
    import pydicom

    write_series(tmp_path / "mixed", ph.pre, ph.affine)
    last = sorted((tmp_path / "mixed").glob("*.dcm"))[-1]
    ds = pydicom.dcmread(last)
    ds.ImageOrientationPatient = ["1", "0", "0", "0", "0.9950042", "0.0998334"]
    ds.save_as(last)
    with pytest.raises(
        ImagingError, match=r"folder .*mixed: slices with different orientations in one series"
    ):
        read_dicom(tmp_path / "mixed")


def test_enhanced_multiframe_dicom(ph, tmp_path):
    """One multi-frame file: geometry from its per-frame groups; several echoes are volumes to pick from."""
    affine = rotated(ph.affine, (10.0, -5.0, 20.0))
    write_enhanced(tmp_path / "one" / "x.dcm", ph.pre, affine)
    vol, _ = read_dicom(tmp_path / "one")
    assert_same_geometry(quantised(ph.pre), affine, vol.data, vol.affine)
    both = np.stack([ph.pre, ph.during], axis=3)
    write_enhanced(tmp_path / "me" / "x.dcm", both, affine, echo_times_ms=(12.0, 24.0))
    with pytest.raises(
        ImagingError,
        match=r"folder .*me: dcm2niix splits the series into 2 volumes \(volume_e1, volume_e2: "
        r"echoes .*\); pick one with .*volume",
    ):
        read_dicom(tmp_path / "me", animal="rat")
    with pytest.raises(ImagingError, match=r"volume 3 does not exist"):
        read_dicom(tmp_path / "me", volume=3)
    for n, truth in ((1, ph.pre), (2, ph.during)):
        vol, meta = read_dicom(tmp_path / "me", volume=n)
        assert_same_geometry(quantised(both)[..., n - 1], affine, vol.data, vol.affine)
        assert meta["volume"] == n
    # a frame missing from the stack is found in the per-frame positions
    write_enhanced(tmp_path / "gap" / "x.dcm", ph.pre, affine, skip_slices=(3,))
    with pytest.raises(
        ImagingError, match=r"folder .*gap: 1 slice\(s\) missing: slice gap 2.0000 mm"
    ):
        read_dicom(tmp_path / "gap")


def test_refuses_multi_echo_without_volume(ph, tmp_path):
    import pydicom.uid

    uid = pydicom.uid.generate_uid()
    write_series(
        tmp_path / "d",
        ph.pre,
        ph.affine,
        series_uid=uid,
        echo_number=1,
        echo_time_ms=10.0,
        name="E1_",
    )
    write_series(
        tmp_path / "d",
        ph.during,
        ph.affine,
        series_uid=uid,
        echo_number=2,
        echo_time_ms=30.0,
        instance_start=9,
        name="E2_",
    )
    with pytest.raises(
        ImagingError,
        match=r"folder .*d: the series holds 2 volumes \(volume 1: echo 1, TE 10.0 ms, 8 slices; "
        r"volume 2: echo 2, TE 30.0 ms, 8 slices\); pick one with .*volume",
    ):
        read_dicom(tmp_path / "d", animal="rat")
    vol, meta = read_dicom(tmp_path / "d", volume=2)
    assert_same_geometry(quantised(ph.during), ph.affine, vol.data, vol.affine)
    assert meta["echo_time_ms"] == 30.0 and meta["volume"] == 2
    with pytest.raises(ImagingError, match=r"volume 3 does not exist"):
        read_dicom(tmp_path / "d", volume=3)


def test_refuses_repeated_series_without_volume(ph, tmp_path):
    """A 4D series (the same slices repeated in time) without echo numbers to tell them apart."""
    import pydicom.uid

    uid = pydicom.uid.generate_uid()
    write_series(
        tmp_path / "d", ph.pre, ph.affine, series_uid=uid, temporal_position=1, name="T1_"
    )
    write_series(
        tmp_path / "d",
        ph.during,
        ph.affine,
        series_uid=uid,
        temporal_position=2,
        instance_start=9,
        name="T2_",
    )
    with pytest.raises(ImagingError, match=r"folder .*d: the series holds 2 volumes"):
        read_dicom(tmp_path / "d")
    vol, _ = read_dicom(tmp_path / "d", volume=1)
    assert_same_geometry(quantised(ph.pre), ph.affine, vol.data, vol.affine)


def test_refuses_empty_folder_and_not_a_folder(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "notes.txt").write_text("not DICOM")
    with pytest.raises(ImagingError, match=r"animal rat, folder .*d: no DICOM image files found"):
        read_dicom(tmp_path / "d", animal="rat")
    with pytest.raises(ImagingError, match=r"folder .*nowhere: not a folder"):
        read_dicom(tmp_path / "nowhere")


def test_refuses_missing_bruker_study(tmp_path):
    with pytest.raises(ImagingError, match=r"animal rat, folder .*nowhere: not a folder"):
        read_scan({"bruker": "nowhere", "scan": 5}, base_dir=tmp_path, animal="rat")


def test_copying_a_folder_keeps_geometry(ph, tmp_path):
    """Reading twice (and from a copy) gives identical voxels: the conversion is deterministic."""
    write_series(tmp_path / "a", ph.pre, ph.affine)
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    va, _ = read_dicom(tmp_path / "a")
    vb, _ = read_dicom(tmp_path / "b")
    np.testing.assert_array_equal(va.data, vb.data)
    np.testing.assert_array_equal(va.affine, vb.affine)


# --- the config accepts scanner data as pre/during ---

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


def test_config_accepts_scanner_forms(tmp_path):
    (tmp_path / "dcm").mkdir()
    (tmp_path / "study").mkdir()
    cfg = {
        "animals": {
            "rat": {"pre": "dcm", "during": {"bruker": "study", "scan": 6, "reco": 1}},
            "rat2": {
                "pre": {"dicom": "dcm", "series": 3, "volume": 1},
                "during": {"dicom": "dcm", "series": "T2 during"},
            },
        }
    }
    out = validate_config(cfg, SCHEMA, base_dir=tmp_path)
    # no key is filled into a scan mapping (a default would leak into the other forms)
    assert out["animals"]["rat"]["during"] == {"bruker": "study", "scan": 6, "reco": 1}
    assert out["animals"]["rat2"]["during"] == {"dicom": "dcm", "series": "T2 during"}


@pytest.mark.parametrize(
    "during, match",
    [
        ({"bruker": "nowhere", "scan": 6}, r"animals\.rat\.during: folder not found: nowhere"),
        (
            {"dicom": "dcm", "scan": 6},
            r"animals\.rat\.during: unknown key\(s\) \[.scan.\]; allowed: \[.dicom., .series., .volume.\]",
        ),
        ({"bruker": "dcm"}, r"animals\.rat\.during: .scan. is a required property"),
        ("nowhere", r"animals\.rat\.during: file not found: nowhere"),
    ],
)
def test_config_refuses_bad_scanner_forms(tmp_path, during, match):
    (tmp_path / "dcm").mkdir()
    with pytest.raises(ConfigError, match=match):
        validate_config(
            {"animals": {"rat": {"pre": "dcm", "during": during}}}, SCHEMA, base_dir=tmp_path
        )


# --- ParaVision: a study written as brkraw discovers it (tests/scanner_synth.write_paravision) ---


@pytest.mark.parametrize(
    "name",
    [
        "axial_head_first",
        "axial_feet_first",
        "coronal",
        "sagittal",
        "oblique",
        "oblique_coronal_feet_first",
    ],
)
def test_paravision_geometry_round_trip(ph, tmp_path, name):
    perm, flip, rot, _ = ORIENTATIONS[name]
    affine = ph.affine if rot is None else rotated(ph.affine, rot)
    data, aff = reorder(ph.pre, affine, perm=perm, flip=flip)
    write_paravision(
        tmp_path / "study",
        5,
        data,
        aff,
        subject_position="Foot_Prone" if "feet" in name else "Head_Prone",
    )
    vol, meta = read_bruker(tmp_path / "study", scan=5, reco=1, animal="rat")
    assert_read_back(ph, affine, aff, vol, axial=perm == (0, 1, 2) and rot is None)
    assert (
        meta["converter"] == "brkraw" and meta["scan"] == 5 and meta["sequence"] == "<Bruker:RARE>"
    )
    assert (
        meta["echo_time_ms"] == 12.0
        and meta["repetition_time_ms"] == 2500.0
        and meta["field_strength_t"] == 7.053
    )


def test_paravision_refusals(ph, tmp_path):
    study = tmp_path / "20190312_rat07"
    write_paravision(study, 5, ph.pre, ph.affine, protocol="T2_pre")
    write_paravision(study, 6, ph.during, ph.affine, protocol="T2_during")
    with pytest.raises(
        ImagingError,
        match=r"animal rat, folder .*20190312_rat07: no scan 7; the study holds: "
        r"scan 5 'T2_pre' \(recos \[1\]\); scan 6 'T2_during' \(recos \[1\]\)",
    ):
        read_bruker(study, scan=7, animal="rat")
    with pytest.raises(
        ImagingError, match=r"folder .*20190312_rat07, scan 6: no reco 2; the scan has recos \[1\]"
    ):
        read_bruker(study, scan=6, reco=2)
    vol, _ = read_scan({"bruker": "20190312_rat07", "scan": 6}, base_dir=tmp_path)
    assert_same_geometry(quantised(ph.during), ph.affine, vol.data, vol.affine)
    # per-frame scaling that brkraw would apply as one slope
    visu = study / "6" / "pdata" / "1" / "visu_pars"
    text = visu.read_text().splitlines()
    k = text.index(next(t for t in text if t.startswith("##$VisuCoreDataSlope")))
    text[k + 1] = " ".join(["0.001"] + text[k + 1].split()[1:])
    visu.write_text("\n".join(text) + "\n")
    with pytest.raises(
        ImagingError, match=r"scan 6, reco 1: VisuCoreDataSlope differs between frames"
    ):
        read_bruker(study, scan=6)
    # a multi-echo scan: one volume per echo, and a refusal without a choice
    write_paravision(study, 8, np.stack([ph.pre, ph.during], axis=3), ph.affine, protocol="MGE")
    with pytest.raises(
        ImagingError,
        match=r"folder .*20190312_rat07, scan 8, reco 1: 2 volumes .*; pick one with .*volume",
    ):
        read_bruker(study, scan=8, animal="rat")
    for n, truth in ((1, ph.pre), (2, ph.during)):
        vol, meta = read_scan(
            {"bruker": "20190312_rat07", "scan": 8, "volume": n}, base_dir=tmp_path
        )
        slope = float(max(ph.pre.max(), ph.during.max())) / 4000
        np.testing.assert_allclose(
            vol.data, np.round(truth / slope) * slope, rtol=0, atol=1e-5 * slope * 4000
        )
        np.testing.assert_allclose(vol.affine, ph.affine, atol=1e-5)
        assert meta["volume"] == n and meta["echo_time_ms"] == 12.0 * n
    with pytest.raises(ImagingError, match=r"volume 3 does not exist"):
        read_bruker(study, scan=8, volume=3)
    with pytest.raises(ImagingError, match=r"folder .*empty: not a readable ParaVision study"):
        (tmp_path / "empty").mkdir()
        read_bruker(tmp_path / "empty", scan=1)


# --- the whole study: a DICOM and a ParaVision copy of an animal give its NIfTI twin's answers ---


@pytest.mark.slow
def test_study_from_scanner_copies_matches_its_nifti_twin(tmp_path):
    """One phantom animal given three ways: NIfTI, DICOM stored feet-first, ParaVision stored bottom-up.

    The voxel values are multiples of 2^-12 and the slope is 2^-12, so DICOM's integers hold them exactly;
    the three animals must get the same converted volumes, contours and pose. The workflow runs to the pose:
    the rules after it read only the contours, the pose and the config (no rule reads a scan or its
    ``mri/*.json``), so the same contours and pose give the same row of voi.csv.
    """
    import os
    import subprocess
    import sys

    import yaml

    from deeptissue.imaging import write_nifti

    spec = PhantomSpec(
        seed=1,
        depth_mm=2.0,
        tilt_deg=(5.0, -3.0),
        bone_rotation_deg=(1.0, -0.5, 0.8),
        bone_translation_mm=(0.05, -0.10, 0.02),
        snr=20,
        supersample=2,
    )
    ph = make_phantom(spec)
    step = 2.0**-12
    data = tmp_path / "data"
    vols = {
        s: (np.round(getattr(ph, s) / step) * step).astype(np.float32) for s in ("pre", "during")
    }
    for s, (series, scan) in {"pre": (3, 5), "during": (4, 6)}.items():
        write_nifti(data / "nifti" / f"{s}.nii.gz", vols[s], ph.affine)
        d, a = reorder(vols[s], ph.affine, flip=(True, False, True))
        write_series(
            data / "dicom",
            d,
            a,
            series_number=series,
            description=f"T2 {s}",
            patient_position="FFS",
            slope=step,
        )
        d, a = reorder(vols[s], ph.affine, flip=(False, True, False))
        write_paravision(data / "study", scan, d, a, protocol=f"T2_{s}", slope=step)
    cfg = {
        "animals": {
            "twin": {s: str(data / "nifti" / f"{s}.nii.gz") for s in ("pre", "during")},
            "dicom": {
                "pre": {"dicom": str(data / "dicom"), "series": 3},
                "during": {"dicom": str(data / "dicom"), "series": 4},
            },
            "bruker": {
                "pre": {"bruker": str(data / "study"), "scan": 5},
                "during": {"bruker": str(data / "study"), "scan": 6},
            },
        },
        "study": {"name": "scanners", "variants": ["sphere"]},
    }
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(cfg))
    wd = tmp_path / "wd"
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "snakemake",
            *(f"results/{a}/pose.json" for a in cfg["animals"]),
            "--cores",
            "2",
            "-s",
            str(ROOT / "Snakefile"),
            "--directory",
            str(wd),
            "--configfile",
            str(tmp_path / "study.yaml"),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=3000,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    for animal in ("dicom", "bruker"):
        for s in ("pre", "during"):
            got = load_nifti(wd / "results" / animal / "mri" / f"{s}.nii.gz")
            np.testing.assert_array_equal(got.data, vols[s])
            np.testing.assert_array_equal(got.affine, ph.affine)
        assert (
            json.loads((wd / "results" / animal / "mri" / "pre.json").read_text())["kind"]
            == animal
        )
    twin = wd / "results" / "twin"
    twin_pose = json.loads((twin / "pose.json").read_text())
    for animal in ("dicom", "bruker"):
        for s in ("pre", "during"):
            got, want = (
                np.load(d / "contours" / f"{s}.npz") for d in (wd / "results" / animal, twin)
            )
            assert sorted(got.files) == sorted(want.files)
            for k in want.files:
                np.testing.assert_array_equal(got[k], want[k], err_msg=f"{animal} {s} {k}")
        pose = json.loads((wd / "results" / animal / "pose.json").read_text())
        assert pose.keys() == twin_pose.keys()
        # every number of the pose, fits and diagnostics included (its strings name the input files)
        for k, want in twin_pose.items():
            if not isinstance(want, str):
                np.testing.assert_array_equal(pose[k], want, err_msg=f"{animal} {k}")


def test_refuses_a_single_slice_volume(ph, tmp_path):
    write_series(tmp_path / "d", ph.pre, ph.affine, slices=[3])
    with pytest.raises(
        ImagingError,
        match=r"animal rat, folder .*d: 1 slice\(s\); the segmentation needs at least 3 slices",
    ):
        read_dicom(tmp_path / "d", animal="rat")


def test_duplicate_files_are_named_as_copies_not_volumes(ph, tmp_path):
    import shutil

    paths = write_series(tmp_path / "d", ph.pre, ph.affine)
    for p in paths[:2]:
        shutil.copy(p, p.with_name("copy_" + p.name))
    with pytest.raises(
        ImagingError,
        match=r"folder .*d: 2 file\(s\) are copies of others \(the same SOPInstanceUID: ",
    ):
        read_dicom(tmp_path / "d")


def test_twin_series_are_told_apart_by_their_uid(ph, tmp_path):
    import pydicom.uid

    uid_pre, uid_dur = pydicom.uid.generate_uid(), pydicom.uid.generate_uid()
    write_series(tmp_path / "d", ph.pre, ph.affine, series_uid=uid_pre, name="A")
    write_series(tmp_path / "d", ph.during, ph.affine, series_uid=uid_dur, name="B")
    with pytest.raises(
        ImagingError,
        match=rf"2 DICOM series match series 'T2 RARE' \(.*uid {uid_pre}.*uid {uid_dur}|"
        rf"2 DICOM series match series 'T2 RARE' \(.*uid {uid_dur}.*uid {uid_pre}",
    ):
        read_dicom(tmp_path / "d", series="T2 RARE")
    vol, _ = read_dicom(tmp_path / "d", series=uid_dur)
    assert_same_geometry(quantised(ph.during), ph.affine, vol.data, vol.affine)


@pytest.mark.parametrize(
    "nucleus, bf1_mhz, field_t",
    [("1H", 500.13, 11.746), ("13C", 125.7707, 11.745), ("19F", 282.404, 7.046)],
)
def test_paravision_field_strength_from_the_nucleus(ph, tmp_path, nucleus, bf1_mhz, field_t):
    # Larmor frequencies of an 11.7 T and a 7 T magnet (Bruker's 500 and 300 MHz systems) for each nucleus
    study = tmp_path / "study"
    write_paravision(study, 5, ph.pre, ph.affine, nucleus=nucleus, bf1_mhz=bf1_mhz)
    _, meta = read_bruker(study, scan=5)
    assert meta["nucleus"] == nucleus
    assert meta["field_strength_t"] == pytest.approx(field_t, abs=0.002)
