"""Speed against error: one animal and variant solved at a ladder of discretisations (issue 7).

A :class:`Discretisation` is one setting of the ladder (global element size, local refinement near
the indenter or none, element order, Newton and contact tolerances); settings of one *family* differ
only in size (or, for the tolerance family, only in tolerance) and are the lines of the error-vs-time
plot. :func:`run_discretisation` meshes, solves and summarises one animal x variant x setting and
times each part, plus one linear-elastic reference solve on the same mesh (``cost_ratio``).
:func:`convergence_table` turns the rows into errors against the finest converged run of the same
variant (and a Richardson extrapolation where three sizes of one family allow it), the accuracy
goal and the Pareto front; :func:`scaling_fit`, :func:`summary_markdown` and
:func:`plot_error_vs_time` make the summary and the figure.

Units: mm, N, s, MB (resident memory, 2**20 bytes); percentages in %, bin errors in percentage
points (pp).
"""

from __future__ import annotations

import logging
import math
import resource
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

# Element orders the mesh, assembly and contact code support: 4-node (model.element_order 1) and
# 10-node (2) tetrahedra.
SUPPORTED_ELEMENT_ORDERS = (1, 2)

ROW_COLUMNS = (
    "animal", "variant", "setting", "family", "element_order", "element_size_mm", "refine_size_mm",
    "tolerance", "rtol", "penetration_tol", "mesh_key", "is_default", "converged", "reason",
    "n_elements", "n_dofs", "increments", "newton_iterations", "gamma_sampling", "voi_mm3", "bins_percent",
    "voi_sampled_mm3", "bins_sampled_percent", "voi_centroid_mm3", "bins_centroid_percent", "peak_gamma",
    "indenter_force_N", "mesh_s", "assembly_s", "linear_solve_s", "contact_s", "solver_other_s",
    "post_s", "solve_s", "wall_s", "linear_setup_s", "linear_assembly_s", "linear_factor_solve_s",
    "linear_wall_s", "cost_ratio", "start_rss_mb", "peak_rss_mb",
)


# The two γ samplings whose errors are always tabulated (summary.GAMMA_SAMPLINGS: 'points' is 'sampled')
ESTIMATES = {"sampled": "γ at 64 points per element", "centroid": "γ at element centroids"}


# --------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class AccuracyGoal:
    """The accuracy goal of issue 7: VOI within 2 %, every bin within 1 pp, force within 2 %."""

    voi_rel_error: float = 0.02
    bin_error_pp: float = 1.0
    force_rel_error: float = 0.02


@dataclass(frozen=True)
class Discretisation:
    """One setting of the ladder.

    element_size_mm: global element size; refine_size_mm: element size near the indenter travel
    (None: no local refinement); element_order: 1 (4-node) or 2 (10-node tetrahedra); rtol: Newton
    residual tolerance at step ends (``fem.solver.rtol``); penetration_tol: allowed contact
    penetration over facet size (``fem.solver.penetration_tol``); tolerance: the name of that
    tolerance pair; family: the plot line the setting belongs to.
    """

    name: str
    family: str
    element_size_mm: float
    refine_size_mm: float | None = None
    element_order: int = 2
    rtol: float = 1e-7
    penetration_tol: float = 0.01
    tolerance: str = "default"

    def __post_init__(self):
        if self.element_order not in (1, 2):
            raise ValueError(f"setting {self.name}: element_order must be 1 or 2, got {self.element_order}")
        if not self.element_size_mm > 0 or (self.refine_size_mm is not None and not self.refine_size_mm > 0):
            raise ValueError(f"setting {self.name}: element sizes must be > 0")
        if not (self.rtol > 0 and self.penetration_tol > 0):
            raise ValueError(f"setting {self.name}: tolerances must be > 0")

    @property
    def mesh_key(self) -> str:
        """Identifies the mesh (order and sizes): settings with the same key differ only in tolerance."""
        r = "none" if self.refine_size_mm is None else f"{self.refine_size_mm:g}"
        return f"p{self.element_order}_h{self.element_size_mm:g}_r{r}"

    def model_settings(self, model_cfg: dict | None = None) -> dict:
        """The ``model`` config with this setting's sizes (no refinement: refine size = global size)
        and element order (``model.element_order``)."""
        d = dict(model_cfg or {})
        d["element_order"] = int(self.element_order)
        d["element_size_mm"] = float(self.element_size_mm)
        d["refine_size_mm"] = float(self.element_size_mm if self.refine_size_mm is None else self.refine_size_mm)
        return d

    def solver_config(self, solver_cfg: dict | None = None) -> dict:
        """The ``fem.solver`` config with this setting's tolerances."""
        d = dict(solver_cfg or {})
        d["rtol"] = float(self.rtol)
        d["penetration_tol"] = float(self.penetration_tol)
        return d

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Discretisation":
        return cls(**d)


def setting_name(*, element_size_mm: float, refine_size_mm: float | None, element_order: int = 2,
                 tolerance: str = "default") -> str:
    """Wildcard-safe name, e.g. ``p2_h1.2`` (uniform), ``p2_h1_r0.5`` (refined), ``p2_h1_r0.5_tight``."""
    name = f"p{element_order}_h{element_size_mm:g}"
    if refine_size_mm is not None:
        name += f"_r{refine_size_mm:g}"
    if tolerance != "default":
        name += f"_{tolerance}"
    return name


@dataclass(frozen=True)
class Ladder:
    """The settings to run, the name of the one equal to the configured default, and notes."""

    settings: tuple
    default_name: str
    notes: tuple = ()

    def by_name(self, name: str) -> Discretisation:
        for s in self.settings:
            if s.name == name:
                return s
        raise KeyError(f"convergence: no setting named {name!r}; known: {[s.name for s in self.settings]}")

    @property
    def names(self) -> list:
        return [s.name for s in self.settings]


