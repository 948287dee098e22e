"""NIfTI input/output: loading with validation, crop boxes in world mm, one leg of touching legs, atomic writing.

Every problem with an input image is an :class:`ImagingError` whose one-line message names the
animal, the file, the slice (where one is at fault) and the problem.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import nibabel as nib
import numpy as np
from scipy import ndimage

from .io import atomic_path

__all__ = [
    "slab",
    "ImagingError",
    "Volume",
    "check_matching",
    "crop_volume",
    "load_nifti",
    "LegSplit",
    "check_not_same_scan",
    "split_legs",
    "write_nifti",
    "body_mask",
]

#: the other leg's centre is a local maximum of the distance from the body's edge at least this deep, relative to
#: the kept leg's centre: a leg of the same build is about as deep, a fold of skin or a toe of tissue is not
LEG_OTHER_DEPTH = 0.5
#: two centres are two legs when the deepest point of the line between their watershed regions (the pass) is
#: shallower than this share of the shallower centre: two touching round legs meet at a pass of at most about
#: half their depth, a leg's bulge (a calf muscle's lobe) joins its centre at nearly the full depth
LEG_PASS_RATIO = 0.75
#: gaps in the body narrower than twice this share of the deepest leg's depth are closed before the legs are parted
LEG_CLOSE = 0.15
#: pixels of the other leg kept along the cut: the cut is jagged by a pixel, and a gap in the leg's own skin
#: would open its fat (0 in a masked scan) to the background and let the skin contour run inside
LEG_CUT_MARGIN_PX = 2


class ImagingError(ValueError):
    """A bad input image; the message names animal, file, slice and problem."""


@dataclass(frozen=True)
class Volume:
    """A 3D image: ``data`` (ni, nj, nk) float32 indexed [i, j, k], ``affine`` (4, 4) voxel index -> world mm (RAS).

    Axial slices are ``data[:, :, k]``; ``index_offset`` is the (i, j, k) of ``data[0, 0, 0]`` in
    the file (non-zero after cropping).
    """

    data: np.ndarray
    affine: np.ndarray
    path: str = ""
    animal: str = ""
    index_offset: tuple = (0, 0, 0)

    @property
    def n_slices(self) -> int:
        """Number of axial slices (``data.shape[2]``)."""
        return self.data.shape[2]

    @property
    def pixel_mm(self) -> tuple[float, float]:
        """In-plane voxel size (along i, along j) [mm]."""
        return float(np.linalg.norm(self.affine[:3, 0])), float(np.linalg.norm(self.affine[:3, 1]))

    def world(self, ijk: np.ndarray) -> np.ndarray:
        """World mm (..., 3) of fractional voxel indices (..., 3)."""
        ijk = np.asarray(ijk, float)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def voxel(self, xyz: np.ndarray) -> np.ndarray:
        """Fractional voxel indices (..., 3) of world points (..., 3)."""
        inv = np.linalg.inv(self.affine)
        return np.asarray(xyz, float) @ inv[:3, :3].T + inv[:3, 3]

    def where(self, k: int | None = None) -> str:
        """ "animal .., file ..[, slice k]" for error messages (k counted in the uncropped file)."""
        s = f"animal {self.animal or '?'}, file {self.path or '?'}"
        return s + (f", slice {k + self.index_offset[2]}" if k is not None else "")


def _check_affine(affine: np.ndarray, where: str) -> None:
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        raise ImagingError(f"{where}: degenerate affine (non-finite or not 4x4)")
    M = affine[:3, :3]
    sv = np.linalg.svd(M, compute_uv=False)
    if sv.min() <= 1e-6 or sv.max() / sv.min() > 1e4:
        raise ImagingError(
            f"{where}: degenerate affine (voxel axes singular values {np.round(sv, 6).tolist()} mm)"
        )


def load_nifti(path: str | Path, *, animal: str = "") -> Volume:
    """Load a 3D NIfTI as float32 with its affine; raise :class:`ImagingError` if it is not usable.

    A 4D image with a single volume is accepted (squeezed); anything else not 3D, a degenerate
    affine (singular or non-finite voxel axes), or non-finite voxel values are errors.

    Parameters
    ----------
    path : str or Path
        ``.nii`` or ``.nii.gz`` file.
    animal : str
        Animal name, used in error messages only.

    Returns
    -------
    Volume
        ``data`` (ni, nj, nk) float32 and ``affine`` (4, 4) voxel index -> world mm, ``index_offset``
        (0, 0, 0).

    Raises
    ------
    ImagingError
        Unreadable file, not 3D, smaller than 4 x 4 in-plane, degenerate affine, non-finite values.
    """
    where = f"animal {animal or '?'}, file {path}"
    try:
        img = nib.load(str(path))
    except Exception as exc:  # nibabel raises several types for unreadable files
        raise ImagingError(f"{where}: cannot read NIfTI ({exc})") from exc
    shape = img.shape
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    if len(shape) != 3:
        raise ImagingError(f"{where}: not a 3D image (shape {tuple(img.shape)})")
    if min(shape) < 1 or shape[0] < 4 or shape[1] < 4:
        raise ImagingError(f"{where}: image too small (shape {tuple(shape)})")
    affine = np.asarray(img.affine, float)
    _check_affine(affine, where)
    try:  # nibabel reads the voxels lazily: a truncated or corrupt file fails here
        data = np.asarray(img.dataobj, dtype=np.float32).reshape(shape)
    except Exception as exc:
        raise ImagingError(
            f"{where}: cannot read the voxel data, the file is truncated or corrupt "
            f"({type(exc).__name__}: {exc})"
        ) from exc
    bad = ~np.isfinite(data)
    if bad.any():
        k = int(np.nonzero(bad.any(axis=(0, 1)))[0][0])
        raise ImagingError(f"{where}, slice {k}: non-finite voxel values")
    return Volume(data=data, affine=affine, path=str(path), animal=animal)


def check_not_same_scan(pre: Volume, during: Volume) -> None:
    """Raise :class:`ImagingError` if ``pre`` and ``during`` are the same scan (the same file, or the same voxels
    under two names): a pre scan given as during has no indenter, which would be reported as missing fluid."""
    same_file = Path(pre.path).resolve() == Path(during.path).resolve()
    if same_file or (
        pre.data.shape == during.data.shape and np.array_equal(pre.data, during.data)
    ):
        what = "the same file" if same_file else "the same voxels in two files"
        raise ImagingError(
            f"animal {during.animal or pre.animal or '?'}: pre {pre.path} and during {during.path} are {what}: "
            "give the scan without the indenter as pre and the one with it as during"
        )


def check_matching(pre: Volume, during: Volume, *, atol_mm: float = 1e-3) -> None:
    """Raise :class:`ImagingError` unless ``during`` has the same slices (grid and position) as ``pre``."""
    where = f"animal {during.animal or pre.animal or '?'}, file {during.path} vs {pre.path}"
    if pre.data.shape[:2] != during.data.shape[:2]:
        raise ImagingError(
            f"{where}: slices do not match: in-plane size {during.data.shape[:2]} vs {pre.data.shape[:2]}"
        )
    nk = min(pre.n_slices, during.n_slices)
    corners = np.array([[0, 0], [pre.data.shape[0] - 1, 0], [0, pre.data.shape[1] - 1]], float)
    for k in range(nk):
        ijk = np.column_stack([corners, np.full(3, k)])
        if not np.allclose(pre.world(ijk), during.world(ijk), atol=atol_mm):
            raise ImagingError(
                f"{where}, slice {k}: slices do not match (slice position/orientation differs between pre and during)"
            )
    if pre.n_slices != during.n_slices:
        raise ImagingError(
            f"{where}, slice {nk}: slices do not match: during has {during.n_slices} slices, pre has {pre.n_slices}"
        )


def crop_volume(vol: Volume, crop_mm) -> Volume:
    """The sub-volume whose voxel centres lie in the world box [[xmin, xmax], [ymin, ymax], [zmin, zmax]] mm."""
    box = np.asarray(crop_mm, float)
    if box.shape != (3, 2) or np.any(box[:, 1] <= box[:, 0]):
        raise ImagingError(
            f"{vol.where()}: crop box {box.tolist()} is not [[xmin, xmax], [ymin, ymax], [zmin, zmax]] with min < max"
        )
    idx = np.indices(vol.data.shape).reshape(3, -1).T
    w = vol.world(idx)
    inside = np.all((w >= box[:, 0]) & (w <= box[:, 1]), axis=1).reshape(vol.data.shape)
    if not inside.any():
        raise ImagingError(f"{vol.where()}: crop box {box.tolist()} mm contains no voxel")
    sl = []
    for ax in range(3):
        other = tuple(a for a in range(3) if a != ax)
        hit = np.nonzero(inside.any(axis=other))[0]
        sl.append(slice(int(hit[0]), int(hit[-1]) + 1))
    off = np.array([s.start for s in sl], float)
    aff = vol.affine.copy()
    aff[:3, 3] = vol.world(off)
    data = np.ascontiguousarray(vol.data[sl[0], sl[1], sl[2]])
    return Volume(
        data=data,
        affine=aff,
        path=vol.path,
        animal=vol.animal,
        index_offset=tuple(int(o + p) for o, p in zip(off, vol.index_offset)),
    )


def slab(vol: Volume, k0: int, k1: int) -> Volume:
    """The slices ``k0`` to ``k1 - 1`` of ``vol`` (indices into ``vol``), with the affine and ``index_offset`` that
    keep every voxel at its world position and its index in the file."""
    if not 0 <= k0 < k1 <= vol.n_slices:
        raise ImagingError(
            f"{vol.where()}: slices {k0} to {k1 - 1} are not within its {vol.n_slices} slices"
        )
    aff = vol.affine.copy()
    aff[:3, 3] = vol.world([0, 0, k0])
    off = vol.index_offset
    return Volume(
        data=np.ascontiguousarray(vol.data[:, :, k0:k1]),
        affine=aff,
        path=vol.path,
        animal=vol.animal,
        index_offset=(off[0], off[1], off[2] + k0),
    )


def body_mask(vol: Volume) -> np.ndarray:
    """The voxels (same shape as ``vol.data``) above the background: ``> 0`` for a masked scan (background exactly
    0), else above its noise floor (median + 6 robust spreads of the border frame of each slice), holes filled
    slice by slice."""
    d = vol.data
    frame = np.concatenate([d[:3].ravel(), d[-3:].ravel(), d[:, :3].ravel(), d[:, -3:].ravel()])
    bg = float(np.median(frame))
    noise = float(1.4826 * np.median(np.abs(frame - bg)))
    body = d > bg + 6 * noise + 1e-6 * max(float(np.percentile(d, 99)) - bg, 1e-12)
    return np.stack([ndimage.binary_fill_holes(body[:, :, k]) for k in range(d.shape[2])], axis=-1)


@dataclass(frozen=True)
class LegSplit:
    """A body of legs parted at ``point_mm`` (:func:`split_legs`): ``leg`` is the image with everything but the
    leg that holds the point set to the background; ``body`` and ``kept`` (same shape as the image, bool) the
    body and the kept leg; ``centres`` per slice the (i, j) index of the kept leg's centre and of the other leg's
    (None where the slice holds no second leg touching it), ``parted`` the slices where a touching body was cut."""

    leg: Volume
    body: np.ndarray
    kept: np.ndarray
    centres: list
    parted: list
    point_mm: tuple

    def describe(self) -> str:
        """One line for the log: the point, the voxels kept, the slices where touching legs were parted."""
        off = self.leg.index_offset[2]
        parted = ", ".join(str(k + off) for k in self.parted) or "none"
        return (
            f"the leg at leg_point_mm {list(self.point_mm)} is segmented: {int(self.kept.sum())} of the body's "
            f"{int(self.body.sum())} voxels; touching legs parted on slice(s) {parted}"
        )


def _climb(dist: np.ndarray, ij) -> tuple[int, int]:
    """The local maximum of ``dist`` reached from ``ij`` by steepest ascent over the 8 neighbours."""
    i, j = int(ij[0]), int(ij[1])
    while True:
        win = dist[max(i - 1, 0) : i + 2, max(j - 1, 0) : j + 2]
        di, dj = np.unravel_index(int(np.argmax(win)), win.shape)
        ni_, nj_ = max(i - 1, 0) + int(di), max(j - 1, 0) + int(dj)
        if dist[ni_, nj_] <= dist[i, j]:
            return i, j
        i, j = ni_, nj_


def _part_slice(body2d: np.ndarray, dist: np.ndarray, start, px_mm: float):
    """``(kept, centre, other)`` on one slice: the leg reached from ``start`` (i, j), its centre, and the other
    leg's centre where a second leg touches it (else None).

    The leg's centre is the maximum of the distance from the body's edge (``dist``, mm) that ``start`` climbs to.
    The other leg's centre is the deepest local maximum of ``dist`` of at least :data:`LEG_OTHER_DEPTH` of the
    leg's depth outside the leg's inscribed disc. A watershed of ``-dist`` from the two centres parts the body
    along its narrowest line; the two are two legs when that line's deepest point (the pass) is shallower than
    :data:`LEG_PASS_RATIO` of the shallower centre, else one leg with a bulge, kept whole."""
    from skimage.feature import peak_local_max
    from skimage.segmentation import watershed

    lab, _ = ndimage.label(body2d, structure=np.ones((3, 3)))
    ci, cj = _climb(dist, start)
    comp = lab == lab[ci, cj]
    depth = dist[ci, cj]
    peaks = peak_local_max(
        np.where(comp, dist, 0),
        min_distance=max(2, int(0.5 * depth / px_mm)),
        threshold_abs=LEG_OTHER_DEPTH * depth,
    )
    far = [p for p in peaks if np.hypot(*(p - (ci, cj))) * px_mm > depth]
    if not far:
        return comp, (int(ci), int(cj)), None
    oi, oj = max(far, key=lambda p: dist[p[0], p[1]])
    markers = np.zeros(dist.shape, np.int32)
    markers[ci, cj], markers[oi, oj] = 1, 2
    ws = watershed(-dist, markers, mask=comp)
    line = (ws == 1) & ndimage.binary_dilation(ws == 2, structure=np.ones((3, 3)))
    if not line.any() or dist[line].max() >= LEG_PASS_RATIO * min(depth, dist[oi, oj]):
        return comp, (int(ci), int(cj)), None  # a bulge of one leg, not a second leg
    return ws == 1, (int(ci), int(cj)), (int(oi), int(oj))


def split_legs(vol: Volume, point_mm) -> LegSplit:
    """Part a body of two legs, touching or not, and keep the leg that holds ``point_mm``.

    Slice by slice, from the point's slice outward, the kept leg's centre is the deepest point of the body
    (the maximum of the in-plane distance from its edge) climbed to from the point, and on the next slices from
    the previous slice's centre; a second leg touching it is parted by a watershed from the two legs' centres
    (:func:`_part_slice`). The kept leg takes :data:`LEG_CUT_MARGIN_PX` pixels more along the cut, so its own skin
    stays whole. Legs that stand apart are parted by their gap; a leg that touches nothing is kept whole.

    Raises
    ------
    ImagingError
        Naming animal and file, if the point lies outside the image or outside the body.
    """
    point = np.asarray(point_mm, float)
    ijk = vol.voxel(point)
    idx = np.round(ijk).astype(int)
    if np.any(idx < 0) or np.any(idx >= vol.data.shape):
        raise ImagingError(
            f"{vol.where()}: leg_point_mm {point.tolist()} lies outside the image "
            f"(voxel {np.round(ijk, 1).tolist()} of shape {list(vol.data.shape)})"
        )
    body = body_mask(vol)
    if not body[tuple(idx)]:
        raise ImagingError(
            f"{vol.where(int(idx[2]))}: leg_point_mm {point.tolist()} lies outside the body "
            "(in the background of the image): give a point inside the leg to segment"
        )
    px = vol.pixel_mm
    nk = vol.n_slices
    # the skin ring of a masked scan, parted from the muscle by zeroed fat, belongs to its leg: the legs are parted
    # on the body with gaps up to LEG_CLOSE of the deepest leg's depth closed
    depth_px = max(ndimage.distance_transform_edt(body[:, :, k]).max() for k in range(nk))
    r = max(1.0, LEG_CLOSE * float(depth_px))
    y, x = np.mgrid[-int(r) : int(r) + 1, -int(r) : int(r) + 1]
    disc = x**2 + y**2 <= r**2
    pad = int(r) + 1
    kept = np.zeros_like(body)
    centres: list = [None] * nk
    parted = []
    k0 = int(idx[2])
    order = [
        (k, k + 1 if k < k0 else k - 1) for k in [k0, *range(k0 + 1, nk), *range(k0 - 1, -1, -1)]
    ]
    for k, prev in order:
        raw = body[:, :, k]
        if not raw.any():
            continue
        b = ndimage.binary_closing(np.pad(raw, pad), structure=disc)[pad:-pad, pad:-pad]
        b = ndimage.binary_fill_holes(b | raw)
        start = idx[:2] if k == k0 else (centres[prev][0] if centres[prev] is not None else None)
        if start is None:
            continue
        if not b[tuple(start)]:  # the leg's centre of the slice before lies outside the body here
            d_out, near = ndimage.distance_transform_edt(~b, return_indices=True)
            start = (near[0][tuple(start)], near[1][tuple(start)])
        # depth from the edge of the body as scanned where it is one piece (closing the notch between two touching
        # legs would move their pass), from the closed body where a masked skin ring lies apart from the muscle
        one_piece = ndimage.label(ndimage.binary_fill_holes(raw))[1] == 1
        dist = ndimage.distance_transform_edt(
            ndimage.binary_fill_holes(raw) if one_piece else b, sampling=px
        )
        leg, centre, other = _part_slice(b, dist, start, float(np.sqrt(px[0] * px[1])))
        centres[k] = (centre, other)
        if other is not None:
            parted.append(k)
            leg = ndimage.binary_dilation(leg, iterations=LEG_CUT_MARGIN_PX) & b
        kept[:, :, k] = leg & raw
    d = vol.data
    frame = np.concatenate([d[:3].ravel(), d[-3:].ravel(), d[:, :3].ravel(), d[:, -3:].ravel()])
    data = np.where(kept, d, np.float32(np.median(frame))).astype(np.float32)
    return LegSplit(
        leg=replace(vol, data=data),
        body=body,
        kept=kept,
        centres=centres,
        parted=sorted(parted),
        point_mm=tuple(float(v) for v in point),
    )


def write_nifti(path: str | Path, data: np.ndarray, affine: np.ndarray) -> None:
    """Write ``data`` (3D) with ``affine`` as NIfTI-1 (float32), atomically (qform and sform set)."""
    img = nib.Nifti1Image(np.asarray(data, np.float32), np.asarray(affine, float))
    img.header.set_xyzt_units("mm", "sec")
    img.set_qform(affine, code=1)
    img.set_sform(affine, code=1)
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))
