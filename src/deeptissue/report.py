"""The study across animals: tables of every summary, the exclusion policy, and the figures.

Exclusion policy (the paper's, made visible): if any variant of an animal did not converge, the
whole animal is *excluded* from comparisons. It stays in every table (``excluded`` true and an
``exclusion_reason`` naming the variants and their reasons) and in every figure (greyed and
hatched, with the reason written on it); the study still completes.

Section figures sample per-element γmax on planes that contain the indenter axis, in the
reference configuration: planes with normal ``n`` = world z projected perpendicular to the axis
(the bar's long axis), spaced 1 mm apart along ``n`` and centred on the axis through the tip.
A grid point takes the γ of the (straight-sided, corner-node) tetrahedron that contains it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .io import atomic_path
from .mesh import TetMesh, locate_in_tets
from .strain import DEFAULT_BIN_EDGES, bin_labels
from .summary import Summary

__all__ = [
    "EXCLUDED_COLOUR",
    "EXCLUDED_HATCH",
    "MEASURE_LABELS",
    "Sections",
    "aggregate_study",
    "exclusions",
    "figure_sections",
    "locate_points",
    "plot_bins",
    "plot_sections",
    "plot_voi",
    "plot_voi_change",
    "sample_sections",
    "section_frame",
    "summary_tables",
    "voi_change_percent",
    "write_csv",
]

EXCLUDED_COLOUR = "0.75"  # grey of an excluded animal's bars
EXCLUDED_HATCH = "///"


# --- tables ----------------------------------------------------------------------------------------


def exclusions(summaries: Sequence[Summary]) -> dict[str, str]:
    """animal -> exclusion reason, for every animal with a variant that did not converge
    ("not converged: <variant>: <reason>; ..."; without the prefix when every such variant was
    infeasible, i.e. not solved because its indenter ends inside the bone)."""
    out: dict[str, list[tuple[str, str]]] = {}
    for s in summaries:
        if not s.converged:
            out.setdefault(s.animal, []).append((s.variant, str(s.reason)))
    return {
        a: ("" if all(why.startswith("infeasible") for _, why in r) else "not converged: ")
        + "; ".join(f"{v}: {why}" for v, why in r)
        for a, r in out.items()
    }


_DICT_FIELDS = (
    "bins_percent",
    "bins_err_pp",
    "bins_sampled_percent",
    "bins_centroid_percent",
    "voi_by_measure_mm3",
    "peak_gamma_by_measure",
)


def _flatten(d: dict) -> dict:
    flat = {}
    for k, v in d.items():
        if v is None and k in _DICT_FIELDS:
            continue  # a failed run: its sub-columns stay empty
        if isinstance(v, dict):
            for kk, vv in v.items():
                flat[f"{k}.{kk}"] = vv
        else:
            flat[k] = v
    return flat


def summary_tables(
    summaries: Sequence[Summary],
    *,
    animals: Sequence[str],
    variants: Sequence[str],
    bin_edges: Sequence[float] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``voi`` (one row per animal × variant, every summary field, dicts flattened as ``key.sub``) and
    ``bins`` (long: animal, variant, bin, percent, excluded), in the configured order. Bin labels come
    from the summaries, or from ``bin_edges`` when no run converged.

    Raises ValueError naming any animal × variant without a summary.
    """
    by_key = {(s.animal, s.variant): s for s in summaries}
    missing = [f"{a}/{v}" for a in animals for v in variants if (a, v) not in by_key]
    if missing:
        raise ValueError(f"no summary for {', '.join(missing)}")
    excl = exclusions([by_key[(a, v)] for a in animals for v in variants])
    rows, bins = [], []
    for a in animals:
        for v in variants:
            s = by_key[(a, v)]
            row = {
                "animal": a,
                "variant": v,
                "excluded": a in excl,
                "exclusion_reason": excl.get(a, ""),
            }
            d = s.to_dict()
            d.pop("animal"), d.pop("variant")
            row.update(_flatten(d))
            rows.append(row)
            labels = (
                list(s.bins_percent or {})
                or _labels_from_any(summaries)
                or (bin_labels(bin_edges) if bin_edges else [])
            )
            for label in labels:
                pct = (s.bins_percent or {}).get(label, np.nan) if s.converged else np.nan
                bins.append(
                    {
                        "animal": a,
                        "variant": v,
                        "bin": label,
                        "percent": pct,
                        "excluded": a in excl,
                    }
                )
    voi = pd.DataFrame(rows)
    return voi, pd.DataFrame(bins, columns=["animal", "variant", "bin", "percent", "excluded"])


