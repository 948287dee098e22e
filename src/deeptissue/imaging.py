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
    "ImagingError",
    "Volume",
    "check_matching",
    "crop_volume",
    "load_nifti",
    "select_leg",
    "write_nifti",
    "body_mask",
]

#: touching legs are parted by in-plane erosions of this step, as a fraction of the widest leg's inscribed radius,
#: up to LEG_ERODE_MAX: at half the radius a convex leg keeps its core and a seam up to the leg's radius long is cut
LEG_ERODE_STEP, LEG_ERODE_MAX = 0.05, 0.5
#: a core is a leg if it holds at least this share of the largest core's volume (not a toe of tissue cut off)
LEG_MIN_SHARE = 0.2
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


def select_leg(vol: Volume, point_mm) -> Volume:
    """``vol`` with everything but the leg that holds ``point_mm`` set to the background, for legs that touch.

    The body (:func:`body_mask`) is eroded in-plane ever deeper, in steps of :data:`LEG_ERODE_STEP` of its
    largest in-plane distance from the edge (the widest leg's inscribed radius) up to :data:`LEG_ERODE_MAX`, until
    its 3D connected cores (in-plane 8-connected, face to face through the slices) are two or more legs: parts of
    at least :data:`LEG_MIN_SHARE` of the largest one's volume. Touching legs part there, where the bridge or the
    seam between them is narrower than the eroded depth; one leg stays one core (a leg is about convex), and its
    core runs through the slices. Each body voxel goes to the core it is reached from first by a watershed of the
    distance from the edge (:func:`skimage.segmentation.watershed`), so the cut runs along the narrowest part
    between the legs. The leg is the part that holds the point, with :data:`LEG_CUT_MARGIN_PX` pixels more along
    the cut.

    Parameters
    ----------
    vol : Volume
        The (cropped) image.
    point_mm : (3,) array_like
        A point inside the leg to keep [mm, world].

    Returns
    -------
    Volume
        The same grid; voxels outside the leg hold the median of the image's border frame (0 for a masked scan).

    Raises
    ------
    ImagingError
        Naming animal and file, if the point lies outside the image or outside the body.
    """
    from skimage.segmentation import watershed

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
    dist = np.stack(
        [ndimage.distance_transform_edt(body[:, :, k], sampling=px) for k in range(body.shape[2])],
        -1,
    )
    structure = np.zeros((3, 3, 3), bool)
    structure[:, :, 1] = True
    structure[1, 1, :] = True
    lab, n = ndimage.label(body, structure=structure)
    for fraction in np.arange(LEG_ERODE_STEP, LEG_ERODE_MAX + 1e-9, LEG_ERODE_STEP):
        core, m = ndimage.label(dist > fraction * dist.max(), structure=structure)
        sizes = np.bincount(core.ravel(), minlength=m + 1)[1:]
        if m >= 2 and np.sort(sizes)[-2] >= LEG_MIN_SHARE * sizes.max():
            keep = sizes >= LEG_MIN_SHARE * sizes.max()
            markers = np.where(np.isin(core, 1 + np.nonzero(keep)[0]), core, 0)
            lab = np.stack(
                [
                    watershed(-dist[:, :, k], markers[:, :, k], mask=body[:, :, k])
                    for k in range(body.shape[2])
                ],
                -1,
            )
            break
    if (
        lab[tuple(idx)] == 0
    ):  # the point lies in a body part that no leg's core reaches on its slice
        raise ImagingError(
            f"{vol.where(int(idx[2]))}: leg_point_mm {point.tolist()} lies in a part of the body "
            "that belongs to no leg; give a point nearer the leg's centre"
        )
    # LEG_CUT_MARGIN_PX more in-plane, so the cut, jagged by a pixel, leaves the leg's own skin whole
    in_plane = np.zeros((3, 3, 3), bool)
    in_plane[:, :, 1] = ndimage.generate_binary_structure(2, 1)
    leg = (
        ndimage.binary_dilation(
            lab == lab[tuple(idx)], structure=in_plane, iterations=LEG_CUT_MARGIN_PX
        )
        & body
    )
    d = vol.data
    frame = np.concatenate([d[:3].ravel(), d[-3:].ravel(), d[:, :3].ravel(), d[:, -3:].ravel()])
    data = np.where(leg, d, np.float32(np.median(frame))).astype(np.float32)
    return replace(vol, data=data)


def write_nifti(path: str | Path, data: np.ndarray, affine: np.ndarray) -> None:
    """Write ``data`` (3D) with ``affine`` as NIfTI-1 (float32), atomically (qform and sform set)."""
    img = nib.Nifti1Image(np.asarray(data, np.float32), np.asarray(affine, float))
    img.header.set_xyzt_units("mm", "sec")
    img.set_qform(affine, code=1)
    img.set_sform(affine, code=1)
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))
