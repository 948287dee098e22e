"""A leg moved in the cast between the scans: the during volume's voxels shifted or turned in the slice
plane, the affine unchanged (scipy.ndimage, independent of the pose stage's registration)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def shift_voxels(volume: np.ndarray, pixels: tuple[float, float]) -> np.ndarray:
    """``volume`` (I, J, K) with its content moved by ``pixels`` (along I, along J) in every slice."""
    return ndimage.shift(volume, (pixels[0], pixels[1], 0.0), order=1, mode="nearest")


def turn_voxels(volume: np.ndarray, affine: np.ndarray, degrees: float) -> np.ndarray:
    """``volume`` (I, J, K) with its content turned by ``degrees`` about the world z axis through the world
    origin (right-handed: +x toward +y), for an ``affine`` with axial slices and diagonal voxel axes."""
    A = np.asarray(affine, float)
    t = np.radians(degrees)
    R = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    # output voxel o: world w = M o + b; it shows the input at R^T w, voxel M^-1 (R^T w - b)
    M, b = A[:3, :3], A[:3, 3]
    Minv = np.linalg.inv(M)
    matrix = Minv @ R.T @ M
    offset = Minv @ (R.T @ b - b)
    return ndimage.affine_transform(volume, matrix, offset=offset, order=1, mode="nearest")


def tilt_voxels(volume: np.ndarray, affine: np.ndarray, degrees: float) -> np.ndarray:
    """``volume`` (I, J, K) with its content tilted by ``degrees`` about the world x axis through the world
    origin (the leg's long axis turned out of the slices; linear interpolation across the slices)."""
    A = np.asarray(affine, float)
    t = np.radians(degrees)
    R = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(t), -np.sin(t)], [0.0, np.sin(t), np.cos(t)]])
    M, b = A[:3, :3], A[:3, 3]
    Minv = np.linalg.inv(M)
    return ndimage.affine_transform(
        volume, Minv @ R.T @ M, offset=Minv @ (R.T @ b - b), order=1, mode="nearest"
    )


MOVES = {
    "x2": ("shift", (2, 0)),
    "x5": ("shift", (5, 0)),
    "x20": ("shift", (20, 0)),
    "y2": ("shift", (0, 2)),
    "y5": ("shift", (0, 5)),
    "y20": ("shift", (0, 20)),
    "turn3": ("turn", 3.0),
    "tilt3": ("tilt", 3.0),
}


def move(volume: np.ndarray, affine: np.ndarray, name: str) -> np.ndarray:
    """The during volume moved as :data:`MOVES` ``name`` says."""
    kind, amount = MOVES[name]
    if kind == "shift":
        return shift_voxels(volume, amount)
    if kind == "turn":
        return turn_voxels(volume, affine, amount)
    return tilt_voxels(volume, affine, amount)