def default_ladder(conv_cfg: dict | None = None, *, model_cfg: dict | None = None,
                   solver_cfg: dict | None = None) -> Ladder:
    """The ladder of config ``convergence`` around the configured default (``model``, ``fem.solver``).

    Families, each at every supported order of ``element_orders``:
    ``P<o> uniform`` (``element_sizes_mm``, no local refinement), ``P<o> refined x<ratio>``
    (``refined_element_sizes_mm`` with refinement ``refine_ratio`` x size), ``P<o> tolerance`` (the
    configured default mesh at each of ``tolerances``), and the configured default itself (family
    ``P<o> default`` if it is not already one of the above). Sizes use the ``default`` tolerance
    (``fem.solver.rtol`` / ``penetration_tol``). Unsupported element orders are left out with a note.
    """
    c = dict(conv_cfg or {})
    m = dict(model_cfg or {})
    sv = dict(solver_cfg or {})
    base_rtol = float(sv.get("rtol", 1e-7))
    base_pen = float(sv.get("penetration_tol", 0.01))
    from .model import ModelSettings  # the model stage's defaults, one definition

    h0 = float(m.get("element_size_mm", ModelSettings.element_size_mm))
    r0 = float(m.get("refine_size_mm", ModelSettings.refine_size_mm))
    r0 = None if r0 >= h0 else r0
    tols = {}
    for t in c.get("tolerances", [{"name": "default"}]):
        tols[t["name"]] = (float(t.get("rtol", base_rtol)), float(t.get("penetration_tol", base_pen)))
    tols.setdefault("default", (base_rtol, base_pen))
    ratio = float(c.get("refine_ratio", 0.5))
    notes = []
    orders = []
    for o in c.get("element_orders", [1, 2]):
        if o in SUPPORTED_ELEMENT_ORDERS:
            orders.append(int(o))
        else:
            notes.append(f"element order {o} left out: the mesh/FE code supports orders {list(SUPPORTED_ELEMENT_ORDERS)} only")
            log.info("convergence: %s", notes[-1])
    if not orders:
        raise ValueError(f"config key convergence.element_orders: none of {c.get('element_orders')} is supported "
                         f"(supported: {list(SUPPORTED_ELEMENT_ORDERS)})")
    out: dict = {}

    def add(family, h, r, order, tol):
        rt, pt = tols[tol]
        name = setting_name(element_size_mm=h, refine_size_mm=r, element_order=order, tolerance=tol)
        if name not in out:
            out[name] = Discretisation(name=name, family=family, element_size_mm=float(h), refine_size_mm=r,
                                       element_order=order, rtol=rt, penetration_tol=pt, tolerance=tol)
        return name

    for o in orders:
        for h in c.get("element_sizes_mm", [1.6, 1.2, 0.9, 0.7, 0.5]):
            add(f"P{o} uniform", float(h), None, o, "default")
        for h in c.get("refined_element_sizes_mm", [1.6, 1.2, 1.0, 0.7]):
            r = round(ratio * float(h), 6)
            add(f"P{o} refined x{ratio:g}", float(h), r if r < float(h) else None, o, "default")
        add(f"P{o} default", h0, r0, o, "default")
        for t in tols:
            add(f"P{o} tolerance", h0, r0, o, t)
    o = int(m.get("element_order", 2))
    if o not in orders:
        o = 2 if 2 in orders else orders[0]
    default_name = setting_name(element_size_mm=h0, refine_size_mm=r0, element_order=o)
    return Ladder(settings=tuple(out.values()), default_name=default_name, notes=tuple(notes))


# --------------------------------------------------------------------------- one run


