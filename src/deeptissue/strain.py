"""Strain post-processing of a quadratic-tetrahedral solution: γmax per element, VOI and its bins.

Everything here works on a :class:`deeptissue.mesh.TetMesh` (10-node tetrahedra in gmsh order) and
a nodal displacement ``(n_nodes, 3)`` in mm; no solver is needed. A first-order TetMesh (4-node
tetrahedra, shape functions ``N_i = L_i``) is handled too: its F is constant in each element and
its volume is that of the corner tetrahedron.

Shape functions and quadrature: :mod:`deeptissue.elements`.

Strain measures (per element, at the centroid of the reference element):

- Green–Lagrange ``E = (FᵀF − I)/2``, principal values ``E1 ≥ E2 ≥ E3``, ``γmax = (E1 − E3)/2``
  (the paper's measure);
- logarithmic (Hencky, what Abaqus reports as LE): principal log stretches ``ln λ1 ≥ ln λ2 ≥ ln λ3``
  with ``λ² `` the eigenvalues of ``C = FᵀF``, ``γmax = (ln λ1 − ln λ3)/2``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .elements import tet10_shape_gradients, tet_quadrature, tet_shape_gradients, tet_subdivision
from .mesh import TetMesh

__all__ = [
    "DEFAULT_BIN_EDGES",
    "STRAIN_MEASURES",
    "ElementStrain",
    "StrainError",
    "VoiStatistics",
    "bin_labels",
    "deformation_gradient_at_centroids",
    "element_strain",
    "element_volumes_mm3",
    "gamma_at_points",
    "green_lagrange",
    "max_shear",
    "principal_log_stretches",
    "principal_values",
    "voi_statistics",
]

log = logging.getLogger(__name__)

STRAIN_MEASURES = ("green_lagrange", "log")
DEFAULT_BIN_EDGES = (
    0.3,
    0.4,
    0.5,
    0.6,
    0.7,
    0.8,
    0.9,
    1.0,
)  # γmax bins from the threshold 0.3 up, last '>1.0'


class StrainError(ValueError):
    """A displacement that has no strain (inverted element, wrong shape)."""


def _check_mesh_and_u(mesh: TetMesh, displacement_mm) -> np.ndarray:
    u = np.asarray(displacement_mm, float)
    if u.shape != mesh.nodes_mm.shape:
        raise StrainError(
            f"displacement: expected shape {mesh.nodes_mm.shape} (one 3-vector per node), got {u.shape}"
        )
    if not np.all(np.isfinite(u)):
        raise StrainError("displacement: non-finite values")
    return u


def element_volumes_mm3(mesh: TetMesh, *, order: int = 3) -> np.ndarray:
    """Reference volumes of the (possibly curved) 10-node tetrahedra (n_tets,) [mm³].

    ``∫ det J dξ`` over the reference element with :func:`tet_quadrature` (exact for the cubic det J
    of a quadratic tetrahedron with the default ``order=3``). Linear (4-node) tetrahedra: the corner
    tetrahedron's volume.
    """
    if mesh.order == 1:
        return mesh.volumes_mm3()
    pts, w = tet_quadrature(order)
    dN = tet10_shape_gradients(pts)  # (q, 10, 3)
    X = mesh.nodes_mm[mesh.tets]  # (m, 10, 3)
    J = np.tensordot(X, dN, axes=([1], [1])).transpose(0, 2, 1, 3)  # (m, q, 3, 3): dX_i/dξ_j
    return np.linalg.det(J) @ w


def deformation_gradient_at_centroids(mesh: TetMesh, displacement_mm) -> np.ndarray:
    """Deformation gradient ``F = I + ∂u/∂X`` at the reference-element centroids (n_tets, 3, 3)."""
    u = _check_mesh_and_u(mesh, displacement_mm)
    # (10, 3); linear tets: the barycentric gradients (4, 3), F constant in the element
    dN = tet_shape_gradients(np.full((1, 3), 0.25), mesh.order)[0]
    X = mesh.nodes_mm[mesh.tets]
    J = np.swapaxes(X, 1, 2) @ dN  # (m, 3, 3): dX_i/dξ_j
    det = np.linalg.det(J)
    if np.any(det <= 0):
        bad = np.flatnonzero(det <= 0)
        raise StrainError(
            f"mesh: {len(bad)} element(s) with non-positive Jacobian in the reference configuration, first {bad[0]}"
        )
    dN_dX = dN[None] @ np.linalg.inv(J)  # (m, 10, 3): dN_a/dX_i
    grad_u = np.swapaxes(u[mesh.tets], 1, 2) @ dN_dX  # (m, 3, 3): du_k/dX_i
    return np.eye(3) + grad_u


def green_lagrange(F) -> np.ndarray:
    """Green–Lagrange strain ``E = (FᵀF − I)/2`` (..., 3, 3) [-]."""
    F = np.asarray(F, float)
    return 0.5 * (np.einsum("...ki,...kj->...ij", F, F) - np.eye(3))


def principal_values(S) -> np.ndarray:
    """Eigenvalues of symmetric tensors (..., 3, 3), sorted descending (..., 3)."""
    S = np.asarray(S, float)
    return np.linalg.eigvalsh(0.5 * (S + np.swapaxes(S, -1, -2)))[..., ::-1]


def max_shear(principal) -> np.ndarray:
    """``γmax = (p1 − p3)/2`` from descending principal values (..., 3) -> (...)."""
    p = np.asarray(principal, float)
    return 0.5 * (p[..., 0] - p[..., 2])


def principal_log_stretches(F) -> np.ndarray:
    """``ln λ1 ≥ ln λ2 ≥ ln λ3`` of ``F`` (..., 3, 3) -> (..., 3); raises for det F <= 0."""
    F = np.asarray(F, float)
    det = np.linalg.det(F)
    if np.any(det <= 0):
        bad = np.flatnonzero(np.ravel(det) <= 0)
        raise StrainError(
            f"deformation gradient: {len(bad)} inverted element(s) (det F <= 0), first {bad[0]}"
        )
    C = np.einsum("...ki,...kj->...ij", F, F)
    return 0.5 * np.log(principal_values(C))


@dataclass(frozen=True)
class ElementStrain:
    """Strain at the element centroids of one solution; arrays over elements (n_tets, ...)."""

    F: np.ndarray  # (n, 3, 3) deformation gradient [-]
    principal_gl: np.ndarray  # (n, 3) Green–Lagrange E1 >= E2 >= E3 [-]
    principal_log: np.ndarray  # (n, 3) ln λ1 >= ln λ2 >= ln λ3 [-]
    volume_mm3: np.ndarray  # (n,) reference element volume [mm^3]

    @property
    def gamma_gl(self) -> np.ndarray:
        """Green–Lagrange γmax = (E1 − E3)/2 (n,) [-]."""
        return max_shear(self.principal_gl)

    @property
    def gamma_log(self) -> np.ndarray:
        """Logarithmic γmax = (ln λ1 − ln λ3)/2 (n,) [-]."""
        return max_shear(self.principal_log)

    def gamma(self, strain_measure: str = "green_lagrange") -> np.ndarray:
        """γmax (n,) [-] of ``strain_measure`` (one of :data:`STRAIN_MEASURES`)."""
        if strain_measure == "green_lagrange":
            return self.gamma_gl
        if strain_measure == "log":
            return self.gamma_log
        raise ValueError(f"strain_measure {strain_measure!r}: expected one of {STRAIN_MEASURES}")


def element_strain(mesh: TetMesh, displacement_mm) -> ElementStrain:
    """Deformation gradient, principal Green–Lagrange and log strains at centroids, reference volumes.

    Parameters
    ----------
    mesh : TetMesh
        Reference mesh, 10-node (gmsh order) or 4-node tetrahedra, nodes in mm.
    displacement_mm : (n_nodes, 3) array_like
        Nodal displacement [mm].

    Returns
    -------
    ElementStrain
        Arrays over the n_tets elements: ``F`` (n, 3, 3), ``principal_gl`` and ``principal_log``
        (n, 3) descending [-], ``volume_mm3`` (n,) reference volume [mm³].

    Raises
    ------
    StrainError
        For a displacement of the wrong shape or an element inverted (det F <= 0) or folded at its centroid.
    """
    F = deformation_gradient_at_centroids(mesh, displacement_mm)
    return ElementStrain(
        F=F,
        principal_gl=principal_values(green_lagrange(F)),
        principal_log=principal_log_stretches(F),
        volume_mm3=element_volumes_mm3(mesh),
    )


def gamma_at_points(
    mesh: TetMesh,
    displacement_mm,
    *,
    levels: int = 2,
    strain_measures: Sequence[str] = ("green_lagrange",),
    chunk: int = 8000,
) -> tuple[dict, np.ndarray, int]:
    """γmax sampled at ``q`` points inside every element, with the volume each point stands for.

    The points are the centroids of :func:`tet_subdivision` (``levels=2``: 64 equal sub-tetrahedra per
    element); each point carries its share ``w·det J`` of the element's reference volume (the weights
    of a straight element sum to its volume exactly, of a curved one to second order). Binning these
    points instead of the centroids estimates the volume of ``{γmax > t}`` inside each element (γmax
    varies within a quadratic element) rather than giving the whole element to one bin, so the
    estimate does not jump when a centroid crosses a bin edge. A linear mesh has constant F per
    element: every point has the centroid's γ.

    An element is sampled at its centroid only (every point gets the centroid's γ and an equal share of
    the element's volume) where a point has no strain: the curved map folds there (det J <= 0, a sliver
    at a curved surface that is fine at the solver's quadrature points) or the displacement inverts it
    (det F <= 0 between the quadrature points of a coarse element). Their number is returned; an element
    whose centroid itself is folded or inverted raises :class:`StrainError` (as :func:`element_strain`).

    Parameters
    ----------
    mesh : TetMesh
        Reference mesh, 10- or 4-node tetrahedra, nodes in mm.
    displacement_mm : (n_nodes, 3) array_like
        Nodal displacement [mm].
    levels : int
        Subdivision levels: q = 8**levels points per element.
    strain_measures : sequence of str
        Measures to return (of :data:`STRAIN_MEASURES`).
    chunk : int
        Elements per batch (bounds the memory of the (chunk, q, 3, 3) temporaries).

    Returns
    -------
    gamma : dict
        ``{measure: (n_tets, q) ndarray}`` γmax [-].
    volume_mm3 : (n_tets, q) ndarray
        Reference volume of each point's share [mm³]; a row sums to the element's volume.
    n_centroid : int
        Number of elements sampled at their centroid only.
    """
    bad_measures = [m for m in strain_measures if m not in STRAIN_MEASURES]
    if bad_measures:
        raise ValueError(f"strain_measure {bad_measures[0]!r}: expected one of {STRAIN_MEASURES}")
    u = _check_mesh_and_u(mesh, displacement_mm)
    pts, w = tet_subdivision(levels)
    dN = tet_shape_gradients(pts, mesh.order)
    gam = {m: np.empty((mesh.n_tets, len(pts))) for m in strain_measures}
    vol = np.empty((mesh.n_tets, len(pts)))
    n_centroid = 0
    for lo in range(0, mesh.n_tets, chunk):
        tets = mesh.tets[lo : lo + chunk]
        X, U = np.swapaxes(mesh.nodes_mm[tets], 1, 2)[:, None], np.swapaxes(u[tets], 1, 2)[:, None]
        J = X @ dN[None]  # (m, q, 3, 3): dX_i/dξ_j
        det = np.linalg.det(J)
        F = np.eye(3) + (U @ dN[None]) @ np.linalg.inv(
            np.where((det > 0)[..., None, None], J, np.eye(3))
        )
        only_c = np.any(det <= 0, axis=1) | np.any(np.linalg.det(F) <= 0, axis=1)
        if only_c.any():  # the centroid's F at every point, equal shares of the element's volume
            n_centroid += int(only_c.sum())
            sub = TetMesh(nodes_mm=mesh.nodes_mm, tets=tets[only_c])
            Fc = deformation_gradient_at_centroids(
                sub, u
            )  # raises for a centroid folded in the reference
            if np.any(np.linalg.det(Fc) <= 0):
                bad = lo + np.flatnonzero(only_c)[np.linalg.det(Fc) <= 0]
                raise StrainError(
                    f"{len(bad)} element(s) inverted at the centroid, first {bad[0]}"
                )
            F[only_c] = Fc[:, None]
            vol_c = element_volumes_mm3(sub)
            det[only_c] = (vol_c / w.sum())[:, None]  # det * w then sums to the element's volume
        c = np.linalg.eigvalsh(np.swapaxes(F, -1, -2) @ F)  # λ² ascending: E_i = (λ² − 1)/2
        for m in strain_measures:
            gam[m][lo : lo + chunk] = 0.25 * (
                (c[..., 2] - c[..., 0]) if m == "green_lagrange" else np.log(c[..., 2] / c[..., 0])
            )
        vol[lo : lo + chunk] = det * w
    if n_centroid:
        log.info(
            "γ sampling: %d of %d element(s) folded or inverted at a sample point: sampled at their centroid",
            n_centroid,
            mesh.n_tets,
        )
    return gam, vol, n_centroid


def _fmt(x: float) -> str:
    s = f"{float(x):g}"
    return s if ("." in s or "e" in s or "inf" in s) else s + ".0"


def bin_labels(bin_edges: Sequence[float]) -> list[str]:
    """Labels of the bins of :func:`voi_statistics`: ``(0.3, 0.4, …, 1.0)`` -> ``['0.3-0.4', …, '0.9-1.0', '>1.0']``."""
    e = list(bin_edges)
    return [f"{_fmt(a)}-{_fmt(b)}" for a, b in zip(e[:-1], e[1:])] + [f">{_fmt(e[-1])}"]


@dataclass(frozen=True)
class VoiStatistics:
    """Volume of interest (γmax > threshold) and how it splits over strain bins."""

    threshold: float
    voi_mm3: float  # reference volume with γmax > threshold
    total_mm3: float  # reference volume of the whole model
    bins_percent: dict  # bin label -> % of the VOI volume (all 0 when the VOI is empty)
    below_threshold_percent: float  # % of the whole model volume with γmax <= threshold
    peak_gamma: float  # max γmax over elements (reported, not used to compare)
    strain_energy_mJ: float | None  # Σ W·V over VOI elements, None without an energy density


def voi_statistics(
    gamma,
    volume_mm3,
    *,
    threshold: float = 0.3,
    bin_edges: Sequence[float] = DEFAULT_BIN_EDGES,
    energy_density_mpa=None,
) -> VoiStatistics:
    """VOI, bin percentages, below-threshold percentage, peak γ and VOI strain energy.

    The VOI is the volume with ``γ > threshold``. Bins are right-closed: ``'0.3-0.4'`` holds
    ``0.3 < γ <= 0.4``; the last bin ``'>1.0'`` holds ``γ > 1.0``.

    Parameters
    ----------
    gamma : (n,) array_like
        γmax [-] per element (or per sample point, :func:`gamma_at_points`).
    volume_mm3 : (n,) array_like
        Reference volume of each element or point [mm³], > 0.
    threshold : float
        VOI threshold on γmax [-].
    bin_edges : sequence of float
        Strictly increasing; ``bin_edges[0]`` must equal ``threshold`` so that the bins partition the
        VOI (percentages sum to 100).
    energy_density_mpa : (n,) array_like or None
        Strain-energy density per reference volume [MPa = mJ/mm³].

    Returns
    -------
    VoiStatistics
        ``voi_mm3``, ``total_mm3``, ``bins_percent`` (label -> % of the VOI, all 0 for an empty VOI),
        ``below_threshold_percent`` (% of the total), ``peak_gamma``, ``strain_energy_mJ`` (None
        without an energy density).

    Raises
    ------
    ValueError
        Mismatched or empty inputs, non-finite values, non-positive volumes, bad bin edges.
    """
    g = np.asarray(gamma, float).ravel()
    v = np.asarray(volume_mm3, float).ravel()
    edges = np.asarray(bin_edges, float).ravel()
    if g.shape != v.shape:
        raise ValueError(f"gamma has {g.size} values but volume_mm3 has {v.size}")
    if g.size == 0:
        raise ValueError("voi_statistics: no elements")
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(v))):
        raise ValueError("voi_statistics: non-finite gamma or volume")
    if np.any(v <= 0):
        raise ValueError(
            f"voi_statistics: {np.count_nonzero(v <= 0)} element(s) with non-positive volume"
        )
    if edges.size < 1 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"bin_edges {list(edges)}: expected strictly increasing numbers")
    if not np.isclose(edges[0], threshold, rtol=0, atol=1e-12):
        raise ValueError(
            f"bin_edges start at {edges[0]} but threshold is {threshold}: the first edge must be the threshold"
        )
    in_voi = g > threshold
    voi = float(v[in_voi].sum())
    total = float(v.sum())
    # bin index: 0 for (e0, e1], ..., len(edges)-1 for > e_last
    idx = np.searchsorted(edges, g[in_voi], side="left") - 1
    per_bin = np.bincount(idx, weights=v[in_voi], minlength=len(edges))
    labels = bin_labels(edges)
    pct = 100.0 * per_bin / voi if voi > 0 else np.zeros(len(edges))
    energy = None
    if energy_density_mpa is not None:
        w = np.asarray(energy_density_mpa, float).ravel()
        if w.shape != g.shape:
            raise ValueError(f"energy_density_mpa has {w.size} values but gamma has {g.size}")
        energy = float(np.sum(w[in_voi] * v[in_voi]))
    return VoiStatistics(
        threshold=float(threshold),
        voi_mm3=voi,
        total_mm3=total,
        bins_percent={k: float(p) for k, p in zip(labels, pct)},
        below_threshold_percent=float(100.0 * v[~in_voi].sum() / total),
        peak_gamma=float(g.max()),
        strain_energy_mJ=energy,
    )
