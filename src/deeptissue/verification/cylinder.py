"""The cylinder scene: the 1.5 mm sphere pushed into the centre of the top face of a tissue cylinder.

A cylinder of radius 8 mm and height 8 mm (axis z, bottom face z = 0 fixed, side and top free) of
the study's Ogden tissue, meshed with gmsh in quadratic tetrahedra, fine under the indenter and
coarse elsewhere; the sphere travels along -z into the centre of the top face. Its force-depth
curve and its max-shear-strain VOI and bins, computed with the study's own functions, are compared
between mesh sizes (:func:`mesh_convergence`): a scene with a known geometry on which the
discretisation error of the study's numbers and its estimate (:mod:`deeptissue.errorest`) are measured.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd

from ..adapt import AdaptSettings, PassEstimate, adapt
from ..errorest import voi_error_estimate
from ..fem.indenters import Indenter
from ..fem.solver import SolverSettings, solve_indentation
from ..io import atomic_path
from ..mesh import TetMesh, set_background_size
from ..rigid import BoneMotion
from ..strain import DEFAULT_BIN_EDGES, gamma_at_points, voi_statistics
from ..summary import SAMPLING_LEVELS, VoiSpec, summarize_solution
from .shapes import _finish, _start

__all__ = [
    "ADAPTIVE_START",
    "CURVE_DEPTHS_MM",
    "CylinderMesh",
    "CylinderScene",
    "REFERENCE_MESH",
    "VOI_DEPTHS_MM",
    "adaptive_comparison",
    "adaptive_cylinder",
    "contact_tets",
    "cylinder_estimate",
    "cylinder_mesh",
    "cylinder_scene",
    "effectivity_table",
    "mesh_convergence",
    "plot_adaptive",
    "write_adaptive_cylinder",
]

CURVE_DEPTHS_MM = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)  # depths of the force-depth curve [mm]
VOI_DEPTHS_MM = (1.5, 2.0, 3.0)  # depths at which the VOI and bins are computed [mm]


@dataclass(frozen=True)
class CylinderMesh:
    """Sizes of the cylinder mesh [mm]: ``element_size_mm`` away from the indenter, ``refine_size_mm``
    within ``refine_radius_mm`` of the axis segment from the top centre ``refine_depth_mm`` down,
    growing back over ``refine_transition_mm``. The defaults are the study's default mesh (1.6 mm,
    0.8 mm within 4 mm of the indenter's travel to 4 mm beyond the deepest tip)."""

    element_size_mm: float = 1.6
    refine_size_mm: float = 0.8
    refine_radius_mm: float = 4.0
    refine_transition_mm: float = 2.0
    refine_depth_mm: float = 7.0

    @property
    def label(self) -> str:
        """``'1.6 / 0.8 mm'``: global and refined size."""
        return f"{self.element_size_mm:g} / {self.refine_size_mm:g} mm"


# the finest mesh of the verification case: 0.4 mm within 2.5 mm of the contact, 1.2 mm elsewhere (70 503
# DOFs); 0.3 mm (126 600 DOFs) takes over 20 minutes for one 3 mm solve on a shared core
REFERENCE_MESH = CylinderMesh(
    element_size_mm=1.2,
    refine_size_mm=0.4,
    refine_radius_mm=2.5,
    refine_transition_mm=2.0,
    refine_depth_mm=4.0,
)


