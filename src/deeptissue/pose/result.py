"""The pose result type: indenter axis and travel, tibia rigid motion (``pose.json``).

The phantom's ``truth.json`` has the same keys, so estimate and truth compare key by key.
Conventions: points are world mm; ``indenter_axis`` is a unit vector pointing from the indenter
into the leg; the indenter tip travels from ``tip_start_mm`` to ``tip_end_mm``; the tibia moves
``x -> R (x - bone_com_mm) + bone_com_mm + bone_translation_mm`` with ``R`` the rotation vector
``bone_rotation_deg`` (see :mod:`deeptissue.rigid`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io import read_json, write_json
from ..rigid import BoneMotion

__all__ = ["Pose", "load_pose", "save_pose"]

_VECTORS = (
    "indenter_axis",
    "tip_start_mm",
    "tip_end_mm",
    "bone_com_mm",
    "bone_rotation_deg",
    "bone_translation_mm",
)


@dataclass(frozen=True)
class Pose:
    """Indenter travel and tibia motion of one animal, as written to ``pose.json``.

    Attributes
    ----------
    indenter_axis : (3,) array
        Unit vector from the indenter into the leg.
    tip_start_mm, tip_end_mm : (3,) array
        Tip position [mm] at the start and at the end of the travel.
    depth_mm : float
        Indentation depth [mm]: the end tip's distance along the axis below the undeformed skin.
    bone_com_mm, bone_rotation_deg, bone_translation_mm : (3,) array
        The tibia's rigid motion: centre [mm] (its pre-state centroid), rotation vector [deg] and
        translation [mm]; :attr:`bone_motion` gives it as a :class:`~deeptissue.rigid.BoneMotion`.
    indenter_com_mm : (3,) array or None
        Centre of mass of the contrast fluid [mm]; None when the axis and tip were given by hand.
    extra : dict
        Fit diagnostics, provenance and the overrides used; written to ``pose.json`` beside the
        quantities above.
    """

    indenter_axis: np.ndarray
    tip_start_mm: np.ndarray
    tip_end_mm: np.ndarray
    depth_mm: float
    bone_com_mm: np.ndarray
    bone_rotation_deg: np.ndarray
    bone_translation_mm: np.ndarray
    indenter_com_mm: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        for name in _VECTORS:
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(
                    f"pose.{name}: expected 3 finite numbers, got {getattr(self, name)!r}"
                )
            object.__setattr__(self, name, v)
        n = np.linalg.norm(self.indenter_axis)
        if not np.isclose(n, 1.0, atol=1e-6):
            raise ValueError(f"pose.indenter_axis: not a unit vector (norm {n:.6g})")
        if self.indenter_com_mm is not None:
            object.__setattr__(
                self, "indenter_com_mm", np.asarray(self.indenter_com_mm, dtype=float)
            )
        depth = float(self.depth_mm)
        if not np.isfinite(depth):
            raise ValueError(f"pose.depth_mm: expected a finite number, got {self.depth_mm!r}")
        object.__setattr__(self, "depth_mm", depth)

    @property
    def travel_mm(self) -> float:
        """Distance [mm] from the start to the end of the tip's travel."""
        return float(np.linalg.norm(self.tip_end_mm - self.tip_start_mm))

    @property
    def bone_motion(self) -> BoneMotion:
        """The tibia's rigid motion (rotation about ``bone_com_mm``, then translation)."""
        return BoneMotion(
            rotation_deg=tuple(self.bone_rotation_deg),
            centre_mm=tuple(self.bone_com_mm),
            translation_mm=tuple(self.bone_translation_mm),
        )

    def to_dict(self) -> dict:
        """The keys of ``pose.json``: the quantities as lists, then ``extra``'s keys."""
        d = {name: getattr(self, name).tolist() for name in _VECTORS}
        d["depth_mm"] = self.depth_mm
        if self.indenter_com_mm is not None:
            d["indenter_com_mm"] = self.indenter_com_mm.tolist()
        d.update(self.extra)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Pose:
        """The Pose of :meth:`to_dict`'s keys; keys it does not know go to ``extra``."""
        known = set(_VECTORS) | {"depth_mm", "indenter_com_mm"}
        missing = [k for k in (*_VECTORS, "depth_mm") if k not in d]
        if missing:
            raise ValueError(f"pose lacks key(s) {missing}")
        return cls(
            **{k: d[k] for k in known if k in d},
            extra={k: v for k, v in d.items() if k not in known},
        )


def save_pose(path: str | Path, pose: Pose) -> None:
    """Write ``pose`` as JSON.

    Parameters
    ----------
    path : str or Path
        The ``pose.json`` (or phantom ``truth.json``) to write, atomically.
    pose : Pose
        Written with :meth:`Pose.to_dict`'s keys.
    """
    write_json(path, pose.to_dict())


def load_pose(path: str | Path) -> Pose:
    """Read a file written by :func:`save_pose`.

    Parameters
    ----------
    path : str or Path
        A ``pose.json`` or phantom ``truth.json``.

    Returns
    -------
    Pose
        Unknown keys are kept in ``extra``.

    Raises
    ------
    ValueError
        Naming ``path``, if a quantity is missing or malformed.
    """
    try:
        return Pose.from_dict(read_json(path))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
