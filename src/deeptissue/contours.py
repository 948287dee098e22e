"""The contour result type of the segmentation stage, and its file format.

A :class:`Contours` holds the skin and tibia contours of every axial slice of one state
(``pre`` or ``during``): arrays of shape ``(n_slices, n_points, 3)`` in world mm, each contour
closed implicitly (the last point is not repeated), counter-clockwise seen from +z, starting
at a fixed polar angle about the slice centroid. Optionally the fibula: an array of the same
layout, ``(n_slices, n_points, 3)``, whose rows are NaN on the slices where no fibula was found
(``None``: no fibula anywhere, e.g. a scan where it is out of view or not segmented).
Optionally ``bone_hidden``, ``(n_slices,)`` bool: the during slices where the tibia touches the indenter,
whose tibia contour is the pre tibia moved by the rigid fit of the other slices (the pose stage leaves them
out of its fit). Written and read only by :func:`save_contours` / :func:`load_contours` (``.npz`` with
arrays ``skin`` and ``bone``, and ``fibula`` and ``bone_hidden`` when there are any).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .io import save_npz

__all__ = [
    "STRUCTURES",
    "Contours",
    "load_contours",
    "point_to_polygon_distance",
    "points_in_polygon",
    "polygon_area_centroid",
    "resample_closed",
    "resample_contour_3d",
    "save_contours",
    "slices_with_contour",
]

#: The structures a :class:`Contours` holds (the fibula optional).
STRUCTURES = ("skin", "bone", "fibula")


@dataclass(frozen=True)
class Contours:
    """Skin, tibia and (optionally) fibula contours of every axial slice of one state (see the module)."""

    skin: np.ndarray  # (n_slices, n_points, 3) world mm
    bone: np.ndarray  # (n_slices, n_points, 3) world mm: the tibia
    fibula: np.ndarray | None = (
        None  # (n_slices, n_points_f, 3) world mm, NaN rows where absent; None: none
    )
    bone_hidden: np.ndarray | None = (
        None  # (n_slices,) bool: tibia against the indenter, contour from the pre bone
    )

    def __post_init__(self):
        for name in ("skin", "bone"):
            a = getattr(self, name)
            if a.ndim != 3 or a.shape[2] != 3:
                raise ValueError(
                    f"contours.{name}: expected shape (n_slices, n_points, 3), got {a.shape}"
                )
            if not np.all(np.isfinite(a)):
                raise ValueError(f"contours.{name}: non-finite coordinates")
        if self.skin.shape[0] != self.bone.shape[0]:
            raise ValueError(
                f"contours: skin has {self.skin.shape[0]} slices but bone has {self.bone.shape[0]}"
            )
        if self.fibula is not None:
            f = np.asarray(self.fibula, float)
            if f.ndim != 3 or f.shape[2] != 3 or f.shape[0] != self.skin.shape[0]:
                raise ValueError(
                    f"contours.fibula: expected shape ({self.skin.shape[0]}, n_points, 3), got {f.shape}"
                )
            fin = np.isfinite(f).reshape(f.shape[0], -1)
            mixed = np.nonzero(fin.any(axis=1) & ~fin.all(axis=1))[0]
            if len(mixed):
                raise ValueError(
                    f"contours.fibula: slice {int(mixed[0])} is partly non-finite (a slice has a whole "
                    "contour or NaN throughout)"
                )
            object.__setattr__(self, "fibula", f if fin.any() else None)
        if self.bone_hidden is not None:
            h = np.asarray(self.bone_hidden, bool)
            if h.shape != (self.skin.shape[0],):
                raise ValueError(
                    f"contours.bone_hidden: expected shape ({self.skin.shape[0]},), got {h.shape}"
                )
            object.__setattr__(self, "bone_hidden", h if h.any() else None)

    @property
    def bone_seen(self) -> np.ndarray:
        """Boolean (n_slices,): the slices whose tibia contour was traced in the image (not ``bone_hidden``)."""
        return np.ones(self.n_slices, bool) if self.bone_hidden is None else ~self.bone_hidden

    @property
    def fibula_slices(self) -> np.ndarray:
        """Boolean (n_slices,): the slices that have a fibula contour."""
        if self.fibula is None:
            return np.zeros(self.n_slices, bool)
        return slices_with_contour(self.fibula)

    @property
    def fibula_rows(self) -> np.ndarray:
        """The fibula contours of the slices that have one, stacked (m, n_points, 3); m = 0 if none."""
        if self.fibula is None:
            return np.zeros((0, 1, 3))
        return self.fibula[self.fibula_slices]

    @property
    def n_slices(self) -> int:
        """Number of slices (first axis of every array)."""
        return self.skin.shape[0]

    @property
    def z_mm(self) -> np.ndarray:
        """Slice positions (mean z of each skin contour)."""
        return self.skin[:, :, 2].mean(axis=1)


def slices_with_contour(stack: np.ndarray) -> np.ndarray:
    """Boolean (n_slices,): the slices of a stack (n_slices, n_points, 3; NaN rows where a structure
    is absent) that have a whole contour."""
    stack = np.asarray(stack, float)
    return np.isfinite(stack).reshape(stack.shape[0], -1).all(axis=1)


def save_contours(path: str | Path, contours: Contours) -> None:
    """Write ``contours`` to ``path`` (``.npz``), atomically.

    Parameters
    ----------
    path : str or Path
        Output file.
    contours : Contours
        Written as arrays ``skin`` and ``bone`` (n_slices, n_points, 3) [mm], ``fibula``
        (n_slices, n_points_f, 3) [mm, NaN rows where absent] when there is one, and ``bone_hidden``
        (n_slices,) bool when a slice has one.
    """
    arrays = dict(skin=contours.skin, bone=contours.bone)
    if contours.fibula is not None:
        arrays["fibula"] = contours.fibula
    if contours.bone_hidden is not None:
        arrays["bone_hidden"] = contours.bone_hidden
    save_npz(path, **arrays)


def load_contours(path: str | Path) -> Contours:
    """Read a file written by :func:`save_contours`.

    Parameters
    ----------
    path : str or Path
        ``.npz`` with arrays ``skin``, ``bone`` and optionally ``fibula``.

    Returns
    -------
    Contours
        Validated as on construction (shapes, finite coordinates, whole-or-NaN fibula rows).

    Raises
    ------
    ValueError
        If the file is unreadable, lacks an array or holds invalid contours; the message names the file.
    """
    try:
        with np.load(path) as data:
            skin, bone = data["skin"], data["bone"]
            fibula = data["fibula"] if "fibula" in data.files else None
            hidden = data["bone_hidden"] if "bone_hidden" in data.files else None
    except KeyError as exc:
        raise ValueError(f"{path}: contour file lacks array {exc}") from exc
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a contour file ({exc})") from exc
    try:
        return Contours(
            skin=np.asarray(skin, float),
            bone=np.asarray(bone, float),
            fibula=None if fibula is None else np.asarray(fibula, float),
            bone_hidden=hidden,
        )
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# Resampling of closed contours (PCHIP over arc length)
# ---------------------------------------------------------------------------------------------


def polygon_area_centroid(xy: np.ndarray) -> tuple[float, np.ndarray]:
    """Signed area (mm², > 0 if counter-clockwise) and area centroid (2,) of a closed polygon (n, 2)."""
    x, y = xy[:, 0], xy[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    if abs(area) < 1e-300:
        return 0.0, xy.mean(axis=0)
    cx = ((x + xn) * cross).sum() / (6 * area)
    cy = ((y + yn) * cross).sum() / (6 * area)
    return float(area), np.array([cx, cy])


def resample_closed(
    xy, *, n_points: int = 100, start_angle_deg: float = 90.0, oversample: int = 16
) -> np.ndarray:
    """Resample a closed planar curve to ``n_points`` circumferentially equidistant points.

    A shape-preserving piecewise cubic (PCHIP, periodic by wrapping) interpolates x and y over the
    polyline's arc length; the interpolant is evaluated densely, its arc length recomputed, and
    ``n_points`` stations equally spaced in that arc length are returned.

    Parameters
    ----------
    xy : (m, 2) array_like
        The curve's vertices in order [mm], either orientation; a repeated closing point and
        zero-length steps are dropped; at least 4 distinct points.
    n_points : int
        Number of output points.
    start_angle_deg : float
        Polar angle [deg] (from +x toward +y) of the ray from the area centroid whose outermost
        crossing with the curve is the first output point.
    oversample : int
        Dense evaluation points per output (or input) point, at least 2000 in all.

    Returns
    -------
    (n_points, 2) ndarray
        Counter-clockwise points [mm], equally spaced in arc length.

    Raises
    ------
    ValueError
        Bad shape, fewer than 4 distinct points, or a start ray that misses the curve.
    """
    from scipy.interpolate import PchipInterpolator

    p = np.asarray(xy, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"resample_closed: expected (m, 2) points, got {p.shape}")
    if len(p) > 1 and np.allclose(p[0], p[-1]):
        p = p[:-1]
    # drop zero-length steps (marching squares may repeat vertices)
    step = np.linalg.norm(np.diff(p, axis=0, append=p[:1]), axis=1)
    p = p[step > 1e-12]
    if len(p) < 4:
        raise ValueError(
            f"resample_closed: a closed contour needs at least 4 distinct points, got {len(p)}"
        )
    area, _ = polygon_area_centroid(p)
    if area < 0:
        p = p[::-1]
    m = len(p)
    seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    length = s[-1]
    k = min(4, m)  # wrap a few points on each side so the interpolant is periodic in effect
    s_ext = np.concatenate([s[m - k : m] - length, s[:m], s[:k] + length])
    p_ext = np.concatenate([p[m - k :], p, p[:k]])
    f = PchipInterpolator(s_ext, p_ext, axis=0)
    n_dense = max(oversample * max(n_points, m), 2000)
    sd = np.linspace(0.0, length, n_dense, endpoint=False)
    d = f(sd)
    # arc length of the dense interpolant
    dd = np.linalg.norm(np.roll(d, -1, axis=0) - d, axis=1)
    sa = np.concatenate([[0.0], np.cumsum(dd)])
    total = sa[-1]
    dclosed = np.vstack([d, d[:1]])
    _, c = polygon_area_centroid(d)
    # start: outermost crossing of the ray from the centroid at the start angle
    u = np.array([np.cos(np.radians(start_angle_deg)), np.sin(np.radians(start_angle_deg))])
    v = np.array([-u[1], u[0]])
    rel = dclosed - c
    side = rel @ v  # signed distance from the ray's line
    along = rel @ u
    cross_i = np.nonzero((side[:-1] <= 0) & (side[1:] > 0) | (side[:-1] < 0) & (side[1:] >= 0))[0]
    best, s0 = -np.inf, 0.0
    for i in cross_i:
        t = side[i] / (side[i] - side[i + 1]) if side[i] != side[i + 1] else 0.0
        a = along[i] + t * (along[i + 1] - along[i])
        if a > 0 and a > best:
            best, s0 = a, sa[i] + t * (sa[i + 1] - sa[i])
    if not np.isfinite(best):
        raise ValueError(
            "resample_closed: the start-angle ray from the centroid does not cross the curve"
        )
    st = (s0 + total * np.arange(n_points) / n_points) % total
    out = np.column_stack([np.interp(st, sa, dclosed[:, j]) for j in range(2)])
    return out


def resample_contour_3d(
    points_mm, *, z_mm: float, n_points: int = 100, start_angle_deg: float = 90.0
) -> np.ndarray:
    """:func:`resample_closed` of the x, y of ``points_mm`` (m, 2 or 3), returned as (n_points, 3) at ``z_mm``."""
    xy = resample_closed(
        np.asarray(points_mm, float)[:, :2], n_points=n_points, start_angle_deg=start_angle_deg
    )
    return np.column_stack([xy, np.full(len(xy), float(z_mm))])


def point_to_polygon_distance(points_xy, polygon_xy) -> np.ndarray:
    """Distance (mm) from each of ``points_xy`` (n, 2) to the closed polygon ``polygon_xy`` (m, 2)."""
    p = np.asarray(points_xy, float)[:, None, :]
    a = np.asarray(polygon_xy, float)
    b = np.roll(a, -1, axis=0)
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    q = a + t[..., None] * ab
    return np.sqrt(((p - q) ** 2).sum(-1)).min(axis=1)


def points_in_polygon(points_xy, polygon_xy) -> np.ndarray:
    """Boolean (n,): which of ``points_xy`` (n, 2) lie inside the closed polygon (m, 2)."""
    from matplotlib.path import Path as _MplPath

    return _MplPath(np.asarray(polygon_xy, float)).contains_points(np.asarray(points_xy, float))