def _labels_from_any(summaries) -> list[str]:
    for s in summaries:
        if s.bins_percent:
            return list(s.bins_percent)
    return []


def write_csv(path: str | Path, df: pd.DataFrame) -> None:
    """Write ``df`` as CSV without its index, atomically."""
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)


# --- bar figures -----------------------------------------------------------------------------------


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    _plt().close(fig)


def _variant_colours(variants):
    cmap = _plt().get_cmap("tab10")
    return {v: cmap(i % 10) for i, v in enumerate(variants)}


def _mark_excluded(ax, x_centre, reason, y_top):
    ax.text(
        x_centre,
        y_top,
        "excluded\n" + _wrap(reason, 28),
        ha="center",
        va="top",
        fontsize=6,
        color="0.3",
    )


def _wrap(text, width):
    import textwrap

    return "\n".join(textwrap.wrap(text, width)[:4])


def plot_voi(
    voi: pd.DataFrame, path: str | Path, *, measure_label: str = "γmax (Green–Lagrange)"
) -> None:
    """Fig. 7A style: VOI [mm³] per animal, one bar per variant; excluded animals greyed and hatched."""
    plt = _plt()
    animals = list(dict.fromkeys(voi["animal"]))
    variants = list(dict.fromkeys(voi["variant"]))
    colours = _variant_colours(variants)
    width = 0.8 / len(variants)
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(animals) + 2), 4))
    top = (
        np.nanmax(pd.to_numeric(voi["voi_mm3"], errors="coerce").to_numpy(float), initial=0.0)
        or 1.0
    )
    for i, a in enumerate(animals):
        sub = voi[voi["animal"] == a].set_index("variant")
        excluded = bool(sub["excluded"].iloc[0])
        for j, v in enumerate(variants):
            x = i - 0.4 + width * (j + 0.5)
            val = sub.loc[v, "voi_mm3"]
            if not bool(sub.loc[v, "converged"]) or val is None or not np.isfinite(float(val)):
                ax.plot(x, 0, marker="x", color="k", ms=5)
                continue
            err = (
                float(
                    pd.to_numeric(pd.Series([sub.loc[v, "voi_err_mm3"]]), errors="coerce").iloc[0]
                )
                if "voi_err_mm3" in sub
                else np.nan
            )
            ax.bar(
                x,
                float(val),
                width,
                color=EXCLUDED_COLOUR if excluded else colours[v],
                hatch=EXCLUDED_HATCH if excluded else None,
                edgecolor="0.4" if excluded else "none",
                yerr=err if np.isfinite(err) else None,
                error_kw=dict(elinewidth=0.8, capsize=2, ecolor="k"),
            )
        if excluded:
            _mark_excluded(ax, i, sub["exclusion_reason"].iloc[0], 1.25 * top)
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[v]) for v in variants]
    handles.append(
        plt.Rectangle(
            (0, 0), 1, 1, facecolor=EXCLUDED_COLOUR, hatch=EXCLUDED_HATCH, edgecolor="0.4"
        )
    )
    # beside the axes, so that it never hides an exclusion note
    ax.legend(
        handles,
        variants + ["excluded animal"],
        fontsize=7,
        bbox_to_anchor=(1.01, 1),
        loc="upper left",
    )
    ax.set_xticks(range(len(animals)), animals)
    ax.set_ylim(0, 1.3 * top)
    ax.set_ylabel("VOI [mm³]")
    sampled = set(voi["gamma_sampling"].dropna()) if "gamma_sampling" in voi else set()
    where = {"points": "64 points per element", "centroid": "element centroids"}
    at = (
        f", sampled at {' / '.join(where.get(x, str(x)) for x in sorted(sampled))}"
        if sampled
        else ""
    )
    bars = ", error bar: estimated discretisation error" if "voi_err_mm3" in voi else ""
    ax.set_title(
        f"Volume with {measure_label} above threshold{at} (x: not converged{bars})", fontsize=10
    )
    _save(fig, path)


