"""Segmentation against the phantom truth (snr 12), PCHIP resampling, manual override, bad input."""

import re

import nibabel as nib
import numpy as np
import pytest
import yaml

from deeptissue.config import ConfigError
from deeptissue.contours import polygon_area_centroid, resample_closed
from deeptissue.imaging import (
    ImagingError,
    Volume,
    check_matching,
    crop_volume,
    load_nifti,
    write_nifti,
)
from deeptissue.phantom import PhantomSpec, _Scene, make_phantom
from deeptissue.segment import (
    SegmentationError,
    SegmentationSettings,
    SegmentJob,
    contour_accuracy,
    load_overrides,
    segment_files,
    segment_volume,
)

# the hardest demo animal (deepest, most tilted) at the lowest claimed snr
SPEC = PhantomSpec(
    seed=2,
    depth_mm=2.5,
    tilt_deg=(-8.0, 6.0),
    bone_rotation_deg=(-1.5, 0.8, 0.3),
    bone_translation_mm=(-0.08, -0.12, 0.04),
    snr=12,
)


@pytest.fixture(scope="module")
def ph():
    return make_phantom(SPEC)


@pytest.fixture(scope="module")
def segmented(ph):
    """Both states segmented with the default settings (about 5 s)."""
    out = {}
    for state in ("pre", "during"):
        vol = Volume(
            data=getattr(ph, state), affine=ph.affine, path=f"{state}.nii.gz", animal="ratT"
        )
        out[state] = segment_volume(vol, state=state)[0]
    return out


def _distances(seg, ph, state, structure):
    """Per point: distance (mm) to the exact boundary, and whether the point is on the posterior half."""
    d, post = [], []
    for k in range(seg.n_slices):
        pts = getattr(seg, structure)[k, :, :2]
        rows = contour_accuracy(
            type(seg)(skin=seg.skin[k : k + 1], bone=seg.bone[k : k + 1]),
            {
                structure: [ph.dense[(state, structure)][k]],
                "skin" if structure == "bone" else "bone": [
                    ph.dense[(state, "skin" if structure == "bone" else "bone")][k]
                ],
            },
        )
        from deeptissue.contours import point_to_polygon_distance

        dk = point_to_polygon_distance(pts, ph.dense[(state, structure)][k][:, :2])
        assert np.isclose(
            dk.mean(), [r for r in rows if r["structure"] == structure][0]["mean_mm"]
        )
        d.append(dk)
        post.append(pts[:, 1] < pts[:, 1].mean())
    return np.concatenate(d), np.concatenate(post)


@pytest.mark.slow
@pytest.mark.parametrize("state", ["pre", "during"])
@pytest.mark.parametrize("structure", ["skin", "bone"])
def test_accuracy_against_truth_at_snr_12(ph, segmented, state, structure):
    d, post = _distances(segmented[state], ph, state, structure)
    assert d.mean() <= 0.05, f"{state} {structure}: mean {d.mean():.4f} mm"
    assert d.max() <= 0.25, f"{state} {structure}: max {d.max():.4f} mm"
    # the poorly lit (posterior, away from the coil) half on its own
    assert d[post].mean() <= 0.05 and d[post].max() <= 0.25


@pytest.mark.slow
@pytest.mark.parametrize("state", ["pre", "during"])
def test_fibula_found_on_every_slice(ph, segmented, state):
    """The fibula, a second dark region (0.76 mm across, on the poorly lit side), is segmented on every
    slice. The 0.15 mm smoothing shrinks so small a section by ~0.05 mm (measured 0.04-0.05 mean
    distance), the same in both states; its centre, which the pose fit uses, is within 0.03 mm."""
    from deeptissue.contours import point_to_polygon_distance

    seg = segmented[state]
    assert seg.fibula is not None and seg.fibula.shape == (20, 100, 3) and seg.fibula_slices.all()
    for k in range(20):
        true = ph.dense[(state, "fibula")][k][:, :2]
        d = point_to_polygon_distance(seg.fibula[k, :, :2], true)
        assert d.mean() <= 0.07 and d.max() <= 0.15, (k, d.mean(), d.max())
        a_seg, c_seg = polygon_area_centroid(seg.fibula[k, :, :2])
        a_true, c_true = polygon_area_centroid(true)
        assert np.linalg.norm(c_seg - c_true) <= 0.03
        assert 0.6 * a_true <= a_seg <= a_true  # smaller, never the tibia or a merged region
    rows = contour_accuracy(seg, {st: ph.dense[(state, st)] for st in ("skin", "bone", "fibula")})
    assert sum(r["structure"] == "fibula" for r in rows) == 20


