"""Phantom truth sanity: grid and affine, indenter travel, tip on the indenter and the skin, bone motion."""

import numpy as np
import pytest

from deeptissue.contours import points_in_polygon, polygon_area_centroid
from deeptissue.phantom import PhantomSpec, _Scene, make_phantom
from deeptissue.rigid import apply_rigid

SPEC = PhantomSpec(
    seed=1,
    depth_mm=2.0,
    tilt_deg=(5.0, -3.0),
    bone_rotation_deg=(1.0, -0.5, 0.8),
    bone_translation_mm=(0.05, -0.10, 0.02),
    snr=20,
)


@pytest.fixture(scope="module")
def ph():
    return make_phantom(SPEC)


def test_grid_and_affine(ph):
    assert ph.pre.shape == ph.during.shape == (256, 256, 20)
    assert ph.pre.dtype == np.float32
    np.testing.assert_allclose(np.diag(ph.affine)[:3], [25 / 256, 25 / 256, 1.0])
    # voxel centres span the 25 mm field of view symmetrically about 0
    corner0 = ph.affine @ [0, 0, 0, 1]
    corner1 = ph.affine @ [255, 255, 19, 1]
    np.testing.assert_allclose(corner0[:2] + corner1[:2], 0, atol=1e-12)
    np.testing.assert_allclose(corner1[:2] - corner0[:2], 25 - 25 / 256)
    np.testing.assert_allclose(np.diff(ph.z_mm), 1.0)


def test_leg_size_and_taper(ph):
    for k in range(20):
        xy = ph.truth_pre.skin[k, :, :2]
        across = np.linalg.norm(xy[:, None] - xy[None], axis=-1).max()
        assert 8.0 <= across <= 11.0
    areas = [polygon_area_centroid(ph.truth_pre.skin[k, :, :2])[0] for k in range(20)]
    assert areas[-1] > areas[0] * 1.1  # tapers distally (z grows proximally)


def test_indenter_truth(ph):
    t = ph.truth
    assert np.linalg.norm(t.indenter_axis) == pytest.approx(1.0)
    assert t.indenter_axis[1] < -0.9  # from the anterior coil side into the leg
    # travel: 1 mm approach plus the depth
    assert t.travel_mm == pytest.approx(SPEC.depth_mm + 1.0, abs=1e-9)
    np.testing.assert_allclose(
        (t.tip_end_mm - t.tip_start_mm) / t.travel_mm, t.indenter_axis, atol=1e-12
    )
    # the skin point is on the pre skin (independently: the truth contour of its slice, interpolated in z)
    sc = _Scene(SPEC)
    skin_pt = np.array(t.extra["skin_point_mm"])
    assert abs(sc.an.phi_pre(*skin_pt)) < 1e-9
    # the final tip is on the indenter surface and on the deformed skin (the skin conforms to the head)
    tip = t.tip_end_mm
    assert abs(sc.indenter_sd(*tip)) < 1e-9
    assert abs(sc.phi(*tip, "during")) < 1e-9
    # the head centre is 1.5 mm behind the tip along the axis
    np.testing.assert_allclose(sc.head_centre, tip - 1.5 * t.indenter_axis)
    # the indenter is aimed at the tibia: the axis line passes through the tibia centre at indenter_z
    c = np.array([*sc.an.tib_centre(0.0), 0.0])
    d = np.linalg.norm(np.cross(c - tip, t.indenter_axis))
    assert d < 1e-9
    # the head does not reach the bone
    assert t.extra["bone_indenter_gap_mm"] > 0.3


def test_bone_motion_and_com(ph):
    t = ph.truth
    # COM from the dense truth boundaries (marching squares of the level function on a 0.01 mm
    # grid; area-weighted slice centroids) agrees with the phantom's polar integrals
    A, C = [], []
    for k in range(20):
        a, c = polygon_area_centroid(ph.dense[("pre", "bone")][k][:, :2])
        A.append(abs(a))
        C.append([*c, ph.z_mm[k]])
    com = (np.array(A)[:, None] * np.array(C)).sum(0) / np.sum(A)
    np.testing.assert_allclose(com, t.bone_com_mm, atol=5e-5)
    # and from the 100-point contours a segmentation gives: the polygon cuts the rounded corners,
    # which differ along z, so the centroid's z is off by a few tenths of a micrometre
    A, C = [], []
    for k in range(20):
        a, c = polygon_area_centroid(ph.truth_pre.bone[k, :, :2])
        A.append(abs(a))
        C.append([*c, ph.z_mm[k]])
    com = (np.array(A)[:, None] * np.array(C)).sum(0) / np.sum(A)
    np.testing.assert_allclose(com, t.bone_com_mm, atol=5e-4)
    # a during-bone boundary point maps back onto the pre bone surface
    sc = _Scene(SPEC)
    k = 10
    pts = ph.dense[("during", "bone")][k][::50]
    back = apply_rigid(
        pts - t.bone_com_mm - t.bone_translation_mm + t.bone_com_mm,
        rotation_deg=-np.asarray(t.bone_rotation_deg),
        centre_mm=t.bone_com_mm,
        translation_mm=[0, 0, 0],
    )
    f = sc.an.bone_f(back[:, 0], back[:, 1], back[:, 2])
    assert np.abs(f).max() < 2e-3
    # and the centroid of the during bone moved roughly by the translation (rotation is small)
    a, c_during = polygon_area_centroid(ph.truth_during.bone[k, :, :2])
    a, c_pre = polygon_area_centroid(ph.truth_pre.bone[k, :, :2])
    assert np.linalg.norm(c_during - c_pre) < 0.5