def plot_bins(bins: pd.DataFrame, path: str | Path, *, voi: pd.DataFrame | None = None) -> None:
    """Fig. 7B style: stacked % of the VOI per strain bin, one bar per animal × variant; with the
    ``voi`` table, the largest estimated bin error (its ``bins_err_pp.*`` columns) is written above each bar."""
    plt = _plt()
    animals = list(dict.fromkeys(bins["animal"]))
    variants = list(dict.fromkeys(bins["variant"]))
    labels = list(dict.fromkeys(bins["bin"]))
    cmap = plt.get_cmap("viridis")
    colours = {b: cmap(k / max(1, len(labels) - 1)) for k, b in enumerate(labels)}
    worst_err = {}
    err_cols = [
        c for c in (voi.columns if voi is not None else []) if c.startswith("bins_err_pp.")
    ]
    if err_cols:
        errs = voi[err_cols].apply(pd.to_numeric, errors="coerce").to_numpy(float)
        worst_err = {
            (a, v): float(np.nanmax(e)) if np.isfinite(e).any() else np.nan
            for a, v, e in zip(voi["animal"], voi["variant"], errs)
        }
    fig, ax = plt.subplots(figsize=(max(6, 0.35 * len(animals) * len(variants) + 2), 4))
    x, ticks, ticklabels = 0.0, [], []
    for a in animals:
        for v in variants:
            sub = bins[(bins["animal"] == a) & (bins["variant"] == v)].set_index("bin")
            excluded = bool(sub["excluded"].iloc[0]) if len(sub) else False
            bottom = 0.0
            for b in labels:
                p = float(sub.loc[b, "percent"]) if b in sub.index else np.nan
                if np.isfinite(p) and p > 0:
                    ax.bar(
                        x,
                        p,
                        0.8,
                        bottom=bottom,
                        color=colours[b],
                        hatch=EXCLUDED_HATCH if excluded else None,
                        edgecolor="0.3" if excluded else "none",
                        alpha=0.35 if excluded else 1.0,
                    )
                    bottom += p
            err = worst_err.get((a, v), np.nan)
            if np.isfinite(err):  # the largest estimated bin error, above the bar
                ax.text(x, 101, f"±{err:.1f}", ha="center", va="bottom", fontsize=5, rotation=90)
            pcts = sub["percent"].to_numpy(float) if len(sub) else np.array([np.nan])
            if not np.isfinite(pcts).any():
                ax.text(x, 2, "n.c.", ha="center", fontsize=6, rotation=90)
            elif np.nansum(pcts) == 0:
                ax.text(x, 2, "empty VOI", ha="center", fontsize=6, rotation=90)
            ticks.append(x)
            ticklabels.append(f"{a} {v}" + (" (excl.)" if excluded else ""))
            x += 1
        x += 0.6
    ax.set_xticks(ticks, ticklabels, rotation=90, fontsize=6)
    ax.set_ylim(0, 115 if worst_err else 105)
    ax.set_ylabel("% of VOI")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[b]) for b in labels]
    ax.legend(
        handles, labels, title="γmax bin", fontsize=7, bbox_to_anchor=(1.01, 1), loc="upper left"
    )
    ax.set_title(
        "Distribution of the VOI over strain bins (hatched: excluded animal; n.c.: not converged;\n"
        "±: largest estimated bin error [pp])"
    )
    _save(fig, path)


