"""Touching legs parted by a point inside one (leg_point_mm), and the tibia and fibula chosen in 3D on masked scans."""

import numpy as np
import pytest
from masked_legs import Leg, masked_legs

from deeptissue import segment
from deeptissue.contours import load_contours, polygon_area_centroid
from deeptissue.imaging import ImagingError, body_mask, split_legs, write_nifti
from deeptissue.segment import (
    SegmentationError,
    SegmentationSettings,
    SegmentJob,
    segment_files,
    segment_volume,
)

# a masked scan: background and fat exactly 0, nothing to smooth, the skin at the edge of the non-zero region
MASKED = SegmentationSettings(
    smooth_mm=0.0,
    skin_level=0.05,
    bone_level=0.25,
    bone_select="anterior",
    bone_min_area_mm2=0.5,
    bias_erode_mm=1.0,
    bias_degree=2,
    fluid_level=None,
)
PX_MM = 0.25
# two legs side by side, offset in x and y, whose skins overlap by 0.4 mm along a 3 mm seam
R_MM = 6.3
A, B = (-5.0, -3.5), (5.0, 3.5)
TWIN = [Leg(A, radius_mm=R_MM), Leg(B, radius_mm=R_MM)]


@pytest.fixture(scope="module")
def twin():
    return masked_legs(TWIN)


def _distance_from(xy, centre):
    return np.hypot(xy[..., 0] - centre[0], xy[..., 1] - centre[1])


def test_no_crop_box_parts_the_touching_legs(twin):
    # the premise: the legs are one body on every slice, and the smallest box around one leg holds part of the other
    from scipy import ndimage

    body = body_mask(twin)
    assert all(ndimage.label(body[:, :, k])[1] == 1 for k in range(twin.n_slices))
    w = twin.world(np.argwhere(body).astype(float))
    in_box = np.all(np.abs(w[:, :2] - A) <= R_MM, axis=1)
    assert (in_box & (_distance_from(w, A) > R_MM + PX_MM)).sum() > 100


@pytest.mark.parametrize(
    "point, mine, other",
    [((-5.0, -3.0, 0.0), A, B), ((4.0, 4.0, -2.0), B, A), ((-1.5, 1.0, 3.0), A, B)],
)
def test_a_point_picks_one_leg_whole(twin, point, mine, other):
    leg = split_legs(twin, point).leg
    body, kept = body_mask(twin), body_mask(leg)
    w = twin.world(np.argwhere(body).astype(float))
    keep = kept[body]
    d_mine, d_other = _distance_from(w, mine), _distance_from(w, other)
    assert keep[d_other > R_MM + PX_MM].all()  # all of the picked leg that is not the other's too
    assert not keep[
        d_mine > R_MM + 3 * PX_MM
    ].any()  # of the other, at most the cut's margin of two pixels
    assert leg.data.shape == twin.data.shape and (leg.data[~kept] == 0).all()


def test_the_picked_leg_segments_alone(twin):
    together, _ = segment_volume(twin, settings=MASKED)
    assert (
        _distance_from(together.skin, A).max() > 2 * R_MM
    )  # without a point the skin runs around both legs
    c, _ = segment_volume(split_legs(twin, (-5.0, -3.0, 0.0)).leg, settings=MASKED)
    r = _distance_from(c.skin, A)
    assert (
        r.min() >= R_MM - PX_MM and r.max() <= R_MM + 3 * PX_MM
    )  # within the margin left along the cut
    tibia = np.add(A, TWIN[0].tibia_mm)
    for k in range(c.n_slices):
        assert np.hypot(*(polygon_area_centroid(c.bone[k, :, :2])[1] - tibia)) < PX_MM


def test_segment_files_takes_the_point(twin, tmp_path):
    img = tmp_path / "legs.nii.gz"
    write_nifti(img, twin.data, twin.affine)
    out = tmp_path / "pre.npz"
    segment_files(
        SegmentJob(
            image=img,
            contours_out=out,
            qc_out=tmp_path / "qc.png",
            animal="twin",
            state="pre",
            settings=MASKED,
            crop_mm=[[-14, 14], [-12, 12], [-2, 2]],
            leg_point_mm=[4.0, 4.0, 0.0],
            checks_out=tmp_path / "checks.csv",
        )
    )
    c = load_contours(out)
    assert c.n_slices == 4 and (tmp_path / "qc.png").stat().st_size > 0
    assert np.abs(_distance_from(c.skin, B) - R_MM).max() <= 3 * PX_MM
    # the legs touch on every slice: the tibia and fibula are the picked leg's, never the other's
    tibia = np.add(B, Leg(B).tibia_mm)
    fibula = np.add(B, Leg(B).fibula_mm)
    for k in range(c.n_slices):
        assert np.hypot(*(polygon_area_centroid(c.bone[k, :, :2])[1] - tibia)) < PX_MM, k
        assert np.hypot(*(polygon_area_centroid(c.fibula[k, :, :2])[1] - fibula)) < PX_MM, k
    # the checks of a pre-only animal are written, every one ok
    rows = (tmp_path / "checks.csv").read_text().splitlines()
    assert rows[0] == "check,slice,value,limit,status,action"
    assert {r.split(",")[0] for r in rows[1:]} >= {
        "tibia_area_step",
        "tibia_centroid_jump_mm_per_mm",
        "tibia_fibula_ratio",
        "skin_to_mask_mm",
        "slices_left_out",
    }
    assert not [r for r in rows[1:] if ",fail," in r]


