"""The error of reading the indenter's pose or the tibia's motion from the scans.

Raised by the modules that read them from the images (:mod:`deeptissue.fluid`, :mod:`deeptissue.bone_motion`),
which the segmentation uses too, and by the pose stage (:mod:`deeptissue.pose`); defined below both so that the
segmentation imports nothing from the pose stage.
"""

from __future__ import annotations

__all__ = ["PoseError"]


class PoseError(ValueError):
    """The pose cannot be read from the scan; the message names the animal and the reason."""


def _where(animal: str) -> str:
    """Message prefix naming the animal ("" when none is given)."""
    return f"animal {animal}: " if animal else ""
