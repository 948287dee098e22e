"""Rigid cast: a triangulated surface (normals toward the leg) the skin may not cross outward.

The contact gap of a point x is a smooth implicit surface through the cast's vertices, not the distance
to its facets: the distance's gradient jumps by the angle between two facets where a point crosses their
common edge, so the contact force of a skin point sliding over an edge would jump and Newton's method
alternate between the two faces without converging. ``Cast.gap`` returns the moving-least-squares
average of the vertices' tangent-plane distances,
``g(x) = sum_v w_v(x) (x - v) . n_v / sum_v w_v(x)``, with n_v the vertex normals (area-weighted
triangle normals, toward the leg) and ``w_v = (1 - |x - v|^2 / r^2)^4`` (zero beyond r, 1.2 times the
longest cast edge), and its exact gradient and Hessian (C^2 in x): a linearisation consistent with the gap.
Near the surface g is the signed distance to within the facets' sagitta (edge^2 / (2 R) for a cast of
radius R). Where no vertex is within r (far from the cast, never a contact candidate) the distance to the
facets is returned. Points whose nearest surface point lies on a free boundary edge (the open ends, the
indenter hole) and which are beyond it are given no contact (g = +inf).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import closest_point_on_triangles

__all__ = ["Cast", "closest_point_on_triangles"]


class Cast:
    """A rigid triangulated cast. vertices_mm (V, 3), triangles (T, 3) oriented toward the leg."""

    def __init__(self, vertices_mm: np.ndarray, triangles: np.ndarray, *, k_nearest: int = 8):
        self.v = np.asarray(vertices_mm, float)
        self.t = np.asarray(triangles, np.int64)
        if (
            self.v.ndim != 2
            or self.v.shape[1] != 3
            or self.t.ndim != 2
            or self.t.shape[1] != 3
            or len(self.t) == 0
        ):
            raise ValueError(
                f"cast: expected vertices (V, 3) and triangles (T, 3), got {self.v.shape} and {self.t.shape}"
            )
        if self.t.min() < 0 or self.t.max() >= len(self.v):
            raise ValueError("cast: triangle vertex index out of range")
        a, b, c = (self.v[self.t[:, i]] for i in range(3))
        nrm = np.cross(b - a, c - a)
        ln = np.linalg.norm(nrm, axis=1)
        if np.any(ln <= 0):
            raise ValueError(f"cast: {np.count_nonzero(ln <= 0)} degenerate triangles")
        self.normal = nrm / ln[:, None]
        vn = np.zeros_like(self.v)
        for i in range(3):
            np.add.at(vn, self.t[:, i], nrm)  # area-weighted
        # the moving-least-squares gap uses the vertices with a normal: one that no triangle uses (inside a hole
        # cut out of the cast) has none
        ln_v = np.linalg.norm(vn, axis=1)
        with_normal = ln_v > 0
        self.mls_vertices_mm = self.v[with_normal]
        self.vertex_normal = vn[with_normal] / ln_v[with_normal, None]
        edges = np.concatenate(
            [self.v[self.t[:, i]] - self.v[self.t[:, (i + 1) % 3]] for i in range(3)]
        )
        self.radius_mm = 1.2 * float(
            np.linalg.norm(edges, axis=1).max()
        )  # support of the vertex weights
        self.vtree = cKDTree(self.mls_vertices_mm)
        self.centroid = (a + b + c) / 3.0
        self.tree = cKDTree(self.centroid)
        self.k = min(k_nearest, len(self.t))
        # boundary edges (used by one triangle): region codes 1..3 of a triangle that are free
        e = np.stack(
            [self.t[:, [0, 1]], self.t[:, [1, 2]], self.t[:, [2, 0]]], axis=1
        )  # (T, 3, 2)
        es = np.sort(e, axis=2).reshape(-1, 2)
        keys = es[:, 0] * len(self.v) + es[:, 1]
        _, inv, cnt = np.unique(keys, return_inverse=True, return_counts=True)
        self.free_edge = (cnt[inv] == 1).reshape(-1, 3)  # (T, 3): edge ab, bc, ca
        vfree = np.zeros(len(self.v), bool)
        vfree[e.reshape(-1, 2)[self.free_edge.ravel()].ravel()] = True
        self.free_vertex = vfree[self.t]  # (T, 3)

    @classmethod
    def load(cls, path: str | Path, **kwargs) -> Cast:
        """Read cast.npz (arrays vertices_mm, triangles); kwargs go to the constructor."""
        try:
            with np.load(path) as d:
                return cls(d["vertices_mm"], d["triangles"], **kwargs)
        except (KeyError, OSError) as exc:
            raise ValueError(f"{path}: not a cast file ({exc})") from exc

    def gap(self, x: np.ndarray, hessian: bool = True):
        """Contact gap of points to the cast (near the surface its signed distance), its gradient and Hessian.

        Parameters
        ----------
        x : (n, 3) array_like
            Points [mm].
        hessian : bool
            Also return the Hessian (about a seventh of the cost; the weighted gaps need it only for the
            curvature of a Newton direction).

        Returns
        -------
        g : (n,) ndarray
            Gap [mm], positive on the leg's side; +inf where no contact is possible (beyond a free edge
            or vertex: the open ends and the hole).
        normal : (n, 3) ndarray
            Gradient of g (the contact normal; unit length to within the facets' angles).
        H : (n, 3, 3) ndarray or None
            Hessian of g [1/mm] (the gradient of the contact normal); None without ``hessian``.
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
        side = np.where(np.einsum("ij,ij->i", r, ntri) >= 0, 1.0, -1.0)
        d = np.linalg.norm(r, axis=1)
        g = np.where(reg == 0, np.einsum("ij,ij->i", r, ntri), side * d)
        nrm = np.where(
            (reg == 0)[:, None] | (d[:, None] <= 1e-12),
            ntri,
            side[:, None] * r / np.maximum(d, 1e-300)[:, None],
        )
        # the moving-least-squares gap and its exact gradient where vertices are within the support
        rr = self.radius_mm
        # the vertices within the support: 16 per point, more (doubled) only for the points whose 16th is inside
        n_v = len(self.mls_vertices_mm)
        kv = min(16, n_v)
        dist, idx = self.vtree.query(x, k=kv, distance_upper_bound=rr)
        dist, idx = dist.reshape(n, -1), idx.reshape(n, -1)
        more = np.flatnonzero(np.isfinite(dist[:, -1]))
        while len(more) and kv < n_v:
            kv = min(2 * kv, n_v)
            d_m, i_m = self.vtree.query(x[more], k=kv, distance_upper_bound=rr)
            dist = np.pad(dist, ((0, 0), (0, kv - dist.shape[1])), constant_values=np.inf)
            idx = np.pad(idx, ((0, 0), (0, kv - idx.shape[1])), constant_values=n_v)
            dist[more], idx[more] = d_m.reshape(len(more), -1), i_m.reshape(len(more), -1)
            more = more[np.isfinite(dist[more, -1])]
        width = max(
            int(np.isfinite(dist).sum(axis=1).max(initial=1)), 1
        )  # nearest first: the rest are outside
        dist, idx = dist[:, :width], idx[:, :width]
        ok = np.isfinite(dist)
        vi = np.where(ok, idx, 0)
        dv = x[:, None, :] - self.mls_vertices_mm[vi]  # (n, k, 3)
        nv = self.vertex_normal[vi]
        s_ = np.where(ok, dist**2 / rr**2, 1.0)
        w = np.where(ok, (1.0 - s_) ** 4, 0.0)
        c1 = np.where(ok, -8.0 * (1.0 - s_) ** 3 / rr**2, 0.0)
        dw = c1[:, :, None] * dv  # grad w_v = c1 dv, its Hessian c2 dv dv^T + c1 I
        W = w.sum(axis=1)
        smooth = W > 1e-6
        Ws = np.where(smooth, W, 1.0)
        fv = np.einsum("nki,nki->nk", dv, nv)
        gm = (w * fv).sum(axis=1) / Ws
        e_ = fv - gm[:, None]
        A = np.matmul(w[:, None, :], nv)[:, 0] + np.matmul(e_[:, None, :], dw)[:, 0]  # W grad g
        grad = A / Ws[:, None]
        g = np.where(smooth, gm, g)
        nrm = np.where(smooth[:, None], grad, nrm)
        H = None
        if hessian:  # zero where the facets' distance is used (flat faces)
            c2 = np.where(ok, 48.0 * (1.0 - s_) ** 2 / rr**4, 0.0)
            dvT = dv.transpose(0, 2, 1)
            dA = (
                np.matmul(nv.transpose(0, 2, 1), dw)
                + np.matmul(dvT * (c2 * e_)[:, None, :], dv)
                + (c1 * e_).sum(axis=1)[:, None, None] * np.eye(3)
                + np.matmul(dw.transpose(0, 2, 1), nv - grad[:, None, :])
            )
            dW = dw.sum(axis=1)
            H = (dA - A[:, :, None] * dW[:, None, :] / Ws[:, None, None]) / Ws[:, None, None]
            H = np.where(smooth[:, None, None], H, 0.0)
        # beyond a free edge / vertex: no contact
        on_free = np.zeros(n, bool)
        e = (reg >= 1) & (reg <= 3)
        on_free[e] = self.free_edge[tri[e], reg[e] - 1]
        vtx = reg >= 4
        on_free[vtx] = self.free_vertex[tri[vtx], reg[vtx] - 4]
        g = np.where(on_free, np.inf, g)
        return g, nrm, H