def test_coil_falloff_and_noise(ph):
    # posterior side has poor signal: muscle near the posterior skin well below the anterior
    img = ph.pre[:, :, 10]
    xy = ph.truth_pre.skin[10, :, :2]
    top, bottom = xy[:, 1].max(), xy[:, 1].min()
    j_top = int(round((top - 1.0 - ph.affine[1, 3]) / ph.affine[1, 1]))
    j_bot = int(round((bottom + 1.0 - ph.affine[1, 3]) / ph.affine[1, 1]))
    i_c = 128
    ant = img[i_c - 3 : i_c + 4, j_top - 3 : j_top + 4].mean()
    post = img[i_c - 3 : i_c + 4, j_bot - 3 : j_bot + 4].mean()
    assert post < 0.6 * ant
    # Rician background: mean = sigma sqrt(pi / 2)
    bg = ph.pre[:20, :20, :]
    assert bg.mean() == pytest.approx(ph.noise_sigma * np.sqrt(np.pi / 2), rel=0.05)


def test_during_skin_excludes_indenter(ph):
    sc = _Scene(SPEC)
    for k in range(20):
        pts = ph.dense[("during", "skin")][k]
        sd = sc.indenter_sd(pts[:, 0], pts[:, 1], pts[:, 2])
        assert sd.min() > -0.02
        # bone inside skin
        assert points_in_polygon(
            ph.truth_during.bone[k, :, :2], ph.truth_during.skin[k, :, :2]
        ).all()


def test_tibia_is_a_tapering_rounded_triangle():
    """The tibia is not a prism: rounded-triangular, convex, tapering and flaring along z."""
    sc = _Scene(SPEC)
    an = sc.an
    area = np.array([an.tib_area_centroid(float(z))[0] for z in sc.z])
    assert np.all(np.diff(area) > 0)  # wider proximally (+z)
    assert area[-1] > 1.5 * area[0]
    xy = an.tib_boundary(0.0, 720)
    across = np.linalg.norm(xy[:, None] - xy[None], axis=-1).max()
    assert 1.8 <= across <= 2.6
    r = np.hypot(*(xy - np.array(an.tib_centre(0.0))).T)
    assert (
        r.max() / r.min() > 1.3
    )  # corners stand out (an ellipse with axes 1.15, 0.95 gives 1.21)
    e1 = np.roll(xy, -1, axis=0) - xy
    e0 = xy - np.roll(xy, 1, axis=0)
    assert np.all(e0[:, 0] * e1[:, 1] - e0[:, 1] * e1[:, 0] > 0)  # convex, counter-clockwise
    # three corners: local maxima of the radius
    n_max = np.sum((r > np.roll(r, 1)) & (r > np.roll(r, -1)))
    assert n_max == 3
    # a 0.5 deg turn about the centre moves the boundary by up to 0.0059 mm: the corners make a turn visible
    th = np.radians(0.5)
    c = np.array(an.tib_centre(0.0))
    rot = (xy - c) @ np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]]) + c
    moved = np.abs(an.bone_f(rot[:, 0], rot[:, 1], 0.0))
    assert moved.max() > 0.004


@pytest.mark.parametrize(
    "bad", [dict(tibia_inradius_mm=0.4), dict(tibia_taper=0.08), dict(tibia_rounding_slope=0.03)]
)
def test_impossible_tibia_is_refused(bad):
    with pytest.raises(ValueError, match="phantom: .*tibia"):
        _Scene(PhantomSpec(seed=1, **bad))