def test_no_fibula_falls_back_to_the_tibia_alone(ph):
    """A scan without a fibula (filled with muscle), one where it shows on too few slices, and
    segmentation.fibula false: no fibula array, the tibia unchanged."""
    data = ph.pre[:, :, :6].copy()
    sc = _Scene(SPEC)
    X, Y = np.meshgrid(*(ph.affine[0, 3] + ph.affine[0, 0] * np.arange(256),) * 2, indexing="ij")
    muscle = np.median(data[100:150, 100:150, 0])
    vol = Volume(data=data, affine=ph.affine, path="pre.nii.gz", animal="ratT")
    auto, info = segment_volume(vol, state="pre")
    assert auto.fibula_slices.all() and info["fibula_slices"] == 6
    filled = data.copy()
    for k in range(6):
        if k != 4:  # a fibula left only on slice 4: a stray spot, dropped
            filled[:, :, k][sc.an.fibula_f(X, Y, ph.z_mm[k]) < 0.2] = muscle
    c, info = segment_volume(Volume(data=filled, affine=ph.affine), state="pre")
    assert c.fibula is None and info["fibula_slices"] == 0
    assert [r["fibula_source"] for r in info["slices"]] == ["none"] * 4 + ["dropped", "none"]
    # the tibia as without the filling (filling the fibula changes the coil fit a little)
    assert np.abs(c.bone - auto.bone).max() < 0.01
    off, _ = segment_volume(vol, state="pre", settings=SegmentationSettings(fibula=False))
    assert off.fibula is None
    np.testing.assert_allclose(off.bone, auto.bone, atol=1e-9)


def test_posterior_side_is_poorly_lit(ph):
    # the claim above covers a real fall-off: posterior muscle below 60 % of anterior
    img = ph.pre[:, :, 10]
    sk = ph.truth_pre.skin[10]
    j = lambda y: int(round((y - ph.affine[1, 3]) / ph.affine[1, 1]))
    i = int(round((sk[:, 0].mean() - ph.affine[0, 3]) / ph.affine[0, 0]))
    ant = img[i - 4 : i + 5, j(sk[:, 1].max() - 1.0)].mean()
    post = img[i - 4 : i + 5, j(sk[:, 1].min() + 1.0)].mean()
    assert post < 0.6 * ant


@pytest.mark.slow
def test_contrast_fluid_does_not_leak_into_skin(ph, segmented):
    sc = _Scene(SPEC)
    skin = segmented["during"].skin
    sd = sc.indenter_sd(skin[..., 0], skin[..., 1], skin[..., 2])
    # no skin point inside the fluid (deeper than the wall); at most on the wall's outer surface
    assert sd.min() > -0.1
    for k in range(skin.shape[0]):
        a_seg = polygon_area_centroid(skin[k, :, :2])[0]
        a_true = polygon_area_centroid(ph.dense[("during", "skin")][k][:, :2])[0]
        assert a_seg == pytest.approx(a_true, rel=0.01)


@pytest.mark.slow
def test_contour_convention(segmented):
    c = segmented["pre"]
    assert c.skin.shape == c.bone.shape == (20, 100, 3)
    for k in range(20):
        for arr in (c.skin[k], c.bone[k]):
            area, cen = polygon_area_centroid(arr[:, :2])
            assert area > 0  # counter-clockwise
            ang = np.degrees(np.arctan2(arr[0, 1] - cen[1], arr[0, 0] - cen[0]))
            assert abs(ang - 90.0) < 1.0
            step = np.linalg.norm(np.diff(np.vstack([arr, arr[:1]])[:, :2], axis=0), axis=1)
            assert step.std() / step.mean() < 0.02


# --- resampling ---------------------------------------------------------------------------------


