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
   then twice more inside the traced contour itself, so the band does not move with the noise. With
   ``skin_close_mm`` the tissue's gaps narrower than twice it are bridged first (:func:`_closed_tissue`), so
   the broken skin ring of a masked scan is one outline.
6. **Tibia**, chosen in 3D (:func:`_choose_tibia`): of the closed contours of ``find_contours(N,
   bone_level)`` around dark regions inside the skin, and the thick cores that an opening by a disc of
   ``bone_open_mm`` parts from dark layers and septa (:func:`_bone_candidates`, :func:`_open_cores`), linked from slice to slice into tracks, the
   one that runs through the slab: the largest (``bone_select: largest``) or the most anterior of
   those at least half as large (``anterior``). Where a dark region holds a neighbouring slice's tibia together
   with another of its dark structures (the tibia joined to the fibula by a septum wider than the opening
   parts), it is parted by a watershed seeded from that slice (:func:`_part_joined`) and the tibia chosen again.
   A slice without it is refused by number, never given another structure. Automatic level: half the median
   muscle value of ``N`` (cortical bone gives no signal).
7. **Fibula** (``fibula: true``), chosen in 3D (:func:`_choose_fibula`): the other dark regions inside
   the skin (same level, outside the tibia) with an area from ``fibula_min_area_mm2`` up to
   ``fibula_max_area_ratio`` times the tibia's and round (4 pi A / P^2 >= 0.5, not a thin or ragged
   gap) are linked from slice to slice like the tibia's candidates, and the longest track is the
   fibula. A track on fewer than ``fibula_min_slices`` slices is no fibula (a stray dark spot is not a
   bone that runs along the leg); the slices where the track has no candidate are NaN in the
   ``fibula`` array of the contour file.
