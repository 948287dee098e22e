"""Skin and tibia contours per axial slice from iso-contours of a coil-corrected image.

Per slice (arrays indexed [i, j] as in the NIfTI, converted to world mm by the affine):

1. **Smooth** with a Gaussian of ``smooth_mm`` (noise), in the slice plane only.
2. **Background** ``b``: median of the image's border frame (the Rician noise floor of a
   phantom; 0 for a masked scan). Its robust spread ``s`` gives a noise-based rough tissue
   mask ``I > b + 6 s`` (holes filled, largest component): it does not depend on the coil's
   fall-off as long as the tissue stands above the noise.
3. **Coil sensitivity**: ``log(I - b)`` over the rough mask eroded by ``bias_erode_mm`` is
   fitted by a polynomial of degree ``bias_degree`` in x, y, robustly (pixels more than 25 %
   off the fit — bone, fat, vessels, contrast fluid — are dropped and the fit repeated). The
   normalised image ``N = (I - b) / B`` is ~1 in muscle everywhere, ~0 in background and cortex.
   The level of a boundary is the midpoint between the plateaus on its two sides in ``N``, so
   it is where the blurred edge crosses half height on the well-lit and on the poorly lit side
   alike.
4. **Contrast fluid**: pixels with ``N > fluid_level`` (the indenter's fluid is far brighter than
   tissue) and a ``fluid_guard_mm`` margin around them are set to 0 before the skin is traced,
   so the fluid cannot join the skin contour even where the indenter wall is thin.
5. **Skin**: ``find_contours(N, skin_level)`` (marching squares, sub-pixel), the largest closed
   contour, tissue 8-connected. Automatic level: half the skin/subcutaneous plateau, the median
   of ``N`` in a one-pixel band 1.5 blur widths inside the edge — first the rough mask's edge,
   then twice more inside the traced contour itself, so the band does not move with the noise.
6. **Tibia**: closed contours of ``find_contours(N, bone_level)`` around dark regions inside the
   skin; the largest (``bone_select: largest``) or the most anterior of those at least half as
   large as the largest (``anterior``). Automatic level: half the median muscle value of ``N``
   (cortical bone gives no signal).
7. **Fibula** (``fibula: true``): of the other dark regions inside the skin (same level, outside
   the tibia) with an area from ``fibula_min_area_mm2`` up to ``fibula_max_area_ratio`` times the
   tibia's and round (4 pi A / P^2 >= 0.5, not a thin or ragged gap), the largest. A volume where
   fewer than ``fibula_min_slices`` slices have one has no fibula (a stray dark spot is not a bone
   that runs along the leg); the slices without one are NaN in the ``fibula`` array of the
   contour file.
8. Every contour is resampled (:func:`deeptissue.contours.resample_closed`): ``n_points``
   points equidistant in arc length (PCHIP), counter-clockwise, starting at ``start_angle_deg``
   about its own area centroid.

Hand-drawn contours (a YAML file, see :func:`load_overrides`) replace the automatic result on
the slices and structures they name.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import yaml
from scipy import ndimage

from .contours import Contours, point_to_polygon_distance, points_in_polygon, polygon_area_centroid, resample_closed
from .imaging import ImagingError, Volume

__all__ = ["STRUCTURES", "SegmentationError", "SegmentationSettings", "contour_accuracy", "load_overrides",
           "segment_files", "segment_volume", "write_accuracy"]

STRUCTURES = ("skin", "bone", "fibula")
# the skin plateau is read in a 1-pixel band starting this many blur widths (+ pixels) inside the edge
_BAND_SIGMAS, _BAND_PX = 1.5, 0.0
# a fibula candidate's isoperimetric ratio 4 pi A / P^2 (1 for a circle; the phantom's ~0.95)
_FIBULA_MIN_ROUNDNESS = 0.5


class SegmentationError(ValueError):
    """A slice that cannot be segmented; the message names animal, file, slice and problem."""


@dataclass(frozen=True)
class SegmentationSettings:
    """Settings of :func:`segment_volume` (config ``segmentation`` plus per-animal overrides)."""

    n_points: int = 100
    start_angle_deg: float = 90.0
    smooth_mm: float = 0.15
    skin_level: float | None = None  # in N units (background 0, local muscle 1); None: automatic
    bone_level: float | None = None
    fluid_level: float | None = 1.6
    fluid_guard_mm: float = 0.2
    bias_degree: int = 3
    bias_erode_mm: float = 0.6
    bone_min_area_mm2: float = 1.0
    bone_select: str = "largest"
    fibula: bool = True
    fibula_min_area_mm2: float = 0.1
    fibula_max_area_ratio: float = 0.6
    fibula_min_slices: int = 3

    @classmethod
    def from_config(cls, *dicts: dict | None) -> "SegmentationSettings":
        """Merge config mappings (later ones win, a null included: null levels mean automatic)."""
        known = {f.name for f in fields(cls)}
        kw: dict = {}
        for d in dicts:
            for k, v in (d or {}).items():
                if k in known:
                    kw[k] = v
        return cls(**kw)


def load_overrides(path: str | Path) -> dict:
    """Read a manual-override YAML: ``{state: {structure: {slice: [[x, y], ...]}}}``.

    ``state`` is ``pre`` or ``during``, ``structure`` ``skin``, ``bone`` (the tibia) or ``fibula``, ``slice`` the axial
    slice index in the NIfTI file (0-based), points world mm (x, y) of a closed curve (at least 4,
    in either orientation; it is resampled like an automatic contour).
    """
    with open(path) as fh:
        data = yaml.safe_load(fh) or {}
    out: dict = {}
    for state, per in data.items():
        if state not in ("pre", "during"):
            raise ValueError(f"{path}: unknown state {state!r} (pre, during)")
        for structure, slices in (per or {}).items():
            if structure not in STRUCTURES:
                raise ValueError(f"{path}: unknown structure {structure!r} (skin, bone, fibula)")
            for k, pts in (slices or {}).items():
                a = np.asarray(pts, float)
                if a.ndim != 2 or a.shape[1] < 2 or len(a) < 4:
                    raise ValueError(f"{path}: {state}.{structure}.{k}: expected at least 4 points [x, y]")
                out.setdefault(state, {}).setdefault(structure, {})[int(k)] = a[:, :2]
    return out


# ---------------------------------------------------------------------------------------------


def _poly_terms(u, v, degree):
    return np.stack([u**p * v**q for p in range(degree + 1) for q in range(degree + 1 - p)], -1)


def _bias_field(img_minus_bg, mask, fit_mask, degree):
    """Smooth multiplicative sensitivity B (same shape) fitted to log intensity over ``fit_mask``."""
    ni, nj = img_minus_bg.shape
    ii, jj = np.nonzero(fit_mask)
    vals = img_minus_bg[ii, jj]
    good = vals > 0
    ii, jj, vals = ii[good], jj[good], vals[good]
    if len(vals) < 10:
        level = np.median(img_minus_bg[mask]) if mask.any() else 1.0
        return np.full(img_minus_bg.shape, max(level, 1e-12))
    ci, cj, sc = ii.mean(), jj.mean(), max(ii.std(), jj.std(), 1.0) * 2
    logv = np.log(vals)
    # start from the bulk of the tissue: neither dark (bone) nor far brighter (contrast fluid)
    keep = np.abs(logv - np.median(logv)) < np.log(2.0)
    coef = None
    for _ in range(4):
        A = _poly_terms((ii[keep] - ci) / sc, (jj[keep] - cj) / sc, degree)
        coef, *_ = np.linalg.lstsq(A, logv[keep], rcond=None)
        res = logv - _poly_terms((ii - ci) / sc, (jj - cj) / sc, degree) @ coef
        new = np.abs(res) < np.log(1.25)
        if new.sum() < 10 or np.array_equal(new, keep):
            break
        keep = new
    lo_i, hi_i, lo_j, hi_j = ii[keep].min(), ii[keep].max(), jj[keep].min(), jj[keep].max()
    I, J = np.meshgrid(np.clip(np.arange(ni), lo_i, hi_i), np.clip(np.arange(nj), lo_j, hi_j), indexing="ij")
    return np.exp(_poly_terms((I - ci) / sc, (J - cj) / sc, degree) @ coef)


def _closed_contours(img, level, fully_connected="low"):
    from skimage.measure import find_contours

    cs = find_contours(img, level, fully_connected=fully_connected)
    return [c for c in cs if len(c) >= 5 and np.allclose(c[0], c[-1])]


def _contour_mean(img, c):
    """Mean of ``img`` over the pixels whose centres lie inside the closed (i, j) contour ``c``."""
    i0, j0 = np.floor(c.min(0)).astype(int)
    i1, j1 = np.ceil(c.max(0)).astype(int)
    I, J = np.meshgrid(np.arange(max(i0, 0), min(i1 + 1, img.shape[0])), np.arange(max(j0, 0), min(j1 + 1, img.shape[1])), indexing="ij")
    P = np.column_stack([I.ravel(), J.ravel()])
    inside = points_in_polygon(P, c)
    if not inside.any():
        return float(img[tuple(np.round(c.mean(0)).astype(int))])
    return float(img[P[inside, 0], P[inside, 1]].mean())


@dataclass
class _SliceResult:
    skin_ij: np.ndarray
    bone_ij: np.ndarray | None
    skin_level: float
    bone_level: float
    fibula_ij: np.ndarray | None = None


def _segment_slice(img, *, bg, noise, px_mm, settings: SegmentationSettings, where: str, need_bone: bool = True):
    s = settings
    rough = img > bg + 6 * noise + 1e-6 * max(float(np.percentile(img, 99)) - bg, 1e-12)
    rough = ndimage.binary_fill_holes(rough)
    lab, n = ndimage.label(rough)
    if n == 0:
        raise SegmentationError(f"{where}: no closed skin contour (no tissue above the background noise)")
    sizes = ndimage.sum(rough, lab, index=np.arange(1, n + 1))
    rough = lab == (1 + int(np.argmax(sizes)))
    erode_px = max(1, int(round(s.bias_erode_mm / px_mm)))
    fit = ndimage.binary_erosion(rough, iterations=erode_px)
    if fit.sum() < 10:
        fit = rough
    B = _bias_field(img - bg, rough, fit, s.bias_degree)
    N = (img - bg) / B
    muscle = float(np.median(N[fit])) if fit.any() else 1.0
    Ns = N
    if s.fluid_level is not None:
        fluid = N > s.fluid_level * muscle
        if fluid.any():
            guard = max(1, int(round(s.fluid_guard_mm / px_mm)))
            fluid = ndimage.binary_dilation(fluid, iterations=guard)
            Ns = N.copy()
            Ns[fluid] = 0.0
    def trace(level):
        # tissue (above the level) is 8-connected, background only 4-connected: single-pixel gaps
        # that touch the outside only diagonally do not cut channels into the skin
        cs = _closed_contours(Ns, level, fully_connected="high")
        if not cs:
            raise SegmentationError(f"{where}: no closed skin contour at level {level:.3g} (does the leg touch the image/crop border?)")
        return max(cs, key=lambda c: abs(polygon_area_centroid(c)[0]))

    def plateau(inside, d1):
        dist = ndimage.distance_transform_edt(inside)
        band = inside & (dist >= d1) & (dist < d1 + 1.0) & (Ns > 0.3 * muscle)
        if band.sum() < 5:
            band = inside & (Ns > 0)
        return float(np.median(Ns[band]))

    if s.skin_level is not None:
        skin_level = float(s.skin_level)
        skin = trace(skin_level)
    else:
        # the skin plateau is read in a band starting _BAND_SIGMAS blur widths inside the edge:
        # first inside the rough (noise-threshold) edge, then, independent of the noise level,
        # inside the traced contour itself
        from skimage.draw import polygon as _raster

        d1 = max(_BAND_SIGMAS * s.smooth_mm / px_mm, 1.0) + _BAND_PX
        skin_level = 0.5 * plateau(rough, d1)
        for _ in range(2):
            skin = trace(skin_level)
            inside = np.zeros_like(rough)
            rr, cc = _raster(skin[:, 0], skin[:, 1], shape=inside.shape)
            inside[rr, cc] = True
            skin_level = 0.5 * plateau(inside, d1)
        skin = trace(skin_level)
    bone_level = float(s.bone_level) if s.bone_level is not None else 0.5 * muscle
    bone = fibula = None
    if need_bone:
        min_area_px = s.bone_min_area_mm2 / px_mm**2
        dark = _closed_contours(N, bone_level)
        cands = []
        for c in dark:
            area = abs(polygon_area_centroid(c)[0])
            if area < min_area_px or not points_in_polygon(c, skin).all():
                continue
            if _contour_mean(N, c) >= bone_level:
                continue  # a bright island, not a dark hole
            cands.append((area, c))
        if not cands:
            raise SegmentationError(f"{where}: no closed bone contour inside the skin at level {bone_level:.3g}")
        amax = max(a for a, _ in cands)
        if s.bone_select == "anterior":
            big = [(a, c) for a, c in cands if a >= 0.5 * amax]
            bone_a, bone = max(big, key=lambda ac: ac[1][:, 1].mean())  # caller maps j to +y
        else:
            bone_a, bone = max(cands, key=lambda ac: ac[0])
        if s.fibula:
            fibula = _pick_fibula(N, dark, skin, bone, bone_a, bone_level, px_mm=px_mm, settings=s)
    return _SliceResult(skin, bone, skin_level, bone_level, fibula)


def _pick_fibula(N, contours, skin, bone, bone_area_px, level, *, px_mm, settings: SegmentationSettings):
    """The fibula's (i, j) contour in one slice, or None: of the closed ``contours`` at ``level``, the largest dark one
    inside the skin and outside the tibia with an area from ``fibula_min_area_mm2`` to
    ``fibula_max_area_ratio`` x the tibia's (``bone_area_px``, pixels)."""
    s = settings
    lo, hi = s.fibula_min_area_mm2 / px_mm**2, s.fibula_max_area_ratio * bone_area_px
    best = None
    for c in contours:
        area = abs(polygon_area_centroid(c)[0])
        if not lo <= area <= hi or (best is not None and area <= best[0]):
            continue
        perimeter = float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())
        if 4 * np.pi * area / max(perimeter, 1e-12) ** 2 < _FIBULA_MIN_ROUNDNESS:
            continue  # a thin or ragged dark gap (fascia, vessel), not a round bone
        if not points_in_polygon(c, skin).all() or points_in_polygon(c, bone).any() or points_in_polygon(bone, c).any():
            continue  # outside the skin, the tibia itself, or a region inside / around it
        if _contour_mean(N, c) >= level:
            continue  # a bright island
        best = (area, c)
    return None if best is None else best[1]


