"""Per-variant results of the study: ``summary.json``, ``result.vtu`` and the skin agreement with MRI.

One FE run (animal × variant) leaves ``results/{animal}/{variant}/summary.json`` (a :class:`Summary`)
and ``result.vtu``. A run that did not converge or failed still leaves a summary
(:func:`failed_summary`: ``converged`` false and the ``reason``) so the aggregate sees every
variant and can apply the exclusion policy; nothing is silently lost.

Skin agreement: the distance from each skin contour point segmented in the *during* scan to the
deformed FE skin surface (10-node tetrahedra's 6-node skin facets, each split into four flat
triangles through its corner and mid-edge nodes; a linear mesh's 3-node facets as they are), exact point-to-triangle distance with KD-tree
candidate search; reported as mean and 95th percentile [mm].
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from .errorest import voi_error_estimate
from .geometry import point_triangle_distance, surface_distance_mm  # noqa: F401 (part of this module's API)
from .io import read_json, write_json
from .mesh import TetMesh
from .strain import (
    DEFAULT_BIN_EDGES,
    STRAIN_MEASURES,
    ElementStrain,
    element_strain,
    gamma_at_points,
    voi_statistics,
)

__all__ = [
    "GAMMA_SAMPLINGS",
    "SAMPLING_LEVELS",
    "Summary",
    "VoiSpec",
    "deformed_surface",
    "failed_summary",
    "point_triangle_distance",
    "qc_warnings_of",
    "read_result_vtu",
    "read_summary",
    "skin_agreement_mm",
    "summarize_solution",
    "surface_distance_mm",
    "tri6_to_tri3",
    "write_result_vtu",
    "write_summary",
]

# How γmax is sampled for the VOI and its bins (config study.gamma_sampling):
# 'points': at the centroids of 64 equal sub-tetrahedra of every element (strain.tet_subdivision(2)),
#   each with its share of the element's volume; 64 points suffice: 512 per element change the VOI by
#   about 0.25 % and the bins by about 0.3 pp on a 2.0 / 1.0 mm bar solution;
# 'centroid': one γmax per element at its centroid, the whole element counted in one bin (the paper's).
GAMMA_SAMPLINGS = ("points", "centroid")
SAMPLING_LEVELS = 2  # 'points' sampling: 8**2 = 64 sub-tetrahedra per element


@dataclass(frozen=True)
class Summary:
    """The numbers of one animal × variant run (``summary.json``). ``None`` where not available."""

    animal: str
    variant: str
    converged: bool
    reason: str | None = None  # why not converged / failed (None when converged)
    strain_measure: str = "green_lagrange"  # which γmax the VOI numbers use
    gamma_sampling: str = (
        "points"  # where γmax is sampled for voi_mm3 / bins_percent (GAMMA_SAMPLINGS)
    )
    threshold: float = 0.3  # γmax threshold of the VOI [-]
    voi_mm3: float | None = None  # reference volume with γmax > threshold (gamma_sampling) [mm^3]
    bins_percent: dict | None = None  # bin label -> % of the VOI volume
    voi_err_mm3: float | None = (
        None  # estimated discretisation error of voi_mm3 (deeptissue.errorest) [mm^3]
    )
    bins_err_pp: dict | None = (
        None  # bin label -> estimated error of that bin's % [percentage points]
    )
    below_threshold_percent: float | None = (
        None  # % of the whole model volume with γmax <= threshold
    )
    peak_gamma: float | None = None  # max centroid γmax over elements [-]
    strain_energy_mJ: float | None = None  # strain energy in the VOI [mJ]
    indenter_force_N: float | None = (
        None  # indenter reaction force along its axis at full depth [N]
    )
    n_elements: int | None = None
    n_dofs: int | None = None
    increments: int | None = None  # load increments used
    newton_iterations: int | None = None  # Newton iterations summed over increments
    wall_s: float | None = None  # wall-clock time of the solve [s]
    skin_mean_mm: float | None = (
        None  # mean distance during-scan skin contours -> deformed FE skin [mm]
    )
    skin_p95_mm: float | None = None  # 95th percentile of that distance [mm]
    voi_sampled_mm3: float | None = (
        None  # the VOI with γmax sampled at 64 points per element [mm^3]
    )
    bins_sampled_percent: dict | None = None  # bin label -> % of that VOI
    voi_centroid_mm3: float | None = None  # the VOI with one centroid γmax per element [mm^3]
    bins_centroid_percent: dict | None = None  # bin label -> % of that VOI
    voi_by_measure_mm3: dict | None = (
        None  # {"green_lagrange": .., "log": ..} VOI with each measure [mm^3]
    )
    peak_gamma_by_measure: dict | None = None  # {"green_lagrange": .., "log": ..}
    qc_warnings: str | None = (
        None  # the animal's QC warnings from pose.json ("check value > limit; ..."), None: none
    )
    extra: dict = field(default_factory=dict)  # further solver diagnostics, kept and tabulated

    def __post_init__(self):
        if self.gamma_sampling not in GAMMA_SAMPLINGS:
            raise ValueError(
                f"summary {self.animal}/{self.variant}: gamma_sampling {self.gamma_sampling!r} not in {GAMMA_SAMPLINGS}"
            )
        if self.strain_measure not in STRAIN_MEASURES:
            raise ValueError(
                f"summary {self.animal}/{self.variant}: strain_measure {self.strain_measure!r} not in {STRAIN_MEASURES}"
            )
        if not isinstance(self.converged, bool):
            raise ValueError(
                f"summary {self.animal}/{self.variant}: converged must be true or false, got {self.converged!r}"
            )
        if not self.converged and not self.reason:
            raise ValueError(
                f"summary {self.animal}/{self.variant}: a run that did not converge needs a reason"
            )

    def to_dict(self) -> dict:
        """The fields as a flat dict (the ``extra`` entries merged in at the top level), as in summary.json."""
        d = asdict(self)
        extra = d.pop("extra")
        d.update(extra)
        return d

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "summary") -> Summary:
        """Inverse of :meth:`to_dict`: unknown keys go to ``extra``; ValueError naming ``source`` if invalid."""
        names = {f.name for f in fields(cls)} - {"extra"}
        missing = [k for k in ("animal", "variant", "converged") if k not in d]
        if missing:
            raise ValueError(f"{source}: missing key(s) {missing}")
        known = {k: v for k, v in d.items() if k in names}
        extra = {k: v for k, v in d.items() if k not in names}
        try:
            return cls(**known, extra=extra)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{source}: {exc}") from exc


def qc_warnings_of(pose_path: str | Path) -> str | None:
    """The QC warnings of ``pose.json`` (key ``qc_warnings``, see :mod:`deeptissue.pose.checks`) joined by "; ",
    or None when it has none."""
    warnings = read_json(pose_path).get("qc_warnings") or []
    return "; ".join(warnings) or None


def write_summary(path: str | Path, summary: Summary) -> None:
    """Write ``summary`` as JSON (:meth:`Summary.to_dict`), atomically.

    Parameters
    ----------
    path : str or Path
        Usually ``results/{animal}/{variant}/summary.json``.
    summary : Summary
        Written with its ``extra`` entries at the top level; NaN written as ``NaN``.
    """
    write_json(path, summary.to_dict())


def read_summary(path: str | Path) -> Summary:
    """Read a summary written by :func:`write_summary`.

    Parameters
    ----------
    path : str or Path
        ``results/{animal}/{variant}/summary.json``; ``animal`` and ``variant`` default to the names
        of the two parent directories when the file lacks them.

    Returns
    -------
    Summary
        Keys that are not fields of :class:`Summary` are in ``extra``.

    Raises
    ------
    ValueError
        Invalid JSON, a missing ``converged``, or an invalid field (names the file).
    """
    path = Path(path)
    d = read_json(path)
    d.setdefault("variant", path.parent.name)
    d.setdefault("animal", path.parent.parent.name)
    return Summary.from_dict(d, source=str(path))


def failed_summary(
    *,
    animal: str,
    variant: str,
    reason: str,
    strain_measure: str = "green_lagrange",
    threshold: float = 0.3,
    gamma_sampling: str = "points",
    **known,
) -> Summary:
    """Summary of a run that did not converge or failed: ``converged`` false, the reason, and any
    numbers that are still known (``n_elements``, ``n_dofs``, ``increments``, ``wall_s``, ...).

    Parameters
    ----------
    animal, variant : str
        The run.
    reason : str
        Why it did not converge or failed (must not be empty).
    strain_measure, threshold, gamma_sampling
        As configured for the study (recorded in the summary).
    **known
        Fields of :class:`Summary` that are known; other keys go to ``extra``.

    Returns
    -------
    Summary
        With ``converged`` False.
    """
    if not reason:
        raise ValueError(f"failed_summary {animal}/{variant}: give the reason")
    names = {f.name for f in fields(Summary)}
    extra = {k: v for k, v in known.items() if k not in names}
    known = {k: v for k, v in known.items() if k in names}
    known["extra"] = {**known.get("extra", {}), **extra}
    return Summary(
        animal=animal,
        variant=variant,
        converged=False,
        reason=str(reason),
        strain_measure=strain_measure,
        threshold=threshold,
        gamma_sampling=gamma_sampling,
        **known,
    )


@dataclass(frozen=True)
class VoiSpec:
    """How the volume of interest is defined and estimated.

    ``strain_measure`` ({'green_lagrange', 'log'}) is the γmax ``voi_mm3`` and the bins use (both
    measures' VOI are always reported); ``threshold`` [-] is the γmax above which tissue is in the VOI
    (0.3, the damage threshold of the indentation studies); ``bin_edges`` are the γmax bin edges, the first
    equal to ``threshold`` (:data:`deeptissue.strain.DEFAULT_BIN_EDGES`); ``gamma_sampling``
    ({'points', 'centroid'}, :data:`GAMMA_SAMPLINGS`) says which estimate the reported VOI is: 'points'
    integrates γmax at sub-element points, which converges faster under mesh refinement than one value
    per element at the centroid."""

    strain_measure: str = "green_lagrange"
    threshold: float = 0.3
    bin_edges: Sequence[float] = DEFAULT_BIN_EDGES
    gamma_sampling: str = "points"

    def __post_init__(self):
        if self.gamma_sampling not in GAMMA_SAMPLINGS:
            raise ValueError(
                f"gamma_sampling {self.gamma_sampling!r}: expected one of {GAMMA_SAMPLINGS}"
            )


def _reported_error(mesh: TetMesh, displacement_mm, s, g_pts, v_pts, voi: VoiSpec):
    """The recovered-strain error estimate of the reported VOI and bins: γh at the same points as
    ``voi_mm3`` (the sub-element points ``g_pts``/``v_pts`` or the centroids of ``s``) against the
    recovered γ*."""
    measure = voi.strain_measure
    at = (
        (g_pts[measure], v_pts)
        if voi.gamma_sampling == "points"
        else (s.gamma(measure)[:, None], s.volume_mm3[:, None])
    )
    return voi_error_estimate(
        mesh,
        displacement_mm,
        threshold=voi.threshold,
        bin_edges=voi.bin_edges,
        strain_measure=measure,
        levels=SAMPLING_LEVELS if voi.gamma_sampling == "points" else 0,
        sampled=at,
    )


def summarize_solution(
    mesh: TetMesh,
    displacement_mm,
    *,
    animal: str,
    variant: str,
    voi: VoiSpec = VoiSpec(),
    energy_density_mpa=None,
    skin_contours_mm=None,
    **solver_info,
) -> tuple[Summary, ElementStrain]:
    """Summary of a converged solution from the reference mesh and its nodal displacement.

    Parameters
    ----------
    mesh : TetMesh
        Reference mesh (nodes in mm, 10- or 4-node tetrahedra, facet set ``skin`` when
        ``skin_contours_mm`` is given).
    displacement_mm : (n_nodes, 3) array_like
        Nodal displacement [mm].
    animal, variant : str
        The run.
    voi : VoiSpec
        Strain measure, threshold, bins and γmax sampling of the VOI. ``voi_mm3``, ``bins_percent``,
        ``below_threshold_percent``, ``strain_energy_mJ`` and ``voi_by_measure_mm3`` follow its
        ``gamma_sampling``; both samplings are always in ``voi_sampled_mm3`` / ``voi_centroid_mm3`` and
        their bins.
    energy_density_mpa : (n_tets,) array_like or None
        Strain-energy density per reference volume [MPa] (= mJ/mm³), for ``strain_energy_mJ``.
    skin_contours_mm : (..., 3) array_like or None
        Skin contour points of the during scan [mm], compared with the deformed ``skin`` facets
        (``skin_mean_mm``, ``skin_p95_mm``).
    **solver_info
        ``indenter_force_N``, ``n_dofs``, ``increments``, ``newton_iterations``, ``wall_s`` and any
        further diagnostics (kept in ``extra``).

    Returns
    -------
    summary : Summary
        ``converged`` True; ``peak_gamma`` is the largest centroid γmax; ``voi_err_mm3`` and
        ``bins_err_pp`` the recovered-strain estimate of the discretisation error of ``voi_mm3`` and
        ``bins_percent`` (:func:`deeptissue.errorest.voi_error_estimate`).
    strain : ElementStrain
        Per-element strain at the centroids (for ``result.vtu``).
    """
    strain_measure, threshold, bin_edges = voi.strain_measure, voi.threshold, voi.bin_edges
    gamma_sampling = voi.gamma_sampling
    s = element_strain(mesh, displacement_mm)
    g_pts, v_pts, n_centroid = gamma_at_points(
        mesh, displacement_mm, levels=SAMPLING_LEVELS, strain_measures=STRAIN_MEASURES
    )
    w = None if energy_density_mpa is None else np.asarray(energy_density_mpa, float).ravel()
    if w is not None and w.shape != (mesh.n_tets,):
        raise ValueError(f"energy_density_mpa has {w.size} values for {mesh.n_tets} elements")

    def stats(measure, sampling, energy=None):
        if sampling == "centroid":
            return voi_statistics(
                s.gamma(measure),
                s.volume_mm3,
                threshold=threshold,
                bin_edges=bin_edges,
                energy_density_mpa=energy,
            )
        return voi_statistics(
            g_pts[measure].ravel(),
            v_pts.ravel(),
            threshold=threshold,
            bin_edges=bin_edges,
            energy_density_mpa=None if energy is None else np.repeat(energy, v_pts.shape[1]),
        )

    centroid, sampled = stats(strain_measure, "centroid", w), stats(strain_measure, "points", w)
    st = sampled if gamma_sampling == "points" else centroid
    by = {m: (st if m == strain_measure else stats(m, gamma_sampling)) for m in STRAIN_MEASURES}
    est = _reported_error(mesh, displacement_mm, s, g_pts, v_pts, voi)
    skin = {}
    if skin_contours_mm is not None:
        verts, tris = deformed_surface(mesh, displacement_mm, facet="skin")
        mean, p95 = skin_agreement_mm(skin_contours_mm, verts, tris)
        skin = {"skin_mean_mm": mean, "skin_p95_mm": p95}
    names = {f.name for f in fields(Summary)}
    extra = {k: v for k, v in solver_info.items() if k not in names}
    extra["sampling_centroid_elements"] = (
        n_centroid  # folded or inverted at a sample point: counted at the centroid
    )
    solver = {k: v for k, v in solver_info.items() if k in names}
    summary = Summary(
        animal=animal,
        variant=variant,
        converged=True,
        reason=None,
        strain_measure=strain_measure,
        threshold=float(threshold),
        voi_mm3=st.voi_mm3,
        bins_percent=st.bins_percent,
        voi_err_mm3=est.voi_err_mm3,
        bins_err_pp=est.bins_err_pp,
        below_threshold_percent=st.below_threshold_percent,
        peak_gamma=centroid.peak_gamma,
        strain_energy_mJ=st.strain_energy_mJ,
        n_elements=int(mesh.n_tets),
        gamma_sampling=gamma_sampling,
        voi_sampled_mm3=sampled.voi_mm3,
        bins_sampled_percent=sampled.bins_percent,
        voi_centroid_mm3=centroid.voi_mm3,
        bins_centroid_percent=centroid.bins_percent,
        voi_by_measure_mm3={m: b.voi_mm3 for m, b in by.items()},
        peak_gamma_by_measure={m: float(s.gamma(m).max()) for m in STRAIN_MEASURES},
        **skin,
        **solver,
        extra=extra,
    )
    return summary, s


# --- result.vtu ------------------------------------------------------------------------------------


def write_result_vtu(
    path: str | Path,
    mesh: TetMesh,
    displacement_mm,
    strain: ElementStrain,
    *,
    cell_data: dict | None = None,
) -> None:
    """Write ``result.vtu`` for ParaView, atomically.

    Parameters
    ----------
    path : str or Path
        Output ``.vtu``.
    mesh : TetMesh
        Reference mesh [mm]; cells are VTK quadratic tetra (``tetra10``), or ``tetra`` for a linear mesh.
    displacement_mm : (n_nodes, 3) array_like
        Nodal displacement [mm], written as point data ``displacement_mm``.
    strain : ElementStrain
        Written as cell data ``gamma_gl``, ``gamma_log`` [-], ``volume_mm3`` [mm³] and ``principal_gl`` (n_tets, 3).
    cell_data : dict or None
        Further cell data by name, (n_tets, ...) arrays.
    """
    from .fem.output import write_tet_vtu

    cd = {
        "gamma_gl": strain.gamma_gl,
        "gamma_log": strain.gamma_log,
        "volume_mm3": strain.volume_mm3,
        "principal_gl": strain.principal_gl,
        **(cell_data or {}),
    }
    write_tet_vtu(
        path,
        mesh,
        point_data={"displacement_mm": np.asarray(displacement_mm, float)},
        cell_data={k: np.asarray(v, float) for k, v in cd.items()},
    )


def read_result_vtu(path: str | Path) -> tuple[TetMesh, np.ndarray, dict]:
    """Read a file written by :func:`write_result_vtu`.

    Parameters
    ----------
    path : str or Path
        ``result.vtu``.

    Returns
    -------
    mesh : TetMesh
        Reference mesh [mm] in gmsh node order, without facet sets.
    displacement_mm : (n_nodes, 3) ndarray
        Nodal displacement [mm].
    cell_data : dict
        Cell data by name, (n_tets, ...) arrays.

    Raises
    ------
    ValueError
        If the file is not a result VTU (names the file).
    """
    import meshio

    try:
        m = meshio.read(path)
        from .fem.output import GMSH_TO_VTK_TET10

        tets = m.get_cells_type("tetra10")[:, GMSH_TO_VTK_TET10]
        if len(tets) == 0:  # a linear mesh
            tets = m.get_cells_type("tetra")
            if len(tets) == 0:
                raise ValueError("no tetra10 or tetra cells")
        cd = {k: np.asarray(v[0]) for k, v in m.cell_data.items()}
        u = np.asarray(m.point_data["displacement_mm"], float)
    except (KeyError, IndexError, ValueError, OSError) as exc:
        raise ValueError(f"{path}: not a deeptissue result.vtu ({exc})") from exc
    return TetMesh(nodes_mm=np.asarray(m.points, float), tets=tets.astype(np.int64)), u, cd


# --- skin agreement --------------------------------------------------------------------------------


def tri6_to_tri3(facets: np.ndarray) -> np.ndarray:
    """Split 6-node triangles (gmsh order: corners 0-2, mid-edges (0,1), (1,2), (2,0)) into four flat
    triangles each, same orientation: (n, 6) -> (4n, 3) node indices."""
    f = np.asarray(facets)
    sub = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])
    return f[:, sub].reshape(-1, 3)


def deformed_surface(
    mesh: TetMesh, displacement_mm, *, facet: str = "skin"
) -> tuple[np.ndarray, np.ndarray]:
    """Deformed positions of a named facet set: vertices (n_nodes, 3) [mm] and flat triangles (T, 3)
    (6-node facets split in four; 3-node facets of a linear mesh as they are)."""
    if facet not in mesh.facets:
        raise ValueError(f"mesh has no facet set {facet!r} (has {sorted(mesh.facets)})")
    f = mesh.facets[facet]
    return mesh.nodes_mm + np.asarray(displacement_mm, float), (
        tri6_to_tri3(f) if mesh.order == 2 else np.asarray(f)
    )


def skin_agreement_mm(
    contour_points_mm, vertices_mm, triangles, *, clip_to_surface_z: bool = True
) -> tuple[float, float]:
    """(mean, 95th percentile) distance [mm] from skin contour points (..., 3) to the surface.

    With ``clip_to_surface_z`` only contour points whose z (leg axis) lies within the z range of the
    surface's triangles count: scan slices beyond the model's ends would otherwise measure the
    distance to the open rim rather than to the skin.
    """
    P = np.asarray(contour_points_mm, float).reshape(-1, 3)
    if clip_to_surface_z:
        z = np.asarray(vertices_mm, float)[np.unique(np.asarray(triangles))][:, 2]
        P = P[(P[:, 2] >= z.min()) & (P[:, 2] <= z.max())]
    d = surface_distance_mm(P, vertices_mm, triangles)
    if d.size == 0:
        raise ValueError("skin agreement: no contour points within the model's z range")
    return float(d.mean()), float(np.percentile(d, 95))