8. **Indenter** (during scan, ``indenter_mask``): the indenter is found from its contrast fluid
   (:func:`find_indenter`: the pose stage's fluid component and axis, the head and fluid radius from the
   fluid's edge, the outer radius ``pose.head_radius_mm``). Pixels within ``indenter_guard_mm`` of its
   outer surface are set to muscle before the bones are traced, and dark regions cut off there from the
   background are filled before the skin is traced, so the indenter's dark wall joins neither the tibia's
   cortex nor the skin. A slice whose tibia comes within the guard and a pixel of the indenter is
   ``bone_hidden``: its tibia is the pre tibia moved by the rigid fit of the other slices, and the pose
   stage leaves it out of its fit.
9. Every contour is resampled (:func:`deeptissue.contours.resample_closed`): ``n_points``
   points equidistant in arc length (PCHIP), counter-clockwise, starting at ``start_angle_deg``
   about its own area centroid.

Hand-drawn contours (a YAML file, see :func:`load_overrides`) replace the automatic result on
the slices and structures they name. Where the legs touch, :func:`deeptissue.imaging.split_legs` keeps
the one holding ``leg_point_mm`` before the contours are traced. Every slice that cannot be segmented is
named in one :class:`SlicesFailed`, unless ``end_slices: leave_out`` leaves the slices at the ends of the stack
out (:func:`_leave_out_ends`: the longest run of slices that segment, more than half of them, is kept);
:func:`segment_files` then draws the failed run's QC figure, and runs the checks of
:mod:`deeptissue.segment_checks` on a run that went through.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
from scipy import ndimage
from skimage.draw import polygon as _polygon_px
from skimage.measure import find_contours
from skimage.segmentation import watershed

from .bone_motion import fit_bone_motion, moved_section, resolve_bone_dof
from .contours import (
    STRUCTURES,
    Contours,
    load_contours,
    points_in_polygon,
    polygon_area_centroid,
    resample_closed,
    save_contours,
)
from .fluid import FluidSearch, indenter_shape, inside_skin_mask, orient_axis
from .imaging import (
    ImagingError,
    Volume,
    check_matching,
    check_not_same_scan,
    crop_volume,
    load_nifti,
    slab,
    split_legs,
)
from .io import load_config_file
from .pose_error import PoseError
from .qc import LEFT_OUT, plot_segmentation
from .segment_accuracy import contour_accuracy, write_accuracy
from .segment_checks import failed_checks_message, segmentation_checks, write_checks

log = logging.getLogger(__name__)

__all__ = [
    "STRUCTURES",
    "SegmentationError",
    "SegmentJob",
    "SegmentationSettings",
    "SlicesFailed",
    "contour_accuracy",
    "find_indenter",
    "load_overrides",
    "segment_files",
    "segment_volume",
    "write_accuracy",
]

# the skin plateau is read in a 1-pixel band starting this many blur widths (+ pixels) inside the edge
_BAND_SIGMAS, _BAND_PX = 1.5, 0.0
# a fibula candidate's isoperimetric ratio 4 pi A / P^2 (1 for a circle; the phantom's ~0.95)
_FIBULA_MIN_ROUNDNESS = 0.5
# dark regions on neighbouring slices are one structure only if their areas differ by at most this factor: a bone's
# section changes slowly along the leg, a tibia merged with the fat around it is several times larger
_LINK_AREA_RATIO = 2.0
# a given skin level above which more than this share of the image border lies is in the background: a leg that
# touches the border covers a few of its pixels, the noise of an unmasked scan half of them at its median
_BACKGROUND_SHARE = 0.2


class SegmentationError(ImagingError):
    """A scan that cannot be segmented; the message names animal, file, the slices and the problem."""


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
    bone_open_mm: float | None = None  # None: a tenth of the skin's inscribed radius; 0: off
    skin_close_mm: float = 0.0
    bone_select: str = "largest"
    fibula: bool = True
    fibula_min_area_mm2: float = 0.1
    fibula_max_area_ratio: float = 0.6
    fibula_min_slices: int = 3
    indenter_mask: bool = True
    indenter_guard_mm: float = 0.15
    end_slices: str = (
        "refuse"  # slices at an end of the stack that cannot be segmented: refuse | leave_out
    )

    @classmethod
    def from_config(cls, *dicts: dict | None) -> SegmentationSettings:
        """Merge config mappings (later ones win, a null included: null levels mean automatic)."""
        known = {f.name for f in fields(cls)}
        kw: dict = {}
        for d in dicts:
            for k, v in (d or {}).items():
                if k in known:
                    kw[k] = v
        return cls(**kw)


def load_overrides(path: str | Path, *, n_slices: int | None = None) -> dict:
    """Read a manual-override YAML: ``{state: {structure: {slice: [[x, y], ...]}}}``.

    ``state`` is ``pre`` or ``during``, ``structure`` ``skin``, ``bone`` (the tibia) or ``fibula``, ``slice`` the axial
    slice index in the NIfTI file (0-based), points world mm (x, y) of a closed curve (at least 4,
    in either orientation; it is resampled like an automatic contour). The file is read strictly
    (:func:`deeptissue.io.load_config_file`): a slice given twice for one structure, which YAML would
    silently reduce to the last, is a :class:`deeptissue.io.ConfigError` naming the file, the key and both lines.
    With ``n_slices`` (the slices in the image file), a slice outside 0 .. n_slices - 1 is an error naming the file
    and the slice: it would otherwise replace nothing without a word.
    """
    data = load_config_file(path)
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
                    raise ValueError(
                        f"{path}: {state}.{structure}.{k}: expected at least 4 points [x, y]"
                    )
                per_slice = out.setdefault(state, {}).setdefault(structure, {})
                try:
                    kk = int(k)
                except (TypeError, ValueError):
                    raise ValueError(
                        f"{path}: {state}.{structure}: slice {k!r} is not a slice number"
                    ) from None
                if kk < 0 or (n_slices is not None and kk >= n_slices):
                    has = (
                        ""
                        if n_slices is None
                        else f" of the {n_slices} in the image (0 to {n_slices - 1})"
                    )
                    raise ValueError(
                        f"{path}: {state}.{structure}: slice {kk} is not a slice{has}; give the slice "
                        "index in the NIfTI file, counted from 0"
                    )
                if int(k) in per_slice:  # 9 and '09': one slice written twice
                    raise ValueError(
                        f"{path}: {state}.{structure}: slice {int(k)} is given twice (key {k!r})"
                    )
                per_slice[int(k)] = a[:, :2]
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
    I, J = np.meshgrid(
        np.clip(np.arange(ni), lo_i, hi_i), np.clip(np.arange(nj), lo_j, hi_j), indexing="ij"
    )
    return np.exp(_poly_terms((I - ci) / sc, (J - cj) / sc, degree) @ coef)


def _closed_contours(img, level, fully_connected="low"):
    cs = find_contours(img, level, fully_connected=fully_connected)
    return [c for c in cs if len(c) >= 5 and np.allclose(c[0], c[-1])]


def _contour_mean(img, c):
    """Mean of ``img`` over the pixels whose centres lie inside the closed (i, j) contour ``c``."""
    i0, j0 = np.floor(c.min(0)).astype(int)
    i1, j1 = np.ceil(c.max(0)).astype(int)
    I, J = np.meshgrid(
        np.arange(max(i0, 0), min(i1 + 1, img.shape[0])),
        np.arange(max(j0, 0), min(j1 + 1, img.shape[1])),
        indexing="ij",
    )
    P = np.column_stack([I.ravel(), J.ravel()])
    inside = points_in_polygon(P, c)
    if not inside.any():
        return float(img[tuple(np.round(c.mean(0)).astype(int))])
    return float(img[P[inside, 0], P[inside, 1]].mean())


def _cut_at_indenter(Ns, sd, *, level, fill, guard_mm, px_mm, min_area_px):
    """``Ns`` with the dark regions that reach the outside only through the indenter's rim filled with ``fill``.

    Where the tibia's dark cortex touches the indenter's dark wall, the two and the dark background form one
    region and the skin contour would run into the bone. Cut at ``guard_mm`` from the indenter (``sd``, mm,
    negative inside), the dark regions (below ``level``) of at least ``min_area_px`` pixels (a bone, not a
    pocket of air between the skin and the indenter) that no longer reach the image border are inside the
    leg: they and the rim pixels beside them are set to ``fill``, so the skin runs along the indenter's
    surface there.
    """
    dark = (Ns < level) & (sd >= guard_mm)
    lab, n = ndimage.label(dark)
    if n == 0:
        return Ns
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    big = np.nonzero(sizes >= min_area_px)[0]
    holes = (lab > 0) & ~np.isin(lab, border) & np.isin(lab, big)
    rim = (sd >= 0) & (sd < guard_mm)
    if not (holes & ndimage.binary_dilation(rim, iterations=2)).any():
        return Ns
    near = ndimage.binary_dilation(holes, iterations=max(1, int(np.ceil(guard_mm / px_mm))) + 1)
    out = Ns.copy()
    out[holes | (rim & near)] = fill
    return out


@dataclass
class _SliceResult:
    skin_ij: np.ndarray
    bone_ij: np.ndarray | None
    skin_level: float
    bone_level: float
    fibula_ij: np.ndarray | None = None
    bone_touch_mm: float | None = (
        None  # the tibia contour's smallest distance from the indenter (None: no indenter)
    )
    # the tibia's candidates: (area [px], (i, j) contour) of the closed dark regions inside the skin; None when the
    # bones were not traced or the tibia is hidden against the indenter
    bone_candidates: list | None = None
    # the fibula's candidates, (area [px], (i, j) contour), once the tibia is set (finish); None: not searched
    fibula_candidates: list | None = None
    trace: dict | None = (
        None  # what _finish_bones needs: the image the bones were traced on, dark contours, sd
    )
    choice: int | None = None  # the tibia's index in bone_candidates, once set (finish)

    def finish(
        self, choice: int | None, *, px_mm: float, settings: SegmentationSettings
    ) -> _SliceResult:
        """Set the tibia to candidate ``choice`` (None: the per-slice rule of ``bone_select``), then the fibula's
        candidates (chosen in 3D by :func:`_choose_fibula`) and the tibia's distance from the indenter."""
        if not self.bone_candidates:
            return self
        s = settings
        if choice is None:
            choice = _pick_per_slice(self.bone_candidates, s.bone_select)
        self.choice = choice
        bone_a, bone = self.bone_candidates[choice]
        t = self.trace
        self.bone_ij = bone
        if s.fibula:
            self.fibula_candidates = _fibula_candidates(
                t["Nb"],
                t["dark"],
                self.skin_ij,
                bone,
                bone_a,
                self.bone_level,
                px_mm=px_mm,
                settings=s,
            )
        if t["sd"] is not None:
            self.bone_touch_mm = float(
                ndimage.map_coordinates(t["sd"], bone.T, order=1, mode="nearest").min()
            )
        return self


def _pick_per_slice(cands: list, select: str) -> int:
    """Index of the largest candidate, or (``anterior``) the most anterior of those at least half as large."""
    amax = max(a for a, _ in cands)
    if select == "anterior":
        big = [i for i, (a, _) in enumerate(cands) if a >= 0.5 * amax]
        return max(big, key=lambda i: cands[i][1][:, 1].mean())  # the caller maps j to +y
    return max(range(len(cands)), key=lambda i: cands[i][0])


def _normalised(img, *, bg, noise, px_mm, settings: SegmentationSettings, where: str):
    """``(N, rough, muscle)``: the coil-corrected image (steps 2-3 of the module docstring), the rough tissue mask
    (largest component above the noise) and the median of ``N`` in muscle."""
    s = settings
    rough = img > bg + 6 * noise + 1e-6 * max(float(np.percentile(img, 99)) - bg, 1e-12)
    rough = ndimage.binary_fill_holes(rough)
    lab, n = ndimage.label(rough)
    if n == 0:
        raise SegmentationError(
            f"{where}: no closed skin contour (no tissue above the background noise)"
        )
    sizes = ndimage.sum(rough, lab, index=np.arange(1, n + 1))
    rough = lab == (1 + int(np.argmax(sizes)))
    erode_px = max(1, int(round(s.bias_erode_mm / px_mm)))
    fit = ndimage.binary_erosion(rough, iterations=erode_px)
    if fit.sum() < 10:
        fit = rough
    B = _bias_field(img - bg, rough, fit, s.bias_degree)
    N = (img - bg) / B
    muscle = float(np.median(N[fit])) if fit.any() else 1.0
    return N, rough, muscle


def _skin_image(N, muscle, *, px_mm, settings: SegmentationSettings, indenter_sd):
    """``N`` with the contrast fluid and its guard set to 0 (step 4) and the dark regions cut off by the indenter
    filled (step 8), the image the skin is traced on."""
    s = settings
    Ns = N
    if s.fluid_level is not None:
        fluid = N > s.fluid_level * muscle
        if fluid.any():
            guard = max(1, int(round(s.fluid_guard_mm / px_mm)))
            fluid = ndimage.binary_dilation(fluid, iterations=guard)
            Ns = N.copy()
            Ns[fluid] = 0.0
    if indenter_sd is not None:
        Ns = _cut_at_indenter(
            Ns,
            indenter_sd,
            level=0.5 * muscle,
            fill=muscle,
            guard_mm=s.indenter_guard_mm,
            px_mm=px_mm,
            min_area_px=s.bone_min_area_mm2 / px_mm**2,
        )
    return Ns


def _disk(radius_px: float) -> np.ndarray:
    """The pixels within ``radius_px`` of a centre pixel (a digital disc, for morphology)."""
    r = int(np.floor(radius_px))
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return x**2 + y**2 <= radius_px**2 + 1e-9


def _closed_tissue(Ns, level: float, close_px: float) -> np.ndarray:
    """``Ns`` with the gaps of the tissue (above ``level``) narrower than ``2 close_px`` pixels bridged and the holes
    so closed filled with ``2 level``: a masked scan's skin ring broken by zeroed fat is traced as one outline."""
    tissue = Ns > level
    pad = int(np.ceil(close_px)) + 1
    closed = ndimage.binary_closing(np.pad(tissue, pad), structure=_disk(close_px))[
        pad:-pad, pad:-pad
    ]
    lab, n = ndimage.label(closed)
    if n:
        sizes = ndimage.sum(closed, lab, index=np.arange(1, n + 1))
        big = ndimage.binary_fill_holes(lab == 1 + int(np.argmax(sizes)))
        closed = closed | big
    return np.where(closed & ~tissue, 2.0 * level, Ns)


def _trace_skin(Ns, rough, muscle, *, px_mm, settings: SegmentationSettings, where: str):
    """``(skin (i, j) contour, skin_level)`` (step 5): the largest closed contour of ``Ns`` at the skin level,
    with the tissue's gaps narrower than ``2 skin_close_mm`` bridged.

    Raises :class:`SegmentationError` when the level lies in the background (a ``skin_level`` set too low), when
    the tissue runs off the image (a leg cut at the image or crop border), or when there is no closed contour."""
    s = settings
    close_px = s.skin_close_mm / px_mm
    if s.skin_level is not None:
        frame = np.concatenate([Ns[0], Ns[-1], Ns[:, 0], Ns[:, -1]])
        if float(np.mean(frame > s.skin_level)) > _BACKGROUND_SHARE:
            raise SegmentationError(
                f"{where}: segmentation.skin_level {s.skin_level:g} lies in the background (much of the image "
                "border is above it), so the skin cannot be told from the noise; raise it or set it to null "
                "(automatic)"
            )

    def trace(level):
        img = _closed_tissue(Ns, level, close_px) if close_px >= 1 else Ns
        # tissue (above the level) is 8-connected, background only 4-connected: single-pixel gaps
        # that touch the outside only diagonally do not cut channels into the skin
        cs = find_contours(img, level, fully_connected="high")
        closed = [c for c in cs if len(c) >= 5 and np.allclose(c[0], c[-1])]
        longest = max(cs, key=len) if cs else None
        if longest is not None and not np.allclose(longest[0], longest[-1]):
            if not closed or len(longest) > len(max(closed, key=len)):
                raise SegmentationError(
                    f"{where}: the leg is cut at the image border (its outline runs off the image); widen "
                    "crop_mm, or scan the whole leg cross-section"
                )
        if not closed:
            raise SegmentationError(f"{where}: no closed skin contour at level {level:.3g}")
        return max(closed, key=lambda c: abs(polygon_area_centroid(c)[0]))

    def plateau(inside, d1):
        dist = ndimage.distance_transform_edt(inside)
        band = inside & (dist >= d1) & (dist < d1 + 1.0) & (Ns > 0.3 * muscle)
        if band.sum() < 5:
            band = inside & (Ns > 0)
        return float(np.median(Ns[band]))

    if s.skin_level is not None:
        return trace(float(s.skin_level)), float(s.skin_level)
    # the skin plateau is read in a band starting _BAND_SIGMAS blur widths inside the edge: first inside the
    # rough (noise-threshold) edge, then, independent of the noise level, inside the traced contour itself
    d1 = max(_BAND_SIGMAS * s.smooth_mm / px_mm, 1.0) + _BAND_PX
    skin_level = 0.5 * plateau(rough, d1)
    for _ in range(2):
        skin = trace(skin_level)
        skin_level = 0.5 * plateau(_raster(skin, rough.shape), d1)
    return trace(skin_level), skin_level


def _raster(c, shape) -> np.ndarray:
    """Boolean mask of the pixels whose centres lie inside the closed (i, j) contour ``c``."""
    out = np.zeros(shape, bool)
    rr, cc = _polygon_px(c[:, 0], c[:, 1], shape=shape)
    out[rr, cc] = True
    return out


def _open_cores(Nb, skin, level, fill, *, open_px: float) -> np.ndarray:
    """``Nb`` with the dark regions inside the skin that are not closed holes parted into their thick cores.

    Where a bone's dark marrow and cortex run into dark (masked) fat, the bone is no closed dark hole. The dark
    pixels inside the skin (below ``level``) are opened by a disc of ``open_px`` pixels: the fat layer and any
    channel narrower than the disc vanish, a bone wider than it stays. The dark parts the opening removed that
    reach more than 1.5 pixels from what it kept (the fat, the channel) are set to ``fill``, and so is everything
    outside the skin; the slivers of a bone's own edge that the digital disc shaved off stay. The bone's core is
    then a closed dark region, bounded by its own edge and, where it opened, by the cut.
    """
    inside = _raster(skin, Nb.shape)
    dark = (Nb < level) & inside
    kept = ndimage.binary_opening(dark, structure=_disk(open_px))
    removed = dark & ~kept
    lab, n = ndimage.label(removed)
    out = np.where(inside, Nb, fill)
    if n == 0:
        return out
    reach = ndimage.maximum(ndimage.distance_transform_edt(~kept), lab, index=np.arange(1, n + 1))
    out[np.isin(lab, 1 + np.nonzero(np.asarray(reach) > 1.5)[0])] = fill
    return out


def _bone_candidates(Nb, skin, level, muscle, *, px_mm, settings: SegmentationSettings):
    """``(candidates, dark)``: the tibia's candidates ``(area [px], (i, j) contour)`` of one slice (step 6) and the
    closed dark contours at ``level`` (for the fibula).

    The candidates are the dark regions inside the skin of at least ``bone_min_area_mm2``: each closed dark region
    whole, unless it is two or more thick parts joined by thin necks (the tibia and the fibula joined by a dark
    septum), which are then candidates each; and the thick parts of the dark regions that open into the fat or
    the background. The thick parts are the cores of :func:`_open_cores` with a disc of ``bone_open_mm`` (None: a
    tenth of the skin's inscribed radius; 0: closed regions whole only)."""
    s = settings
    min_area_px = s.bone_min_area_mm2 / px_mm**2
    dark = _closed_contours(Nb, level)

    def regions(cs):
        out = []
        for c in cs:
            area = abs(polygon_area_centroid(c)[0])
            if area < min_area_px or not points_in_polygon(c, skin).all():
                continue
            if _contour_mean(Nb, c) >= level:
                continue  # a bright island, not a dark hole
            out.append((area, c))
        return out

    whole = regions(dark)
    if s.bone_open_mm is None:
        inscribed = ndimage.distance_transform_edt(_raster(skin, Nb.shape)).max()
        open_px = 0.1 * float(inscribed)
    else:
        open_px = s.bone_open_mm / px_mm
    if open_px < 1:
        return whole, dark
    cores = regions(_closed_contours(_open_cores(Nb, skin, level, muscle, open_px=open_px), level))
    cands, used = [], set()
    for a, c in whole:
        inner = [
            j
            for j, (_, d) in enumerate(cores)
            if points_in_polygon(polygon_area_centroid(d)[1][None], c)[0]
        ]
        used.update(inner)
        cands += [cores[j] for j in inner] if len(inner) >= 2 else [(a, c)]
    return cands + [cc for j, cc in enumerate(cores) if j not in used], dark


def _segment_slice(
    img,
    *,
    bg,
    noise,
    px_mm,
    settings: SegmentationSettings,
    where: str,
    need_bone: bool = True,
    indenter_sd=None,
):
    """Skin, tibia and fibula of one slice (steps in the module docstring). ``indenter_sd`` (same shape as
    ``img``, mm): distance from the indenter's outer surface, negative inside; pixels closer than
    ``indenter_guard_mm`` are set to muscle before the bones are traced, so the indenter's dark wall cannot
    join the tibia's dark cortex. With it, a slice without a bone contour where the indenter reaches within
    1 mm of the inside of the skin returns ``bone_ij`` None instead of raising (the tibia hidden against it)."""
    s = settings
    N, rough, muscle = _normalised(img, bg=bg, noise=noise, px_mm=px_mm, settings=s, where=where)
    Ns = _skin_image(N, muscle, px_mm=px_mm, settings=s, indenter_sd=indenter_sd)
    skin, skin_level = _trace_skin(Ns, rough, muscle, px_mm=px_mm, settings=s, where=where)
    bone_level = float(s.bone_level) if s.bone_level is not None else 0.5 * muscle
    if not need_bone:
        return _SliceResult(skin, None, skin_level, bone_level)
    Nb = N
    if indenter_sd is not None:
        Nb = N.copy()
        Nb[indenter_sd < s.indenter_guard_mm] = muscle
    cands, dark = _bone_candidates(Nb, skin, bone_level, muscle, px_mm=px_mm, settings=s)
    if not cands and indenter_sd is not None:
        # the tibia may be hidden against the indenter only where the indenter reaches into the leg
        near = np.argwhere(indenter_sd < 1.0)
        if len(near) and points_in_polygon(near, skin).any():
            return _SliceResult(skin, None, skin_level, bone_level, None, -np.inf)
    if not cands:
        raise SegmentationError(
            f"{where}: no closed bone contour inside the skin at level {bone_level:.3g}"
        )
    # the tibia is chosen among the candidates in 3D (_choose_tibia), then _SliceResult.finish
    return _SliceResult(
        skin,
        None,
        skin_level,
        bone_level,
        bone_candidates=cands,
        trace={"Nb": Nb, "dark": dark, "sd": indenter_sd},
    )


def _track(candidates: list, *, overlap: bool = False) -> tuple[list[dict], dict]:
    """Dark structures along the leg: the candidates of successive slices linked into tracks.

    ``candidates`` holds, per slice, a list of ``(area [px], (i, j) contour)`` or None (a slice not searched). A
    candidate joins a track when its centroid lies inside the track's contour on the track's last slice, or that
    contour's centroid inside it (with ``overlap``: when the discs of their areas about their centroids overlap),
    and their areas differ by at most :data:`_LINK_AREA_RATIO`, nearest centroids first; a track may skip slices
    (the structure not closed or not searched there). ``overlap`` serves a thin bone crossing the slices obliquely:
    the phantom's fibula, 0.8 mm across, moves by up to 0.6 mm between its 1 mm slices, so its sections do not
    contain each other's centroids. Returns the tracks (``{slice: candidate index}``) and
    ``{(slice, index): (area, centroid)}``.
    """
    ks = [k for k, c in enumerate(candidates) if c is not None]
    geom = {
        (k, i): (a, polygon_area_centroid(c)[1])
        for k in ks
        for i, (a, c) in enumerate(candidates[k])
    }
    tracks: list[dict] = []
    for k in ks:
        pairs = []
        for t, track in enumerate(tracks):
            kl = max(track)
            al, cl = geom[(kl, track[kl])]
            poly_l = candidates[kl][track[kl]][1]
            for i, (a, c) in enumerate(candidates[k]):
                cen = geom[(k, i)][1]
                if max(a, al) > _LINK_AREA_RATIO * min(a, al):
                    continue
                d = float(np.hypot(*(cen - cl)))
                if overlap:
                    linked = d < np.sqrt(a / np.pi) + np.sqrt(al / np.pi)
                else:
                    linked = (
                        points_in_polygon(cen[None], poly_l)[0]
                        or points_in_polygon(cl[None], c)[0]
                    )
                if linked:
                    pairs.append((d, t, i))
        used_t, used_i = set(), set()
        for _, t, i in sorted(pairs):
            if t not in used_t and i not in used_i:
                tracks[t][k] = i
                used_t.add(t)
                used_i.add(i)
        tracks += [{k: i} for i in range(len(candidates[k])) if i not in used_i]
    return tracks, geom


def _choose_tibia(
    candidates: list, *, select: str, vol: Volume, flip_j: bool
) -> tuple[list, dict]:
    """The tibia's candidate on every slice, chosen in 3D: the index into each slice's ``candidates`` (None on the
    slices given as None: not traced, drawn by hand, or hidden against the indenter), and ``{slice: message}`` of
    the traced slices where it is missing.

    Candidates are linked into tracks by :func:`_track`: a candidate that jumps between slices, or whose area
    differs from its neighbour's by more than :data:`_LINK_AREA_RATIO`, starts a track of its own. Of the tracks on
    at least half of the traced slices, the tibia is the largest (median area) or, with ``anterior``, the most
    anterior of those at least half as large: a track a fraction of the other's area is not the tibia. It must be
    on every traced slice: a slice where it is missing has the tibia's dark region open into another dark one
    (on a masked scan, its cortex into the fat, wider than ``bone_open_mm`` parts) or no tibia at all, and
    another structure there would be taken for the tibia without a word.
    """
    ks = [k for k, c in enumerate(candidates) if c is not None]
    out: list = [None] * len(candidates)
    if not ks:
        return out, {}
    tracks, geom = _track(candidates)
    n = len(ks)
    off = vol.index_offset[2]
    long = [t for t in tracks if 2 * len(t) >= n]
    if not long:
        best = max(tracks, key=len)
        msg = (
            f"{vol.where()}: no dark structure runs through half of the {n} traced slices (the longest is on "
            f"{len(best)}: slices {_slice_list(sorted(best), off)}), so none is taken for the tibia; check "
            "segmentation.bone_level and crop_mm, or draw the tibia in an overrides file"
        )
        return out, dict.fromkeys(ks, msg)
    area = [float(np.median([geom[(k, i)][0] for k, i in t.items()])) for t in long]
    if select == "anterior":
        big = [j for j in range(len(long)) if area[j] >= 0.5 * max(area)]
        j = max(big, key=lambda j: np.mean([geom[(k, i)][1][1] for k, i in long[j].items()]))
    else:
        j = int(np.argmax(area))
    tibia = long[j]
    for k, i in tibia.items():
        out[k] = i
    missing = [k for k in ks if k not in tibia]
    if not missing:
        return out, {}
    k0 = next(iter(tibia))
    cen = geom[(k0, tibia[k0])][1]
    ij = np.array([cen[0], vol.data.shape[1] - 1 - cen[1] if flip_j else cen[1], k0])
    x, y = vol.world(ij)[:2]
    msg = (
        f"the tibia ({'the most anterior' if select == 'anterior' else 'the largest'} dark structure along the "
        f"leg, near x {x:.1f} mm, y {y:.1f} mm) is not a closed dark region inside the skin on slice(s) "
        f"{_slice_list(missing, off)} of {n}: its dark region opens into another there (on a masked scan, the "
        "cortex into the fat: a larger segmentation.bone_open_mm parts them), or the slice lies beyond its shaft "
        "(into the ankle or the knee), and another structure would be taken for it"
    )
    return out, dict.fromkeys(missing, msg)


def _seed_px(point, mask) -> tuple[int, int] | None:
    """The pixel of ``mask`` nearest the (i, j) ``point``, within 1.5 pixels of it (None: the point lies outside)."""
    i, j = int(round(point[0])), int(round(point[1]))
    best = None
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            p = (i + di, j + dj)
            if 0 <= p[0] < mask.shape[0] and 0 <= p[1] < mask.shape[1] and mask[p]:
                d = float(np.hypot(p[0] - point[0], p[1] - point[1]))
                if best is None or d < best[0]:
                    best = (d, p)
    return None if best is None else best[1]


def _split_joined(Nb, level: float, contour, tibia_seed, other_seeds) -> tuple | None:
    """``(tibia, others)``: the dark region inside ``contour`` parted into the tibia's section and the other bones'
    (``(area [px], (i, j) contour)`` each), or None when the seeds do not part it.

    The region is split by a watershed on its distance transform from the seeds, ``tibia_seed`` and
    ``other_seeds`` ((i, j) points: the centroids of the tibia and the other dark structures on a neighbouring
    slice where they are apart). The tibia's part keeps the stub of the septum or channel that joined it to the
    others; an opening by a disc just wider than the neck (the largest distance to the edge along the watershed
    line) removes it, as :func:`_open_cores` does with a fixed disc, so the tibia's contour runs along its own edge
    and across the neck's root. The contours are traced at ``level`` on ``Nb`` with the other parts set bright."""
    inside = _raster(contour, Nb.shape)
    mask = inside & (Nb < level)
    t = _seed_px(tibia_seed, mask)
    os_ = [p for p in (_seed_px(o, mask) for o in other_seeds) if p is not None and p != t]
    if t is None or not os_:
        return None
    markers = np.zeros(Nb.shape, np.int32)
    for lab_, p in enumerate([t, *os_], start=1):
        markers[p] = lab_
    dist = ndimage.distance_transform_edt(mask)
    parts = watershed(-dist, markers, mask=mask)
    tib = parts == 1
    line = tib & ndimage.binary_dilation((parts > 1), structure=np.ones((3, 3), bool))
    # no line: the parts touch only where the contour's sub-pixel saddle joins them, no pixel of neck to cut
    kept = (
        ndimage.binary_opening(tib, structure=_disk(float(dist[line].max()) + 1.0))
        if line.any()
        else tib
    )
    if kept[t]:
        removed = tib & ~kept
        lab, n = ndimage.label(removed)
        if n:
            away = ndimage.distance_transform_edt(~kept)
            reach = ndimage.maximum(away, lab, index=np.arange(1, n + 1))
            # the stub reaches beyond the slivers of the core's own edge that the digital disc shaved off
            tib = tib & ~np.isin(lab, 1 + np.nonzero(np.asarray(reach) > 1.5)[0])
    fill = max(2.0 * level, 1.0)
    # the image the parts are traced on: the region's dark pixels outside ``region`` and everything outside the
    # region's contour but its bright rim (whose values place the edge between pixels) set bright
    rim = ndimage.binary_dilation(inside, structure=np.ones((3, 3), bool)) & (Nb >= level)

    def traced(region, seed):
        img = np.where((mask & region) | rim, Nb, fill)
        for c in _closed_contours(img, level):
            if points_in_polygon(np.asarray(seed, float)[None], c)[0]:
                return abs(polygon_area_centroid(c)[0]), c
        return None

    tibia = traced(tib, t)
    if tibia is None or any(points_in_polygon(np.asarray(os_, float), tibia[1])):
        return None
    others = [o for o in (traced(parts == i + 2, p) for i, p in enumerate(os_)) if o is not None]
    return tibia, others


def _part_joined(traced: list, choice: list) -> bool:
    """Part, on every slice, the dark region that holds the tibia of a neighbouring slice together with another dark
    structure of that slice (the tibia joined to the fibula by a septum, or to a dark layer, wider than
    ``bone_open_mm`` parts): :func:`_split_joined`, seeded by the neighbour's centroids. The parts replace the
    region among the slice's tibia candidates, the parts other than the tibia join the fibula's dark contours, and
    the tibia's part becomes the slice's choice; a slice so parted seeds its own neighbours in turn. Returns whether
    any region was parted."""
    n = len(traced)
    any_split, changed = False, True
    while changed:
        changed = False
        for k in range(n):
            res = traced[k][1]
            if res is None or not res.bone_candidates:
                continue
            for nb in (k - 1, k + 1):
                if not 0 <= nb < n or choice[nb] is None or traced[nb][1] is None:
                    continue
                cands = traced[nb][1].bone_candidates
                tib = cands[choice[nb]][1]
                t = polygon_area_centroid(tib)[1]
                others = [
                    polygon_area_centroid(c)[1]
                    for i, (_, c) in enumerate(cands)
                    if i != choice[nb]
                ]
                hit = _joined_candidate(res.bone_candidates, t, others)
                if hit is None:
                    continue
                i, seeds = hit
                split = _split_joined(
                    res.trace["Nb"], res.bone_level, res.bone_candidates[i][1], t, seeds
                )
                if split is None:
                    continue
                tibia, parts = split
                res.bone_candidates = [c for j, c in enumerate(res.bone_candidates) if j != i]
                res.bone_candidates += [tibia, *parts]
                res.trace["dark"] = list(res.trace["dark"]) + [c for _, c in parts]
                choice[k] = len(res.bone_candidates) - 1 - len(parts)
                changed = any_split = True
                break
    return any_split


def _joined_candidate(cands: list, tibia_c, other_cs) -> tuple | None:
    """``(index, other centroids inside)`` of the candidate that holds the centroid ``tibia_c`` and at least one of
    ``other_cs`` (a neighbouring slice's tibia and other dark structures), or None."""
    for i, (_, c) in enumerate(cands):
        if not points_in_polygon(np.asarray(tibia_c)[None], c)[0]:
            continue
        inside = [o for o in other_cs if points_in_polygon(np.asarray(o)[None], c)[0]]
        if inside:
            return i, inside
    return None


def _slice_list(ks, off: int) -> str:
    """Slice indices in the file, comma-separated."""
    return ", ".join(str(int(k) + off) for k in ks)


def _fibula_candidates(
    N, contours, skin, bone, bone_area_px, level, *, px_mm, settings: SegmentationSettings
) -> list:
    """The fibula's candidates in one slice, ``(area [px], (i, j) contour)``: of the closed ``contours`` at ``level``,
    the dark ones inside the skin and outside the tibia (``bone``), round (:data:`_FIBULA_MIN_ROUNDNESS`), with an
    area from ``fibula_min_area_mm2`` to ``fibula_max_area_ratio`` x the tibia's (``bone_area_px``, pixels)."""
    s = settings
    lo, hi = s.fibula_min_area_mm2 / px_mm**2, s.fibula_max_area_ratio * bone_area_px
    out = []
    for c in contours:
        area = abs(polygon_area_centroid(c)[0])
        if not lo <= area <= hi:
            continue
        perimeter = float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())
        if 4 * np.pi * area / max(perimeter, 1e-12) ** 2 < _FIBULA_MIN_ROUNDNESS:
            continue  # a thin or ragged dark gap (fascia, vessel), not a round bone
        if (
            not points_in_polygon(c, skin).all()
            or points_in_polygon(c, bone).any()
            or points_in_polygon(bone, c).any()
        ):
            continue  # outside the skin, the tibia itself, or a region inside / around it
        if _contour_mean(N, c) >= level:
            continue  # a bright island
        out.append((area, c))
    return out