def segment_volume(vol: Volume, *, settings: SegmentationSettings = SegmentationSettings(), state: str = "pre",
                   overrides: dict | None = None) -> tuple[Contours, dict]:
    """Skin, tibia and (where found) fibula contours on every slice of ``vol`` (steps in the module docstring).

    Parameters
    ----------
    vol : Volume
        The (cropped) image; axial slices ``data[:, :, k]``.
    settings : SegmentationSettings
        Smoothing, levels, coil-fit and fibula options.
    state : {'pre', 'during'}
        Which part of ``overrides`` applies.
    overrides : dict or None
        From :func:`load_overrides`: hand-drawn contours that replace the automatic ones on the
        slices and structures they name.

    Returns
    -------
    contours : Contours
        ``skin``, ``bone`` (n_slices, n_points, 3) [mm, world], each slice at the z of its centre;
        ``fibula`` the same shape with NaN rows on the slices without one, None when no slice has one.
    info : dict
        ``background`` and ``noise`` (image units), ``slices`` (one row per slice: ``slice`` index in
        the file, ``z_mm``, ``skin_level`` / ``bone_level`` in N units, ``*_source`` auto / manual /
        none / dropped), ``settings``, ``fibula_slices`` (count).

    Raises
    ------
    SegmentationError
        Naming animal, file and slice, if a slice has no closed skin or bone contour, or a bone or
        fibula contour lies outside the skin.
    ValueError
        For an unknown ``bone_select``.
    """
    s = settings
    if s.bone_select not in ("largest", "anterior"):
        raise ValueError(f"segmentation.bone_select: {s.bone_select!r} is not 'largest' or 'anterior'")
    px = vol.pixel_mm
    px_mm = float(np.sqrt(px[0] * px[1]))
    data = vol.data.astype(float)
    sig = (s.smooth_mm / px[0], s.smooth_mm / px[1], 0.0)
    sm = ndimage.gaussian_filter(data, sig, mode="nearest") if s.smooth_mm > 0 else data
    frame = np.concatenate([sm[:3].ravel(), sm[-3:].ravel(), sm[:, :3].ravel(), sm[:, -3:].ravel()])
    bg = float(np.median(frame))
    noise = float(1.4826 * np.median(np.abs(frame - bg)))
    ov = (overrides or {}).get(state, {})
    off = vol.index_offset[2]
    # +y direction in index space (for the 'anterior' choice): flip j if the affine's y runs opposite
    flip_j = vol.affine[1, 1] < 0
    skins, bones, fibulas, info_slices = [], [], [], []
    for k in range(vol.n_slices):
        where = vol.where(k)
        kf = k + off
        manual = {st: ov.get(st, {}).get(kf) for st in STRUCTURES}
        img = sm[:, :, k]
        if flip_j:
            img = img[:, ::-1]
        auto_fibula = s.fibula and manual["fibula"] is None
        need_auto = manual["skin"] is None or manual["bone"] is None or auto_fibula
        res = None
        if need_auto:
            try:
                res = _segment_slice(img, bg=bg, noise=noise, px_mm=px_mm, settings=s, where=where,
                                     need_bone=manual["bone"] is None or auto_fibula)
            except SegmentationError:
                if manual["bone"] is None or manual["skin"] is None:
                    raise
                res = None  # skin and tibia drawn by hand: no automatic fibula on this slice
        z_c = float(vol.world([(vol.data.shape[0] - 1) / 2, (vol.data.shape[1] - 1) / 2, k])[2])
        out = {}
        for st in STRUCTURES:
            if manual[st] is not None:
                xy = manual[st]
            else:
                ij = None if res is None else getattr(res, f"{st}_ij")
                if ij is None:  # no fibula found (or not searched) on this slice
                    out[st] = None
                    continue
                if flip_j:
                    ij = np.column_stack([ij[:, 0], vol.data.shape[1] - 1 - ij[:, 1]])
                xy = vol.world(np.column_stack([ij, np.full(len(ij), k)]))[:, :2]
            try:
                r = resample_closed(xy, n_points=s.n_points, start_angle_deg=s.start_angle_deg)
            except ValueError as exc:
                if st == "fibula" and manual[st] is None:  # an automatic candidate that is not a bone's outline
                    out[st] = None
                    continue
                raise SegmentationError(f"{where}: {st} contour: {exc}") from exc
            out[st] = np.column_stack([r, np.full(s.n_points, z_c)])
        for st in ("bone", "fibula"):
            if out[st] is None:
                continue
            inside = points_in_polygon(out[st][:, :2], out["skin"][:, :2])
            if not inside.all():
                raise SegmentationError(f"{where}: {st} contour outside the skin ({int((~inside).sum())} of {len(inside)} points)")
        skins.append(out["skin"])
        bones.append(out["bone"])
        fibulas.append(out["fibula"])
        info_slices.append({
            "slice": kf,
            "z_mm": z_c,
            "skin_level": None if res is None else res.skin_level,
            "bone_level": None if res is None else res.bone_level,
            "skin_source": "manual" if manual["skin"] is not None else "auto",
            "bone_source": "manual" if manual["bone"] is not None else "auto",
            "fibula_source": "manual" if manual["fibula"] is not None else ("auto" if out["fibula"] is not None else "none"),
        })
    n_auto = sum(1 for r in info_slices if r["fibula_source"] == "auto")
    if s.fibula and 0 < n_auto < s.fibula_min_slices:
        # a dark spot on a slice or two is not a bone that runs along the leg: drop the automatic ones
        for k, r in enumerate(info_slices):
            if r["fibula_source"] == "auto":
                fibulas[k] = None
                r["fibula_source"] = "dropped"
    found = [f is not None for f in fibulas]
    fibula = None
    if any(found):
        fibula = np.stack([f if f is not None else np.full((s.n_points, 3), np.nan) for f in fibulas])
    info = {"background": bg, "noise": noise, "slices": info_slices, "settings": s.__dict__,
            "fibula_slices": int(sum(found))}
    return Contours(skin=np.stack(skins), bone=np.stack(bones), fibula=fibula), info


