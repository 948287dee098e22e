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
from .mesh import TetMesh, containing_tets
from .strain import DEFAULT_BIN_EDGES, bin_labels
from .summary import Summary

__all__ = [
    "EXCLUDED_COLOUR",
    "EXCLUDED_HATCH",
    "MEASURE_LABELS",
    "AggregateJob",
    "SectionGrid",
    "Sections",
    "aggregate_study",
    "exclusions",
    "figure_sections",
    "locate_points",
    "plot_bins",
    "plot_sections",
    "plot_voi",
    "plot_voi_change",
    "pyplot",
    "sample_sections",
    "section_frame",
    "save_figure",
    "summary_tables",
    "variants_by_animal",
    "voi_changes",
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


def variants_by_animal(
    animals: Sequence[str], variants: Sequence[str] | Mapping[str, Sequence[str]]
) -> dict[str, list[str]]:
    """``{animal: its variants}`` in the configured order: ``variants`` is one list for every animal, or
    each animal's own (config ``animals.<name>.variants``, else ``study.variants``).

    Raises ValueError naming an animal that a mapping leaves out.
    """
    if isinstance(variants, Mapping):
        missing = [a for a in animals if a not in variants]
        if missing:
            raise ValueError(f"no variants given for animal(s) {', '.join(missing)}")
        return {a: list(variants[a]) for a in animals}
    return {a: list(variants) for a in animals}


def summary_tables(
    summaries: Sequence[Summary],
    *,
    animals: Sequence[str],
    variants: Sequence[str] | Mapping[str, Sequence[str]],
    bin_edges: Sequence[float] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``voi`` (one row per animal × variant, every summary field, dicts flattened as ``key.sub``, each
    error estimate right after its number) and ``bins`` (long: animal, variant, bin, percent, err_pp
    (its estimated error [percentage points]), excluded), in the configured order. ``variants``: one
    list for every animal or each animal's own (:func:`variants_by_animal`); an animal has rows for its
    own variants only. Bin labels come from the summaries, or from ``bin_edges`` when no run converged.

    Raises ValueError naming any animal × variant without a summary.
    """
    runs = [(a, v) for a, vs in variants_by_animal(animals, variants).items() for v in vs]
    by_key = {(s.animal, s.variant): s for s in summaries}
    missing = [f"{a}/{v}" for a, v in runs if (a, v) not in by_key]
    if missing:
        raise ValueError(f"no summary for {', '.join(missing)}")
    excl = exclusions([by_key[k] for k in runs])
    rows, bins = [], []
    for a, v in runs:
        s = by_key[(a, v)]
        row = {
            "animal": a,
            "variant": v,
            "excluded": a in excl,
            "exclusion_reason": excl.get(a, ""),
        }
        d = s.to_dict()
        d.pop("animal"), d.pop("variant")
        row.update(_beside_errors(_flatten(d)))
        rows.append(row)
        labels = (
            list(s.bins_percent or {})
            or _labels_from_any(summaries)
            or (bin_labels(bin_edges) if bin_edges else [])
        )
        for label in labels:
            ok = s.converged
            bins.append(
                {
                    "animal": a,
                    "variant": v,
                    "bin": label,
                    "percent": (s.bins_percent or {}).get(label, np.nan) if ok else np.nan,
                    "err_pp": (s.bins_err_pp or {}).get(label, np.nan) if ok else np.nan,
                    "excluded": a in excl,
                }
            )
    voi = pd.DataFrame(rows)
    return voi, pd.DataFrame(bins, columns=BINS_COLUMNS)


BINS_COLUMNS = ["animal", "variant", "bin", "percent", "err_pp", "excluded"]


def _beside_errors(flat: dict) -> dict:
    """The same entries with each error estimate right after its number: ``voi_err_mm3`` after
    ``voi_mm3``, ``bins_err_pp.<bin>`` after ``bins_percent.<bin>``."""
    errors = {"voi_mm3": "voi_err_mm3"}
    errors.update(
        {
            k: "bins_err_pp." + k[len("bins_percent.") :]
            for k in flat
            if k.startswith("bins_percent.")
        }
    )
    placed = set(errors.values())
    out = {}
    for k, v in flat.items():
        if k in placed:
            continue
        out[k] = v
        if k in errors and errors[k] in flat:
            out[errors[k]] = flat[errors[k]]
    out.update({k: v for k, v in flat.items() if k not in out})
    return out


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


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend (the rules run without a display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> None:
    """Write ``fig`` as PNG (120 dpi, tight), atomically, and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    pyplot().close(fig)


def _variant_colours(variants):
    cmap = pyplot().get_cmap("tab10")
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
    """Fig. 7A style: VOI [mm³] per animal, one bar per variant; excluded animals greyed and hatched; an
    animal without a variant (its own variant list) leaves that variant's place empty."""
    plt = pyplot()
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
            if v not in sub.index:
                continue  # not a variant of this animal
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
    save_figure(fig, path)


def plot_bins(bins: pd.DataFrame, path: str | Path) -> None:
    """Fig. 7B style: stacked % of the VOI per strain bin, one bar per animal × variant of the table (an
    animal's own variants only); the largest estimated bin error (the ``err_pp`` column of
    :func:`summary_tables`' bins) is written above each bar."""
    plt = pyplot()
    animals = list(dict.fromkeys(bins["animal"]))
    variants = list(dict.fromkeys(bins["variant"]))
    labels = list(dict.fromkeys(bins["bin"]))
    cmap = plt.get_cmap("viridis")
    colours = {b: cmap(k / max(1, len(labels) - 1)) for k, b in enumerate(labels)}
    errs = bins.assign(err=_numbers(bins, "err_pp")).groupby(["animal", "variant"], sort=False)[
        "err"
    ]
    worst_err = {k: float(e.max()) for k, e in errs if np.isfinite(e).any()}
    fig, ax = plt.subplots(figsize=(max(6, 0.35 * len(animals) * len(variants) + 2), 4))
    x, ticks, ticklabels = 0.0, [], []
    for a in animals:
        for v in variants:
            sub = bins[(bins["animal"] == a) & (bins["variant"] == v)].set_index("bin")
            if not len(sub):
                continue  # not a variant of this animal
            excluded = bool(sub["excluded"].iloc[0])
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
            pcts = sub["percent"].to_numpy(float)
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
    save_figure(fig, path)


def _numbers(df: pd.DataFrame, column: str) -> np.ndarray:
    """A column as floats (NaN where empty or absent: a table without error estimates)."""
    if column not in df:
        return np.full(len(df), np.nan)
    return pd.to_numeric(df[column], errors="coerce").to_numpy(float)


VOI_CHANGE_COLUMNS = [
    "animal",
    "variant",
    "voi_mm3",
    "reference_voi_mm3",
    "change_mm3",
    "change_err_mm3",
    "voi_change_percent",
    "change_err_percent",
    "larger_than_error",
    "excluded",
    "exclusion_reason",
]


def voi_changes(voi: pd.DataFrame, *, reference: str = "sphere") -> pd.DataFrame:
    """The VOI change of every variant ≠ ``reference`` against it, per animal, with its uncertainty.

    ``change_mm3`` = VOI − VOI_reference; ``change_err_mm3`` = ``voi_err_mm3`` of the variant plus that
    of the reference (the sum of the two error estimates: the errors of two solutions on related meshes
    may have either sign, and their sum bounds the error of the difference whatever the correlation);
    ``voi_change_percent`` = 100 · change / VOI_reference and ``change_err_percent`` = 100 ·
    change_err / VOI_reference [%]. ``larger_than_error`` is True where |change| > change_err, False
    where not, and NaN (missing) where either is undefined (a variant not converged, an empty
    reference VOI, no error estimate).
    """
    rows = []
    for a, sub in voi.groupby("animal", sort=False):
        sub = sub.set_index("variant")
        if reference not in sub.index:
            continue
        vals, errs = _numbers(sub, "voi_mm3"), _numbers(sub, "voi_err_mm3")
        i_ref = list(sub.index).index(reference)
        ref, ref_err = vals[i_ref], errs[i_ref]
        for k, v in enumerate(sub.index):
            if v == reference:
                continue
            change, err = vals[k] - ref, errs[k] + ref_err
            defined = np.isfinite(ref) and ref > 0 and np.isfinite(vals[k])
            rows.append(
                {
                    "animal": a,
                    "variant": v,
                    "voi_mm3": vals[k],
                    "reference_voi_mm3": ref,
                    "change_mm3": change if defined else np.nan,
                    "change_err_mm3": err if defined else np.nan,
                    "voi_change_percent": 100.0 * change / ref if defined else np.nan,
                    "change_err_percent": 100.0 * err / ref if defined else np.nan,
                    "larger_than_error": bool(abs(change) > err)
                    if defined and np.isfinite(err)
                    else None,
                    "excluded": bool(sub["excluded"].iloc[0]),
                    "exclusion_reason": sub["exclusion_reason"].iloc[0],
                }
            )
    return pd.DataFrame(rows, columns=VOI_CHANGE_COLUMNS)


def plot_voi_change(voi: pd.DataFrame, path: str | Path, *, reference: str = "sphere") -> None:
    """VOI change of every other orientation of the reference indenter (variants named
    ``<reference>_…``, e.g. ``sphere_rx+15``) against the estimated orientation per animal [%], with its
    uncertainty as error bar (:func:`voi_changes`); a change larger than its uncertainty is drawn solid
    and marked ``*``, one within it pale; an animal without an orientation (its own variant list) leaves
    its place empty, one with none says so. Other indenters (the bar, several times the sphere's VOI) would set the scale and
    hide the orientations (their change is in :func:`voi_changes`)."""
    plt = pyplot()
    ch = voi_changes(voi, reference=reference)
    animals = list(dict.fromkeys(voi["animal"]))
    all_variants = list(dict.fromkeys(voi["variant"]))
    variants = [v for v in all_variants if v != reference and v.startswith(f"{reference}_")]
    colours = _variant_colours(all_variants)
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(animals) + 2), 4))
    width = 0.8 / max(1, len(variants))
    shown = ch[ch["variant"].isin(variants)]
    ends = np.concatenate(
        [
            _numbers(shown, "voi_change_percent") + _numbers(shown, "change_err_percent"),
            _numbers(shown, "voi_change_percent") - _numbers(shown, "change_err_percent"),
            _numbers(shown, "voi_change_percent"),
        ]
    )
    hi = max(10.0, 1.3 * float(np.nanmax(ends, initial=0.0)))
    lo = min(-10.0, 1.3 * float(np.nanmin(ends, initial=0.0)))
    n_real = int((shown["larger_than_error"] == True).sum())  # noqa: E712 (None: undefined)
    n_defined = int(shown["larger_than_error"].notna().sum())
    runs = set(zip(voi["animal"], voi["variant"]))
    for i, a in enumerate(animals):
        sub = ch[ch["animal"] == a].set_index("variant")
        excluded = bool(sub["excluded"].iloc[0]) if len(sub) else False
        if variants and not any((a, v) in runs for v in variants):
            ax.text(i, 0, "no turned variant", ha="center", va="bottom", fontsize=6, color="0.3")
        for j, v in enumerate(variants):
            if (a, v) not in runs:
                continue  # not a variant of this animal
            x = i - 0.4 + width * (j + 0.5)
            val = float(sub.loc[v, "voi_change_percent"]) if v in sub.index else np.nan
            if not np.isfinite(val):
                ax.plot(x, 0, marker="x", color="k", ms=5)
                continue
            err = float(sub.loc[v, "change_err_percent"])
            real = sub.loc[v, "larger_than_error"] == True  # noqa: E712 (None: undefined)
            ax.bar(
                x,
                val,
                width,
                color=EXCLUDED_COLOUR if excluded else colours[v],
                hatch=EXCLUDED_HATCH if excluded else None,
                edgecolor="0.4" if excluded else "none",
                alpha=1.0 if real else 0.35,
                yerr=err if np.isfinite(err) else None,
                error_kw=dict(elinewidth=0.8, capsize=2, ecolor="k"),
            )
            if real:
                top = val + err if val >= 0 else val - err
                ax.text(x, top, "*", ha="center", va="bottom" if val >= 0 else "top", fontsize=9)
        if excluded:
            _mark_excluded(ax, i, sub["exclusion_reason"].iloc[0], 0.98 * hi)
    ax.axhline(0, color="k", lw=0.8)
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[v]) for v in variants]
    ax.legend(handles, variants, fontsize=7, bbox_to_anchor=(1.01, 1), loc="upper left")
    ax.set_xticks(range(len(animals)), animals)
    ax.set_xlim(-0.6, len(animals) - 0.4)
    ax.set_ylim(lo, hi)
    ax.set_ylabel(f"VOI change vs '{reference}' [%]")
    ax.set_title(
        f"VOI of each orientation relative to the estimated one '{reference}' (x: undefined)\n"
        f"error bar: sum of the two VOIs' estimated errors; * (solid): change larger than it, "
        f"{n_real} of {n_defined}",
        fontsize=9,
    )
    save_figure(fig, path)


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
    (:func:`deeptissue.mesh.containing_tets`). ``points_mm`` (..., 3) -> (...) int."""
    P = np.asarray(points_mm, float)
    return containing_tets(mesh, P, tol=tol).reshape(P.shape[:-1])


@dataclass(frozen=True)
class Sections:
    """γmax sampled on parallel planes containing the indenter axis (reference configuration)."""

    values: np.ndarray  # (n_sections, n_v, n_u) γ, NaN outside the mesh
    offsets_mm: np.ndarray  # (n_sections,) plane offset along n from the tip [mm]
    u_mm: np.ndarray  # (n_u,) in-plane coordinate across the indenter (along e) [mm]
    v_mm: np.ndarray  # (n_v,) in-plane coordinate along the indenter axis, + into the leg [mm]


@dataclass(frozen=True)
class SectionGrid:
    """Where :func:`sample_sections` samples: ``n_sections`` planes ``spacing_mm`` apart (the paper's
    seven planes 1 mm apart), each a grid ``u ∈ [−half_width_mm, half_width_mm]`` across the indenter and
    ``v ∈ v_range_mm`` along its axis from the tip (+ into the leg) [mm], ``resolution_mm`` apart
    (0.1 mm: finer than the smallest element of the default meshes)."""

    n_sections: int = 7
    spacing_mm: float = 1.0
    half_width_mm: float = 6.0
    v_range_mm: tuple[float, float] = (-2.0, 8.0)
    resolution_mm: float = 0.1


def sample_sections(
    mesh: TetMesh,
    gamma,
    *,
    axis,
    tip_mm,
    grid: SectionGrid = SectionGrid(),
    leg_axis=(0.0, 0.0, 1.0),
) -> Sections:
    """Sample per-element ``gamma`` (n_tets,) on ``grid.n_sections`` planes through the indenter axis.

    Plane ``k`` contains the line ``tip_mm + t·axis`` moved by ``offsets_mm[k]·n`` with offsets
    ``spacing·(k − (n_sections − 1)/2)``; the grid spans ``u ∈ [−half_width, half_width]`` along
    ``e`` and ``v ∈ v_range`` along the axis from ``tip_mm`` (:class:`SectionGrid`).
    """
    g = np.asarray(gamma, float)
    if g.shape != (mesh.n_tets,):
        raise ValueError(
            f"gamma: expected one value per element ({mesh.n_tets}), got shape {g.shape}"
        )
    a, e, n = section_frame(axis, leg_axis=leg_axis)
    tip = np.asarray(tip_mm, float)
    offsets = grid.spacing_mm * (np.arange(grid.n_sections) - (grid.n_sections - 1) / 2)
    step = grid.resolution_mm
    u = np.arange(-grid.half_width_mm, grid.half_width_mm + 0.5 * step, step)
    v = np.arange(grid.v_range_mm[0], grid.v_range_mm[1] + 0.5 * step, step)
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
    plt = pyplot()
    from matplotlib.colors import Normalize

    names = list(sections)
    if not names:
        fig, ax = plt.subplots(figsize=(5, 2))
        ax.axis("off")
        ax.text(0.5, 0.5, "no variant of this kind is configured", ha="center", va="center")
        if title:
            fig.suptitle(title, fontsize=9)
        save_figure(fig, path)
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
    save_figure(fig, path)


# --- the whole aggregate step ------------------------------------------------------------------------

MEASURE_LABELS = {"green_lagrange": "γmax (Green–Lagrange)", "log": "γmax (logarithmic)"}
_CELL_FIELD = {"green_lagrange": "gamma_gl", "log": "gamma_log"}


def figure_sections(
    results: Mapping[str, tuple[Summary, str | Path]],
    pose,
    *,
    strain_measure: str = "green_lagrange",
    grid: SectionGrid = SectionGrid(),
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
        out[name] = sample_sections(mesh, cells[field], axis=axis, tip_mm=start, grid=grid)
    return out


@dataclass(frozen=True)
class AggregateJob:
    """What rule ``aggregate`` reads and writes.

    ``summary_paths``: every ``summary.json`` of the study (:func:`deeptissue.summary.read_summary`);
    ``animals``, ``variants``: the configured order of the tables and figures, each animal with a summary of
    each of its variants (``variants``: one list for every animal, or ``{animal: its own}``,
    :func:`variants_by_animal`);
    ``outputs``: paths by key, ``voi_csv``, ``bins_csv`` (:func:`summary_tables`), ``voi_png``,
    ``bins_png``, ``voi_change_png``, ``sections_png`` (sphere vs bar, seven sections) and
    ``orientations_png`` (sections 3–5 of every sphere variant); ``figure_animal``: the animal of the
    section figures, ``figure_results``: variant -> its ``result.vtu``, ``pose_path``: its pose (indenter
    axis and tip of the section planes); ``strain_measure``: the γmax the sections show; ``threshold``:
    the γmax drawn as a contour line [-]; ``bin_edges``: for the bin labels when no run converged;
    ``reference``: the variant the VOI changes are relative to (the estimated orientation).
    """

    summary_paths: Sequence[str | Path]
    animals: Sequence[str]
    variants: Sequence[str] | Mapping[str, Sequence[str]]
    outputs: Mapping[str, str | Path]
    figure_animal: str
    figure_results: Mapping[str, str | Path]
    pose_path: str | Path
    strain_measure: str = "green_lagrange"
    threshold: float = 0.3
    bin_edges: Sequence[float] = DEFAULT_BIN_EDGES
    reference: str = "sphere"


def aggregate_study(job: AggregateJob) -> None:
    """Rule ``aggregate``: read every summary, write the tables and the figures of the study
    (:class:`AggregateJob`). ValueError if an animal × variant has no summary."""
    from .summary import read_summary

    summaries = [read_summary(p) for p in job.summary_paths]
    voi, bins = summary_tables(
        summaries, animals=job.animals, variants=job.variants, bin_edges=job.bin_edges
    )
    out = job.outputs
    write_csv(out["voi_csv"], voi)
    write_csv(out["bins_csv"], bins)
    label = MEASURE_LABELS[job.strain_measure]
    plot_voi(voi, out["voi_png"], measure_label=label)
    plot_bins(bins, out["bins_png"])
    plot_voi_change(voi, out["voi_change_png"], reference=job.reference)
    _write_section_figures(job, {(s.animal, s.variant): s for s in summaries}, label)


def _write_section_figures(job: AggregateJob, by_key: Mapping, label: str) -> None:
    """``sections_png`` and ``orientations_png`` of :class:`AggregateJob` for its figure animal."""
    from .pose import load_pose
    from .variants import parse_variant

    animal, out = job.figure_animal, job.outputs
    own = variants_by_animal([animal], job.variants)[animal]
    excl = exclusions([by_key[(animal, v)] for v in own])
    note = f" — EXCLUDED ({excl[animal]})" if animal in excl else ""
    results = {v: (by_key[(animal, v)], job.figure_results[v]) for v in job.figure_results}
    sections = figure_sections(
        results, load_pose(job.pose_path), strain_measure=job.strain_measure
    )
    pair = {v: sections[v] for v in ("sphere", "bar") if v in sections}
    plot_sections(
        pair,
        out["sections_png"],
        threshold=job.threshold,
        measure_label=label,
        title=f"{animal}: {label} in seven planes 1 mm apart containing the indenter axis{note}",
    )
    spheres = {v: s for v, s in sections.items() if parse_variant(v).indenter == "sphere"}
    plot_sections(
        spheres,
        out["orientations_png"],
        columns=[2, 3, 4],
        threshold=job.threshold,
        measure_label=label,
        title=f"{animal}: slices 3-5 for every sphere orientation{note}",
    )