def _choose_fibula(candidates: list, *, min_slices: int) -> tuple[list, list]:
    """The fibula's candidate per slice, chosen in 3D, and the slices of a track too short to be it.

    ``candidates`` as for :func:`_track` (None: a slice not searched), linked where their sections overlap. The
    fibula is the longest track (the largest median area of equally long ones), on at least ``min_slices``
    slices: a dark spot on a slice or two is not a bone that runs along the leg. Returns the index into each
    slice's candidates (None where the track has none) and, when the longest track is shorter than
    ``min_slices``, its slices (else an empty list).
    """
    out: list = [None] * len(candidates)
    tracks, geom = _track(candidates, overlap=True)
    if not tracks:
        return out, []
    fibula = max(
        tracks, key=lambda t: (len(t), float(np.median([geom[(k, i)][0] for k, i in t.items()])))
    )
    if len(fibula) < min_slices:
        return out, sorted(fibula)
    for k, i in fibula.items():
        out[k] = i
    return out, []


class SlicesFailed(SegmentationError):
    """Slices that cannot be segmented, all named at once; ``failed`` maps the slice index in ``vol`` to its
    message, ``partial`` holds what was traced (``{structure: [(n_points, 3) world mm or None per slice]}``) for
    the QC figure of the failed run."""

    def __init__(self, message: str, *, failed: dict, partial: dict):
        super().__init__(message)
        self.failed = failed
        self.partial = partial