def _rss_mb() -> float:
    """Peak resident set size of this process so far [MB] (Linux: ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def linear_reference_solve(mesh, *, material, solver_settings, load_set: str = "patch",
                           direction=(0.0, 0.0, -1.0)) -> dict:
    """One linear-elastic solve on ``mesh``: the tangent at u = 0 assembled once, factorised once.

    The bone facets (``solver_settings.bone_set``) are fixed; a total force of 1 N along
    ``direction`` is spread over the nodes of ``load_set``. Timed as the nonlinear solve is: set-up
    (skfem basis, sparsity pattern: ``linear_setup_s``), assembly (``linear_assembly_s``),
    factorisation + solve with the configured linear solver (``linear_factor_solve_s``, symbolic
    analysis included). Returns the times [s] and the largest displacement [mm].
    """
    from .fem.assembly import Assembler, as_material_law
    from .fem.linsolve import make_solver
    from .fem.skmesh import straighten_invalid

    s = solver_settings
    t0 = time.perf_counter()
    mesh, _ = straighten_invalid(mesh, order=s.quadrature_order)
    n = len(mesh.nodes_mm)
    constrained = np.zeros(3 * n, bool)
    bone = np.unique(mesh.facets[s.bone_set])
    constrained[(3 * bone[:, None] + np.arange(3)).ravel()] = True
    asm = Assembler(mesh, as_material_law(material), constrained=constrained, intorder=s.quadrature_order)
    t1 = time.perf_counter()
    _, _, data, _ = asm.tangent(np.zeros(3 * n))
    t2 = time.perf_counter()
    loaded = np.unique(mesh.facets[load_set if load_set in mesh.facets else "skin"])
    loaded = loaded[~constrained[3 * loaded]]
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    rhs = np.zeros(3 * n)
    rhs[(3 * loaded[:, None] + np.arange(3)).ravel()] = np.tile(d / max(len(loaded), 1), len(loaded))
    solver = make_solver(s.linear_solver, coords_mm=mesh.nodes_mm, free=asm.free, precision=s.linear_precision)
    try:
        x = solver.solve(asm.csr(data), rhs[asm.free])
    finally:
        solver.close()
    t3 = time.perf_counter()
    return dict(linear_setup_s=t1 - t0, linear_assembly_s=t2 - t1, linear_factor_solve_s=t3 - t2,
                linear_wall_s=t3 - t0, linear_max_displacement_mm=float(np.max(np.abs(x))) if len(x) else 0.0)


def run_discretisation(*, animal: str, variant: str, setting: Discretisation, contours, pose, cast=None,
                       model_cfg: dict | None = None, fem_cfg: dict | None = None, study_cfg: dict | None = None,
                       mesh_variants=None, linear_reference: bool = True, is_default: bool = False) -> dict:
    """Mesh, solve and summarise one animal x variant at one setting; returns one row (dict).

    contours: pre-state :class:`deeptissue.contours.Contours`; pose: :class:`deeptissue.pose.Pose`;
    cast: a ``deeptissue.model.Cast`` (None: built here, outside the timing; ``False``: built for
    the mesh only, no cast contact in the solve); model_cfg / fem_cfg / study_cfg: the config sections (the setting overrides sizes and
    tolerances); mesh_variants: variants whose travel the mesh is refined around (default: those
    sharing the variant's study mesh, ``model.mesh_groups`` of study.variants, so the mesh is the study's
    mesh; the solved variant is always included).
    The row has :data:`ROW_COLUMNS`: times [s] of meshing (``mesh_s``), the solver's assembly,
    linear solves and contact and the rest (``solver_other_s``), post-processing (``post_s``), the
    solver's wall time (``solve_s``), all of it (``wall_s``), the linear-elastic reference
    (``linear_*``) and ``cost_ratio = solve_s / linear_wall_s``; peak resident memory of the process
    (``peak_rss_mb``; ``start_rss_mb`` before meshing). A failed mesh or solve gives a row with
    ``converged`` false and the reason (never raises for those).
    """
    from .fem.cast import Cast as FemCast
    from .fem.material import Ogden
    from .fem.solver import solver_settings_from_config
    from .model import ModelSettings, build_cast, build_model
    from .study import StudySettings, solve_variant, variant_indenter
    from .variants import mesh_groups

    if setting.element_order not in SUPPORTED_ELEMENT_ORDERS:
        raise ValueError(f"setting {setting.name}: element order {setting.element_order} is not supported by the mesh/FE "
                         f"code (supported: {list(SUPPORTED_ELEMENT_ORDERS)})")
    fem_cfg = dict(fem_cfg or {})
    study_cfg = dict(study_cfg or {})
    start_rss = _rss_mb()
    row: dict = {k: None for k in ROW_COLUMNS}
    row.update(animal=animal, variant=variant, setting=setting.name, family=setting.family,
               element_order=setting.element_order, element_size_mm=setting.element_size_mm,
               refine_size_mm=setting.refine_size_mm, tolerance=setting.tolerance, rtol=setting.rtol,
               penetration_tol=setting.penetration_tol, mesh_key=setting.mesh_key, is_default=bool(is_default),
               converged=False, start_rss_mb=start_rss)
    if mesh_variants:
        variants = list(mesh_variants)
    else:  # the variants of the variant's study mesh
        groups = mesh_groups(study_cfg.get("variants") or [variant], by=(model_cfg or {}).get("mesh_groups", ModelSettings.mesh_groups))
        variants = next((list(m) for m in groups.values() if variant in m), [])
    if variant not in variants:
        variants.append(variant)
    msettings = setting.model_settings(model_cfg)
    msettings.setdefault("bar_length_mm", float(fem_cfg.get("bar_length_mm", 10.0)))
    use_cast = cast is not False
    if cast is None or cast is False:  # the cast does not depend on the element size: built untimed
        cast = build_cast(contours, pose, variants=variants, settings=msettings, animal=animal)
    t0 = time.perf_counter()
    try:
        model = build_model(contours, pose, variants=variants, settings=msettings, animal=animal, cast=cast)
    except Exception as exc:  # a mesh that fails the quality gate is a result of this setting
        log.error("%s/%s/%s: meshing failed: %s", animal, variant, setting.name, exc)
        row.update(reason=f"meshing failed: {type(exc).__name__}: {exc}", mesh_s=time.perf_counter() - t0,
                   peak_rss_mb=_rss_mb())
        return row
    mesh = model.mesh
    row["mesh_s"] = time.perf_counter() - t0
    row["n_elements"] = int(mesh.n_tets)
    study = StudySettings.from_config(study_cfg)
    settings = solver_settings_from_config(setting.solver_config(fem_cfg.get("solver")))
    material = Ogden(**fem_cfg.get("material", {}))
    fem_cast = None if not use_cast else FemCast(model.cast.vertices_mm, model.cast.triangles)
    bar = float(fem_cfg.get("bar_length_mm", 10.0))
    t1 = time.perf_counter()
    try:
        summary, _, _ = solve_variant(animal=animal, variant=variant, mesh=mesh, pose=pose, cast=fem_cast,
                                      material=material, settings=settings, study=study, bar_length_mm=bar)
    except Exception as exc:  # set-up errors of the solver: recorded, the ladder goes on
        log.exception("%s/%s/%s: solve failed", animal, variant, setting.name)
        row.update(reason=f"{type(exc).__name__}: {exc}", peak_rss_mb=_rss_mb())
        return row
    run_s = time.perf_counter() - t1  # solve + post-processing (strain, VOI, bins)
    d = summary.to_dict()
    solve_s = float(d.get("solver_wall_s") or 0.0)
    parts = {k: float(d.get(k) or 0.0) for k in ("assembly_s", "linear_solve_s", "contact_s")}
    row.update(
        converged=bool(summary.converged), reason=summary.reason, n_dofs=d.get("n_dofs"),
        increments=d.get("increments"), newton_iterations=d.get("newton_iterations"), voi_mm3=summary.voi_mm3,
        bins_percent=summary.bins_percent, gamma_sampling=summary.gamma_sampling,
        voi_sampled_mm3=summary.voi_sampled_mm3, bins_sampled_percent=summary.bins_sampled_percent,
        voi_centroid_mm3=summary.voi_centroid_mm3, bins_centroid_percent=summary.bins_centroid_percent,
        peak_gamma=summary.peak_gamma,
        indenter_force_N=summary.indenter_force_N,
        solve_s=solve_s, solver_other_s=max(solve_s - sum(parts.values()), 0.0),
        post_s=max(run_s - solve_s, 0.0), **parts,
    )
    row["wall_s"] = row["mesh_s"] + run_s
    if linear_reference:
        axis = variant_indenter(pose, variant, bar_length_mm=bar).axis
        patch = f"patch_{variant}" if f"patch_{variant}" in mesh.facets else "patch"
        try:
            lin = linear_reference_solve(mesh, material=material, solver_settings=settings, load_set=patch, direction=axis)
            row.update({k: v for k, v in lin.items() if k in ROW_COLUMNS})
            row["cost_ratio"] = solve_s / lin["linear_wall_s"] if lin["linear_wall_s"] > 0 else None
        except Exception as exc:
            log.exception("%s/%s/%s: linear reference solve failed", animal, variant, setting.name)
            row["linear_error"] = f"{type(exc).__name__}: {exc}"
    row["peak_rss_mb"] = _rss_mb()
    log.info("%s/%s/%s: converged %s, %s tets, %s dofs, solve %.1f s, linear %.2f s, peak %.0f MB",
             animal, variant, setting.name, row["converged"], row["n_elements"], row["n_dofs"], solve_s,
             row["linear_wall_s"] or float("nan"), row["peak_rss_mb"])
    return row


def run_convergence_job(*, animal: str, variant: str, setting: dict, contours_path, pose_path, cast_path,
                        row_path, model_cfg: dict, fem_cfg: dict, study_cfg: dict, mesh_variants=None,
                        is_default: bool = False, linear_reference: bool = True) -> dict:
    """Rule ``convergence_run``: read the animal's pre contours, pose and cast; write the row as JSON."""
    from .contours import load_contours
    from .io import write_json
    from .model import load_cast
    from .pose import load_pose

    row = run_discretisation(
        animal=animal, variant=variant, setting=Discretisation.from_dict(setting),
        contours=load_contours(contours_path), pose=load_pose(pose_path),
        cast=load_cast(cast_path) if cast_path else None, model_cfg=model_cfg, fem_cfg=fem_cfg,
        study_cfg=study_cfg, mesh_variants=mesh_variants, is_default=is_default, linear_reference=linear_reference,
    )
    write_json(row_path, row)
    return row


