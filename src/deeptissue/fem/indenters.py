"""Rigid analytical indenters: signed distance, outward normal and normal gradient, vectorised.

Both indenters are "distance to a segment (or ray) minus a radius":

- ``sphere``: a hollow cylinder of radius R ending in a hemispherical head of radius R. The core
  line is the ray from the head centre ``c = tip - R * axis`` backwards along ``-axis``.
- ``bar``: a capsule (cylinder of radius R with hemispherical ends), total length ``length_mm`` end
  to end, long axis perpendicular to ``axis`` and along the leg (world z projected onto the plane
  perpendicular to ``axis``). The core line is the segment through ``c = tip - R * axis`` of half
  length ``length_mm / 2 - R``.

``axis`` is the unit vector FROM the indenter INTO the leg; the tip is the point furthest along it.
All functions take points ``x`` of shape (n, 3) [mm] and return arrays over n.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import bar_direction as _bar_direction

__all__ = ["Indenter", "indenter_gap"]


@dataclass(frozen=True)
class Indenter:
    """A rigid indenter moving from ``start_mm`` to ``end_mm`` (tip positions, world mm).

    kind: 'sphere' (hollow cylinder with a hemispherical head) or 'bar' (capsule along the leg).
    axis: (3,) direction of travel, from the indenter into the leg (normalised on use).
    radius_mm: radius of head / shaft / bar (default 1.5 mm: 3 mm diameter).
    bar_length_mm: total length of the bar end to end (only for 'bar').
    """

    kind: str = "sphere"
    axis: tuple = (0.0, 0.0, -1.0)
    start_mm: tuple = (0.0, 0.0, 0.0)
    end_mm: tuple = (0.0, 0.0, 0.0)
    radius_mm: float = 1.5
    bar_length_mm: float = 10.0

    def __post_init__(self):
        if self.kind not in ("sphere", "bar"):
            raise ValueError(f"Indenter.kind: expected 'sphere' or 'bar', got {self.kind!r}")
        a = np.asarray(self.axis, float)
        if a.shape != (3,) or not np.linalg.norm(a) > 0:
            raise ValueError(f"Indenter.axis: expected a non-zero 3-vector, got {self.axis!r}")
        if self.radius_mm <= 0:
            raise ValueError(f"Indenter.radius_mm must be > 0, got {self.radius_mm}")
        if self.kind == "bar" and self.bar_length_mm < 2 * self.radius_mm:
            raise ValueError(
                f"Indenter.bar_length_mm must be >= 2 * radius_mm, got {self.bar_length_mm}"
            )

    @property
    def unit_axis(self) -> np.ndarray:
        """``axis`` normalised, (3,)."""
        a = np.asarray(self.axis, float)
        return a / np.linalg.norm(a)

    def bar_direction(self) -> np.ndarray:
        """Unit long axis of the bar: world z projected onto the plane perpendicular to the axis
        (:func:`deeptissue.geometry.bar_direction`, the direction the model refines and tags the patch
        along; ValueError for an axis along the leg)."""
        return _bar_direction(self.unit_axis)

    @property
    def bar_half_length_mm(self) -> float:
        """Half length of the bar's straight part (between the centres of its rounded ends) [mm]."""
        return 0.5 * float(self.bar_length_mm) - float(self.radius_mm)

    def tip_at(self, s: float) -> np.ndarray:
        """Tip position at travel fraction s in [0, 1] (3,) [mm]."""
        a, b = np.asarray(self.start_mm, float), np.asarray(self.end_mm, float)
        return a + s * (b - a)

    def gap(self, x: np.ndarray, tip_mm: np.ndarray, hessian: bool = True):
        """Signed distance from points x (n, 3) to the indenter surface with its tip at ``tip_mm``.

        Returns g (n,) [mm] (negative inside), n (n, 3) outward unit normal (= grad g) and
        H (n, 3, 3) [1/mm] = grad n (the Hessian of g; None without ``hessian``).
        """
        return indenter_gap(self, x, tip_mm, hessian=hessian)


def indenter_gap(ind: Indenter, x: np.ndarray, tip_mm: np.ndarray, hessian: bool = True):
    """Signed distance, outward normal and normal gradient of ``ind`` with its tip at ``tip_mm``.

    Parameters
    ----------
    ind : Indenter
    x : (n, 3) array_like
        Points [mm].
    tip_mm : (3,) array_like
        Tip position [mm].
    hessian : bool
        Also return H.

    Returns
    -------
    g : (n,) ndarray
        Signed distance to the surface [mm], negative inside.
    n : (n, 3) ndarray
        Outward unit normal (gradient of g).
    H : (n, 3, 3) ndarray or None
        Gradient of n (Hessian of g) [1/mm]; None without ``hessian``.
    """
    x = np.asarray(x, float).reshape(-1, 3)
    a = ind.unit_axis
    R = float(ind.radius_mm)
    c = np.asarray(tip_mm, float) - R * a
    d = x - c
    if ind.kind == "sphere":
        t = -a  # ray direction
        s = d @ t
        on_line = s > 0
        s = np.where(on_line, s, 0.0)
    else:
        t = ind.bar_direction()
        h = ind.bar_half_length_mm
        s = d @ t
        on_line = np.abs(s) < h
        s = np.clip(s, -h, h)
    r = d - s[:, None] * t
    dist = np.linalg.norm(r, axis=1)
    safe = np.maximum(dist, 1e-12 * R)
    n = r / safe[:, None]
    g = dist - R
    if not hessian:
        return g, n, None
    eye = np.eye(3)
    P = eye - n[:, :, None] * n[:, None, :]
    tt = np.outer(t, t)
    P = P - on_line[:, None, None] * tt
    H = P / safe[:, None, None]
    return g, n, H