@pytest.mark.parametrize("start", [90.0, 0.0, -135.0])
def test_pchip_resampling_on_a_circle(start):
    rng = np.random.default_rng(3)
    r, c = 3.0, np.array([1.0, -2.0])
    ang = (np.arange(60) + rng.uniform(-0.3, 0.3, 60)) * (2 * np.pi / 60)
    ang = ang[::-1]  # clockwise, unevenly spaced
    pts = c + r * np.column_stack([np.cos(ang), np.sin(ang)])
    out = resample_closed(pts, n_points=100, start_angle_deg=start)
    assert out.shape == (100, 2)
    rad = np.linalg.norm(out - c, axis=1)
    np.testing.assert_allclose(rad, r, atol=5e-3)  # exact on a circle within tolerance
    area, cen = polygon_area_centroid(out)
    assert area > 0  # counter-clockwise
    first = np.degrees(np.arctan2(out[0, 1] - c[1], out[0, 0] - c[0]))
    assert abs((first - start + 180) % 360 - 180) < 0.05
    step = np.linalg.norm(np.diff(np.vstack([out, out[:1]]), axis=0), axis=1)
    np.testing.assert_allclose(step, step.mean(), rtol=2e-3)  # equidistant
    np.testing.assert_allclose(step.sum(), 2 * np.pi * r, rtol=2e-3)


def test_pchip_is_shape_preserving_on_a_square():
    # no overshoot at corners: a square stays within its bounding box
    sq = np.array([[0, 0], [1, 0], [2, 0], [2, 1], [2, 2], [1, 2], [0, 2], [0, 1]], float)
    out = resample_closed(sq, n_points=40, start_angle_deg=0.0)
    assert out.min() >= -1e-9 and out.max() <= 2 + 1e-9


# --- manual override ------------------------------------------------------------------------------


def test_manual_override_replaces_slices(ph, tmp_path):
    vol = Volume(data=ph.pre[:, :, :6], affine=ph.affine, path="pre.nii.gz", animal="ratT")
    auto, _ = segment_volume(vol, state="pre")
    cen = polygon_area_centroid(auto.skin[3, :, :2])[1]
    th = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    circle = (cen + 4.0 * np.column_stack([np.cos(th), np.sin(th)])).round(4).tolist()
    f = tmp_path / "ov.yaml"
    f.write_text(yaml.safe_dump({"pre": {"skin": {3: circle}}}))
    ov = load_overrides(f)
    man, info = segment_volume(vol, state="pre", overrides=ov)
    assert info["slices"][3]["skin_source"] == "manual"
    # slice 3 skin is the hand-drawn curve (PCHIP through 12 points of a circle: radius within 2 %)
    rad = np.linalg.norm(man.skin[3, :, :2] - cen, axis=1)
    np.testing.assert_allclose(rad, 4.0, rtol=0.02)
    np.testing.assert_allclose(man.bone[3], auto.bone[3])
    np.testing.assert_allclose(np.delete(man.skin, 3, 0), np.delete(auto.skin, 3, 0))
    # the override of the other state does not apply
    man2, _ = segment_volume(vol, state="during", overrides=ov)
    np.testing.assert_allclose(man2.skin, auto.skin)


def test_override_bone_outside_skin_is_an_error(ph, tmp_path):
    vol = Volume(data=ph.pre[:, :, :8], affine=ph.affine, path="pre.nii.gz", animal="ratT")
    far = [[9, 9], [10, 9], [10, 10], [9, 10]]
    with pytest.raises(
        SegmentationError,
        match=r"animal ratT, file pre\.nii\.gz, slice 5: bone contour outside the skin",
    ):
        segment_volume(vol, state="pre", overrides={"pre": {"bone": {5: np.array(far, float)}}})


@pytest.mark.parametrize("k", [99, -1])
def test_override_of_a_slice_that_does_not_exist_names_file_and_slice(tmp_path, k):
    path = tmp_path / "ov.yaml"
    path.write_text(f"pre:\n  bone:\n    {k}: [[0, 0], [1, 0], [1, 1], [0, 1]]\n")
    with pytest.raises(
        ValueError, match=rf"ov\.yaml: pre\.bone: slice {k} is not a slice of the 20"
    ):
        load_overrides(path, n_slices=20)