# --------------------------------------------------------------------------- errors


@dataclass(frozen=True)
class Richardson:
    """f(h) = value + k h^p fitted exactly through three sizes (the finest three of a family)."""

    order_p: float
    extrapolated: float
    k: float
    sizes: tuple  # the three h used, coarse to fine


def richardson_extrapolation(h, f, *, p_bounds=(0.1, 10.0)) -> Richardson | None:
    """Richardson extrapolation through the three finest of (h, f) (h any consistent size measure).

    Solves (f1 − f2)/(f2 − f3) = (h1^p − h2^p)/(h2^p − h3^p) for the order p (h1 > h2 > h3; any
    ratios), then f0 = f3 − k h3^p with k = (f2 − f3)/(h2^p − h3^p). Returns None if fewer than
    three distinct sizes, if the differences change sign or vanish (no monotone convergence), or if
    p is outside ``p_bounds``.
    """
    from scipy.optimize import brentq

    h = np.asarray(h, float)
    f = np.asarray(f, float)
    ok = np.isfinite(h) & np.isfinite(f) & (h > 0)
    h, f = h[ok], f[ok]
    order = np.argsort(-h)
    h, f = h[order], f[order]
    if len(np.unique(h)) < 3:
        return None
    h, f = h[-3:], f[-3:]
    if len(np.unique(h)) < 3:
        return None
    d12, d23 = f[0] - f[1], f[1] - f[2]
    if d23 == 0 or d12 * d23 <= 0:
        return None
    r = d12 / d23

    def g(p):
        return (h[0] ** p - h[1] ** p) / (h[1] ** p - h[2] ** p) - r

    lo, hi = p_bounds
    if g(lo) * g(hi) > 0:
        return None
    p = brentq(g, lo, hi, xtol=1e-13, rtol=1e-13)
    k = d23 / (h[1] ** p - h[2] ** p)
    return Richardson(order_p=float(p), extrapolated=float(f[2] - k * h[2] ** p), k=float(k), sizes=tuple(h.tolist()))


def size_measure(row: dict, *, measure: str = "dofs") -> float:
    """The size h of a run for Richardson: ``dofs`` -> n_dofs^(-1/3) (the effective size of an
    unstructured mesh), ``element_size`` -> the nominal global element size [mm]."""
    if measure == "dofs":
        n = row.get("n_dofs")
        return float(n) ** (-1.0 / 3.0) if n else float("nan")
    if measure == "element_size":
        return float(row["element_size_mm"])
    raise ValueError(f"size measure {measure!r}: expected 'dofs' or 'element_size'")


def _ok(r: dict) -> bool:
    return bool(r.get("converged")) and r.get("voi_mm3") is not None


def reference_rows(rows) -> dict:
    """{variant: the finest converged row}: most DOFs, then tightest rtol and penetration tolerance."""
    ref = {}
    for r in rows:
        if not _ok(r):
            continue
        key = (r.get("n_dofs") or 0, -float(r.get("rtol") or 1.0), -float(r.get("penetration_tol") or 1.0))
        cur = ref.get(r["variant"])
        if cur is None or key > cur[0]:
            ref[r["variant"]] = (key, r)
    return {v: k_r[1] for v, k_r in ref.items()}


