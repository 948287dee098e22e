"""NIfTI input/output: loading with validation, crop boxes in world mm, atomic writing.

Every problem with an input image is an :class:`ImagingError` whose one-line message names the
animal, the file, the slice (where one is at fault) and the problem.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import numpy as np

from .io import atomic_path

__all__ = ["ImagingError", "Volume", "check_matching", "crop_volume", "load_nifti", "write_nifti"]


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
        """"animal .., file ..[, slice k]" for error messages (k counted in the uncropped file)."""
        s = f"animal {self.animal or '?'}, file {self.path or '?'}"
        return s + (f", slice {k + self.index_offset[2]}" if k is not None else "")


def _check_affine(affine: np.ndarray, where: str) -> None:
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        raise ImagingError(f"{where}: degenerate affine (non-finite or not 4x4)")
    M = affine[:3, :3]
    sv = np.linalg.svd(M, compute_uv=False)
    if sv.min() <= 1e-6 or sv.max() / sv.min() > 1e4:
        raise ImagingError(f"{where}: degenerate affine (voxel axes singular values {np.round(sv, 6).tolist()} mm)")


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
        raise ImagingError(f"{where}: cannot read the voxel data, the file is truncated or corrupt "
                           f"({type(exc).__name__}: {exc})") from exc
    bad = ~np.isfinite(data)
    if bad.any():
        k = int(np.nonzero(bad.any(axis=(0, 1)))[0][0])
        raise ImagingError(f"{where}, slice {k}: non-finite voxel values")
    return Volume(data=data, affine=affine, path=str(path), animal=animal)


def check_matching(pre: Volume, during: Volume, *, atol_mm: float = 1e-3) -> None:
    """Raise :class:`ImagingError` unless ``during`` has the same slices (grid and position) as ``pre``."""
    where = f"animal {during.animal or pre.animal or '?'}, file {during.path} vs {pre.path}"
    if pre.data.shape[:2] != during.data.shape[:2]:
        raise ImagingError(f"{where}: slices do not match: in-plane size {during.data.shape[:2]} vs {pre.data.shape[:2]}")
    nk = min(pre.n_slices, during.n_slices)
    corners = np.array([[0, 0], [pre.data.shape[0] - 1, 0], [0, pre.data.shape[1] - 1]], float)
    for k in range(nk):
        ijk = np.column_stack([corners, np.full(3, k)])
        if not np.allclose(pre.world(ijk), during.world(ijk), atol=atol_mm):
            raise ImagingError(f"{where}, slice {k}: slices do not match (slice position/orientation differs between pre and during)")
    if pre.n_slices != during.n_slices:
        raise ImagingError(f"{where}, slice {nk}: slices do not match: during has {during.n_slices} slices, pre has {pre.n_slices}")


def crop_volume(vol: Volume, crop_mm) -> Volume:
    """The sub-volume whose voxel centres lie in the world box [[xmin, xmax], [ymin, ymax], [zmin, zmax]] mm."""
    box = np.asarray(crop_mm, float)
    if box.shape != (3, 2) or np.any(box[:, 1] <= box[:, 0]):
        raise ImagingError(f"{vol.where()}: crop box {box.tolist()} is not [[xmin, xmax], [ymin, ymax], [zmin, zmax]] with min < max")
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
    return Volume(data=data, affine=aff, path=vol.path, animal=vol.animal,
                  index_offset=tuple(int(o + p) for o, p in zip(off, vol.index_offset)))


def write_nifti(path: str | Path, data: np.ndarray, affine: np.ndarray) -> None:
    """Write ``data`` (3D) with ``affine`` as NIfTI-1 (float32), atomically (qform and sform set)."""
    img = nib.Nifti1Image(np.asarray(data, np.float32), np.asarray(affine, float))
    img.header.set_xyzt_units("mm", "sec")
    img.set_qform(affine, code=1)
    img.set_sform(affine, code=1)
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))
