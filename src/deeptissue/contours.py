"""The contour result type of the segmentation stage, and its file format.

A :class:`Contours` holds the skin and tibia contours of every axial slice of one state
(``pre`` or ``during``): arrays of shape ``(n_slices, n_points, 3)`` in world mm, each contour
closed implicitly (the last point is not repeated), counter-clockwise seen from +z, starting
at a fixed polar angle about the slice centroid. Written and read only by
:func:`save_contours` / :func:`load_contours` (``.npz`` with arrays ``skin`` and ``bone``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .io import save_npz


@dataclass(frozen=True)
class Contours:
    skin: np.ndarray  # (n_slices, n_points, 3) world mm
    bone: np.ndarray  # (n_slices, n_points, 3) world mm

    def __post_init__(self):
        for name in ("skin", "bone"):
            a = getattr(self, name)
            if a.ndim != 3 or a.shape[2] != 3:
                raise ValueError(f"contours.{name}: expected shape (n_slices, n_points, 3), got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"contours.{name}: non-finite coordinates")
        if self.skin.shape[0] != self.bone.shape[0]:
            raise ValueError(
                f"contours: skin has {self.skin.shape[0]} slices but bone has {self.bone.shape[0]}"
            )

    @property
    def n_slices(self) -> int:
        return self.skin.shape[0]

    @property
    def z_mm(self) -> np.ndarray:
        """Slice positions (mean z of each skin contour)."""
        return self.skin[:, :, 2].mean(axis=1)


def save_contours(path: str | Path, contours: Contours) -> None:
    save_npz(path, skin=contours.skin, bone=contours.bone)


def load_contours(path: str | Path) -> Contours:
    try:
        with np.load(path) as data:
            skin, bone = data["skin"], data["bone"]
    except KeyError as exc:
        raise ValueError(f"{path}: contour file lacks array {exc}") from exc
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a contour file ({exc})") from exc
    try:
        return Contours(skin=np.asarray(skin, float), bone=np.asarray(bone, float))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