def contour_accuracy(seg: Contours, truth: Contours | dict) -> list[dict]:
    """In-plane distances from segmented points to the true contour, per slice and structure.

    Parameters
    ----------
    seg : Contours
        Segmented contours.
    truth : Contours or dict
        The true contours (each curve taken as the closed polygon through its points), or a dict
        ``structure -> list of (m, 2|3) dense polylines per slice`` [mm].

    Returns
    -------
    list of dict
        Rows ``{slice, structure, mean_mm, max_mm}`` (slice counted in ``seg``); the fibula's only
        on the slices where both the segmentation and the truth have one.
    """
    rows = []
    for st in STRUCTURES:
        segs = getattr(seg, st)
        true = truth.get(st) if isinstance(truth, dict) else getattr(truth, st)
        if segs is None or true is None:
            continue
        for k in range(segs.shape[0]):
            t = np.asarray(true[k], float)
            if not np.isfinite(segs[k]).all() or not np.isfinite(t).all():
                continue  # fibula absent from this slice in the segmentation or the truth
            d = point_to_polygon_distance(segs[k, :, :2], t[:, :2])
            rows.append({"slice": k, "structure": st, "mean_mm": float(d.mean()), "max_mm": float(d.max())})
    return rows


def segment_files(image, *, contours_out, qc_out, animal: str, state: str, settings: dict | SegmentationSettings,
                  crop_mm=None, reference=None, overrides=None, truth=None) -> Contours:
    """The rule ``segment``: load and check the image, segment, write contours and the QC figure.

    Parameters
    ----------
    image : str or Path
        NIfTI to segment.
    contours_out, qc_out : str or Path
        Contour file (:func:`deeptissue.contours.save_contours`) and QC figure (PNG) to write.
    animal : str
        Animal name, for messages.
    state : {'pre', 'during'}
        State of ``image`` (selects the overrides).
    settings : dict or SegmentationSettings
        Config ``segmentation`` mapping (merged by :meth:`SegmentationSettings.from_config`) or settings.
    crop_mm : (3, 2) array_like or None
        World box [[xmin, xmax], [ymin, ymax], [zmin, zmax]] [mm] to crop to before segmenting.
    reference : str or Path or None
        The pre image that a during ``image`` must match slice by slice.
    overrides : str or Path or None
        Manual-override YAML (:func:`load_overrides`).
    truth : str or Path or None
        Truth contour file (phantom), drawn in the QC figure with the distances to it in the title.

    Returns
    -------
    Contours
        What was written to ``contours_out``.
    """
    from .contours import load_contours, save_contours
    from .imaging import check_matching, crop_volume, load_nifti
    from .qc import plot_segmentation

    vol = load_nifti(image, animal=animal)
    if reference is not None:
        check_matching(load_nifti(reference, animal=animal), vol)
    if crop_mm is not None:
        vol = crop_volume(vol, crop_mm)
    if not isinstance(settings, SegmentationSettings):
        settings = SegmentationSettings.from_config(settings)
    ov = load_overrides(overrides) if overrides else None
    contours, info = segment_volume(vol, settings=settings, state=state, overrides=ov)
    import logging

    log = logging.getLogger(__name__)
    log.info("%s %s: background %.4g, noise %.4g", animal, state, info["background"], info["noise"])
    for row in info["slices"]:
        log.info("slice %(slice)d z %(z_mm).2f mm: skin %(skin_source)s (level %(skin_level)s), "
                 "bone %(bone_source)s (level %(bone_level)s), fibula %(fibula_source)s", row)
    if not settings.fibula:
        log.info("%s %s: fibula not segmented (segmentation.fibula is false)", animal, state)
    elif info["fibula_slices"] == 0:
        log.info("%s %s: no fibula found on any slice; the contour file has no 'fibula' array", animal, state)
    else:
        log.info("%s %s: fibula on %d of %d slices", animal, state, info["fibula_slices"], len(info["slices"]))
    true = load_contours(truth) if truth else None
    rows = contour_accuracy(contours, true) if true is not None else None
    save_contours(contours_out, contours)
    plot_segmentation(vol, contours, qc_out, truth=true, accuracy=rows, title=f"{animal} {state}")
    return contours


def write_accuracy(contours_path, truth_path, csv_path) -> list[dict]:
    """Write the CSV of :func:`contour_accuracy` (slice, structure, mean_mm, max_mm) of a contour file vs a truth file.

    Parameters
    ----------
    contours_path, truth_path : str or Path
        Contour files (:func:`deeptissue.contours.load_contours`), segmented and true.
    csv_path : str or Path
        Output CSV, distances [mm].

    Returns
    -------
    list of dict
        The rows written.
    """
    import pandas as pd

    from .contours import load_contours
    from .io import atomic_path

    rows = contour_accuracy(load_contours(contours_path), load_contours(truth_path))
    with atomic_path(csv_path) as tmp:
        pd.DataFrame(rows).to_csv(tmp, index=False, float_format="%.5f")
    return rows