@dataclass(frozen=True)
class _Scan:
    """What every slice of :func:`segment_volume` needs: the smoothed image, its background and noise."""

    vol: Volume
    smoothed: np.ndarray
    bg: float
    noise: float
    px_mm: float
    flip_j: (
        bool  # the affine's y runs opposite to j: slices are traced with j reversed, so +j is +y
    )
    settings: SegmentationSettings
    overrides: dict  # {structure: {slice in the file: (m, 2) world mm}} of the state
    skin_only: bool = False


def _scan(vol: Volume, settings: SegmentationSettings, overrides: dict, skin_only: bool) -> _Scan:
    s = settings
    px = vol.pixel_mm
    data = vol.data.astype(float)
    sig = (s.smooth_mm / px[0], s.smooth_mm / px[1], 0.0)
    sm = ndimage.gaussian_filter(data, sig, mode="nearest") if s.smooth_mm > 0 else data
    frame = np.concatenate(
        [sm[:3].ravel(), sm[-3:].ravel(), sm[:, :3].ravel(), sm[:, -3:].ravel()]
    )
    bg = float(np.median(frame))
    return _Scan(
        vol=vol,
        smoothed=sm,
        bg=bg,
        noise=float(1.4826 * np.median(np.abs(frame - bg))),
        px_mm=float(np.sqrt(px[0] * px[1])),
        flip_j=bool(vol.affine[1, 1] < 0),
        settings=s,
        overrides=overrides,
        skin_only=skin_only,
    )