def richardson_by_family(rows, *, measure: str = "dofs") -> list[dict]:
    """Richardson extrapolation of VOI and force for every variant x family with >= 3 converged sizes
    at one tolerance. One dict per (variant, family, quantity): order_p, extrapolated, sizes, settings."""
    out = []
    groups: dict = {}
    for r in rows:
        if _ok(r):
            groups.setdefault((r["variant"], r["family"], r.get("tolerance")), []).append(r)
    for (variant, family, tol), rs in sorted(groups.items(), key=lambda kv: tuple(str(x) for x in kv[0])):
        if len({r["mesh_key"] for r in rs}) < 3:
            continue
        for q in ("voi_mm3", "voi_sampled_mm3", "voi_centroid_mm3", "indenter_force_N"):
            if all(r.get(q) is None for r in rs):
                continue
            h = [size_measure(r, measure=measure) for r in rs]
            f = [float(r[q]) if r.get(q) is not None else np.nan for r in rs]
            res = richardson_extrapolation(h, f)
            finest = sorted(rs, key=lambda r: -size_measure(r, measure=measure))[-3:]
            out.append(dict(variant=variant, family=family, tolerance=tol, quantity=q,
                            order_p=None if res is None else res.order_p,
                            extrapolated=None if res is None else res.extrapolated,
                            sizes=None if res is None else list(res.sizes),
                            settings=[r["setting"] for r in finest], n_sizes=len(rs)))
    return out


def _rel(a, b) -> float:
    if a is None or b is None:
        return float("nan")
    a, b = float(a), float(b)
    if b == 0:
        return 0.0 if a == 0 else float("inf")
    return abs(a - b) / abs(b)


def _bin_error(a: dict | None, b: dict | None) -> float:
    if not a or not b:
        return float("nan")
    labels = set(a) | set(b)
    vals = [abs(float(a.get(k) or 0.0) - float(b.get(k) or 0.0)) for k in labels]
    return float(max(vals)) if vals else float("nan")


def pareto_mask(cost, error) -> np.ndarray:
    """True where no other point has cost <= and error <= with one of them strictly lower (NaN: False)."""
    c = np.asarray(cost, float)
    e = np.asarray(error, float)
    ok = np.isfinite(c) & np.isfinite(e)
    mask = np.zeros(len(c), bool)
    for i in np.flatnonzero(ok):
        dom = ok & (c <= c[i]) & (e <= e[i]) & ((c < c[i]) | (e < e[i]))
        mask[i] = not dom.any()
    return mask


def goal_error(voi_rel: float, bin_pp: float, force_rel: float, goal: AccuracyGoal = AccuracyGoal()) -> float:
    """The largest error as a multiple of its goal: <= 1 means the goal is met (NaN if any is unknown)."""
    v = [voi_rel / goal.voi_rel_error, bin_pp / goal.bin_error_pp, force_rel / goal.force_rel_error]
    return float("nan") if any(not np.isfinite(x) and not np.isinf(x) for x in v) else float(max(v))


def convergence_table(rows, *, goal: AccuracyGoal = AccuracyGoal(), measure: str = "dofs"):
    """One row per run with its errors; returns a pandas DataFrame.

    Added columns: ``reference_setting`` (the finest converged run of the variant, see
    :func:`reference_rows`), ``is_reference``, ``voi_rel_error`` (|VOI − VOI_ref| / VOI_ref),
    ``bin_max_error_pp`` (largest |bin % − bin %_ref|, percentage points), ``force_rel_error``,
    ``goal_error`` (largest error over its goal), ``meets_goal``, ``voi_rel_error_richardson`` and
    ``force_rel_error_richardson`` (against the Richardson extrapolation of the reference's family,
    or of the family with the most sizes, where it exists), ``meets_goal_richardson``, ``pareto``
    (not dominated in (wall_s, goal_error) among the converged runs of the variant), and one
    ``bin_<label>`` column per VOI bin [%]. Rows that did not converge keep NaN errors.
    """
    import pandas as pd

    rows = [dict(r) for r in rows]
    refs = reference_rows(rows)
    rich = richardson_by_family(rows, measure=measure)
    rich_ref: dict = {}
    for variant, ref in refs.items():
        cands = [x for x in rich if x["variant"] == variant and x["extrapolated"] is not None]
        for q in ("voi_mm3", "voi_sampled_mm3", "voi_centroid_mm3", "indenter_force_N"):
            qc = [x for x in cands if x["quantity"] == q]
            same = [x for x in qc if x["family"] == ref["family"] and x["tolerance"] == ref.get("tolerance")]
            pick = same[0] if same else (max(qc, key=lambda x: x["n_sizes"]) if qc else None)
            if pick is not None:
                rich_ref[(variant, q)] = pick
    labels = []
    for r in rows:
        for k in (r.get("bins_percent") or {}):
            if k not in labels:
                labels.append(k)
    for r in rows:
        ref = refs.get(r["variant"])
        ok = _ok(r) and ref is not None
        r["reference_setting"] = ref["setting"] if ref is not None else None
        r["is_reference"] = ref is not None and r["setting"] == ref["setting"]
        r["voi_rel_error"] = _rel(r["voi_mm3"], ref["voi_mm3"]) if ok else float("nan")
        r["bin_max_error_pp"] = _bin_error(r.get("bins_percent"), ref.get("bins_percent")) if ok else float("nan")
        r["force_rel_error"] = _rel(r["indenter_force_N"], ref["indenter_force_N"]) if ok else float("nan")
        r["goal_error"] = goal_error(r["voi_rel_error"], r["bin_max_error_pp"], r["force_rel_error"], goal) if ok else float("nan")
        r["meets_goal"] = bool(ok and r["goal_error"] <= 1.0)
        rv, rf = rich_ref.get((r["variant"], "voi_mm3")), rich_ref.get((r["variant"], "indenter_force_N"))
        r["voi_rel_error_richardson"] = _rel(r["voi_mm3"], rv["extrapolated"]) if (ok and rv) else float("nan")
        r["force_rel_error_richardson"] = _rel(r["indenter_force_N"], rf["extrapolated"]) if (ok and rf) else float("nan")
        if ok and rv and rf:
            r["meets_goal_richardson"] = bool(goal_error(r["voi_rel_error_richardson"], r["bin_max_error_pp"],
                                                         r["force_rel_error_richardson"], goal) <= 1.0)
        else:
            r["meets_goal_richardson"] = None
        for k in labels:
            r[f"bin_{k}"] = (r.get("bins_percent") or {}).get(k)
        for est in ESTIMATES:  # the errors of both γ samplings, whichever voi_mm3 is
            voi, bins = f"voi_{est}_mm3", f"bins_{est}_percent"
            ok_e = ok and r.get(voi) is not None and ref.get(voi) is not None
            r[f"voi_{est}_rel_error"] = _rel(r.get(voi), ref[voi]) if ok_e else float("nan")
            r[f"bin_{est}_max_error_pp"] = _bin_error(r.get(bins), ref.get(bins)) if ok_e else float("nan")
            r[f"goal_error_{est}"] = (goal_error(r[f"voi_{est}_rel_error"], r[f"bin_{est}_max_error_pp"],
                                                 r["force_rel_error"], goal) if ok_e else float("nan"))
            r[f"meets_goal_{est}"] = bool(ok_e and r[f"goal_error_{est}"] <= 1.0)
            rs = rich_ref.get((r["variant"], voi))
            r[f"voi_{est}_rel_error_richardson"] = _rel(r.get(voi), rs["extrapolated"]) if (ok_e and rs) else float("nan")
            for k in labels:
                r[f"bin_{est}_{k}"] = (r.get(bins) or {}).get(k)
    df = pd.DataFrame(rows)
    df = df.drop(columns=[c for c in ("bins_percent", *(f"bins_{e}_percent" for e in ESTIMATES)) if c in df])
    df["pareto"] = False
    for variant, idx in df.groupby("variant").groups.items():
        sub = df.loc[idx]
        conv = sub["converged"].astype(bool).to_numpy()
        m = pareto_mask(np.where(conv, sub["wall_s"].astype(float), np.nan), sub["goal_error"].astype(float))
        df.loc[idx, "pareto"] = m
    return df