def test_a_point_outside_the_leg_is_refused(twin):
    with pytest.raises(
        ImagingError,
        match=r"animal twin, file legs\.nii\.gz, slice 3: leg_point_mm \[12\.0, -10\.0, "
        r"-0\.5\] lies outside the body",
    ):
        split_legs(twin, (12.0, -10.0, -0.5))
    with pytest.raises(
        ImagingError,
        match=r"animal twin, file legs\.nii\.gz: leg_point_mm \[0\.0, 0\.0, 9\.0\] lies "
        r"outside the image",
    ):
        split_legs(twin, (0.0, 0.0, 9.0))


def test_one_leg_is_kept_whole():
    one = masked_legs([Leg((0.0, 0.0))])
    assert (split_legs(one, (0.0, 0.0, 0.0)).leg.data == one.data).all()


# --- the tibia in 3D --------------------------------------------------------------------------------


def test_masked_tibia_on_every_slice_not_a_larger_dark_spot_on_one():
    # on slice 3 a dark region larger than the tibia (a vessel, a gap): slice by slice 'largest' would take it
    vol = masked_legs([Leg((0.0, 0.0))], extra={3: (2.0, -2.0, 1.6)})
    c, _ = segment_volume(
        vol, settings=SegmentationSettings(**{**MASKED.__dict__, "bone_select": "largest"})
    )
    for k in range(vol.n_slices):
        assert np.hypot(*(polygon_area_centroid(c.bone[k, :, :2])[1] - (0.5, 2.6))) < PX_MM, (
            f"slice {k}"
        )


def _circle_error_mm(c, k, centre, radius):
    return np.abs(np.hypot(*(c.bone[k, :, :2] - centre).T) - radius)


@pytest.mark.parametrize("select", ["anterior", "largest"])
def test_masked_tibia_open_into_the_fat_is_parted_from_it(select):
    # on slices 2 and 5 the tibia's dark region runs into the dark fat through a 0.8 mm channel: its thick core is
    # parted from the fat and the channel (bone_open_mm null: a tenth of the leg's inscribed radius, 0.6 mm), and
    # its contour lies on the true circle as on the slices where it is closed
    vol = masked_legs([Leg((0.0, 0.0), open_slices=(2, 5))])
    settings = SegmentationSettings(**{**MASKED.__dict__, "bone_select": select})
    c, _ = segment_volume(vol, settings=settings)
    tibia = Leg((0.0, 0.0))
    d = [
        _circle_error_mm(c, k, tibia.tibia_mm, tibia.tibia_radius_mm) for k in range(vol.n_slices)
    ]
    closed_mean = np.mean(
        [d[k].mean() for k in (0, 1, 3, 4, 6, 7)]
    )  # the binary disc's own jag, 0.07 mm
    for k in (2, 5):
        assert d[k].mean() <= closed_mean + 0.05 and d[k].max() <= 0.25, (
            k,
            d[k].mean(),
            d[k].max(),
        )


@pytest.mark.parametrize("select", ["anterior", "largest"])
def test_masked_tibia_open_into_the_fat_is_refused_without_parting(select):
    # bone_open_mm 0: no closed tibia on slices 2 and 5, the fibula is the only dark region left there, and it
    # is not taken for the tibia: both slices named in one refusal
    vol = masked_legs([Leg((0.0, 0.0), open_slices=(2, 5))])
    settings = SegmentationSettings(
        **{**MASKED.__dict__, "bone_select": select, "bone_open_mm": 0}
    )
    with pytest.raises(
        SegmentationError,
        match=r"animal twin, file legs\.nii\.gz: 2 of 8 slices cannot be segmented \(slices 2, 5, .*\): the "
        r"tibia \(.* near x 0\.5 mm, y 2\.6 mm\) is not a closed dark region inside the skin on slice\(s\) "
        r"2, 5 of 8",
    ):
        segment_volume(vol, settings=settings)
    assert isinstance(SegmentationError("x"), ImagingError)


def test_no_structure_along_the_leg_is_refused():
    # the tibia and fibula on slices 0-2 only; on 3-7 a dark spot that moves 1.4 mm a slice (no bone does)
    n = (64, 64, 8)
    bones = masked_legs([Leg((0.0, 0.0))], n=n)
    spots = masked_legs(
        [Leg((0.0, 0.0), tibia_radius_mm=0.0, fibula_radius_mm=0.0)],
        n=n,
        extra={k: (-2.8 + 1.4 * (k - 3), -3.0, 0.6) for k in range(3, 8)},
    )
    data = np.concatenate([bones.data[:, :, :3], spots.data[:, :, 3:]], axis=2)
    vol = type(bones)(data=data, affine=bones.affine, path=bones.path, animal=bones.animal)
    with pytest.raises(
        SegmentationError,
        match=r"animal twin, file legs\.nii\.gz: 8 of 8 slices .*: no dark structure runs through half "
        r"of the 8 traced slices \(the longest is on 3: slices 0, 1, 2\)",
    ):
        segment_volume(vol, settings=MASKED)


