"""Synthetic masked scans of two legs (background and fat exactly 0), for leg selection and the 3D tibia choice.

Each leg is a disc of muscle (1.0) inside a skin ring (0.5) and a fat ring (0, masked), with a dark tibia (0) on
its anterior (+y) side and a smaller dark fibula (0) posterolaterally, straight along z. Everything is given in
world mm on a grid of ``px_mm`` pixels and ``dz_mm`` slices centred on the origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from deeptissue.imaging import Volume

SKIN_MM, FAT_MM = 0.4, 0.3  # the skin ring's and the fat ring's widths


@dataclass(frozen=True)
class Leg:
    centre_mm: tuple[float, float]
    radius_mm: float = 5.9
    tibia_mm: tuple[float, float] = (0.5, 2.6)  # tibia centre, from the leg's centre
    tibia_radius_mm: float = 1.3
    fibula_mm: tuple[float, float] = (-2.6, -1.2)
    fibula_radius_mm: float = 0.7
    # slices on which the tibia's dark region opens into the dark fat ring (a dark channel of this width)
    open_slices: tuple[int, ...] = field(default=())
    channel_mm: float = 0.8
    # the leg's centre moves by this much per slice [mm] (legs that meet over some slices)
    drift_mm: tuple[float, float] = (0.0, 0.0)
    # slices into the ankle (the tibia's shaft gone: tendons, no bone section) and into the knee (the tibia's
    # plateau, 2.2 times its shaft's radius, which takes the fibula's place)
    ankle_slices: tuple[int, ...] = field(default=())
    knee_slices: tuple[int, ...] = field(default=())
    # slices on which a dark septum of this width joins the tibia to the fibula (wider than an opening parts)
    septum_slices: tuple[int, ...] = field(default=())
    septum_mm: float = 1.2

    def centre_at(self, k: int) -> np.ndarray:
        """The leg's centre on slice ``k`` [mm]."""
        return np.add(self.centre_mm, np.multiply(self.drift_mm, k))

    def tibia_at(self, k: int) -> tuple[np.ndarray, float] | None:
        """The true tibia on slice ``k``: centre [mm] and radius [mm], None where it has no section."""
        if k in self.ankle_slices:
            return None
        r = self.tibia_radius_mm * (2.2 if k in self.knee_slices else 1.0)
        return self.centre_at(k) + self.tibia_mm, r


def _one_leg(leg: Leg, X, Y, k: int) -> np.ndarray:
    """One leg's intensities on slice ``k`` at the points (X, Y) [mm]."""
    one = np.zeros(X.shape, np.float32)
    cx, cy = leg.centre_at(k)
    r = np.hypot(X - cx, Y - cy)
    one[r <= leg.radius_mm] = 0.5
    one[r <= leg.radius_mm - SKIN_MM] = 0.0
    inner = leg.radius_mm - SKIN_MM - FAT_MM
    one[r <= inner] = 1.0 + 0.05 * np.cos(3 * np.arctan2(Y - cy, X - cx))[r <= inner]
    tibia = leg.tibia_at(k)
    if tibia is not None:
        (tx, ty), tr = tibia
        one[np.hypot(X - tx, Y - ty) <= tr] = 0.0
        if k in leg.open_slices:  # a dark channel from the tibia straight out into the fat ring
            one[(np.abs(X - tx) <= leg.channel_mm / 2) & (Y >= ty) & (r <= inner + 0.05)] = 0.0
    if k not in leg.knee_slices:
        fx, fy = cx + leg.fibula_mm[0], cy + leg.fibula_mm[1]
        one[np.hypot(X - fx, Y - fy) <= leg.fibula_radius_mm] = 0.0
        if (
            k in leg.septum_slices and tibia is not None
        ):  # a dark band from the fibula's centre to the tibia's
            (tx, ty), _ = tibia
            u = np.array([tx - fx, ty - fy]) / np.hypot(tx - fx, ty - fy)
            along = (X - fx) * u[0] + (Y - fy) * u[1]
            across = np.abs(-(X - fx) * u[1] + (Y - fy) * u[0])
            length = np.hypot(tx - fx, ty - fy)
            one[(across <= leg.septum_mm / 2) & (along >= 0) & (along <= length)] = 0.0
    return one


def masked_legs(
    legs,
    *,
    n=(112, 96, 8),
    px_mm=0.25,
    dz_mm=1.0,
    extra=None,
    animal="twin",
    path="legs.nii.gz",
    supersample: int = 1,
):
    """A :class:`Volume` of ``legs`` (a list of :class:`Leg`); ``extra``: ``{slice: (x, y, radius)}`` dark discs
    [mm] added on single slices (structures that do not run along the leg). With ``supersample`` s, each pixel
    is the mean of s x s samples (partial volume at every edge, as a scanner's pixel), else its centre's value."""
    ni, nj, nk = n
    affine = np.diag([px_mm, px_mm, dz_mm, 1.0])
    affine[:3, 3] = [-(ni - 1) / 2 * px_mm, -(nj - 1) / 2 * px_mm, -(nk - 1) / 2 * dz_mm]
    ss = int(supersample)
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    X, Y = np.meshgrid(
        affine[0, 3] + px_mm * (np.arange(ni)[:, None] + sub).ravel(),
        affine[1, 3] + px_mm * (np.arange(nj)[:, None] + sub).ravel(),
        indexing="ij",
    )
    data = np.zeros(n, np.float32)
    for k in range(nk):
        img = np.zeros(X.shape, np.float32)
        for leg in legs:  # where legs touch, each keeps its skin (the brighter of the two images)
            img = np.maximum(img, _one_leg(leg, X, Y, k))
        for kk, (x, y, rad) in (extra or {}).items():
            if kk == k:
                img[np.hypot(X - x, Y - y) <= rad] = 0.0
        data[:, :, k] = img.reshape(ni, ss, nj, ss).mean(axis=(1, 3))
    return Volume(data=data, affine=affine, path=path, animal=animal)


def centroid_xy(contour):
    """Area centroid of one closed contour (n, 2|3) [mm]."""
    from deeptissue.contours import polygon_area_centroid

    return np.asarray(polygon_area_centroid(np.asarray(contour)[:, :2])[1])