def _trace_slices(scan: _Scan, indenter) -> tuple[list, dict]:
    """``(traced, failed)``: per slice ``(manual contours, _SliceResult or None)``, and ``{slice: message}`` of
    the slices that cannot be traced (every one, not only the first)."""
    vol, s = scan.vol, scan.settings
    off = vol.index_offset[2]
    traced, failed = [], {}
    ii, jj = np.meshgrid(np.arange(vol.data.shape[0]), np.arange(vol.data.shape[1]), indexing="ij")
    for k in range(vol.n_slices):
        manual = {st: scan.overrides.get(st, {}).get(k + off) for st in STRUCTURES}
        img = scan.smoothed[:, :, k]
        if scan.flip_j:
            img = img[:, ::-1]
        if scan.skin_only:
            manual["bone"] = manual["fibula"] = None
        auto_fibula = s.fibula and manual["fibula"] is None and not scan.skin_only
        sd = None
        if indenter is not None and not scan.skin_only:
            sd = indenter.signed_distance_mm(
                vol.world(np.stack([ii, jj, np.full(ii.shape, k)], axis=-1))
            )
            sd = sd[:, ::-1] if scan.flip_j else sd
        res = None
        if manual["skin"] is None or manual["bone"] is None or auto_fibula:
            try:
                res = _segment_slice(
                    img,
                    bg=scan.bg,
                    noise=scan.noise,
                    px_mm=scan.px_mm,
                    settings=s,
                    where=vol.where(k),
                    need_bone=(manual["bone"] is None or auto_fibula) and not scan.skin_only,
                    indenter_sd=sd,
                )
            except SegmentationError as exc:
                if manual["bone"] is None or manual["skin"] is None:
                    failed[k] = str(exc)
                # skin and tibia drawn by hand: no automatic fibula on this slice
        traced.append((manual, res))
    return traced, failed