def setting_table(df, *, goal: AccuracyGoal = AccuracyGoal()):
    """Per setting over all variants: converged everywhere, largest goal_error, summed wall time and
    solve time, largest cost_ratio and peak memory, meets_goal (in every variant) and the Pareto
    flag on (total wall, largest goal_error). A pandas DataFrame sorted by total wall time."""
    import pandas as pd

    n_var = df["variant"].nunique()
    out = []
    for name, g in df.groupby("setting", sort=False):
        conv = bool(g["converged"].astype(bool).all()) and len(g) == n_var
        out.append(dict(
            setting=name, family=g["family"].iloc[0], is_default=bool(g["is_default"].astype(bool).any()),
            is_reference=bool(g["is_reference"].astype(bool).any()), converged=conv,
            n_dofs=g["n_dofs"].max(), wall_s=float(g["wall_s"].astype(float).sum()),
            solve_s=float(g["solve_s"].astype(float).sum()),
            goal_error=float(g["goal_error"].astype(float).max()) if conv else float("nan"),
            **{f"goal_error_{e}": (float(g[f"goal_error_{e}"].astype(float).max())
                                   if conv and f"goal_error_{e}" in g else float("nan")) for e in ESTIMATES},
            cost_ratio=float(g["cost_ratio"].astype(float).max()), peak_rss_mb=float(g["peak_rss_mb"].astype(float).max()),
        ))
    st = pd.DataFrame(out)
    st["meets_goal"] = st["converged"] & (st["goal_error"] <= 1.0)
    for e in ESTIMATES:
        st[f"meets_goal_{e}"] = st["converged"] & (st[f"goal_error_{e}"] <= 1.0)
    st["pareto"] = pareto_mask(np.where(st["converged"], st["wall_s"], np.nan), st["goal_error"])
    return st.sort_values("wall_s", kind="stable").reset_index(drop=True)


# --------------------------------------------------------------------------- scaling


@dataclass(frozen=True)
class ScalingFit:
    """value ≈ prefactor · n_dofs^exponent (log–log least squares); r2 of the fit in log space."""

    quantity: str
    exponent: float
    prefactor: float
    r2: float
    n_points: int