def test_the_same_scan_as_pre_and_during_is_named(ph, tmp_path):
    from deeptissue.imaging import check_not_same_scan

    pre = tmp_path / "pre.nii.gz"
    write_nifti(pre, ph.pre, ph.affine)
    copy = tmp_path / "during.nii.gz"
    write_nifti(copy, ph.pre, ph.affine)
    a = load_nifti(pre, animal="rat9")
    with pytest.raises(
        ImagingError,
        match=r"animal rat9: pre .*pre\.nii\.gz and during .*pre\.nii\.gz are the same file",
    ):
        check_not_same_scan(a, load_nifti(pre, animal="rat9"))
    with pytest.raises(ImagingError, match=r"are the same voxels in two files"):
        check_not_same_scan(a, load_nifti(copy, animal="rat9"))


def test_override_slice_given_twice_names_file_and_key(tmp_path):
    pts = "[[0, 0], [1, 0], [1, 1], [0, 1]]"
    f = tmp_path / "ov.yaml"
    f.write_text(f"pre:\n  bone:\n    4: {pts}\n    5: {pts}\n    4: {pts}\n")
    with pytest.raises(
        ConfigError,
        match=rf"config file {re.escape(str(f))}, line 5: key '4' is given twice \(lines 3 and 5\)",
    ):
        load_overrides(f)
    f.write_text(
        f"pre:\n  bone:\n    4: {pts}\n    '04': {pts}\n"
    )  # YAML reads these as two keys: one slice
    with pytest.raises(
        ValueError, match=rf"{re.escape(str(f))}: pre\.bone: slice 4 is given twice \(key '04'\)"
    ):
        load_overrides(f)
    f.write_text(
        f"during:\n  bone:\n    4: {pts}\n  skin:\n    4: {pts}\n"
    )  # one slice per structure is fine
    assert sorted(load_overrides(f)["during"]) == ["bone", "skin"]


# --- bad input ------------------------------------------------------------------------------------


def _nifti(path, data, affine):
    nib.save(nib.Nifti1Image(np.asarray(data, np.float32), affine), str(path))
    return path


def test_not_3d(tmp_path):
    p = _nifti(tmp_path / "x.nii.gz", np.zeros((8, 8, 3, 2)), np.eye(4))
    with pytest.raises(ImagingError, match=r"animal rat9, file .*x\.nii\.gz: not a 3D image"):
        load_nifti(p, animal="rat9")
    p = _nifti(tmp_path / "y.nii.gz", np.zeros((8, 8)), np.eye(4))
    with pytest.raises(ImagingError, match="not a 3D image"):
        load_nifti(p, animal="rat9")


def test_degenerate_affine(tmp_path):
    A = np.eye(4)
    A[2, 2] = 0.0  # the slice axis collapses
    img = nib.Nifti1Image(np.zeros((8, 8, 3), np.float32), np.eye(4))
    img.set_qform(None, code=0)
    img.set_sform(A, code=1)
    p = tmp_path / "d.nii.gz"
    nib.save(img, str(p))
    with pytest.raises(ImagingError, match=r"animal rat9, file .*d\.nii\.gz: degenerate affine"):
        load_nifti(p, animal="rat9")


def test_mismatched_slices(ph, tmp_path):
    pre = _nifti(tmp_path / "pre.nii.gz", ph.pre[:16, :16], ph.affine)
    A = ph.affine.copy()
    A[2, 3] += 0.5
    shifted = _nifti(tmp_path / "during.nii.gz", ph.pre[:16, :16], A)
    with pytest.raises(
        ImagingError,
        match=r"animal rat9, file .*during\.nii\.gz vs .*pre\.nii\.gz, slice 0: slices do not match",
    ):
        check_matching(load_nifti(pre, animal="rat9"), load_nifti(shifted, animal="rat9"))
    fewer = _nifti(tmp_path / "during2.nii.gz", ph.pre[:16, :16, :19], ph.affine)
    with pytest.raises(
        ImagingError, match=r"slice 19: slices do not match: during has 19 slices, pre has 20"
    ):
        check_matching(load_nifti(pre, animal="rat9"), load_nifti(fewer, animal="rat9"))