def cylinder_mesh(
    sizes: CylinderMesh = CylinderMesh(),
    *,
    radius_mm: float = 8.0,
    height_mm: float = 8.0,
    order: int = 2,
    size_field=None,
) -> TetMesh:
    """The tissue cylinder ``x² + y² <= radius², 0 <= z <= height`` meshed with gmsh.

    Facet sets: ``bone`` (bottom face z = 0, fixed), ``patch`` (top face, the indenter's contact
    set), ``side``, and ``skin`` (top and side: every free face). Sizes: :class:`CylinderMesh`, or
    a background size (:class:`deeptissue.mesh.SizeField`, capped at ``sizes.element_size_mm``)
    that replaces its refinement around the axis.
    """

    if sizes.refine_size_mm > sizes.element_size_mm:
        raise ValueError(
            f"refine_size_mm {sizes.refine_size_mm} > element_size_mm {sizes.element_size_mm}"
        )
    gmsh = _start("cylinder")
    try:
        gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, height_mm, radius_mm)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [t for _, t in gmsh.model.getEntities(3)], name="tissue")
        groups = {"bone": [], "patch": [], "side": []}
        for _, t in gmsh.model.getEntities(2):
            z = gmsh.model.occ.getCenterOfMass(2, t)[2]
            groups[
                "bone" if abs(z) < 1e-6 else "patch" if abs(z - height_mm) < 1e-6 else "side"
            ].append(t)
        for name, tags in groups.items():
            gmsh.model.addPhysicalGroup(2, tags, name=name)
        gmsh.model.addPhysicalGroup(2, groups["patch"] + groups["side"], name="skin")
        h, hr = float(sizes.element_size_mm), float(sizes.refine_size_mm)
        opt = gmsh.option.setNumber
        opt("Mesh.MeshSizeMax", h)
        opt("Mesh.MeshSizeMin", 0.5 * hr)
        for k in ("MeshSizeExtendFromBoundary", "MeshSizeFromPoints", "MeshSizeFromCurvature"):
            opt(f"Mesh.{k}", 0)
        if size_field is not None:
            opt("Mesh.MeshSizeMin", 0.5 * min(size_field.h_min_mm, h))
            set_background_size(gmsh, size_field)
        elif hr < h:  # distance to points along the axis below the top centre, then a linear ramp
            n = max(2, int(np.ceil(sizes.refine_depth_mm / (0.25 * hr))) + 1)
            z = np.linspace(height_mm, max(0.0, height_mm - sizes.refine_depth_mm), n)
            pts = [gmsh.model.occ.addPoint(0.0, 0.0, float(zi)) for zi in z]
            gmsh.model.occ.synchronize()
            fd = gmsh.model.mesh.field.add("Distance")
            gmsh.model.mesh.field.setNumbers(fd, "PointsList", pts)
            ft = gmsh.model.mesh.field.add("Threshold")
            for k, v in dict(
                InField=fd,
                SizeMin=hr,
                SizeMax=h,
                DistMin=sizes.refine_radius_mm,
                DistMax=sizes.refine_radius_mm + sizes.refine_transition_mm,
            ).items():
                gmsh.model.mesh.field.setNumber(ft, k, v)
            gmsh.model.mesh.field.setAsBackgroundMesh(ft)
        return _finish(gmsh, order)
    finally:
        gmsh.finalize()


def _indenter(depth_mm: float, height_mm: float, radius_mm: float = 1.5) -> Indenter:
    return Indenter(
        "sphere",
        axis=(0.0, 0.0, -1.0),
        start_mm=(0.0, 0.0, height_mm + 1e-3),
        end_mm=(0.0, 0.0, height_mm - depth_mm),
        radius_mm=radius_mm,
    )


@dataclass(frozen=True)
class CylinderScene:
    """The cylinder's height and the VOI measured in it, shared by the fixed and the adaptive meshes.

    ``height_mm``: the height of :func:`cylinder_mesh`, 8 mm like its radius, so the 3 mm deepest
    indentation stays far from the fixed bottom face; ``threshold``: the VOI's max-shear-strain
    threshold, 0.3 as in the study; ``bin_edges``: the VOI's bin edges, None: the study's
    :data:`deeptissue.strain.DEFAULT_BIN_EDGES`.
    """

    height_mm: float = 8.0
    threshold: float = 0.3
    bin_edges: tuple[float, ...] | None = None

    @property
    def edges(self) -> tuple[float, ...]:
        """The bin edges used: ``bin_edges`` or the study's default."""
        return DEFAULT_BIN_EDGES if self.bin_edges is None else tuple(self.bin_edges)