def test_fibula_is_a_thin_oblique_bone_that_moves_with_the_tibia(ph):
    """The fibula: thin, lateral-posterior, clear of tibia and skin, crossing the slices obliquely
    (a shift along z moves it in the slice), and moved rigidly with the tibia in the during state."""
    t = ph.truth
    assert ph.truth_pre.fibula.shape == ph.truth_during.fibula.shape == (20, 100, 3)
    assert ph.truth_pre.fibula_slices.all() and ph.truth_during.fibula_slices.all()
    sc = _Scene(SPEC)
    rel = []
    for k in range(20):
        f = ph.dense[("pre", "fibula")][k][:, :2]
        across = np.linalg.norm(f[:, None] - f[None], axis=-1).max()
        assert 0.6 <= across <= 0.9  # the rat's fibula
        area, cf = polygon_area_centroid(f)
        _, ct = polygon_area_centroid(ph.dense[("pre", "bone")][k][:, :2])
        d = cf - ct
        assert (
            d[0] > 0 and d[1] < 0
        )  # lateral (+x, away from the tibia's side of the leg) and posterior
        # separate from the tibia, inside the skin below the skin layer
        from deeptissue.contours import point_to_polygon_distance

        assert point_to_polygon_distance(f, ph.dense[("pre", "bone")][k][:, :2]).min() >= 0.3
        assert points_in_polygon(f, ph.truth_pre.skin[k, :, :2]).all()
        assert np.all(sc.an.phi_pre(f[:, 0], f[:, 1], ph.z_mm[k]) < -SPEC.skin_thickness_mm)
        rel.append(np.linalg.norm(d))
    # it converges on the tibia distally (-z), fast enough somewhere to show a shift along z:
    # at least 0.4 mm across the slice per mm of z on two neighbouring slice pairs
    speed = np.abs(np.diff(rel))
    assert rel[0] < rel[-1] - 1.0
    assert np.sort(speed)[-2] >= 0.4
    # the during fibula is the pre fibula moved by the tibia's rigid motion (about the tibia's centre)
    for k in (0, 7, 15):
        pts = ph.dense[("during", "fibula")][k][::25]
        back = apply_rigid(
            pts - t.bone_translation_mm,
            rotation_deg=-np.asarray(t.bone_rotation_deg),
            centre_mm=t.bone_com_mm,
            translation_mm=[0, 0, 0],
        )
        assert np.abs(sc.an.fibula_f(back[:, 0], back[:, 1], back[:, 2])).max() < 2e-3
    # and it is dark in the image: cortex and marrow below half the muscle signal
    k = 10
    cf = polygon_area_centroid(ph.truth_pre.fibula[k, :, :2])[1]
    i, j = np.round((cf - ph.affine[:2, 3]) / np.diag(ph.affine)[:2]).astype(int)
    around = ph.pre[i - 12 : i + 13, j - 12 : j + 13, k]
    assert ph.pre[i, j, k] < 0.5 * np.median(around)


def test_phantom_without_fibula():
    spec = PhantomSpec(seed=3, n_slices=3, n_pixels=96, fov_mm=12.0, supersample=2, fibula=False)
    ph = make_phantom(spec)
    assert ph.truth_pre.fibula is None and ph.truth_during.fibula is None
    assert ("pre", "fibula") not in ph.dense
    with_fib = make_phantom(PhantomSpec(**{**spec.__dict__, "fibula": True}))
    # the same leg and tibia, with the fibula's dark spot added
    np.testing.assert_allclose(ph.truth_pre.bone, with_fib.truth_pre.bone)
    np.testing.assert_allclose(ph.truth.bone_com_mm, with_fib.truth.bone_com_mm)
    assert (with_fib.pre < ph.pre - 0.3).sum() > 50


@pytest.mark.parametrize(
    "bad, what",
    [
        (dict(fibula_offset_mm=5.0), "skin"),
        (dict(fibula_distal_offset_mm=1.3), "tibia"),
        (dict(fibula_cortex_mm=0.38), "marrow"),
    ],
)
def test_impossible_fibula_is_refused(bad, what):
    with pytest.raises(ValueError, match=f"phantom: .*fibula.*{what}"):
        _Scene(PhantomSpec(seed=1, **bad))


@pytest.mark.parametrize(
    "key, value",
    [
        ("bone_rotation_deg", (float("nan"), 0.0, 0.0)),
        ("snr", float("nan")),
        ("depth_mm", float("inf")),
        ("tilt_deg", (0.0, float("-inf"))),
    ],
)
def test_non_finite_parameters_are_refused_naming_the_key(key, value):
    with pytest.raises(ValueError, match=rf"phantom: {key} .*: not a finite number"):
        PhantomSpec(**{key: value})