def test_no_closed_contour_names_slice_and_writes_nothing(ph, tmp_path):
    data = ph.pre.copy()
    data[:, :, 7] = data[0:10, 0:10, 7].mean()  # slice 7: background only
    img = tmp_path / "pre.nii.gz"
    write_nifti(img, data, ph.affine)
    out = tmp_path / "out" / "pre.npz"
    with pytest.raises(
        SegmentationError,
        match=r"animal rat9, file .*pre\.nii\.gz: 1 of 20 slices cannot be segmented \(slices 7, .*\): "
        r"slice\(s\) 7: no closed skin contour .*by hand in a file named by config key animals\.rat9\.overrides"
        r".*QC figure with the failing slices marked: .*qc_failed\.png",
    ):
        segment_files(
            SegmentJob(
                image=img,
                contours_out=out,
                qc_out=tmp_path / "out" / "qc.png",
                animal="rat9",
                state="pre",
                settings={},
            )
        )
    assert not out.exists() and not (tmp_path / "out" / "qc.png").exists()
    assert (tmp_path / "out" / "qc_failed.png").stat().st_size > 10_000


def test_leg_cut_by_the_crop_is_named_as_such(ph):
    vol = Volume(data=ph.pre, affine=ph.affine, path="pre.nii.gz", animal="rat9")
    cut = crop_volume(
        vol, [[-12.5, 12.5], [0.0, 12.5], [-10, 10]]
    )  # the posterior half is cut off
    with pytest.raises(
        SegmentationError,
        match=r"slice\(s\) 0, 1, .*: the leg is cut at the image border.*widen crop_mm",
    ):
        segment_volume(cut, state="pre")


def test_a_skin_level_in_the_background_is_named_as_such(ph):
    vol = Volume(data=ph.pre, affine=ph.affine, path="pre.nii.gz", animal="rat9")
    with pytest.raises(
        SegmentationError,
        match=r"slice\(s\) 0, 1, .*: segmentation.skin_level 0.001 lies in the background",
    ):
        segment_volume(vol, settings=SegmentationSettings(skin_level=0.001), state="pre")


def test_no_bone_is_an_error(ph):
    data = ph.pre.copy()
    sc = _Scene(SPEC)
    X, Y = np.meshgrid(*(ph.affine[0, 3] + ph.affine[0, 0] * np.arange(256),) * 2, indexing="ij")
    data[:, :, 4][sc.an.bone_f(X, Y, ph.z_mm[4]) < 0.3] = np.median(
        data[100:150, 100:150, 4]
    )  # fill the tibia
    vol = Volume(data=data, affine=ph.affine, path="pre.nii.gz", animal="rat9")
    with pytest.raises(
        SegmentationError, match=r"slice\(s\) 4: no closed bone contour inside the skin"
    ):
        segment_volume(vol, state="pre")


def test_crop_keeps_world_coordinates(ph):
    vol = Volume(data=ph.pre, affine=ph.affine, path="pre.nii.gz", animal="rat9")
    c = crop_volume(vol, [[-8, 8], [-8, 8], [-5, 5]])
    assert c.n_slices == 10
    np.testing.assert_allclose(c.world([0, 0, 0]), vol.world(c.index_offset))
    with pytest.raises(ImagingError, match="contains no voxel"):
        crop_volume(vol, [[100, 101], [0, 1], [0, 1]])


@pytest.mark.slow
def test_accuracy_holds_at_high_snr():
    # "snr >= 12" includes nearly noise-free images: the automatic skin level must not drift with noise
    ph = make_phantom(
        PhantomSpec(
            seed=5, depth_mm=2.0, tilt_deg=(4.0, -4.0), snr=80, n_slices=6, indenter_z_mm=-2.5
        )
    )
    for state in ("pre", "during"):
        seg, _ = segment_volume(Volume(data=getattr(ph, state), affine=ph.affine), state=state)
        for structure in ("skin", "bone"):
            rows = contour_accuracy(seg, {s: ph.dense[(state, s)] for s in ("skin", "bone")})
            d_mean = np.mean([r["mean_mm"] for r in rows if r["structure"] == structure])
            d_max = max(r["max_mm"] for r in rows if r["structure"] == structure)
            assert d_mean <= 0.05 and d_max <= 0.25, (state, structure, d_mean, d_max)