def cylinder_scene(
    material,
    sizes: CylinderMesh = CylinderMesh(),
    *,
    curve_depths_mm: Sequence[float] = CURVE_DEPTHS_MM,
    voi_depths_mm: Sequence[float] = VOI_DEPTHS_MM,
    scene: CylinderScene = CylinderScene(),
    settings: SolverSettings | None = None,
    mesh: TetMesh | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Solve the cylinder scene on one mesh: a force-depth curve and the VOI at each of ``voi_depths_mm``.

    Each depth is its own solve to that depth with the solver's defaults (no cast, zero bone motion),
    so every number is a converged end state; the VOI, bins and their error estimate are those of
    the study (:func:`deeptissue.summary.summarize_solution`) at ``scene``'s threshold and bins.

    Returns
    -------
    curve : DataFrame
        depth_mm, force_N, converged, increments, newton_iterations, wall_s, one row per depth of
        ``curve_depths_mm`` ∪ ``voi_depths_mm``; attrs n_dofs, n_tets, mesh (label).
    voi : DataFrame
        One row per depth of ``voi_depths_mm``: depth_mm, voi_mm3, voi_err_mm3, bins_percent.<bin>,
        bins_err_pp.<bin> and voi_centroid_mm3 (:func:`deeptissue.summary.summarize_solution`).
    """

    edges, height_mm, threshold = scene.edges, scene.height_mm, scene.threshold
    m = cylinder_mesh(sizes, height_mm=height_mm) if mesh is None else mesh
    st = SolverSettings() if settings is None else settings
    rows, vois = [], []
    for d in sorted(set(map(float, curve_depths_mm)) | set(map(float, voi_depths_mm))):
        t0 = time.perf_counter()
        r = solve_indentation(
            m,
            material=material,
            indenter=_indenter(d, height_mm),
            bone_motion=BoneMotion(),
            settings=st,
        )
        rows.append(
            dict(
                depth_mm=d,
                force_N=r.indenter_force_N if r.converged else np.nan,
                converged=r.converged,
                increments=r.increments,
                newton_iterations=r.newton_iterations,
                wall_s=time.perf_counter() - t0,
            )
        )
        if d in voi_depths_mm and r.converged:
            s, _ = summarize_solution(
                m,
                r.displacement_mm,
                animal="cylinder",
                variant=f"{d:g}mm",
                voi=VoiSpec(threshold=threshold, bin_edges=edges),
            )
            vois.append(
                dict(
                    depth_mm=d,
                    voi_mm3=s.voi_mm3,
                    voi_err_mm3=s.voi_err_mm3,
                    voi_centroid_mm3=s.voi_centroid_mm3,
                    **{f"bins_percent.{b}": p for b, p in s.bins_percent.items()},
                    **{f"bins_err_pp.{b}": p for b, p in s.bins_err_pp.items()},
                )
            )
    curve = pd.DataFrame(rows)
    curve.attrs.update(n_dofs=3 * len(m.nodes_mm), n_tets=int(m.n_tets), mesh=sizes.label)
    return curve, pd.DataFrame(vois)


def mesh_convergence(
    material, meshes: Sequence[CylinderMesh], **kw
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """:func:`cylinder_scene` on each of ``meshes`` (the last is the reference): the curves and VOI
    tables stacked, with columns mesh (label), n_dofs, n_tets and mesh_wall_s (all solves of the mesh)."""
    curves, vois = [], []
    for sizes in meshes:
        t0 = time.perf_counter()
        c, v = cylinder_scene(material, sizes, **kw)
        info = dict(
            mesh=sizes.label,
            n_dofs=c.attrs["n_dofs"],
            n_tets=c.attrs["n_tets"],
            mesh_wall_s=time.perf_counter() - t0,
        )
        curves.append(c.assign(**info))
        vois.append(v.assign(**info))
    return pd.concat(curves, ignore_index=True), pd.concat(vois, ignore_index=True)


def effectivity_table(voi: pd.DataFrame) -> pd.DataFrame:
    """Effectivity (estimate / true error) of the summary's recovered-strain estimate in ``voi``
    (cylinder_voi.csv) for each mesh but the finest (most DOFs) at each depth: columns mesh, depth_mm,
    true_voi_mm3 (signed), true_voi_percent, true_bins_pp (largest over the bins), voi (``voi_err_mm3``
    over |true_voi_mm3|) and bins (the largest ``bins_err_pp.*`` over true_bins_pp). An effectivity
    >= 0.5 means the true error is within twice the estimate."""
    bins = [c for c in voi.columns if c.startswith("bins_percent.")]
    ref_mesh = voi.loc[voi["n_dofs"].idxmax(), "mesh"]
    ref = voi[voi["mesh"] == ref_mesh].set_index("depth_mm")
    rows = []
    for _, r in voi[voi["mesh"] != ref_mesh].iterrows():
        f = ref.loc[r["depth_mm"]]
        true_voi = r["voi_mm3"] - f["voi_mm3"]
        true_bins = max(abs(r[b] - f[b]) for b in bins)
        est_b = max(r[c] for c in voi.columns if c.startswith("bins_err_pp."))
        rows.append(
            dict(
                mesh=r["mesh"],
                depth_mm=r["depth_mm"],
                true_voi_mm3=true_voi,
                true_voi_percent=100 * true_voi / f["voi_mm3"],
                true_bins_pp=true_bins,
                voi=r["voi_err_mm3"] / abs(true_voi) if true_voi else np.inf,
                bins=est_b / true_bins if true_bins else np.inf,
            )
        )
    return pd.DataFrame(rows)


def contact_tets(
    mesh: TetMesh, displacement_mm, indenter: Indenter, *, tol_mm: float = 0.02
) -> np.ndarray:
    """The elements (n_tets,) bool with a node of the ``patch`` facets that ends within ``tol_mm`` of the
    sphere's surface or inside it: the contact zone that decides the indenter's force."""
    if indenter.kind != "sphere":
        raise ValueError(f"contact_tets: a sphere indenter only, got {indenter.kind!r}")
    centre = np.asarray(indenter.end_mm, float) - indenter.radius_mm * indenter.unit_axis
    nodes = np.unique(mesh.facets["patch"])
    x = mesh.nodes_mm[nodes] + np.asarray(displacement_mm, float)[nodes]
    touching = np.zeros(len(mesh.nodes_mm), bool)
    touching[nodes[np.linalg.norm(x - centre, axis=1) <= indenter.radius_mm + tol_mm]] = True
    return touching[mesh.tets].any(axis=1)


def cylinder_estimate(
    mesh: TetMesh, solution, indenter: Indenter, *, threshold: float = 0.3, bin_edges=None
):
    """The estimate of one cylinder solve for :func:`deeptissue.adapt.adapt`: the VOI, its estimated error
    and the largest bin's, as the study's summary computes them (γh at 64 points per element against
    the patch-recovered γ*, :func:`deeptissue.errorest.voi_error_estimate`), its per-element indicator,
    the force and the contact zone (:func:`contact_tets`)."""

    edges = DEFAULT_BIN_EDGES if bin_edges is None else tuple(bin_edges)
    u = solution.displacement_mm
    g, v, _ = gamma_at_points(mesh, u, levels=SAMPLING_LEVELS, strain_measures=("green_lagrange",))
    g = g["green_lagrange"]
    s = voi_statistics(g.ravel(), v.ravel(), threshold=threshold, bin_edges=edges)
    e = voi_error_estimate(
        mesh, u, threshold=threshold, bin_edges=edges, levels=SAMPLING_LEVELS, sampled=(g, v)
    )
    return PassEstimate(
        voi_mm3=s.voi_mm3,
        voi_err_mm3=e.voi_err_mm3,
        bins_err_pp=max(e.bins_err_pp.values()),
        force_N=solution.indenter_force_N,
        indicator_mm3=e.indicator_mm3,
        contact_tets=contact_tets(mesh, u, indenter),
        bins_percent=dict(s.bins_percent),
        voi_indicator_mm3=e.threshold_indicator_mm3,
    )


# the first mesh of the adaptive runs: the study's element size everywhere, no refinement around the axis
ADAPTIVE_START = CylinderMesh(element_size_mm=1.6, refine_size_mm=1.6)


def adaptive_cylinder(
    material,
    depth_mm: float,
    settings=None,
    *,
    start: CylinderMesh = ADAPTIVE_START,
    scene: CylinderScene = CylinderScene(),
    solver_settings: SolverSettings | None = None,
    log=None,
):
    """The cylinder scene at one depth on adaptive meshes (:func:`deeptissue.adapt.adapt`): the first
    pass on ``start`` (uniform 1.6 mm: 10 809 DOFs, a quarter of the default mesh's solve), each next one remeshed from the previous solution's
    estimate (:func:`cylinder_estimate`) until it meets the goal of ``settings``
    (:class:`deeptissue.adapt.AdaptSettings`) or its budget is spent; the height, VOI threshold and
    bins are ``scene``'s. Returns the AdaptResult."""

    ind = _indenter(depth_mm, scene.height_mm)
    st = SolverSettings() if solver_settings is None else solver_settings

    return adapt(
        lambda field: cylinder_mesh(start, height_mm=scene.height_mm, size_field=field),
        lambda m: solve_indentation(
            m, material=material, indenter=ind, bone_motion=BoneMotion(), settings=st
        ),
        lambda m, r: cylinder_estimate(
            m, r, ind, threshold=scene.threshold, bin_edges=scene.bin_edges
        ),
        AdaptSettings() if settings is None else settings,
        log=log,
    )


def adaptive_comparison(
    passes: pd.DataFrame, voi: pd.DataFrame, curve: pd.DataFrame
) -> pd.DataFrame:
    """The adaptive passes against the fixed meshes of the verification (cylinder_voi.csv and
    cylinder_curve.csv, whose finest mesh is the reference), one row per pass and per fixed mesh and depth.
    A pass at a depth of the force-depth curve without a VOI row (0.5, 1 and 2.5 mm) has the force's true
    error only.

    ``passes``: :meth:`deeptissue.adapt.AdaptResult.table` rows with a depth_mm column. Columns: kind
    ('adaptive' or 'fixed'), mesh, depth_mm, pass_index (adaptive), n_dofs, wall_s (adaptive: every pass so far; fixed:
    the one solve at that depth), est_voi_percent, est_bins_pp (largest bin), est_force_percent
    (adaptive only), true_voi_percent, true_bins_pp, true_force_percent (against the reference),
    goal_met (adaptive: by its own estimate). The reference's own rows are left out: its true errors are zero by definition.
    """
    bins = [c for c in voi.columns if c.startswith("bins_percent.")]
    ref_mesh = voi.loc[voi["n_dofs"].idxmax(), "mesh"]
    ref = voi[voi["mesh"] == ref_mesh].set_index("depth_mm")
    ref_force = curve[curve["mesh"] == ref_mesh].set_index("depth_mm")["force_N"]
    rows = []
    for _, r in voi[voi["mesh"] != ref_mesh].iterrows():
        d = r["depth_mm"]
        c = curve[(curve["mesh"] == r["mesh"]) & (curve["depth_mm"] == d)].iloc[0]
        rows.append(
            dict(
                kind="fixed",
                mesh=r["mesh"],
                depth_mm=d,
                n_dofs=r["n_dofs"],
                wall_s=c["wall_s"],
                est_voi_percent=100 * r["voi_err_mm3"] / r["voi_mm3"],
                est_bins_pp=max(r[c2] for c2 in voi.columns if c2.startswith("bins_err_pp.")),
                true_voi_percent=100 * (r["voi_mm3"] / ref.loc[d, "voi_mm3"] - 1),
                true_bins_pp=max(abs(r[b] - ref.loc[d, b]) for b in bins),
                true_force_percent=100 * (c["force_N"] / ref_force.loc[d] - 1),
            )
        )
    for _, p in passes.iterrows():
        d = p["depth_mm"]
        has_voi = d in ref.index  # the reference's VOI and bins are known at the VOI depths only
        true_bins = (
            max((abs(p[b] - ref.loc[d, b]) for b in bins if b in p), default=np.nan)
            if has_voi
            else np.nan
        )
        rows.append(
            dict(
                kind="adaptive",
                mesh="adaptive",
                depth_mm=d,
                pass_index=p["index"],
                n_dofs=p["n_dofs"],
                wall_s=p["wall_s"],
                est_voi_percent=p["voi_err_percent"],
                est_bins_pp=p["bins_err_pp"],
                est_force_percent=p["force_err_percent"],
                true_voi_percent=100 * (p["voi_mm3"] / ref.loc[d, "voi_mm3"] - 1)
                if has_voi
                else np.nan,
                true_bins_pp=true_bins,
                true_force_percent=100 * (p["force_N"] / ref_force.loc[d] - 1),
                goal_met=p["goal_met"],
            )
        )
    return pd.DataFrame(rows)


def plot_adaptive(table: pd.DataFrame, path) -> None:
    """True VOI error [%], largest bin error [pp] and force error [%] against wall time [s]
    (:func:`adaptive_comparison`'s table): the adaptive passes of each depth as a line (open markers:
    estimate not yet within the goal), the fixed meshes (but the reference) as squares, the goals of
    the verification case as dotted lines. A depth without a VOI row appears in the force's panel only."""

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for j, d in enumerate(sorted(table["depth_mm"].unique())):
        colour = f"C{j}"
        a = table[(table["kind"] == "adaptive") & (table["depth_mm"] == d)].sort_values("wall_s")
        f = table[(table["kind"] == "fixed") & (table["depth_mm"] == d)]
        for ax, col in zip(axes, ("true_voi_percent", "true_bins_pp", "true_force_percent")):
            if not np.isfinite(a[col].to_numpy(float)).any():
                continue
            ax.plot(a["wall_s"], a[col].abs(), "-", color=colour, label=f"{d:g} mm adaptive")
            met = a["goal_met"].astype(bool).to_numpy()
            ax.plot(a["wall_s"][met], a[col].abs()[met], "o", color=colour)
            ax.plot(a["wall_s"][~met], a[col].abs()[~met], "o", color=colour, mfc="none")
            ax.plot(f["wall_s"], f[col].abs(), "s", color=colour, mfc="none", ms=8)
    for ax, goal, label in zip(
        axes,
        (2.0, 1.0, 0.5),
        (
            "|VOI error| against the reference [%]",
            "largest bin error [pp]",
            "|force error| against the reference [%]",
        ),
    ):
        ax.axhline(goal, ls=":", color="k", lw=1)
        ax.set_xscale("log")
        ax.set_xlabel("wall time [s] (adaptive: all passes so far)")
        ax.set_ylabel(label)
    fixed = ", ".join(dict.fromkeys(table.loc[table["kind"] == "fixed", "mesh"]))
    axes[2].legend(fontsize=8, title=f"squares: fixed {fixed}", title_fontsize=8)
    fig.suptitle("Cylinder scene: adaptive meshes against fixed meshes")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def write_adaptive_cylinder(
    material,
    *,
    voi_csv,
    curve_csv,
    out_csv,
    figure_png,
    depths_mm: Sequence[float] = CURVE_DEPTHS_MM,
    settings=None,
) -> pd.DataFrame:
    """:func:`adaptive_cylinder` at each of ``depths_mm`` against the fixed meshes of the verification
    (``voi_csv``, ``curve_csv``: cylinder_voi.csv and cylinder_curve.csv, whose finest mesh is the
    reference): the table of :func:`adaptive_comparison` with a stop_reason column (out_csv) and
    :func:`plot_adaptive` (figure_png). Each pass is logged."""

    logger = logging.getLogger(__name__)
    runs = []
    for d in depths_mm:
        r = adaptive_cylinder(
            material, float(d), settings, log=lambda line, d=d: logger.info("%g mm: %s", d, line)
        )
        runs.append(r.table().assign(depth_mm=float(d), stop_reason=r.stop_reason))
    passes = pd.concat(runs, ignore_index=True)
    table = adaptive_comparison(passes, pd.read_csv(voi_csv), pd.read_csv(curve_csv))
    table["stop_reason"] = (
        table["depth_mm"]
        .map(passes.groupby("depth_mm")["stop_reason"].first())
        .where(table["kind"] == "adaptive")
    )
    Path(out_csv).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_csv) as tmp:
        table.to_csv(tmp, index=False)
    plot_adaptive(table, figure_png)
    return table


if (
    __name__ == "__main__"
):  # python -m deeptissue.verification.cylinder results/verification/cylinder_voi.csv [more.csv ...]
    pd.set_option("display.width", 250)
    tables = pd.concat([pd.read_csv(p) for p in sys.argv[1:]], ignore_index=True)
    print(effectivity_table(tables).round(3).T.to_string())