def voi_change_percent(voi: pd.DataFrame, *, reference: str = "sphere") -> pd.DataFrame:
    """Per animal and variant ≠ reference: 100 (VOI_variant / VOI_reference − 1) [%] (NaN where undefined)."""
    rows = []
    for a, sub in voi.groupby("animal", sort=False):
        sub = sub.set_index("variant")
        if reference not in sub.index:
            continue
        ref = pd.to_numeric(pd.Series([sub.loc[reference, "voi_mm3"]]), errors="coerce").iloc[0]
        for v in sub.index:
            if v == reference:
                continue
            val = pd.to_numeric(pd.Series([sub.loc[v, "voi_mm3"]]), errors="coerce").iloc[0]
            change = (
                100.0 * (val / ref - 1.0)
                if (np.isfinite(ref) and ref > 0 and np.isfinite(val))
                else np.nan
            )
            rows.append(
                {
                    "animal": a,
                    "variant": v,
                    "voi_change_percent": change,
                    "excluded": bool(sub["excluded"].iloc[0]),
                    "exclusion_reason": sub["exclusion_reason"].iloc[0],
                }
            )
    return pd.DataFrame(
        rows, columns=["animal", "variant", "voi_change_percent", "excluded", "exclusion_reason"]
    )


def plot_voi_change(voi: pd.DataFrame, path: str | Path, *, reference: str = "sphere") -> None:
    """VOI change of every other orientation of the reference indenter (variants named
    ``<reference>_…``, e.g. ``sphere_rx+15``) against the estimated orientation per animal [%]; other
    indenters (the bar, several times the sphere's VOI) would set the scale and hide the orientations
    (their change is in :func:`voi_change_percent`)."""
    plt = _plt()
    ch = voi_change_percent(voi, reference=reference)
    animals = list(dict.fromkeys(voi["animal"]))
    all_variants = list(dict.fromkeys(voi["variant"]))
    variants = [v for v in all_variants if v != reference and v.startswith(f"{reference}_")]
    colours = _variant_colours(all_variants)
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(animals) + 2), 4))
    width = 0.8 / max(1, len(variants))
    vals = ch[ch["variant"].isin(variants)]["voi_change_percent"].to_numpy(float)
    hi = max(10.0, 1.3 * float(np.nanmax(vals, initial=0.0))) if len(vals) else 10.0
    lo = min(-10.0, 1.3 * float(np.nanmin(vals, initial=0.0))) if len(vals) else -10.0
    for i, a in enumerate(animals):
        sub = ch[ch["animal"] == a].set_index("variant")
        excluded = bool(sub["excluded"].iloc[0]) if len(sub) else False
        for j, v in enumerate(variants):
            x = i - 0.4 + width * (j + 0.5)
            val = float(sub.loc[v, "voi_change_percent"]) if v in sub.index else np.nan
            if not np.isfinite(val):
                ax.plot(x, 0, marker="x", color="k", ms=5)
                continue
            ax.bar(
                x,
                val,
                width,
                color=EXCLUDED_COLOUR if excluded else colours[v],
                hatch=EXCLUDED_HATCH if excluded else None,
                edgecolor="0.4" if excluded else "none",
            )
        if excluded:
            _mark_excluded(ax, i, sub["exclusion_reason"].iloc[0], 0.98 * hi)
    ax.axhline(0, color="k", lw=0.8)
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[v]) for v in variants]
    ax.legend(handles, variants, fontsize=7, bbox_to_anchor=(1.01, 1), loc="upper left")
    ax.set_xticks(range(len(animals)), animals)
    ax.set_ylim(lo, hi)
    ax.set_ylabel(f"VOI change vs '{reference}' [%]")
    ax.set_title(
        f"VOI of each orientation relative to the estimated one '{reference}' (x: undefined)"
    )
    _save(fig, path)