def test_rule_functions_write_whole_outputs(tmp_path):
    """The phantom and segment rules' package functions: files, round trips, accuracy CSV."""
    import pandas as pd

    from deeptissue.contours import Contours, load_contours, save_contours
    from deeptissue.phantom import write_phantom
    from deeptissue.pose import load_pose
    from deeptissue.segment import write_accuracy

    spec = PhantomSpec(seed=6, snr=15, n_slices=4, indenter_z_mm=0.0)
    m = tmp_path / "mri"
    ph = write_phantom(
        spec,
        pre_path=m / "pre.nii.gz",
        during_path=m / "during.nii.gz",
        truth_path=m / "truth.json",
        truth_pre_path=m / "truth_pre.npz",
        truth_during_path=m / "truth_during.npz",
        n_points=64,
    )
    vol = load_nifti(m / "during.nii.gz", animal="ratW")
    np.testing.assert_allclose(vol.affine, ph.affine, atol=1e-6)
    np.testing.assert_allclose(vol.data, ph.during, atol=1e-6)
    np.testing.assert_allclose(load_pose(m / "truth.json").tip_end_mm, ph.truth.tip_end_mm)
    ov = tmp_path / "ov.yaml"
    ov.write_text(
        yaml.safe_dump(
            {
                "during": {
                    "bone": {2: ph.truth_during.bone[2, :, :2].tolist()},
                    "fibula": {1: ph.truth_during.fibula[1, :, :2].tolist()},
                }
            }
        )
    )
    out = tmp_path / "contours" / "during.npz"
    segment_files(
        SegmentJob(
            image=m / "during.nii.gz",
            contours_out=out,
            qc_out=tmp_path / "qc" / "seg.png",
            animal="ratW",
            state="during",
            settings={"n_points": 64},
            reference=m / "pre.nii.gz",
            overrides=ov,
            truth=m / "truth_during.npz",
        )
    )
    c = load_contours(out)
    assert c.skin.shape == (4, 64, 3) and c.fibula.shape == (4, 64, 3)
    assert (tmp_path / "qc" / "seg.png").stat().st_size > 10_000
    # the overridden slice carries the hand-drawn (here: true) bone contour
    np.testing.assert_allclose(c.bone[2], ph.truth_during.bone[2], atol=1e-3)
    np.testing.assert_allclose(
        c.fibula[1], ph.truth_during.fibula[1], atol=1e-3
    )  # a hand-drawn fibula too
    rows = write_accuracy(out, m / "truth_during.npz", tmp_path / "qc" / "acc.csv")
    df = pd.read_csv(tmp_path / "qc" / "acc.csv")
    assert len(df) == 12 and set(df["structure"]) == {"skin", "bone", "fibula"}
    tib = df[df["structure"] != "fibula"]
    assert tib["mean_mm"].max() <= 0.05 and tib["max_mm"].max() <= 0.25
    assert df["mean_mm"].max() <= 0.07 and df["max_mm"].max() <= 0.25
    assert len(rows) == 12
    # the truth files carry the fibula; a contour file without one reads back as None
    assert load_contours(m / "truth_during.npz").fibula.shape == (4, 64, 3)
    save_contours(tmp_path / "nofib.npz", Contours(skin=c.skin, bone=c.bone))
    with np.load(tmp_path / "nofib.npz") as z:
        assert set(z.files) == {"skin", "bone"}
    assert load_contours(tmp_path / "nofib.npz").fibula is None


def test_pre_and_during_swapped_are_named_as_such(ph, tmp_path):
    # the scan with the indenter given as pre and the one without as during: the during scan has no fluid
    # while its reference has, which is named, not reported as fluid missing
    from deeptissue.contours import save_contours

    scan_with, scan_without = tmp_path / "with.nii.gz", tmp_path / "without.nii.gz"
    write_nifti(scan_with, ph.during, ph.affine)
    write_nifti(scan_without, ph.pre, ph.affine)
    vol = Volume(data=ph.during, affine=ph.affine, path=str(scan_with), animal="rat9")
    given_pre, _ = segment_volume(vol, state="pre")
    save_contours(tmp_path / "pre.npz", given_pre)
    with pytest.raises(
        SegmentationError,
        match=r"animal rat9: the pre scan .*with\.nii\.gz holds the indenter's contrast fluid and the during "
        r"scan .*without\.nii\.gz has none: pre and during are swapped",
    ):
        segment_files(
            SegmentJob(
                image=scan_without,
                contours_out=tmp_path / "during.npz",
                qc_out=tmp_path / "during.png",
                animal="rat9",
                state="during",
                settings={},
                reference=scan_with,
                pre_contours=tmp_path / "pre.npz",
            )
        )
