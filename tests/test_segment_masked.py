"""The real failure modes of masked scans, each on a phantom with its truth (tests/masked_legs.py, partial volume).

A Dixon water image masked by its fat fraction has the subcutaneous fat (and the background) exactly 0; the tibia's
cortex can open into that fat; two legs can touch over several slices; a slab can run into the ankle or the knee.
Each case either gives contours within the segmentation's bounds on the demo phantoms (0.05 mm mean, 0.25 mm max
from the true circle) or a refusal that names the slices.
"""

import numpy as np
import pytest
from masked_legs import Leg, masked_legs

from deeptissue.imaging import split_legs
from deeptissue.segment import SegmentationError, SegmentationSettings, segment_volume

# a masked scan with partial volume: levels at half the steps they trace (skin 0.5 over a background of 0, muscle
# 1 over a dark bone), so the contours lie on the true edges
SETTINGS = SegmentationSettings(
    smooth_mm=0.0,
    skin_level=0.25,
    bone_level=0.45,
    bone_select="anterior",
    bone_min_area_mm2=0.5,
    bias_erode_mm=1.0,
    bias_degree=2,
    fluid_level=None,
)
MEAN_MM, MAX_MM = 0.05, 0.25


def _circle_error(contour, centre, radius):
    return np.abs(np.hypot(*(contour[:, :2] - centre).T) - radius)


def _assert_on_circle(contour, centre, radius, what):
    d = _circle_error(contour, centre, radius)
    assert d.mean() <= MEAN_MM and d.max() <= MAX_MM, (what, round(d.mean(), 3), round(d.max(), 3))


def _assert_leg(c, leg: Leg, slices):
    for k in slices:
        _assert_on_circle(c.skin[k], leg.centre_at(k), leg.radius_mm, f"skin, slice {k}")
        centre, radius = leg.tibia_at(k)
        _assert_on_circle(c.bone[k], centre, radius, f"tibia, slice {k}")


def test_subcutaneous_fat_set_to_zero():
    leg = Leg((0.0, 0.0))
    c, _ = segment_volume(masked_legs([leg], supersample=4), settings=SETTINGS)
    _assert_leg(c, leg, range(c.n_slices))


def test_tibia_cortex_open_into_the_zeroed_fat():
    # on slices 2 and 5 a 0.8 mm dark channel joins the tibia to the fat ring, and through it to the background
    leg = Leg((0.0, 0.0), open_slices=(2, 5))
    c, _ = segment_volume(masked_legs([leg], supersample=4), settings=SETTINGS)
    _assert_leg(c, leg, range(c.n_slices))


def test_two_legs_touching_over_more_than_half_the_slices():
    # the legs draw together by 0.5 mm a slice: apart on slices 0-4, their skins overlapping on 5-11 (up to 1.8 mm)
    mine = Leg((-7.0, -1.0), drift_mm=(0.25, 0.0))
    other = Leg((7.0, 1.0), drift_mm=(-0.25, 0.0))
    vol = masked_legs([mine, other], n=(128, 96, 12), supersample=4)
    split = split_legs(vol, (-7.0, -1.0, 0.0))
    assert set(range(5, 12)) <= set(split.parted)  # and where a gap under 1.8 mm is bridged first
    c, _ = segment_volume(split.leg, settings=SETTINGS)
    for k in range(c.n_slices):
        # the skin on the true circle away from the cut (points farther from the other leg than its radius)
        far = np.hypot(*(c.skin[k, :, :2] - other.centre_at(k)).T) > other.radius_mm + 0.5
        d = _circle_error(c.skin[k, far], mine.centre_at(k), mine.radius_mm)
        assert d.mean() <= MEAN_MM and d.max() <= MAX_MM, (k, d.mean(), d.max())
        centre, radius = mine.tibia_at(k)
        _assert_on_circle(c.bone[k], centre, radius, f"tibia, slice {k}")
        # the other leg's bones are never chosen
        fib = np.nanmean(c.fibula[k, :, :2], axis=0)
        assert np.hypot(*(fib - (mine.centre_at(k) + mine.fibula_mm))) < 0.1, k


def test_slices_into_the_ankle_and_the_knee_are_named_in_one_refusal():
    # slices 0-1: the ankle (no tibia section); slice 9: the knee (the tibia's plateau, 4.8 times its shaft's area)
    leg = Leg((0.0, 0.0), ankle_slices=(0, 1), knee_slices=(9,))
    vol = masked_legs([leg], n=(112, 96, 10), supersample=4)
    with pytest.raises(
        SegmentationError,
        match=r"3 of 10 slices cannot be segmented \(slices 0, 1, 9, .*\): the tibia \(the most anterior dark "
        r"structure along the leg, near x 0\.5 mm, y 2\.6 mm\) is not a closed dark region inside the skin on "
        r"slice\(s\) 0, 1 of 9: .*into the ankle or the knee.*; slice\(s\) 9: no closed bone contour",
    ):
        segment_volume(vol, settings=SETTINGS)
    # the slab without them is segmented within the bounds
    from deeptissue.imaging import crop_volume

    c, _ = segment_volume(crop_volume(vol, [[-20, 20], [-20, 20], [-2.6, 3.6]]), settings=SETTINGS)
    assert c.n_slices == 7
    _assert_leg(c, Leg((0.0, 0.0)), range(7))