# --- the fibula in 3D -------------------------------------------------------------------------------

FIBULA = np.add((0.0, 0.0), Leg((0.0, 0.0)).fibula_mm)  # the fibula's centre on every slice [mm]


def _fibula_centres(c):
    return [
        None
        if not np.isfinite(c.fibula[k]).all()
        else polygon_area_centroid(c.fibula[k, :, :2])[1]
        for k in range(c.n_slices)
    ]


def test_masked_fibula_on_every_slice_not_a_larger_dark_spot_on_one():
    # on slice 3 a round dark spot larger than the fibula, 2.6 mm from it: slice by slice the largest would be taken
    vol = masked_legs([Leg((0.0, 0.0))], extra={3: (-2.0, 1.2, 0.9)})
    c, info = segment_volume(vol, settings=MASKED)
    assert info["fibula_slices"] == vol.n_slices
    for k, cen in enumerate(_fibula_centres(c)):
        assert np.hypot(*(cen - FIBULA)) < PX_MM, f"slice {k}"


def test_a_dark_spot_where_the_fibula_is_missing_is_not_taken(monkeypatch):
    # on slice 4 the fibula is not seen (filled with muscle) and a smaller round dark spot lies 1.6 mm from where it
    # runs: it is the only fibula candidate there, and slice by slice it would be taken
    n = (112, 96, 8)
    legs = masked_legs([Leg((0.0, 0.0))], n=n)
    gap = masked_legs([Leg((0.0, 0.0), fibula_radius_mm=0.0)], n=n, extra={4: (-1.6, -2.5, 0.55)})
    data = legs.data.copy()
    data[:, :, 4] = gap.data[:, :, 4]
    vol = type(legs)(data=data, affine=legs.affine, path=legs.path, animal=legs.animal)
    seen = []  # each slice's fibula candidates
    real = segment._fibula_candidates
    monkeypatch.setattr(
        segment, "_fibula_candidates", lambda *a, **kw: seen.append(real(*a, **kw)) or seen[-1]
    )
    c, info = segment_volume(vol, settings=MASKED)
    assert len(seen[4]) == 1  # the premise
    assert (
        np.hypot(*(vol.world([*polygon_area_centroid(seen[4][0][1])[1], 4])[:2] - (-1.6, -2.5)))
        < PX_MM
    )
    cens = _fibula_centres(c)
    assert cens[4] is None and info["slices"][4]["fibula_source"] == "none"
    assert info["fibula_slices"] == vol.n_slices - 1
    for k, cen in enumerate(cens):
        if k != 4:
            assert np.hypot(*(cen - FIBULA)) < PX_MM, f"slice {k}"


def test_a_failed_check_stops_the_rule_naming_every_slice_and_leaves_its_figure(tmp_path):
    # skin_level above the skin ring (0.5): the skin is traced on the muscle's edge, 0.7 mm inside the leg's edge
    # on every slice; the check names them all at once, and the figure and checks of the failed run stay
    one = masked_legs([Leg((0.0, 0.0))])
    img = tmp_path / "leg.nii.gz"
    write_nifti(img, one.data, one.affine)
    job = SegmentJob(
        image=img,
        contours_out=tmp_path / "pre.npz",
        qc_out=tmp_path / "qc.png",
        checks_out=tmp_path / "checks.csv",
        animal="one",
        settings=SegmentationSettings(**{**MASKED.__dict__, "skin_level": 0.7}),
    )
    with pytest.raises(
        SegmentationError,
        match=r"animal one, file .*leg\.nii\.gz: failed segmentation check\(s\): skin_to_mask_mm on slice\(s\) "
        r"0, 1, 2, 3, 4, 5, 6, 7 \(worst 0\.\d+, maximum 0\.25\): the skin lies off the edge of the leg.*"
        r"qc_failed\.png; the checks: .*checks_failed\.csv",
    ):
        segment_files(job)
    assert not (tmp_path / "pre.npz").exists() and not (tmp_path / "qc.png").exists()
    assert (tmp_path / "qc_failed.png").stat().st_size > 10_000
    rows = (tmp_path / "checks_failed.csv").read_text().splitlines()
    assert (
        sum(
            ",skin_to_mask_mm," in r or r.startswith("skin_to_mask_mm,") and ",fail," in r
            for r in rows
        )
        == 8
    )
    # the same scan at the right level passes, and the failed run's files are gone
    segment_files(SegmentJob(**{**job.__dict__, "settings": MASKED}))
    assert (tmp_path / "pre.npz").exists() and not (tmp_path / "qc_failed.png").exists()
    assert not (tmp_path / "checks_failed.csv").exists()
