"""Discretisation-error estimate of the VOI and its bins (recovered strain, Zienkiewicz–Zhu type).

γmax of a quadratic-tetrahedral solution jumps between elements; where the VOI's surface
(γ = threshold) and the bin edges cross coarse elements, which side of an edge a sub-volume falls
on is decided by that discontinuous element field γh. The estimate recovers a continuous field γ*
by superconvergent patch recovery (:func:`patch_recovered_gamma`: at every node, the linear
least-squares fit of γmax at the Gauss points of the elements sharing it, interpolated with the
element's shape functions) and compares γ* with γh at the same sample points as the VOI
(:func:`deeptissue.strain.gamma_at_points`):

- ``voi_err_mm3``: the volume on different sides of the threshold under γ* and γh [mm³] (at least
  ``|VOI(γ*) − VOI(γh)|``: where errors of both signs cancel in the VOI, they still count);
- ``bins_err_pp[k] = |p_k(γ*) − p_k(γh)|`` [percentage points of the VOI];
- the per-element indicator (:func:`element_indicator`): the volume of each element whose class
  (below the threshold, or which bin) differs between γ* and γh [mm³]; non-zero only in elements
  that straddle the threshold or a bin edge, it is what a refinement loop refines by; its part on
  different sides of the threshold (``threshold_indicator_mm3``) sums to ``voi_err_mm3``, the rest
  is the volume moved between bins.

On the adaptive loop's passes after the first, the VOI and bins are judged by their change from the
previous pass instead (:func:`deeptissue.adapt.extrapolated_error`); this estimate judges the first pass
and a fixed mesh, and its indicator says where to refine.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .elements import tet10_shape_functions, tet_shape_gradients, tet_subdivision
from .mesh import TetMesh
from .strain import (
    DEFAULT_BIN_EDGES,
    bin_labels,
    gamma_at_points,
    voi_statistics,
)

__all__ = [
    "GAUSS_XI",
    "VoiErrorEstimate",
    "element_indicator",
    "patch_recovered_gamma",
    "voi_error_estimate",
]


def _gamma(F: np.ndarray, strain_measure: str) -> np.ndarray:
    c = np.linalg.eigvalsh(np.swapaxes(F, -1, -2) @ F)  # λ² ascending
    if strain_measure == "green_lagrange":
        return 0.25 * (c[..., 2] - c[..., 0])
    if strain_measure == "log":
        return 0.25 * np.log(c[..., 2] / np.maximum(c[..., 0], 1e-300))
    raise ValueError(f"strain_measure {strain_measure!r}: expected 'green_lagrange' or 'log'")


def _gamma_at(
    mesh: TetMesh, displacement_mm, xi, strain_measure: str, chunk: int = 8000
) -> np.ndarray:
    """Each element's own γmax at reference points ``xi`` (q, 3) -> (n_tets, q) [-]; a point where the
    curved element's map folds (det J <= 0) gets the element's centroid γ."""
    u = np.asarray(displacement_mm, float)
    if u.shape != mesh.nodes_mm.shape:
        raise ValueError(f"displacement: expected shape {mesh.nodes_mm.shape}, got {u.shape}")
    q = len(xi)
    pts = np.vstack([xi, [[0.25, 0.25, 0.25]]])
    dN = tet_shape_gradients(pts, mesh.order)
    out = np.empty((mesh.n_tets, q))
    for lo in range(0, mesh.n_tets, chunk):
        tets = mesh.tets[lo : lo + chunk]
        X, U = np.swapaxes(mesh.nodes_mm[tets], 1, 2)[:, None], np.swapaxes(u[tets], 1, 2)[:, None]
        J = X @ dN[None]
        det = np.linalg.det(J)
        F = np.eye(3) + (U @ dN[None]) @ np.linalg.inv(
            np.where((det > 0)[..., None, None], J, np.eye(3))
        )
        g = _gamma(F, strain_measure)
        out[lo : lo + chunk] = np.where(det[:, :q] > 0, g[:, :q], g[:, q:])
    return out


# the 4-point degree-2 rule of the tetrahedron (barycentric a, b, b, b and permutations): the sampling
# points of the patch recovery, where the strain of a quadratic element is most accurate
_GA, _GB = 0.5854101966249685, 0.1381966011250105
GAUSS_XI = np.array([[_GB, _GB, _GB], [_GA, _GB, _GB], [_GB, _GA, _GB], [_GB, _GB, _GA]])


def patch_recovered_gamma(
    mesh: TetMesh, displacement_mm, *, strain_measure: str = "green_lagrange"
) -> np.ndarray:
    """Superconvergent patch recovery (Zienkiewicz–Zhu): at every mesh node, the value at the node of
    the linear least-squares fit of γmax at the 4 Gauss points of every element sharing the node (n_nodes,) [-]."""
    g = _gamma_at(mesh, displacement_mm, GAUSS_XI, strain_measure)  # (m, 4)
    N = (
        tet10_shape_functions(GAUSS_XI)
        if mesh.order == 2
        else np.column_stack([1.0 - GAUSS_XI.sum(axis=1), GAUSS_XI])
    )
    X = np.einsum("qa,mai->mqi", N, mesh.nodes_mm[mesh.tets])  # (m, 4, 3) Gauss point positions
    h = (
        np.cbrt(np.abs(np.linalg.det(X[:, 1:] - X[:, :1])))[:, None, None] + 1e-300
    )  # element length scale
    n_nodes, k = len(mesh.nodes_mm), mesh.tets.shape[1]
    A = np.zeros((n_nodes, 4, 4))
    b = np.zeros((n_nodes, 4))
    for a in range(
        k
    ):  # each node of each element: its 4 Gauss points, relative to the node, in element lengths
        node = mesh.tets[:, a]
        P = np.concatenate(
            [np.ones(X.shape[:2] + (1,)), (X - mesh.nodes_mm[node][:, None]) / h], axis=2
        )  # (m, 4, 4)
        np.add.at(A, node, np.einsum("mqi,mqj->mij", P, P))
        np.add.at(b, node, np.einsum("mqi,mq->mi", P, g))
    A += 1e-9 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(4)
    return np.linalg.solve(A, b[..., None])[:, 0, 0]


def _classes(gamma: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """0 below or at the threshold edges[0], k for the k-th bin (right-closed), as voi_statistics."""
    return np.searchsorted(edges, gamma, side="left")


@dataclass(frozen=True)
class VoiErrorEstimate:
    """Estimated discretisation error of the VOI and its bins, from the recovered field γ* against γh.

    ``voi_err_mm3``: the volume on different sides of the threshold under γ* and γh [mm³];
    ``bins_err_pp``: bin label -> |p(γ*) − p(γh)| [percentage points of the VOI];
    ``indicator_mm3`` (n_tets,): the volume per element whose class differs between γ* and γh [mm³];
    ``threshold_indicator_mm3`` (n_tets,): its part on different sides of the threshold [mm³].
    """

    voi_err_mm3: float
    bins_err_pp: dict
    indicator_mm3: np.ndarray
    threshold_indicator_mm3: np.ndarray


def voi_error_estimate(
    mesh: TetMesh,
    displacement_mm,
    *,
    threshold: float = 0.3,
    bin_edges: Sequence[float] = DEFAULT_BIN_EDGES,
    strain_measure: str = "green_lagrange",
    levels: int = 2,
    sampled=None,
) -> VoiErrorEstimate:
    """The recovered-strain estimate of the VOI and bin errors of one solution.

    Parameters
    ----------
    mesh : TetMesh
        Reference mesh [mm].
    displacement_mm : (n_nodes, 3) array_like
        Nodal displacement [mm].
    threshold, bin_edges : float, sequence of float
        VOI threshold and bin edges (as :func:`deeptissue.strain.voi_statistics`).
    strain_measure : {'green_lagrange', 'log'}
        The γmax of the VOI.
    levels : int
        Sub-tetrahedron levels of the sample points (:func:`deeptissue.strain.tet_subdivision`;
        0: the centroid only).
    sampled : (gamma (n_tets, q), volume (n_tets, q)) or None
        γh and the point volumes at those points, if already computed (:func:`gamma_at_points`).

    Returns
    -------
    VoiErrorEstimate
    """
    edges = np.asarray(bin_edges, float)
    if sampled is None:
        g, v, _ = gamma_at_points(
            mesh, displacement_mm, levels=levels, strain_measures=(strain_measure,)
        )
        sampled = (g[strain_measure], v)
    g_h, v = (np.asarray(a, float) for a in sampled)
    pts, _ = tet_subdivision(levels)
    N = (
        tet10_shape_functions(pts)
        if mesh.order == 2
        else np.column_stack([1.0 - pts.sum(axis=1), pts])
    )
    nodal = patch_recovered_gamma(mesh, displacement_mm, strain_measure=strain_measure)
    g_star = nodal[mesh.tets] @ N.T  # (n_tets, q)
    if g_star.shape != g_h.shape:
        raise ValueError(f"sampled gamma {g_h.shape}: expected {g_star.shape} (levels={levels})")
    kw = dict(threshold=threshold, bin_edges=edges)
    h = voi_statistics(g_h.ravel(), v.ravel(), **kw)
    r = voi_statistics(g_star.ravel(), v.ravel(), **kw)
    c_h, c_s = _classes(g_h, edges), _classes(g_star, edges)
    return VoiErrorEstimate(
        voi_err_mm3=float(np.sum(v * ((c_h > 0) != (c_s > 0)))),
        bins_err_pp={k: abs(r.bins_percent[k] - h.bins_percent[k]) for k in bin_labels(edges)},
        indicator_mm3=((c_s != c_h) * v).sum(axis=1),
        threshold_indicator_mm3=(((c_s > 0) != (c_h > 0)) * v).sum(axis=1),
    )


def element_indicator(mesh: TetMesh, displacement_mm, **kw) -> np.ndarray:
    """Per-element error indicator (n_tets,) [mm³]: the volume of each element whose class (below the
    threshold, or which bin) differs between the recovered field γ* and γh (:func:`voi_error_estimate`,
    same keywords). Zero in every element that neither field puts across the threshold or a bin edge."""
    return voi_error_estimate(mesh, displacement_mm, **kw).indicator_mm3
