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

The nodal average of each element's own nodal γ (``recovery='average'``) and the difference of two
samplings of γh (:func:`sampling_difference`) are kept for comparison: on the cylinder scene
(:func:`deeptissue.verification.cylinder.effectivity_table`) they miss errors the patch recovery bounds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .elements import GMSH_TET10_EDGES, tet10_shape_functions, tet_shape_gradients, tet_subdivision
from .mesh import TetMesh
from .strain import (
    DEFAULT_BIN_EDGES,
    bin_labels,
    gamma_at_points,
    voi_statistics,
)

__all__ = [
    "GAUSS_XI",
    "NODE_XI",
    "VoiErrorEstimate",
    "element_indicator",
    "gamma_at_nodes",
    "patch_recovered_gamma",
    "recovered_gamma",
    "sampling_difference",
    "voi_error_estimate",
]

_CORNERS = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
# reference coordinates of the 10 nodes of a gmsh Tetrahedron10 (corners, then the mid-edge nodes)
NODE_XI = np.vstack([_CORNERS, [(_CORNERS[a] + _CORNERS[b]) / 2 for a, b in GMSH_TET10_EDGES]])


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


def gamma_at_nodes(
    mesh: TetMesh, displacement_mm, *, strain_measure: str = "green_lagrange"
) -> np.ndarray:
    """Each element's own γmax at each of its nodes (n_tets, 10) (or (n_tets, 4) for a linear mesh) [-]."""
    return _gamma_at(mesh, displacement_mm, NODE_XI[: mesh.tets.shape[1]], strain_measure)


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


def recovered_gamma(mesh: TetMesh, gamma_nodes, volume_mm3) -> np.ndarray:
    """Nodal averages of the element-wise nodal γ (n_tets, n_nodes_per_tet), weighted by the element
    volumes (n_tets,): the continuous recovered field's value at every mesh node (n_nodes,) [-]."""
    g = np.asarray(gamma_nodes, float)
    w = np.asarray(volume_mm3, float)
    if g.shape != mesh.tets.shape or w.shape != (mesh.n_tets,):
        raise ValueError(
            f"gamma_nodes {g.shape} / volume_mm3 {w.shape}: expected {mesh.tets.shape} / ({mesh.n_tets},)"
        )
    num = np.bincount(
        mesh.tets.ravel(), weights=(g * w[:, None]).ravel(), minlength=len(mesh.nodes_mm)
    )
    den = np.bincount(
        mesh.tets.ravel(), weights=np.repeat(w, mesh.tets.shape[1]), minlength=len(mesh.nodes_mm)
    )
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def _classes(gamma: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """0 below or at the threshold edges[0], k for the k-th bin (right-closed), as voi_statistics."""
    return np.searchsorted(edges, gamma, side="left")


@dataclass(frozen=True)
class VoiErrorEstimate:
    """Estimated discretisation error of the VOI and its bins, from the recovered field γ* against γh."""

    voi_err_mm3: float  # volume on different sides of the threshold under γ* and γh [mm³]
    bins_err_pp: dict  # bin label -> |p(γ*) − p(γh)| [percentage points of the VOI]
    voi_recovered_mm3: float  # the VOI of γ* [mm³]
    voi_diff_mm3: float  # VOI(γ*) − VOI(γh), signed (|.| <= voi_err_mm3) [mm³]
    bins_moved_pp: (
        dict  # bin label -> volume in that bin under one field only, % of VOI(γh) (>= bins_err_pp)
    )
    indicator_mm3: (
        np.ndarray
    )  # (n_tets,) volume per element whose class differs between γ* and γh [mm³]
    threshold_indicator_mm3: (
        np.ndarray
    )  # (n_tets,) the part of it on different sides of the threshold [mm³]


def voi_error_estimate(
    mesh: TetMesh,
    displacement_mm,
    *,
    threshold: float = 0.3,
    bin_edges: Sequence[float] = DEFAULT_BIN_EDGES,
    strain_measure: str = "green_lagrange",
    levels: int = 2,
    sampled=None,
    recovery: str = "patch",
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
    recovery : {'patch', 'average'}
        How γ* is recovered: ``'patch'`` (:func:`patch_recovered_gamma`, the default: on the cylinder
        scene and on smooth fields its estimate bounds the true error) or ``'average'`` (nodal averages
        of each element's own nodal γ, :func:`recovered_gamma`; blind to smooth-field errors of quadratic
        elements, whose nodal strains err alike on both sides of a node).

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
    vol = v.sum(axis=1)
    pts, _ = tet_subdivision(levels)
    N = (
        tet10_shape_functions(pts)
        if mesh.order == 2
        else np.column_stack([1.0 - pts.sum(axis=1), pts])
    )
    if recovery == "patch":
        nodal = patch_recovered_gamma(mesh, displacement_mm, strain_measure=strain_measure)
    elif recovery == "average":
        nodal = recovered_gamma(
            mesh, gamma_at_nodes(mesh, displacement_mm, strain_measure=strain_measure), vol
        )
    else:
        raise ValueError(f"recovery {recovery!r}: expected 'patch' or 'average'")
    g_star = nodal[mesh.tets] @ N.T  # (n_tets, q)
    if g_star.shape != g_h.shape:
        raise ValueError(f"sampled gamma {g_h.shape}: expected {g_star.shape} (levels={levels})")
    kw = dict(threshold=threshold, bin_edges=edges)
    h = voi_statistics(g_h.ravel(), v.ravel(), **kw)
    r = voi_statistics(g_star.ravel(), v.ravel(), **kw)
    c_h, c_s = _classes(g_h, edges), _classes(g_star, edges)
    labels = bin_labels(edges)
    moved = {
        k: float(100.0 * np.sum(v * ((c_h == i + 1) != (c_s == i + 1))) / h.voi_mm3)
        if h.voi_mm3 > 0
        else 0.0
        for i, k in enumerate(labels)
    }
    return VoiErrorEstimate(
        voi_err_mm3=float(np.sum(v * ((c_h > 0) != (c_s > 0)))),
        bins_err_pp={k: abs(r.bins_percent[k] - h.bins_percent[k]) for k in labels},
        voi_recovered_mm3=r.voi_mm3,
        voi_diff_mm3=r.voi_mm3 - h.voi_mm3,
        bins_moved_pp=moved,
        indicator_mm3=((c_s != c_h) * v).sum(axis=1),
        threshold_indicator_mm3=(((c_s > 0) != (c_h > 0)) * v).sum(axis=1),
    )


def element_indicator(mesh: TetMesh, displacement_mm, **kw) -> np.ndarray:
    """Per-element error indicator (n_tets,) [mm³]: the volume of each element whose class (below the
    threshold, or which bin) differs between the recovered field γ* and γh (:func:`voi_error_estimate`,
    same keywords). Zero in every element that neither field puts across the threshold or a bin edge."""
    return voi_error_estimate(mesh, displacement_mm, **kw).indicator_mm3


def sampling_difference(
    voi_points_mm3: float, bins_points: dict, voi_centroid_mm3: float, bins_centroid: dict
) -> tuple[float, dict]:
    """The two-samplings estimate: ``(|VOI_points − VOI_centroid| [mm³], {bin: |Δp| [pp]})``, γh sampled
    at 64 points per element against the centroids (``voi_sampled_mm3`` and ``voi_centroid_mm3`` of a summary)."""
    return abs(voi_points_mm3 - voi_centroid_mm3), {
        k: abs(bins_points[k] - bins_centroid[k]) for k in bins_points
    }