def scaling_fit(n_dofs, values, *, quantity: str = "") -> ScalingFit | None:
    """Least-squares fit of log(values) = log(prefactor) + exponent · log(n_dofs) over the points with
    both positive and finite; None if fewer than two distinct n_dofs remain."""
    n = np.asarray(n_dofs, float)
    v = np.asarray(values, float)
    ok = np.isfinite(n) & np.isfinite(v) & (n > 0) & (v > 0)
    n, v = n[ok], v[ok]
    if len(np.unique(n)) < 2:
        return None
    x, y = np.log(n), np.log(v)
    A = np.stack([np.ones_like(x), x], axis=1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ coef
    tot = np.sum((y - y.mean()) ** 2)
    r2 = 1.0 - float(np.sum(res**2) / tot) if tot > 0 else 1.0
    return ScalingFit(quantity=quantity, exponent=float(coef[1]), prefactor=float(np.exp(coef[0])), r2=r2, n_points=int(len(n)))


def scaling_fits(df) -> list:
    """Growth with n_dofs of the solver wall time, the linear reference, the whole run and the memory
    (peak RSS above the process's start), over the converged runs at the default tolerance."""
    sel = df[df["converged"].astype(bool) & (df["tolerance"] == "default")]
    n = sel["n_dofs"].astype(float)
    fits = [
        scaling_fit(n, sel["solve_s"].astype(float), quantity="solve_s"),
        scaling_fit(n, sel["linear_wall_s"].astype(float), quantity="linear_wall_s"),
        scaling_fit(n, sel["wall_s"].astype(float), quantity="wall_s"),
        scaling_fit(n, sel["peak_rss_mb"].astype(float) - sel["start_rss_mb"].astype(float), quantity="rss_above_start_mb"),
        scaling_fit(n, sel["peak_rss_mb"].astype(float), quantity="peak_rss_mb"),
    ]
    return [f for f in fits if f is not None]


# --------------------------------------------------------------------------- report


def _fmt(x, spec=".3g", pct=False) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    if not np.isfinite(x):
        return "–"
    return f"{100 * x:{spec}} %" if pct else f"{x:{spec}}"


def summary_markdown(df, *, default_name: str | None, goal: AccuracyGoal = AccuracyGoal(), notes=(),
                     max_cost_ratio: float = 15.0, measure: str = "dofs") -> str:
    """The text of ``summary.md``: cheapest setting meeting the goal in every variant, the Pareto
    front, the Richardson orders, the fitted scaling exponents, and the verdict on the default."""
    st = setting_table(df, goal=goal)
    rows = df.to_dict("records")
    lines = ["# Speed against error", ""]
    lines.append(f"Animal {', '.join(sorted(df['animal'].astype(str).unique()))}; variants "
                 f"{', '.join(sorted(df['variant'].astype(str).unique()))}; {st.shape[0]} settings, {len(df)} runs "
                 f"({int(df['converged'].astype(bool).sum())} converged).")
    lines.append(f"Goal: VOI within {100 * goal.voi_rel_error:g} %, every bin within {goal.bin_error_pp:g} pp, "
                 f"force within {100 * goal.force_rel_error:g} % of the reference (the finest converged run of each "
                 "variant), in every variant.")
    lines.append("")
    refs = df[df["is_reference"].astype(bool)]
    for _, r in refs.iterrows():
        lines.append(f"- reference for `{r['variant']}`: `{r['setting']}` ({int(r['n_dofs'])} DOFs, VOI "
                     f"{_fmt(r['voi_mm3'], '.4g')} mm³, force {_fmt(r['indenter_force_N'], '.4g')} N)")
    lines.append("")
    cand = st[st["meets_goal"] & ~st["is_reference"]]
    if len(cand):
        c = cand.iloc[0]
        lines.append(f"**Cheapest setting meeting the goal: `{c['setting']}`** ({c['family']}; {_fmt(c['wall_s'], '.1f')} s "
                     f"for all variants, largest error {_fmt(c['goal_error'], '.2f')} × goal, largest cost ratio {_fmt(c['cost_ratio'], '.1f')}).")
    else:
        lines.append("**No setting other than the reference meets the goal in every variant.**")
    lines.append("")
    sampling = ", ".join(sorted(df["gamma_sampling"].dropna().astype(str).unique())) if "gamma_sampling" in df else ""
    if sampling:
        lines.append(f"The errors above are those of the configured γ sampling (`study.gamma_sampling`: {sampling}). Each sampling:")
        lines.append("")
        for e, what in ESTIMATES.items():
            if st[f"goal_error_{e}"].notna().any():
                cand = st[st[f"meets_goal_{e}"] & ~st["is_reference"]]
                best = (f"cheapest setting meeting the goal `{cand.iloc[0]['setting']}` ({_fmt(cand.iloc[0]['wall_s'], '.1f')} s, "
                        f"largest error {_fmt(cand.iloc[0][f'goal_error_{e}'], '.2f')} × goal)" if len(cand)
                        else "no setting other than the reference meets the goal")
                lines.append(f"- {what} (`voi_{e}_mm3`): {best}")
        lines.append("")
    lines.append("Pareto front (total wall time of all variants against the largest error as a multiple of its goal):")
    lines.append("")
    lines.append("| setting | family | wall [s] | error / goal | meets goal | error / goal: points, centroid | cost ratio | peak RSS [MB] |")
    lines.append("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for _, r in st[st["pareto"]].iterrows():
        lines.append(f"| `{r['setting']}`{' (default)' if r['is_default'] else ''}{' (reference)' if r['is_reference'] else ''} "
                     f"| {r['family']} | {_fmt(r['wall_s'], '.1f')} | {_fmt(r['goal_error'], '.2f')} | "
                     f"{'yes' if r['meets_goal'] else 'no'} | {_fmt(r['goal_error_sampled'], '.2f')}, "
                     f"{_fmt(r['goal_error_centroid'], '.2f')} | "
                     f"{_fmt(r['cost_ratio'], '.1f')} | {_fmt(r['peak_rss_mb'], '.0f')} |")
    lines.append("")
    lines.append("Configured default:")
    d = st[st["setting"] == default_name] if default_name else st.iloc[0:0]
    if len(d) and bool(d.iloc[0]["is_reference"]):
        d = d.iloc[0]
        lines.append(f"`{default_name}` is the reference itself (the finest converged run): its error is not measured; "
                     f"add finer settings to the ladder. Its cost ratio is {_fmt(d['cost_ratio'], '.1f')}.")
    elif len(d):
        d = d.iloc[0]
        ratio_ok = np.isfinite(d["cost_ratio"]) and d["cost_ratio"] <= max_cost_ratio
        lines.append(f"`{default_name}` {'meets' if d['meets_goal'] else 'does NOT meet'} the goal "
                     f"(error {_fmt(d['goal_error'], '.2f')} × goal), {'sits' if d['pareto'] else 'does NOT sit'} on the "
                     f"Pareto front, and its cost ratio (solve / one linear-elastic solve) is {_fmt(d['cost_ratio'], '.1f')} "
                     f"({'within' if ratio_ok else 'above'} the {max_cost_ratio:g} × goal).")
    else:
        lines.append(f"`{default_name}` was not run.")
    lines.append("")
    rich = richardson_by_family(rows, measure=measure)
    if rich:
        lines.append(f"Richardson extrapolation (three finest sizes of a family, h = {'n_dofs^(-1/3)' if measure == 'dofs' else 'element size'}):")
        lines.append("")
        lines.append("| variant | family | quantity | order p | extrapolated | settings |")
        lines.append("| --- | --- | --- | --- | --- | --- |")
        for x in rich:
            lines.append(f"| {x['variant']} | {x['family']} | {x['quantity']} | {_fmt(x['order_p'], '.2f')} | "
                         f"{_fmt(x['extrapolated'], '.4g')} | {', '.join(x['settings'])} |")
        lines.append("")
    fits = scaling_fits(df)
    if fits:
        lines.append("Growth with n_dofs (log–log least squares over the converged runs at the default tolerance):")
        lines.append("")
        for f in fits:
            lines.append(f"- `{f.quantity}` ∝ n_dofs^{f.exponent:.2f} (R² {f.r2:.2f}, {f.n_points} runs)")
        lines.append("")
    failed = df[~df["converged"].astype(bool)]
    if len(failed):
        lines.append("Runs that did not converge:")
        lines.append("")
        for _, r in failed.iterrows():
            lines.append(f"- `{r['setting']}` / {r['variant']}: {r['reason']}")
        lines.append("")
    for n in notes:
        lines.append(f"Note: {n}")
    return "\n".join(lines).rstrip() + "\n"


def write_summary_md(path, df, *, default_name: str | None, goal: AccuracyGoal = AccuracyGoal(), notes=(),
                     max_cost_ratio: float = 15.0, measure: str = "dofs") -> str:
    """Write :func:`summary_markdown` to ``path`` (atomically); returns the text."""
    from .io import atomic_path

    text = summary_markdown(df, default_name=default_name, goal=goal, notes=notes, max_cost_ratio=max_cost_ratio,
                            measure=measure)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
    return text


def plot_error_vs_time(path, df, *, goal: AccuracyGoal = AccuracyGoal()) -> None:
    """Log–log error against wall time, one line per family (and variant), three panels: VOI, largest
    bin error, force. The goal is a dashed line; references (error 0) are not drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    from .io import atomic_path

    panels = [("voi_rel_error", "VOI error [%]", 100.0, 100 * goal.voi_rel_error),
              ("bin_max_error_pp", "largest bin error [pp]", 1.0, goal.bin_error_pp),
              ("force_rel_error", "force error [%]", 100.0, 100 * goal.force_rel_error)]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6))
    ok = df[df["converged"].astype(bool)]
    families = list(dict.fromkeys(df["family"]))
    variants = list(dict.fromkeys(df["variant"]))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    markers = ["o", "s", "^", "D", "v", "P"]
    for ax, (col, label, scale, g) in zip(axes, panels):
        for i, fam in enumerate(families):
            mk = set(ok.loc[ok["family"] == fam, "mesh_key"])
            for j, var in enumerate(variants):
                sel = ok[(ok["variant"] == var) & ((ok["family"] == fam) | (ok["mesh_key"].isin(mk) & fam.endswith("tolerance")))]
                sel = sel.sort_values("wall_s")
                y = sel[col].astype(float) * scale
                m = (y > 0) & np.isfinite(y)
                if not m.any():
                    continue
                ax.plot(sel["wall_s"][m], y[m], marker=markers[j % len(markers)], color=colours[i % len(colours)],
                        ls="-" if j == 0 else "--", label=f"{fam}, {var}")
                default = sel[m & sel["is_default"].astype(bool)]
                if len(default):
                    ax.plot(default["wall_s"], default[col].astype(float) * scale, marker="*", ms=16, mfc="none",
                            mec="k", ls="none")
        ax.axhline(g, color="k", ls=":", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall time (mesh + solve + post) [s]")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    h, lab = axes[0].get_legend_handles_labels()
    if h:
        fig.legend(h, lab, loc="lower center", ncol=min(4, len(h)), fontsize=8, frameon=False)
    fig.suptitle("Error against the finest converged run vs wall time (dotted: goal; star: configured default)", fontsize=10)
    fig.tight_layout(rect=(0, 0.12 if h else 0, 1, 0.95))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def read_benchmark(path) -> dict:
    """Snakemake ``benchmark:`` TSV -> {benchmark_s, benchmark_max_rss_mb, benchmark_cpu_s} (first row)."""
    import pandas as pd

    b = pd.read_csv(path, sep="\t")
    if len(b) == 0:
        return {}
    r = b.iloc[0]
    out = {"benchmark_s": float(r.get("s", np.nan))}
    for src, dst in (("max_rss", "benchmark_max_rss_mb"), ("cpu_time", "benchmark_cpu_s")):
        try:
            out[dst] = float(r[src])
        except (KeyError, TypeError, ValueError):
            out[dst] = float("nan")
    return out


def aggregate_convergence(*, row_paths, benchmark_paths=(), csv_path, png_path, md_path, default_name: str | None,
                          goal: dict | None = None, notes=(), max_cost_ratio: float = 15.0, measure: str = "dofs"):
    """Rule ``convergence``: rows (JSON) + benchmark TSVs -> convergence.csv, error_vs_time.png, summary.md."""
    from .io import atomic_path, read_json

    g = AccuracyGoal(**(goal or {}))
    bench = {}
    for p in benchmark_paths:
        try:
            bench[Path(p).stem] = read_benchmark(p)
        except Exception as exc:  # a missing or empty benchmark is not a reason to lose the table
            log.warning("benchmark %s unreadable: %s", p, exc)
    rows = []
    for p in row_paths:
        r = read_json(p)
        r.update(bench.get(f"{r['variant']}_{r['setting']}", {}))
        rows.append(r)
    df = convergence_table(rows, goal=g, measure=measure)
    with atomic_path(csv_path) as tmp:
        df.to_csv(tmp, index=False)
    plot_error_vs_time(png_path, df, goal=g)
    write_summary_md(md_path, df, default_name=default_name, goal=g, notes=notes, max_cost_ratio=max_cost_ratio,
                     measure=measure)
    return df