def test_the_tilt_range_check_indenter_advertises_keeps_the_fluid_column_in_the_image():
    # the pose stage fails with less than 5 mm of fluid column (pose.checks.LIMITS): 60 deg leaves 1.8 mm of the
    # fluid's axis in the 19 mm slab, so check_indenter refuses it and advertises a range that keeps 5 mm
    import re

    from deeptissue.phantom import (
        _affine,
        _Anatomy,
        _fluid_in_image,
        _indenter_entry,
        check_indenter,
    )

    spec = PhantomSpec(tilt_deg=(60.0, 0.0))
    with pytest.raises(ValueError, match=r"5 mm of its fluid column in the image") as exc:
        check_indenter(spec)
    lo, hi = map(float, re.search(r"works from (\S+) to (\S+) deg", str(exc.value)).groups())
    assert -60.0 < lo < -45.0 and 45.0 < hi < 60.0
    z = _affine(spec)[2, 2] * np.arange(spec.n_slices) + _affine(spec)[2, 3]
    for tilt in (lo, hi):
        s = PhantomSpec(tilt_deg=(tilt, 0.0))
        check_indenter(s)
        axis, skin = _indenter_entry(_Anatomy(s), s, s.tilt_deg)
        front = skin + (s.depth_mm - s.indenter_wall_mm) * axis
        # the column's axis from its front back to where it leaves the slab, by hand: dz / |axis_z|
        dz = (z.max() - front[2]) if -axis[2] > 0 else (front[2] - z.min())
        by_hand = dz / abs(axis[2])
        # at these tilts the column leaves through the slab's end, not the in-plane field of view
        assert _fluid_in_image(s, front, axis, (z.min(), z.max())) == pytest.approx(
            by_hand, abs=1e-9
        )
        assert by_hand >= 5.0 - 1e-6


def test_bones_evaluated_near_their_boundaries_give_the_whole_grids_contours_and_image():
    """The truth contours and the anti-aliased image evaluate the bones' level functions only near their
    boundaries; against every grid point and every sub-sample, the answer is the same to the bit."""
    from functools import partial

    from skimage.measure import find_contours

    from deeptissue.phantom import _level_grid

    # a bone moved more than the demo's, so that the moved tibia's slices are tilted
    sc = _Scene(PhantomSpec(seed=3, depth_mm=1.5, bone_rotation_deg=(3.0, -2.0, 4.0)))
    z = float(sc.z[13])
    for state in ("pre", "during"):
        tibia, fibula = np.array(sc.an.tib_centre(z)), np.array(sc.an.fib_centre(z))
        for fn, h, centre, half in (
            (partial(sc.bone, z=z, state=state), 0.01, tibia, 2.5),
            (partial(sc.fibula, z=z, state=state), 0.005, fibula, 1.0),
        ):
            x = centre[0] + np.arange(-half, half, h)
            y = centre[1] + np.arange(-half, half + 0.2, h)
            whole = fn(*np.meshgrid(x, y, indexing="ij"))
            banded = _level_grid(fn, x, y, h_mm=h)
            assert np.array_equal(np.sign(banded), np.sign(whole))
            filled = banded != whole
            assert filled.sum() > 0.7 * whole.size  # most of the grid was not evaluated
            # ... and more than two grid steps from the boundary: no grid edge from it crosses the boundary
            assert np.abs(whole[filled]).min() > 2 * h
            cs_whole, cs_banded = find_contours(whole, 0.0), find_contours(banded, 0.0)
            assert len(cs_whole) == len(cs_banded) >= 1
            assert all(np.array_equal(a, b) for a, b in zip(cs_whole, cs_banded))
        # every sub-sample of every pixel near a boundary, every level function evaluated at each
        n, S, dx = sc.s.n_pixels, sc.s.supersample, sc.affine[0, 0]
        xc = sc.affine[0, 3] + np.arange(n) * dx
        XC, YC = np.meshgrid(xc, xc, indexing="ij")
        lv = sc._levels(XC, YC, z, state)
        img = sc._intensity(lv)
        near = np.nonzero(sc._margin(lv) < 1.5 * dx)
        off = ((np.arange(S) + 0.5) / S - 0.5) * dx
        ox, oy = np.meshgrid(off, off, indexing="ij")
        Xs, Ys = XC[near][:, None] + ox.ravel(), YC[near][:, None] + oy.ravel()
        img[near] = sc._intensity(sc._levels(Xs, Ys, z, state)).mean(axis=1)
        assert np.array_equal(sc.render_slice(13, state), img * sc.coil(XC, YC, z))
