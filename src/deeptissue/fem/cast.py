"""Rigid cast: a triangulated surface (normals toward the leg) the skin may not cross outward.

``Cast.gap(x)`` returns the signed distance of points to the surface, positive on the side the
triangle normals point to (the leg), its gradient (the contact normal; continuous across triangle
edges) and the gradient of that normal (nonzero near edges and vertices).
Points whose nearest surface point lies on a free boundary edge (the open ends, the indenter
hole) and which are beyond it are given no contact (g = +inf).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import closest_point_on_triangles

__all__ = ["Cast", "closest_point_on_triangles"]


class Cast:
    """A rigid triangulated cast. vertices_mm (V, 3), triangles (T, 3) oriented toward the leg."""

    def __init__(self, vertices_mm: np.ndarray, triangles: np.ndarray, *, k_nearest: int = 8, curvature: bool = True):
        self.curvature = curvature
        self.v = np.asarray(vertices_mm, float)
        self.t = np.asarray(triangles, np.int64)
        if self.v.ndim != 2 or self.v.shape[1] != 3 or self.t.ndim != 2 or self.t.shape[1] != 3 or len(self.t) == 0:
            raise ValueError(f"cast: expected vertices (V, 3) and triangles (T, 3), got {self.v.shape} and {self.t.shape}")
        if self.t.min() < 0 or self.t.max() >= len(self.v):
            raise ValueError("cast: triangle vertex index out of range")
        a, b, c = (self.v[self.t[:, i]] for i in range(3))
        nrm = np.cross(b - a, c - a)
        ln = np.linalg.norm(nrm, axis=1)
        if np.any(ln <= 0):
            raise ValueError(f"cast: {np.count_nonzero(ln <= 0)} degenerate triangles")
        self.normal = nrm / ln[:, None]
        self.centroid = (a + b + c) / 3.0
        self.tree = cKDTree(self.centroid)
        self.k = min(k_nearest, len(self.t))
        # boundary edges (used by one triangle): region codes 1..3 of a triangle that are free
        e = np.stack([self.t[:, [0, 1]], self.t[:, [1, 2]], self.t[:, [2, 0]]], axis=1)  # (T, 3, 2)
        es = np.sort(e, axis=2).reshape(-1, 2)
        keys = es[:, 0] * len(self.v) + es[:, 1]
        _, inv, cnt = np.unique(keys, return_inverse=True, return_counts=True)
        self.free_edge = (cnt[inv] == 1).reshape(-1, 3)  # (T, 3): edge ab, bc, ca
        vfree = np.zeros(len(self.v), bool)
        vfree[e.reshape(-1, 2)[self.free_edge.ravel()].ravel()] = True
        self.free_vertex = vfree[self.t]  # (T, 3)

    @classmethod
    def load(cls, path: str | Path, **kwargs) -> "Cast":
        """Read cast.npz (arrays vertices_mm, triangles); kwargs go to the constructor."""
        try:
            with np.load(path) as d:
                return cls(d["vertices_mm"], d["triangles"], **kwargs)
        except (KeyError, OSError) as exc:
            raise ValueError(f"{path}: not a cast file ({exc})") from exc

    def gap(self, x: np.ndarray):
        """Signed distance of points to the cast, its gradient and the gradient of that normal.

        Parameters
        ----------
        x : (n, 3) array_like
            Points [mm].

        Returns
        -------
        g : (n,) ndarray
            Signed distance [mm], positive on the leg's side; +inf where no contact is possible
            (beyond a free edge or vertex: the open ends and the hole).
        normal : (n, 3) ndarray
            Unit gradient of g (the contact normal).
        H : (n, 3, 3) ndarray or None
            Gradient of the normal [1/mm] (zero on faces), None when built with ``curvature=False``.
        """
        x = np.asarray(x, float).reshape(-1, 3)
        n = len(x)
        _, cand = self.tree.query(x, k=self.k)
        cand = cand.reshape(n, -1)
        kk = cand.shape[1]
        P = np.repeat(x, kk, axis=0)
        T = cand.ravel()
        q, region = closest_point_on_triangles(P, *(self.v[self.t[T, i]] for i in range(3)))
        d2 = np.sum((P - q) ** 2, axis=1).reshape(n, kk)
        j = np.argmin(d2, axis=1)
        sel = np.arange(n) * kk + j
        tri = T[sel]
        reg = region[sel]
        q = q[sel]
        ntri = self.normal[tri]
        r = x - q
        d = np.linalg.norm(r, axis=1)
        side = np.where(np.einsum("ij,ij->i", r, ntri) >= 0, 1.0, -1.0)
        # signed distance and its gradient: continuous across triangle edges (C1 off the surface)
        tiny = d <= 1e-10
        nrm = np.where(tiny[:, None] | (reg[:, None] == 0), ntri, side[:, None] * r / np.where(tiny, 1.0, d)[:, None])
        g = np.where(reg == 0, np.einsum("ij,ij->i", r, ntri), side * d)
        # gradient of the normal: zero on faces, (I - n n - e e) / d at edges, (I - n n) / d at vertices
        H = np.zeros((n, 3, 3))
        curved = (reg > 0) & ~tiny
        if np.any(curved):
            nn = nrm[curved]
            P = np.eye(3) - nn[:, :, None] * nn[:, None, :]
            rc = reg[curved]
            tv = self.v[self.t[tri[curved]]]  # (m, 3, 3)
            i0 = np.where(rc == 1, 0, np.where(rc == 2, 1, 2))
            i1 = np.where(rc == 1, 1, np.where(rc == 2, 2, 0))
            m_idx = np.arange(len(rc))
            e = tv[m_idx, i1] - tv[m_idx, i0]
            e /= np.linalg.norm(e, axis=1)[:, None]
            edge = (rc <= 3)[:, None, None]
            P = P - edge * e[:, :, None] * e[:, None, :]
            H[curved] = side[curved][:, None, None] * P / d[curved][:, None, None]
        # beyond a free edge / vertex: no contact
        on_free = np.zeros(n, bool)
        e = (reg >= 1) & (reg <= 3)
        on_free[e] = self.free_edge[tri[e], reg[e] - 1]
        vtx = reg >= 4
        on_free[vtx] = self.free_vertex[tri[vtx], reg[vtx] - 4]
        g = np.where(on_free, np.inf, g)
        return g, nrm, (H if self.curvature else None)