# --- sections --------------------------------------------------------------------------------------


def section_frame(axis, *, leg_axis=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (a, e, n): ``a`` the indenter axis, ``n`` the leg axis projected perpendicular to
    ``a`` (plane normal; the bar's long axis), ``e = n × a`` (in-plane, across the indenter)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    n = np.asarray(leg_axis, float) - np.dot(leg_axis, a) * a
    if np.linalg.norm(n) < 1e-6:
        raise ValueError("section_frame: the indenter axis is parallel to the leg axis")
    n /= np.linalg.norm(n)
    return a, np.cross(n, a), n


def locate_points(mesh: TetMesh, points_mm, *, tol: float = 1e-9) -> np.ndarray:
    """Index of the tetrahedron (straight, through its corner nodes) containing each point, -1 outside
    (:func:`deeptissue.mesh.locate_in_tets`). ``points_mm`` (..., 3) -> (...) int."""
    P = np.asarray(points_mm, float)
    elem, lam = locate_in_tets(mesh, P)
    return np.where(lam.min(axis=1) >= -tol, elem, -1).reshape(P.shape[:-1])


@dataclass(frozen=True)
class Sections:
    """γmax sampled on parallel planes containing the indenter axis (reference configuration)."""

    values: np.ndarray  # (n_sections, n_v, n_u) γ, NaN outside the mesh
    offsets_mm: np.ndarray  # (n_sections,) plane offset along n from the tip [mm]
    u_mm: np.ndarray  # (n_u,) in-plane coordinate across the indenter (along e) [mm]
    v_mm: np.ndarray  # (n_v,) in-plane coordinate along the indenter axis, + into the leg [mm]


def sample_sections(
    mesh: TetMesh,
    gamma,
    *,
    axis,
    tip_mm,
    n_sections: int = 7,
    spacing_mm: float = 1.0,
    half_width_mm: float = 6.0,
    v_range_mm: tuple[float, float] = (-2.0, 8.0),
    resolution_mm: float = 0.1,
    leg_axis=(0.0, 0.0, 1.0),
) -> Sections:
    """Sample per-element ``gamma`` (n_tets,) on ``n_sections`` planes through the indenter axis.

    Plane ``k`` contains the line ``tip_mm + t·axis`` moved by ``offsets_mm[k]·n`` with offsets
    ``spacing·(k − (n_sections − 1)/2)``; the grid spans ``u ∈ [−half_width, half_width]`` along
    ``e`` and ``v ∈ v_range`` along the axis from ``tip_mm``.
    """
    g = np.asarray(gamma, float)
    if g.shape != (mesh.n_tets,):
        raise ValueError(
            f"gamma: expected one value per element ({mesh.n_tets}), got shape {g.shape}"
        )
    a, e, n = section_frame(axis, leg_axis=leg_axis)
    tip = np.asarray(tip_mm, float)
    offsets = spacing_mm * (np.arange(n_sections) - (n_sections - 1) / 2)
    u = np.arange(-half_width_mm, half_width_mm + 0.5 * resolution_mm, resolution_mm)
    v = np.arange(v_range_mm[0], v_range_mm[1] + 0.5 * resolution_mm, resolution_mm)
    pts = (
        tip
        + offsets[:, None, None, None] * n
        + v[None, :, None, None] * a
        + u[None, None, :, None] * e
    )  # (s, nv, nu, 3)
    elem = locate_points(mesh, pts)
    vals = np.where(elem >= 0, g[np.clip(elem, 0, None)], np.nan)
    return Sections(values=vals, offsets_mm=offsets, u_mm=u, v_mm=v)


def plot_sections(
    sections: Mapping[str, Sections | str],
    path: str | Path,
    *,
    columns: Sequence[int] | None = None,
    threshold: float = 0.3,
    vmax: float = 1.0,
    title: str = "",
    measure_label: str = "γmax",
) -> None:
    """Rows: variants (a :class:`Sections`, or a string: the reason there is none); columns: the
    chosen section indices (default all). The threshold is drawn as a contour line."""
    plt = _plt()
    from matplotlib.colors import Normalize

    names = list(sections)
    if not names:
        fig, ax = plt.subplots(figsize=(5, 2))
        ax.axis("off")
        ax.text(0.5, 0.5, "no variant of this kind is configured", ha="center", va="center")
        if title:
            fig.suptitle(title, fontsize=9)
        _save(fig, path)
        return
    first = next((s for s in sections.values() if isinstance(s, Sections)), None)
    n_total = first.values.shape[0] if first is not None else 7
    cols = list(range(n_total)) if columns is None else list(columns)
    aspect = (
        1.0
        if first is None
        else (first.v_mm[-1] - first.v_mm[0]) / (first.u_mm[-1] - first.u_mm[0])
    )
    fig, axes = plt.subplots(
        len(names),
        len(cols),
        figsize=(1.9 * len(cols) + 1.2, 1.9 * aspect * len(names) + 0.9),
        squeeze=False,
        sharex=True,
        sharey=True,
    )
    norm = Normalize(0.0, vmax)
    im = None
    for r, name in enumerate(names):
        s = sections[name]
        for c, k in enumerate(cols):
            ax = axes[r, c]
            ax.set_aspect("equal")
            if isinstance(s, Sections):
                ext = (s.u_mm[0], s.u_mm[-1], s.v_mm[-1], s.v_mm[0])
                im = ax.imshow(
                    s.values[k], extent=ext, cmap="inferno", norm=norm, interpolation="nearest"
                )
                vals = np.ma.masked_invalid(s.values[k])
                if vals.count() and vals.min() <= threshold < vals.max():
                    ax.contour(
                        s.u_mm, s.v_mm, vals, levels=[threshold], colors="c", linewidths=0.6
                    )
                ax.plot(0, 0, marker="v", color="c", ms=4)
                if r == 0:
                    ax.set_title(f"slice {k + 1}: {s.offsets_mm[k]:+.1f} mm", fontsize=7)
            else:
                ax.set_facecolor(EXCLUDED_COLOUR)
                ax.text(
                    0.5,
                    0.5,
                    _wrap(str(s), 20),
                    transform=ax.transAxes,
                    ha="center",
                    va="center",
                    fontsize=6,
                )
                ax.set_xticks([]), ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(f"{name}\ndepth [mm]", fontsize=7)
            if r == len(names) - 1:
                ax.set_xlabel("across [mm]", fontsize=7)
            ax.tick_params(labelsize=6)
    if im is not None:
        cb = fig.colorbar(im, ax=axes, shrink=0.8)
        cb.set_label(f"{measure_label} (cyan line: {threshold:g})", fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    _save(fig, path)


# --- the whole aggregate step ------------------------------------------------------------------------

MEASURE_LABELS = {"green_lagrange": "γmax (Green–Lagrange)", "log": "γmax (logarithmic)"}
_CELL_FIELD = {"green_lagrange": "gamma_gl", "log": "gamma_log"}


def figure_sections(
    results: Mapping[str, tuple[Summary, str | Path]],
    pose,
    *,
    strain_measure: str = "green_lagrange",
    **sample_kw,
) -> dict[str, Sections | str]:
    """Sections of every given variant of one animal: variant -> (summary, result.vtu path).

    Planes follow each variant's own indenter axis (:func:`deeptissue.variants.variant_travel` of the
    pose) and are centred on its start tip; a variant that did not converge gives its reason instead.
    """
    from .summary import read_result_vtu
    from .variants import parse_variant, variant_travel

    out: dict[str, Sections | str] = {}
    for name, (summary, vtu) in results.items():
        if not summary.converged:
            out[name] = f"{name}: not converged ({summary.reason})"
            continue
        mesh, _, cells = read_result_vtu(vtu)
        field = _CELL_FIELD[strain_measure]
        if field not in cells:
            raise ValueError(f"{vtu}: no cell data {field!r} (has {sorted(cells)})")
        axis, start, _ = variant_travel(
            parse_variant(name),
            axis=pose.indenter_axis,
            tip_start_mm=pose.tip_start_mm,
            tip_end_mm=pose.tip_end_mm,
        )
        out[name] = sample_sections(mesh, cells[field], axis=axis, tip_mm=start, **sample_kw)
    return out


def aggregate_study(
    *,
    summary_paths: Sequence[str | Path],
    animals: Sequence[str],
    variants: Sequence[str],
    outputs: Mapping[str, str | Path],
    figure_animal: str,
    figure_results: Mapping[str, str | Path],
    pose_path: str | Path,
    strain_measure: str = "green_lagrange",
    threshold: float = 0.3,
    bin_edges: Sequence[float] = DEFAULT_BIN_EDGES,
    reference: str = "sphere",
) -> None:
    """Rule ``aggregate``: read every summary, write the tables and the figures of the study.

    Parameters
    ----------
    summary_paths : sequence of str or Path
        Every ``summary.json`` of the study (:func:`deeptissue.summary.read_summary`).
    animals, variants : sequence of str
        The configured order of the tables and figures; each pair must have a summary.
    outputs : mapping
        Output paths by key: ``voi_csv``, ``bins_csv`` (:func:`summary_tables`), ``voi_png``,
        ``bins_png``, ``voi_change_png``, ``sections_png`` (sphere vs bar, seven sections) and
        ``orientations_png`` (sections 3–5 of every sphere variant).
    figure_animal : str
        The animal of the section figures.
    figure_results : mapping
        Variant -> ``result.vtu`` of ``figure_animal``, for the section figures.
    pose_path : str or Path
        Pose of ``figure_animal`` (indenter axis and tip of the section planes).
    strain_measure : {'green_lagrange', 'log'}
        Which γmax the section figures show (and the axis labels name).
    threshold : float
        γmax threshold drawn as a contour line in the sections [-].
    bin_edges : sequence of float
        Bin edges, for the labels of the bins table when no run converged.
    reference : str
        Variant the VOI changes are relative to.

    Raises
    ------
    ValueError
        If an animal × variant has no summary.
    """
    from .pose import load_pose
    from .summary import read_summary
    from .variants import parse_variant

    summaries = [read_summary(p) for p in summary_paths]
    voi, bins = summary_tables(summaries, animals=animals, variants=variants, bin_edges=bin_edges)
    write_csv(outputs["voi_csv"], voi)
    write_csv(outputs["bins_csv"], bins)
    label = MEASURE_LABELS[strain_measure]
    plot_voi(voi, outputs["voi_png"], measure_label=label)
    plot_bins(bins, outputs["bins_png"], voi=voi)
    plot_voi_change(voi, outputs["voi_change_png"], reference=reference)

    by_key = {(s.animal, s.variant): s for s in summaries}
    pose = load_pose(pose_path)
    excl = exclusions([by_key[(figure_animal, v)] for v in variants])
    note = f" — EXCLUDED ({excl[figure_animal]})" if figure_animal in excl else ""
    results = {v: (by_key[(figure_animal, v)], figure_results[v]) for v in figure_results}
    sections = figure_sections(results, pose, strain_measure=strain_measure)
    pair = {v: sections[v] for v in ("sphere", "bar") if v in sections}
    plot_sections(
        pair,
        outputs["sections_png"],
        threshold=threshold,
        measure_label=label,
        title=f"{figure_animal}: {label} in seven planes 1 mm apart containing the indenter axis{note}",
    )
    spheres = {v: s for v, s in sections.items() if parse_variant(v).indenter == "sphere"}
    plot_sections(
        spheres,
        outputs["orientations_png"],
        columns=[2, 3, 4],
        threshold=threshold,
        measure_label=label,
        title=f"{figure_animal}: slices 3-5 for every sphere orientation{note}",
    )