def _slice_contours(scan: _Scan, k: int, manual: dict, res) -> dict:
    """World contours ``{structure: (n_points, 3) or None}`` of slice ``k``, resampled (step 9), bones inside the
    skin; a manual contour replaces the automatic one."""
    vol, s = scan.vol, scan.settings
    where = vol.where(k)
    z_c = float(vol.world([(vol.data.shape[0] - 1) / 2, (vol.data.shape[1] - 1) / 2, k])[2])
    out = {}
    for st in STRUCTURES:
        if scan.skin_only and st != "skin":
            out[st] = None
            continue
        xy = manual[st]
        if xy is None:
            ij = None if res is None else getattr(res, f"{st}_ij")
            if (
                ij is None
            ):  # no fibula found (or not searched), or the tibia hidden by the indenter
                out[st] = None
                continue
            if scan.flip_j:
                ij = np.column_stack([ij[:, 0], vol.data.shape[1] - 1 - ij[:, 1]])
            xy = vol.world(np.column_stack([ij, np.full(len(ij), k)]))[:, :2]
        try:
            r = resample_closed(xy, n_points=s.n_points, start_angle_deg=s.start_angle_deg)
        except ValueError as exc:
            if st == "fibula" and manual[st] is None:
                out[st] = None  # an automatic candidate that is not a bone's outline
                continue
            raise SegmentationError(f"{where}: {st} contour: {exc}") from exc
        out[st] = np.column_stack([r, np.full(s.n_points, z_c)])
    for st in ("bone", "fibula"):
        if out[st] is None:
            continue
        inside = points_in_polygon(out[st][:, :2], out["skin"][:, :2])
        if not inside.all():
            raise SegmentationError(
                f"{where}: {st} contour outside the skin ({int((~inside).sum())} of {len(inside)} points)"
            )
    return out


def _failure(scan: _Scan, traced: list, failed: dict) -> SlicesFailed:
    """One error naming every failing slice with its reason, and what to do."""
    vol = scan.vol
    off = vol.index_offset[2]
    partial: dict = {st: [None] * vol.n_slices for st in STRUCTURES}
    for k, (manual, res) in enumerate(traced):
        if k in failed:
            continue
        try:
            out = _slice_contours(scan, k, manual, res)
        except SegmentationError:
            continue
        for st in STRUCTURES:
            partial[st][k] = out[st]
    ks = sorted(failed)
    z = [float(vol.world([0, 0, k])[2]) for k in ks]
    reasons: dict = {}  # reason -> slices, the animal and file said once
    for k in ks:
        msg = failed[k]
        for prefix in (vol.where(k) + ": ", vol.where() + ": "):
            msg = msg.removeprefix(prefix)
        reasons.setdefault(msg, []).append(k)
    lines = "; ".join(
        r if "slice" in r.split(":")[0] else f"slice(s) {_slice_list(v, off)}: {r}"
        for r, v in reasons.items()
    )
    return SlicesFailed(
        f"{vol.where()}: {len(ks)} of {vol.n_slices} slices cannot be segmented (slices "
        f"{_slice_list(ks, off)}, z {min(z):.1f} to {max(z):.1f} mm): {lines}. Leave them out with the z range "
        "of crop_mm (or, at the ends of the stack, with segmentation.end_slices: leave_out), or draw them by hand",
        failed=failed,
        partial=partial,
    )


