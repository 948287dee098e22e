"""The quadratic tetrahedron (gmsh Tetrahedron10): its edge table, shape functions, quadrature and
subdivision on the reference element. The bottom layer of the mesh, strain and FE modules.

Shape functions (gmsh Tetrahedron10). With reference coordinates ``(ξ, η, ζ)`` and barycentric
coordinates ``L0 = 1 − ξ − η − ζ, L1 = ξ, L2 = η, L3 = ζ`` (corner ``i`` at ``L_i = 1``):

- corner ``i`` (local nodes 0–3): ``N_i = L_i (2 L_i − 1)``, ``∇N_i = (4 L_i − 1) ∇L_i``;
- mid-edge node of edge ``(a, b)``: ``N = 4 L_a L_b``, ``∇N = 4 (L_b ∇L_a + L_a ∇L_b)``, with the
  edges in gmsh order ``(0,1), (1,2), (0,2), (0,3), (2,3), (1,3)`` for local nodes 4–9.

At the centroid (all ``L = 1/4``) the corner gradients vanish and each mid-edge gradient is
``∇L_a + ∇L_b``: the centroid deformation gradient depends on the mid-edge nodes only.
"""

from __future__ import annotations

import numpy as np

# local mid-edge nodes 4..9 of a gmsh Tetrahedron10 sit on these corner pairs
GMSH_TET10_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (2, 3), (1, 3))

# gradients of the barycentric coordinates L0..L3 with respect to (ξ, η, ζ): (4, 3)
_DL = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _barycentric(xi: np.ndarray) -> np.ndarray:
    xi = np.atleast_2d(np.asarray(xi, float))
    return np.column_stack([1.0 - xi.sum(axis=1), xi])


def tet10_shape_functions(xi) -> np.ndarray:
    """Values of the 10 P2 shape functions (gmsh order) at reference points ``xi`` (n, 3) -> (n, 10)."""
    L = _barycentric(xi)
    out = np.empty((len(L), 10))
    out[:, :4] = L * (2.0 * L - 1.0)
    for k, (a, b) in enumerate(GMSH_TET10_EDGES):
        out[:, 4 + k] = 4.0 * L[:, a] * L[:, b]
    return out


def tet10_shape_gradients(xi) -> np.ndarray:
    """Gradients of the 10 P2 shape functions (gmsh order) w.r.t. (ξ, η, ζ) at ``xi`` (n, 3) -> (n, 10, 3)."""
    L = _barycentric(xi)
    out = np.empty((len(L), 10, 3))
    out[:, :4] = (4.0 * L - 1.0)[:, :, None] * _DL[None]
    for k, (a, b) in enumerate(GMSH_TET10_EDGES):
        out[:, 4 + k] = 4.0 * (L[:, b, None] * _DL[a] + L[:, a, None] * _DL[b])
    return out


def tet_shape_gradients(xi, order: int) -> np.ndarray:
    """Gradients of the shape functions of a tet of ``order`` (2: 10 nodes, 1: 4 corners; gmsh order) w.r.t.
    (ξ, η, ζ) at ``xi`` (n, 3) -> (n, 10 or 4, 3)."""
    xi = np.atleast_2d(np.asarray(xi, float))
    return tet10_shape_gradients(xi) if order == 2 else np.broadcast_to(_DL, (len(xi), 4, 3))


def tet_quadrature(n: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Collapsed (Duffy) Gauss rule on the reference tetrahedron: points (n³, 3), weights (n³,).

    Maps the unit cube onto the tetrahedron ``ξ, η, ζ ≥ 0, ξ + η + ζ ≤ 1`` (volume 1/6); with ``n``
    Gauss–Legendre points per direction it integrates polynomials of total degree ``2n − 3`` exactly
    (``n = 3``: degree 3, enough for det J of a curved 10-node tetrahedron).
    """
    g, w = np.polynomial.legendre.leggauss(n)
    g, w = 0.5 * (g + 1.0), 0.5 * w
    u, v, t = np.meshgrid(g, g, g, indexing="ij")
    wu, wv, wt = np.meshgrid(w, w, w, indexing="ij")
    xi = u
    eta = v * (1.0 - u)
    zeta = t * (1.0 - u) * (1.0 - v)
    weights = wu * wv * wt * (1.0 - u) ** 2 * (1.0 - v)
    return np.column_stack([xi.ravel(), eta.ravel(), zeta.ravel()]), weights.ravel()


def tet_subdivision(levels: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Centroids of the reference tetrahedron split ``levels`` times into eight (Bey's red refinement:
    four corner tetrahedra and the octahedron cut along one diagonal into four, all of equal volume):
    points (8^levels, 3), weights (8^levels,) all ``(1/6) / 8^levels``.

    A midpoint rule on equal sub-volumes: the share of points inside a region converges to the region's
    volume fraction without the clustering of a Gauss rule (whose points sample an indicator unevenly).
    """
    if levels < 0:
        raise ValueError(f"levels {levels}: expected >= 0")
    tets = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
    for _ in range(levels):
        v0, v1, v2, v3 = (tets[:, i] for i in range(4))
        m01, m02, m03 = (v0 + v1) / 2, (v0 + v2) / 2, (v0 + v3) / 2
        m12, m13, m23 = (v1 + v2) / 2, (v1 + v3) / 2, (v2 + v3) / 2
        children = [
            (v0, m01, m02, m03),
            (m01, v1, m12, m13),
            (m02, m12, v2, m23),
            (m03, m13, m23, v3),
            (m01, m02, m03, m13),
            (m01, m02, m12, m13),
            (m02, m03, m13, m23),
            (m02, m12, m13, m23),
        ]
        tets = np.concatenate([np.stack(c, axis=1) for c in children])
    n = len(tets)
    return tets.mean(axis=1), np.full(n, 1.0 / 6.0 / n)