def segment_volume(
    vol: Volume,
    *,
    settings: SegmentationSettings = SegmentationSettings(),
    state: str = "pre",
    overrides: dict | None = None,
    indenter=None,
    pre: Contours | None = None,
    _skin_only: bool = False,
) -> tuple[Contours, dict]:
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
    indenter : IndenterShape or None
        The indenter of a during scan (:func:`find_indenter`): the bones are traced with it masked out
        (``indenter_guard_mm``), and a slice whose tibia comes within the guard and a pixel of it, or
        cannot be traced beside it, is ``bone_hidden``.
    pre : Contours or None
        The pre contours on the same slices: the tibia of a ``bone_hidden`` slice is the pre tibia moved by
        the rigid fit (:func:`deeptissue.bone_motion.fit_bone_motion`) of the other slices. Without them a hidden
        slice keeps its traced contour (cut at the guard), or is an error if it has none.

    Returns
    -------
    contours : Contours
        ``skin``, ``bone`` (n_slices, n_points, 3) [mm, world], each slice at the z of its centre;
        ``fibula`` the same shape with NaN rows on the slices without one, None when no slice has one;
        ``bone_hidden`` the slices whose tibia touches the indenter.
    info : dict
        ``background`` and ``noise`` (image units), ``slices`` (one row per slice: ``slice`` index in
        the file, ``z_mm``, ``skin_level`` / ``bone_level`` in N units, ``*_source`` auto / manual /
        none / hidden, and for the fibula dropped: on a track shorter than ``fibula_min_slices``),
        ``bone_touch_mm`` (distance from the indenter, with one), ``settings``,
        ``fibula_slices`` (count), ``bone_hidden`` (slice indices in the file), ``tibia_other_ratio`` (per
        slice, the tibia's area over the largest other dark candidate's; NaN without one), ``left_out`` (``{slice
        in the file: why}``, the slices left out at the ends with ``end_slices: leave_out``) and ``slab`` (the
        slices ``(k0, k1)`` of ``vol`` the contours are on: ``(0, n_slices)`` unless some were left out).

    Raises
    ------
    SlicesFailed
        Naming animal, file and every slice that has no closed skin or bone contour, or where the tibia chosen
        in 3D is missing (:func:`_choose_tibia`), with the reason of each.
    SegmentationError
        If a bone or fibula contour lies outside the skin, or the tibia is hidden by the indenter on more than
        half the slices.
    ValueError
        For an unknown ``bone_select``.
    """
    s = settings
    if s.bone_select not in ("largest", "anterior"):
        raise ValueError(
            f"segmentation.bone_select: {s.bone_select!r} is not 'largest' or 'anterior'"
        )
    if s.end_slices not in ("refuse", "leave_out"):
        raise ValueError(
            f"segmentation.end_slices: {s.end_slices!r} is not 'refuse' or 'leave_out'"
        )
    scan = _scan(vol, s, (overrides or {}).get(state, {}), _skin_only)
    traced, failed = _trace_slices(scan, indenter)
    choice = [None] * vol.n_slices
    if not _skin_only:
        # the tibia in 3D: the one dark structure that runs through every slice whose tibia is traced; where it
        # is joined to another dark structure, parted and chosen again
        def tibia_choice():
            return _choose_tibia(
                [
                    r.bone_candidates
                    if r is not None and m["bone"] is None and k not in failed
                    else None
                    for k, (m, r) in enumerate(traced)
                ],
                select=s.bone_select,
                vol=vol,
                flip_j=scan.flip_j,
            )

        choice, missing = tibia_choice()
        if _part_joined(
            [(m, r if k not in failed else None) for k, (m, r) in enumerate(traced)], choice
        ):
            choice, missing = tibia_choice()
        failed.update(missing)
    if failed:
        run = _kept_run(vol.n_slices, failed) if s.end_slices == "leave_out" else None
        if run is None:
            raise _failure(scan, traced, failed)
        call = dict(
            settings=s,
            state=state,
            overrides=overrides,
            indenter=indenter,
            pre=pre,
            _skin_only=_skin_only,
        )
        return _leave_out_ends(vol, run, failed, call)
    for k, (_, res) in enumerate(traced):
        if res is not None:
            res.finish(choice[k], px_mm=scan.px_mm, settings=s)
    return _assemble(scan, traced, pre)


def _kept_run(n: int, failed: dict) -> tuple[int, int] | None:
    """``(k0, k1)``: the longest run of consecutive slices ``k0`` to ``k1 - 1`` none of which failed, when it holds
    more than half of the ``n`` slices (the failing slices lie towards the ends of the stack, not along the leg);
    else None."""
    best, start = (0, 0), 0
    for k in range(n + 1):
        if k == n or k in failed:
            if k - start > best[1] - best[0]:
                best = (start, k)
            start = k + 1
    return best if 2 * (best[1] - best[0]) > n else None


def _leave_out_ends(vol: Volume, run: tuple, failed: dict, call: dict) -> tuple[Contours, dict]:
    """:func:`segment_volume` on the slices ``run`` (``(k0, k1)``) of ``vol`` only (``end_slices: leave_out``), with
    its other arguments ``call``: the slices beyond the run, at the ends of the stack, are left out;
    ``info['left_out']`` maps each (index in the file) to why (``failed``: ``{slice in vol: message}``),
    ``info['slab']`` is ``run``. A slice of the run that fails there is refused as always."""
    k0, k1 = run
    off = vol.index_offset[2]
    pre = call["pre"]
    if pre is not None:
        hid = None if pre.bone_hidden is None else pre.bone_hidden[k0:k1]
        fib = None if pre.fibula is None else pre.fibula[k0:k1]
        pre = Contours(skin=pre.skin[k0:k1], bone=pre.bone[k0:k1], fibula=fib, bone_hidden=hid)
    contours, info = segment_volume(
        slab(vol, k0, k1),
        **{**call, "pre": pre, "settings": replace(call["settings"], end_slices="refuse")},
    )
    left = {}
    for k in [*range(k0), *range(k1, vol.n_slices)]:
        edge = k0 - 1 if k < k0 else k1
        msg = failed.get(k) or f"beyond slice {edge + off}, which cannot be segmented"
        for prefix in (vol.where(k) + ": ", vol.where() + ": "):
            msg = msg.removeprefix(prefix)
        left[k + off] = msg
    info["left_out"] = left
    info["slab"] = run
    return contours, info


def _other_ratio(res, choice) -> float:
    """The tibia's area over the largest other candidate's on one slice (NaN: no other, or not traced)."""
    if res is None or not res.bone_candidates or choice is None:
        return float("nan")
    others = [a for i, (a, _) in enumerate(res.bone_candidates) if i != choice]
    return float(res.bone_candidates[choice][0] / max(others)) if others else float("nan")


def _assemble(scan: _Scan, traced: list, pre: Contours | None) -> tuple[Contours, dict]:
    """The contours and info of :func:`segment_volume` once every slice is traced and the tibia chosen."""
    vol, s = scan.vol, scan.settings
    off = vol.index_offset[2]
    # the fibula in 3D: the longest dark structure along the leg among the other round dark regions
    fib_choice, fib_short = _choose_fibula(
        [
            res.fibula_candidates if res is not None and manual["fibula"] is None else None
            for manual, res in traced
        ],
        min_slices=s.fibula_min_slices,
    )
    skins, bones, fibulas, rows = [], [], [], []
    hidden = np.zeros(vol.n_slices, bool)
    for k, (manual, res) in enumerate(traced):
        if res is not None and fib_choice[k] is not None:
            res.fibula_ij = res.fibula_candidates[fib_choice[k]][1]
        touch = None if res is None else res.bone_touch_mm
        if (
            manual["bone"] is None
            and touch is not None
            and touch < s.indenter_guard_mm + scan.px_mm
        ):
            hidden[k] = True
        out = _slice_contours(scan, k, manual, res)
        skins.append(out["skin"])
        bones.append(out["bone"])
        fibulas.append(out["fibula"])
        rows.append(
            {
                "slice": k + off,
                "z_mm": float(out["skin"][0, 2]),
                "skin_level": None if res is None else res.skin_level,
                "bone_level": None if res is None else res.bone_level,
                "skin_source": "manual" if manual["skin"] is not None else "auto",
                "bone_source": "hidden"
                if hidden[k]
                else ("manual" if manual["bone"] is not None else "auto"),
                "fibula_source": "manual"
                if manual["fibula"] is not None
                else ("auto" if out["fibula"] is not None else "none"),
                "bone_touch_mm": touch,
                "tibia_other_ratio": _other_ratio(res, None if res is None else res.choice),
            }
        )
    if scan.skin_only:
        return Contours(skin=np.stack(skins), bone=np.stack(skins)), {"slices": rows}
    if hidden.any():
        bones = _fill_hidden(vol, bones, fibulas, hidden, pre, s)
    for k in fib_short:  # a dark spot on a slice or two is not a bone that runs along the leg
        rows[k]["fibula_source"] = "dropped"
    found = [f is not None for f in fibulas]
    fibula = None
    if any(found):
        fibula = np.stack(
            [f if f is not None else np.full((s.n_points, 3), np.nan) for f in fibulas]
        )
    info = {
        "background": scan.bg,
        "noise": scan.noise,
        "slices": rows,
        "settings": s.__dict__,
        "fibula_slices": int(sum(found)),
        "bone_hidden": [int(k + off) for k in np.nonzero(hidden)[0]],
        "left_out": {},
        "slab": (0, vol.n_slices),
    }
    return Contours(
        skin=np.stack(skins), bone=np.stack(bones), fibula=fibula, bone_hidden=hidden
    ), info


def _fill_hidden(
    vol: Volume,
    bones: list,
    fibulas: list,
    hidden: np.ndarray,
    pre: Contours | None,
    s: SegmentationSettings,
) -> list:
    """The tibia contours with those of the ``hidden`` slices replaced by the pre tibia moved by the rigid fit
    of the other slices (see :func:`segment_volume`)."""
    off = vol.index_offset[2]
    names = ", ".join(str(int(k + off)) for k in np.nonzero(hidden)[0])
    n = len(bones)
    if hidden.sum() > n // 2:
        raise SegmentationError(
            f"{vol.where()}: the tibia touches the indenter on {int(hidden.sum())} of {n} slices "
            f"({names}); too few slices show it to fit its motion"
        )
    if pre is None or pre.n_slices != n:
        if any(b is None for b in bones):
            raise SegmentationError(
                f"{vol.where()}: the tibia cannot be traced beside the indenter on slice(s) {names} "
                "and no pre contours on the same slices are given to fill them"
            )
        return bones
    seen = ~hidden
    dur = np.stack([pre.bone[k] if b is None else b for k, b in enumerate(bones)])
    fib = None
    if any(f is not None for f in fibulas):
        fib = np.stack([np.full((s.n_points, 3), np.nan) if f is None else f for f in fibulas])
    during = Contours(skin=dur, bone=dur, fibula=fib)
    dof, _ = resolve_bone_dof("auto", pre, during)
    fit = fit_bone_motion(
        pre.bone,
        dur,
        fibula_pre_mm=pre.fibula,
        fibula_during_mm=fib,
        dof=dof,
        during_slices=seen,
        animal=vol.animal,
    )
    out = list(bones)
    for k in np.nonzero(hidden)[0]:
        try:
            out[k] = moved_section(
                pre.bone,
                fit.motion,
                float(dur[k, :, 2].mean()),
                n_points=s.n_points,
                start_angle_deg=s.start_angle_deg,
            )
        except ValueError as exc:
            raise SegmentationError(
                f"{vol.where(k)}: tibia hidden by the indenter: {exc}"
            ) from exc
    return out


def find_indenter(
    vol: Volume, skin_mm: np.ndarray, *, radius_mm: float = 1.5, pose_options: dict | None = None
):
    """The indenter of a during scan from its contrast fluid, or None when the scan has no fluid column.

    The fluid and its axis are found as by the pose stage (:func:`deeptissue.fluid.find_fluid_component`
    outside the skin contours ``skin_mm`` (n_slices, n_points, 3) [mm], settings from the config section
    ``pose`` given as ``pose_options``); the head and the fluid radius by
    :func:`deeptissue.fluid.indenter_shape`, with the outer radius ``radius_mm`` (``pose.head_radius_mm``).
    """
    data = np.asarray(vol.data, float)
    mask = inside_skin_mask(data.shape, vol.affine, skin_mm)
    try:
        fluid = FluidSearch.from_config(pose_options).find(
            data, vol.affine, mask, animal=vol.animal
        )
        axis = orient_axis(
            fluid.axis, from_mm=fluid.com_mm, toward_mm=np.asarray(skin_mm).reshape(-1, 3).mean(0)
        )
        return indenter_shape(
            data,
            vol.affine,
            fluid,
            axis=axis,
            radius_mm=radius_mm,
            exclude_mask=mask,
            animal=vol.animal,
        )
    except PoseError as exc:
        log.info("%s: bones traced without an indenter mask (%s)", vol.where(), exc)
        return None


@dataclass(frozen=True)
class SegmentJob:
    """The files and settings of one run of the rule ``segment`` (:func:`segment_files`).

    ``image`` is the NIfTI to segment, of ``state`` (pre or during, which selects the overrides) of ``animal``;
    ``contours_out``, ``qc_out`` and ``checks_out`` the contour file (:func:`deeptissue.contours.save_contours`),
    the QC figure (PNG) and the segmentation checks (CSV, :mod:`deeptissue.segment_checks`) to write.
    ``settings`` is the config ``segmentation`` mapping or :class:`SegmentationSettings`. ``crop_mm`` is a world
    box [[xmin, xmax], [ymin, ymax], [zmin, zmax]] [mm] to crop to; ``leg_point_mm`` a point [mm, world] inside
    the leg to segment where the legs touch (:func:`deeptissue.imaging.split_legs`; the indenter is looked for in
    the whole image). ``reference`` is the pre image a during ``image`` must match slice by slice,
    ``pre_contours`` its contour file (it fills the slices where the tibia touches the indenter), ``overrides``
    the manual-override YAML (:func:`load_overrides`), ``truth`` a phantom's true contour file (drawn, with the
    distances in the title), ``pose_options`` the config section ``pose`` (how the contrast fluid is found, and
    the indenter's ``head_radius_mm``, for the indenter mask of a during scan).
    """

    image: str | Path
    contours_out: str | Path
    qc_out: str | Path
    checks_out: str | Path | None = None
    animal: str = ""
    state: str = "pre"
    settings: dict | SegmentationSettings | None = None
    crop_mm: object = None
    leg_point_mm: object = None
    reference: str | Path | None = None
    overrides: str | Path | None = None
    truth: str | Path | None = None
    pre_contours: str | Path | None = None
    pose_options: dict | None = None

    @property
    def failed_qc(self) -> Path:
        """The QC figure of a failed run, beside ``qc_out``: the rule's outputs are removed when it fails."""
        q = Path(self.qc_out)
        return q.with_name(q.stem + "_failed" + q.suffix)

    @property
    def failed_checks(self) -> Path:
        """The checks of a run whose checks failed, beside ``checks_out`` (or the QC figure without one)."""
        c = Path(self.checks_out) if self.checks_out else Path(self.qc_out).with_name("checks.csv")
        return c.with_name(c.stem + "_failed.csv")


def _load_leg(job: SegmentJob):
    """``(vol, leg, split)``: the checked and cropped image, the leg to segment and the leg split (or None)."""
    vol = load_nifti(job.image, animal=job.animal)
    if job.reference is not None:
        ref = load_nifti(job.reference, animal=job.animal)
        check_not_same_scan(ref, vol)
        check_matching(ref, vol)
    n_file = vol.n_slices
    if job.crop_mm is not None:
        vol = crop_volume(vol, job.crop_mm)
    split = None
    leg = vol
    if job.leg_point_mm is not None:
        split = split_legs(vol, job.leg_point_mm)
        leg = split.leg
        log.info("%s %s: %s", job.animal, job.state, split.describe())
    return vol, leg, split, n_file


def _find_indenter(job: SegmentJob, vol, leg, settings, ov):
    if job.state != "during" or not settings.indenter_mask:
        return None
    skins, _ = segment_volume(
        leg, settings=settings, state=job.state, overrides=ov, _skin_only=True
    )
    indenter = find_indenter(
        vol,
        skins.skin,
        radius_mm=float((job.pose_options or {}).get("head_radius_mm", 1.5)),
        pose_options=job.pose_options,
    )
    if indenter is None and job.reference is not None and job.pre_contours:
        # a during scan without fluid beside a pre scan with it: the two were given the wrong way round
        ref = load_nifti(job.reference, animal=job.animal)
        if job.crop_mm is not None:
            ref = crop_volume(ref, job.crop_mm)
        pre_skin = load_contours(job.pre_contours).skin
        if pre_skin.shape[0] == ref.n_slices and find_indenter(
            ref, pre_skin, pose_options=job.pose_options
        ):
            raise SegmentationError(
                f"animal {job.animal}: the pre scan {job.reference} holds the indenter's contrast fluid and the "
                f"during scan {job.image} has none: pre and during are swapped; give the scan with the indenter "
                "as during"
            )
    if indenter is not None:
        log.info(
            "%s %s: indenter masked: head centre %s mm, axis %s, fluid radius %.3f mm, wall %.3f mm",
            job.animal,
            job.state,
            np.round(indenter.head_centre_mm, 3),
            np.round(indenter.axis, 4),
            indenter.fluid_radius_mm,
            indenter.wall_mm,
        )
    return indenter


def _log_info(job: SegmentJob, settings: SegmentationSettings, info: dict) -> None:
    animal, state = job.animal, job.state
    if info["bone_hidden"]:
        log.info(
            "%s %s: the tibia touches the indenter on slice(s) %s: their contour is the pre tibia moved by "
            "the rigid fit of the other slices",
            animal,
            state,
            info["bone_hidden"],
        )
    log.info(
        "%s %s: background %.4g, noise %.4g", animal, state, info["background"], info["noise"]
    )
    for row in info["slices"]:
        log.info(
            "slice %(slice)d z %(z_mm).2f mm: skin %(skin_source)s (level %(skin_level)s), "
            "bone %(bone_source)s (level %(bone_level)s, from the indenter %(bone_touch_mm)s mm), "
            "fibula %(fibula_source)s",
            row,
        )
    if not settings.fibula:
        log.info("%s %s: fibula not segmented (segmentation.fibula is false)", animal, state)
    elif info["fibula_slices"] == 0:
        log.info(
            "%s %s: no fibula found on any slice; the contour file has no 'fibula' array",
            animal,
            state,
        )
    else:
        log.info(
            "%s %s: fibula on %d of %d slices",
            animal,
            state,
            info["fibula_slices"],
            len(info["slices"]),
        )


def _shown(vol: Volume, contours: Contours, info: dict) -> tuple:
    """``(contours, marked)`` for the QC figure of ``vol``: the contours on every slice of ``vol`` (None on the
    slices left out at the ends) and ``{slice index in vol: reason}`` of those slices (:data:`LEFT_OUT`)."""
    k0, k1 = info["slab"]
    if (k0, k1) == (0, vol.n_slices):
        return contours, {}
    shown = {}
    for st in STRUCTURES:
        arr = getattr(contours, st)
        per = [None] * vol.n_slices
        if arr is not None:
            for k in range(k0, k1):
                per[k] = arr[k - k0] if np.isfinite(arr[k - k0]).all() else None
        shown[st] = per
    off = vol.index_offset[2]
    return shown, {k - off: LEFT_OUT + why for k, why in info["left_out"].items()}


def segment_files(job: SegmentJob) -> Contours:
    """The rule ``segment``: load and check the image, part the legs, segment, check, write contours, checks and
    the QC figure.

    Every slice that cannot be segmented, and every failed check (:mod:`deeptissue.segment_checks`), is named
    in one :class:`SegmentationError`; the run then writes its QC figure with the failing slices marked to
    ``job.failed_qc`` (and the checks, when they ran) before raising, and writes no contour file.
    """
    settings = job.settings
    if not isinstance(settings, SegmentationSettings):
        settings = SegmentationSettings.from_config(settings)
    vol, leg, split, n_file = _load_leg(job)
    ov = load_overrides(job.overrides, n_slices=n_file) if job.overrides else None
    title = f"{job.animal} {job.state}"
    indenter = _find_indenter(job, vol, leg, settings, ov)
    pre = load_contours(job.pre_contours) if job.pre_contours and indenter is not None else None
    failed_qc = job.failed_qc
    try:
        contours, info = segment_volume(
            leg, settings=settings, state=job.state, overrides=ov, indenter=indenter, pre=pre
        )
    except SlicesFailed as exc:
        plot_segmentation(vol, exc.partial, failed_qc, failed=exc.failed, split=split, title=title)
        where = job.overrides or f"a file named by config key animals.{job.animal}.overrides"
        raise SegmentationError(
            f"{exc} in {where} ({job.state}: {{structure: {{slice: [[x, y], ...]}}}}). The QC figure with the "
            f"failing slices marked: {failed_qc}"
        ) from exc
    _log_info(job, settings, info)
    left_out = info["left_out"]
    if left_out:
        log.warning(
            "%s %s: %d slice(s) at the ends of the stack left out (segmentation.end_slices: leave_out): %s",
            job.animal,
            job.state,
            len(left_out),
            "; ".join(f"slice {k}: {why}" for k, why in left_out.items()),
        )
    k0, k1 = info["slab"]
    checks = segmentation_checks(
        slab(leg, k0, k1),
        contours,
        info,
        smooth_mm=settings.smooth_mm,
        n_file_slices=n_file,
    )
    true = load_contours(job.truth) if job.truth else None
    rows = contour_accuracy(contours, true) if true is not None else None
    message = failed_checks_message(checks, vol.where())
    bad = {
        c.slice - vol.index_offset[2]: c.name
        for c in checks
        if c.status == "fail" and c.slice >= 0
    }
    if (
        message is not None
    ):  # the rule's outputs are removed on failure: the checks and figure go beside them
        failed_csv = job.failed_checks
        write_checks(failed_csv, checks)
        shown, marked = _shown(vol, contours, info)
        plot_segmentation(
            vol, shown, failed_qc, truth=true, failed=marked | bad, split=split, title=title
        )
        raise SegmentationError(
            f"{message}. The QC figure with the failing slices marked: {failed_qc}; the checks: {failed_csv}"
        )
    failed_qc.unlink(missing_ok=True)
    job.failed_checks.unlink(missing_ok=True)
    if job.checks_out is not None:
        write_checks(job.checks_out, checks)
    save_contours(job.contours_out, contours)
    shown, marked = _shown(vol, contours, info)
    plot_segmentation(
        vol, shown, job.qc_out, truth=true, accuracy=rows, failed=marked, split=split, title=title
    )
    return contours
