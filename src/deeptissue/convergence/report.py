"""The convergence report: summary.md, the error-vs-time figure, and rule ``convergence_aggregate``.

:func:`aggregate_convergence` reads the rows (JSON) and Snakemake's benchmark TSVs, and writes
convergence.csv (:func:`deeptissue.convergence.analysis.convergence_table`), error_vs_time.png
(:func:`plot_error_vs_time`) and summary.md (:func:`summary_markdown`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .analysis import (
    ADAPTIVE_FAMILY,
    ESTIMATES,
    adaptive_pass_errors,
    adaptive_rows,
    convergence_table,
    goal_error,
    reference_rows,
    richardson_by_family,
    scaling_fits,
    setting_table,
)
from .ladder import AccuracyGoal

log = logging.getLogger(__name__)


def _fmt(x, spec=".3g", pct=False) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    if not np.isfinite(x):
        return "–"
    return f"{100 * x:{spec}} %" if pct else f"{x:{spec}}"


def summary_markdown(
    df,
    *,
    default_name: str | None,
    goal: AccuracyGoal = AccuracyGoal(),
    notes=(),
    max_cost_ratio: float = 15.0,
    measure: str = "dofs",
    cylinder=None,
) -> str:
    """The text of ``summary.md``: cheapest setting meeting the goal in every animal and variant, the
    Pareto front, the verdict on the default, the adaptive runs against the reference (true error
    beside the estimate) and the cylinder scene (``cylinder``, rule ``verify_cylinder_adaptive``'s
    table), the Richardson orders and the fitted scaling exponents."""
    st = setting_table(df, goal=goal)
    lines = _head_lines(df, st, goal)
    lines += _sampling_lines(df, st)
    lines += _pareto_lines(st)
    lines += _default_lines(st, default_name, max_cost_ratio)
    lines += _effectivity_lines(df)
    lines += _adaptive_lines(df, goal)
    lines += _cylinder_lines(cylinder, goal)
    lines += _richardson_lines(df.to_dict("records"), measure)
    lines += _scaling_lines(df)
    failed = df[~df["converged"].astype(bool)]
    if len(failed):
        lines.append("Runs that did not converge:")
        lines.append("")
        for _, r in failed.iterrows():
            lines.append(f"- `{r['setting']}` / {r['animal']} {r['variant']}: {r['reason']}")
        lines.append("")
    for n in notes:
        lines.append(f"Note: {n}")
    return "\n".join(lines).rstrip() + "\n"


def _head_lines(df, st, goal: AccuracyGoal) -> list:
    """summary.md's title, the runs, the goal, the references and the cheapest setting meeting the goal."""
    lines = ["# Speed against error", ""]
    lines.append(
        f"Animals {', '.join(dict.fromkeys(df['animal'].astype(str)))}; variants "
        f"{', '.join(sorted(df['variant'].astype(str).unique()))}; {st.shape[0]} settings, {len(df)} runs "
        f"({int(df['converged'].astype(bool).sum())} converged)."
    )
    lines.append(
        f"Goal: VOI within {100 * goal.voi_rel_error:g} %, every bin within {goal.bin_error_pp:g} pp, "
        f"force within {100 * goal.force_rel_error:g} % of the reference (the finest converged run of each "
        "animal and variant), in every animal and variant."
    )
    lines.append("")
    refs = df[df["is_reference"].astype(bool)]
    for _, r in refs.iterrows():
        lines.append(
            f"- reference for {r['animal']} `{r['variant']}`: `{r['setting']}` ({int(r['n_dofs'])} DOFs, VOI "
            f"{_fmt(r['voi_mm3'], '.4g')} mm³, force {_fmt(r['indenter_force_N'], '.4g')} N)"
        )
    lines.append("")
    cand = st[st["meets_goal"] & ~st["is_reference"]]
    if len(cand):
        c = cand.iloc[0]
        lines.append(
            f"**Cheapest setting meeting the goal: `{c['setting']}`** ({c['family']}; {_fmt(c['wall_s'], '.1f')} s "
            f"for all variants, largest error {_fmt(c['goal_error'], '.2f')} × goal, largest cost ratio {_fmt(c['cost_ratio'], '.1f')})."
        )
    else:
        lines.append(
            "**No setting other than the reference meets the goal in every animal and variant.**"
        )
    lines.append("")
    return lines


def _sampling_lines(df, st) -> list:
    """summary.md's cheapest setting meeting the goal by each γ sampling of :data:`ESTIMATES`."""
    sampling = (
        ", ".join(sorted(df["gamma_sampling"].dropna().astype(str).unique()))
        if "gamma_sampling" in df
        else ""
    )
    each = []
    for e, what in ESTIMATES.items():
        if st[f"goal_error_{e}"].notna().any():
            cand = st[st[f"meets_goal_{e}"] & ~st["is_reference"]]
            best = (
                f"cheapest setting meeting the goal `{cand.iloc[0]['setting']}` ({_fmt(cand.iloc[0]['wall_s'], '.1f')} s, "
                f"largest error {_fmt(cand.iloc[0][f'goal_error_{e}'], '.2f')} × goal)"
                if len(cand)
                else "no setting other than the reference meets the goal"
            )
            each.append(f"- {what} (`voi_{e}_mm3`): {best}")
    if sampling and each:
        return [
            f"The errors above are those of the configured γ sampling (`study.gamma_sampling`: {sampling}). "
            "Each sampling:",
            "",
            *each,
            "",
        ]
    return []


def _pareto_lines(st) -> list:
    """summary.md's table of the settings on the Pareto front."""
    lines = [
        "Pareto front (total wall time of all variants against the largest error as a multiple of its goal):",
        "",
        "| setting | family | wall [s] | error / goal | meets goal | error / goal: points, centroid | cost ratio | peak RSS [MB] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for _, r in st[st["pareto"]].iterrows():
        lines.append(
            f"| `{r['setting']}`{' (default)' if r['is_default'] else ''}{' (reference)' if r['is_reference'] else ''} "
            f"| {r['family']} | {_fmt(r['wall_s'], '.1f')} | {_fmt(r['goal_error'], '.2f')} | "
            f"{'yes' if r['meets_goal'] else 'no'} | {_fmt(r['goal_error_sampled'], '.2f')}, "
            f"{_fmt(r['goal_error_centroid'], '.2f')} | "
            f"{_fmt(r['cost_ratio'], '.1f')} | {_fmt(r['peak_rss_mb'], '.0f')} |"
        )
    lines.append("")
    return lines


def _default_lines(st, default_name: str | None, max_cost_ratio: float) -> list:
    """summary.md's verdict on the configured default: goal, Pareto front and cost ratio."""
    lines = ["Configured default:"]
    d = st[st["setting"] == default_name] if default_name else st.iloc[0:0]
    if len(d) and bool(d.iloc[0]["is_reference"]):
        d = d.iloc[0]
        lines.append(
            f"`{default_name}` is the reference itself (the finest converged run): its error is not measured; "
            f"add finer settings to the ladder. Its cost ratio is {_fmt(d['cost_ratio'], '.1f')}."
        )
    elif len(d):
        d = d.iloc[0]
        ratio_ok = np.isfinite(d["cost_ratio"]) and d["cost_ratio"] <= max_cost_ratio
        lines.append(
            f"`{default_name}` {'meets' if d['meets_goal'] else 'does NOT meet'} the goal "
            f"(error {_fmt(d['goal_error'], '.2f')} × goal), {'sits' if d['pareto'] else 'does NOT sit'} on the "
            f"Pareto front, and its cost ratio (solve / one linear-elastic solve) is {_fmt(d['cost_ratio'], '.1f')} "
            f"({'within' if ratio_ok else 'above'} the {max_cost_ratio:g} × goal)."
        )
    else:
        lines.append(f"`{default_name}` was not run.")
    lines.append("")
    return lines


def _richardson_lines(rows, measure: str) -> list:
    """summary.md's table of the Richardson orders and extrapolations per family (:func:`richardson_by_family`)."""
    rich = richardson_by_family(rows, measure=measure)
    if not rich:
        return []
    lines = [
        f"Richardson extrapolation (three finest sizes of a family, h = {'n_dofs^(-1/3)' if measure == 'dofs' else 'element size'}):",
        "",
        "| animal | variant | family | quantity | order p | extrapolated | settings |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for x in rich:
        lines.append(
            f"| {x['animal']} | {x['variant']} | {x['family']} | {x['quantity']} | {_fmt(x['order_p'], '.2f')} | "
            f"{_fmt(x['extrapolated'], '.4g')} | {', '.join(x['settings'])} |"
        )
    lines.append("")
    return lines


def _scaling_lines(df) -> list:
    """summary.md's fitted growth of time and memory with n_dofs (:func:`scaling_fits`)."""
    fits = scaling_fits(df)
    if not fits:
        return []
    lines = [
        "Growth with n_dofs (log–log least squares over the converged runs at the default tolerance):",
        "",
    ]
    for f in fits:
        lines.append(
            f"- `{f.quantity}` ∝ n_dofs^{f.exponent:.2f} (R² {f.r2:.2f}, {f.n_points} runs)"
        )
    lines.append("")
    return lines


def _within(true, estimate) -> str:
    """'yes' where the true error is within twice its estimate, 'no' where not, '–' where either is unknown."""
    t, e = float(true), float(estimate)
    if not (np.isfinite(t) and np.isfinite(e)):
        return "–"
    return "yes" if t <= 2.0 * e else "no"


def _effectivity_lines(df) -> list:
    """summary.md's line on the runs' own error estimates against their errors from the reference: the
    effectivity (estimate / true error) range and how often the true error is within twice the estimate."""
    if "voi_effectivity" not in df:
        return []
    lines = []
    for col, what in (("voi_effectivity", "VOI"), ("bin_effectivity", "largest bin")):
        e = df[col].astype(float)
        e = e[np.isfinite(e)]
        if len(e):
            lines.append(
                f"- {what}: effectivity (own estimate / true error) {e.min():.2g}–{e.max():.2g} over {len(e)} runs; "
                f"the true error is within twice the estimate in {int((e >= 0.5).sum())} of them"
            )
    return (
        [
            "Each run's own error estimate (`voi_err_mm3`, `bins_err_pp`) against its error from the reference:",
            "",
            *lines,
            "",
        ]
        if lines
        else []
    )


def _adaptive_lines(df, goal: AccuracyGoal) -> list:
    """summary.md's table of the adaptive runs: cost, the true error against the ladder's reference and the
    run's own estimate, and whether the true error is within twice the estimate."""
    runs = df[df["family"] == ADAPTIVE_FAMILY] if "family" in df else df.iloc[0:0]
    if not len(runs):
        return []
    st = setting_table(df[df["family"] != ADAPTIVE_FAMILY], goal=goal)
    fixed = st[st["meets_goal"] & ~st["is_reference"]]
    lines = [
        "Adaptive meshes (rule `adapt_variant`, refined until their own estimate meets the goal) against the "
        "reference; true error / own estimate, and whether the true error is within twice the estimate "
        "(VOI, bins, force):",
        "",
        "| animal | variant | passes, stop | DOFs (reference) | wall [s] | VOI [%] | largest bin [pp] | force [%] | "
        "within 2 × estimate | reference's own estimate: VOI [%], bins [pp] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for _, r in runs.iterrows():
        ref = df[
            (df["animal"] == r["animal"])
            & (df["variant"] == r["variant"])
            & df["is_reference"].astype(bool)
        ]
        ref_dofs = f"{int(ref['n_dofs'].iloc[0])}" if len(ref) else "–"
        ref_est = (
            f"{_fmt(100 * float(ref['voi_err_mm3'].iloc[0]) / float(ref['voi_mm3'].iloc[0]), '.2f')}, "
            f"{_fmt(ref['bin_err_max_pp'].iloc[0], '.2f')}"
            if len(ref) and "voi_err_mm3" in ref
            else "–"
        )
        dofs = f"{int(r['n_dofs'])}" if np.isfinite(float(r.get("n_dofs") or np.nan)) else "–"
        lines.append(
            f"| {r['animal']} | {r['variant']} | {int(r['adapt_passes'])}, {r['adapt_stop_reason']} | {dofs} ({ref_dofs}) | "
            f"{_fmt(r['wall_s'], '.0f')} | {_fmt(100 * float(r['voi_rel_error']), '.2f')} / {_fmt(r['est_voi_percent'], '.2f')} | "
            f"{_fmt(r['bin_max_error_pp'], '.2f')} / {_fmt(r['est_bins_pp'], '.2f')} | "
            f"{_fmt(100 * float(r['force_rel_error']), '.2f')} / {_fmt(r['est_force_percent'], '.2f')} | "
            f"{_within(100 * float(r['voi_rel_error']), r['est_voi_percent'])}, {_within(r['bin_max_error_pp'], r['est_bins_pp'])}, "
            f"{_within(100 * float(r['force_rel_error']), r['est_force_percent'])} | {ref_est} |"
        )
    lines.append("")
    total = float(runs["wall_s"].astype(float).sum())
    met = int(runs["adapt_goal_met"].astype(bool).sum())
    lines.append(
        f"The adaptive runs take {total:.0f} s together and meet the goal by their own estimate in {met} of "
        f"{len(runs)} runs; "
        + (
            f"the cheapest fixed setting that meets it in every run, `{fixed.iloc[0]['setting']}`, "
            f"takes {fixed.iloc[0]['wall_s']:.0f} s"
            if len(fixed)
            else "no fixed setting cheaper than the reference meets it in every run"
        )
        + ". Where the reference's own estimate is not well below the adaptive run's, the difference measures the "
        "reference as much as the run."
    )
    lines.append("")
    return lines


def _cylinder_lines(cylinder, goal: AccuracyGoal) -> list:
    """summary.md's table of the cylinder scene: the fixed mesh and each adaptive run's last pass against the
    finest fixed mesh, true error / own estimate."""
    if cylinder is None or not len(cylinder):
        return []
    lines = [
        "Cylinder scene of `verify` (rule `verify_cylinder_adaptive`; reference: its finest fixed mesh), true error / "
        "own estimate:",
        "",
        "| depth [mm] | mesh | DOFs | wall [s] | VOI [%] | largest bin [pp] | force [%] | meets goal (true) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for d in sorted(cylinder["depth_mm"].unique()):
        at = cylinder[cylinder["depth_mm"] == d]
        picks = [r for _, r in at[at["kind"] == "fixed"].iterrows()]
        a = at[at["kind"] == "adaptive"].sort_values("wall_s")
        if len(a):
            picks.append(a.iloc[-1])
        for r in picks:
            tv, tb, tf = (
                abs(float(r["true_voi_percent"])),
                float(r["true_bins_pp"]),
                float(r["true_force_percent"]),
            )
            known = np.isfinite(
                tv
            )  # a depth without a VOI row (0.5, 1, 2.5 mm) is judged on its force
            met = (
                goal_error(tv / 100.0 if known else 0.0, tb if known else 0.0, tf / 100.0, goal)
                <= 1.0
            )
            name = (
                r["mesh"]
                if r["kind"] == "fixed"
                else f"adaptive, {int(r['pass_index']) + 1} passes"
            )
            lines.append(
                f"| {d:g} | {name} | {int(r['n_dofs'])} | {_fmt(r['wall_s'], '.1f')} | {_fmt(tv, '.2f')} / "
                f"{_fmt(r['est_voi_percent'], '.2f')} | {_fmt(tb, '.2f')} / {_fmt(r['est_bins_pp'], '.2f')} | "
                f"{_fmt(tf, '.2f')} / {_fmt(r.get('est_force_percent'), '.2f')} | {'yes' if met else 'no'} |"
            )
    lines.append("")
    return lines


def write_summary_md(
    path,
    df,
    *,
    default_name: str | None,
    goal: AccuracyGoal = AccuracyGoal(),
    notes=(),
    max_cost_ratio: float = 15.0,
    measure: str = "dofs",
    cylinder=None,
) -> str:
    """Write :func:`summary_markdown` to ``path`` (atomically); returns the text."""
    from ..io import atomic_path

    text = summary_markdown(
        df,
        default_name=default_name,
        goal=goal,
        notes=notes,
        max_cost_ratio=max_cost_ratio,
        measure=measure,
        cylinder=cylinder,
    )
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
    return text


_MARKERS = ["o", "s", "^", "D", "v", "P"]  # one per variant of a row of the figure
# the cylinder table's true error of each panel's column
_CYLINDER_TRUE = {
    "voi_rel_error": "true_voi_percent",
    "bin_max_error_pp": "true_bins_pp",
    "force_rel_error": "true_force_percent",
}


def _line(handles: dict, ax, x, y, label, **kw) -> None:
    """Plot the positive finite points of ``y`` against ``x``; the first line of a label is its legend handle."""
    y = np.asarray(y, float)
    m = (y > 0) & np.isfinite(y)
    if m.any():
        (h,) = ax.plot(np.asarray(x, float)[m], y[m], **kw)
        handles.setdefault(label, h)


def _plot_ladder(ax, mine, col, scale, *, families, variants, colours, handles) -> None:
    """One panel of an animal's row: a line per ladder family and variant, a star on the default."""
    for i, fam in enumerate(families):
        mk = set(mine.loc[mine["family"] == fam, "mesh_key"])
        for j, var in enumerate(variants):
            sel = mine[
                (mine["variant"] == var)
                & (
                    (mine["family"] == fam)
                    | (mine["mesh_key"].isin(mk) & fam.endswith("tolerance"))
                )
            ]
            sel = sel.sort_values("wall_s")
            _line(
                handles,
                ax,
                sel["wall_s"],
                sel[col].astype(float) * scale,
                f"{fam}, {var}",
                marker=_MARKERS[j % len(_MARKERS)],
                color=colours[i % len(colours)],
                ls="-" if j == 0 else "--",
            )
            default = sel[sel["is_default"].astype(bool)]
            _line(
                handles,
                ax,
                default["wall_s"],
                default[col].astype(float) * scale,
                "configured default",
                marker="*",
                ms=16,
                mfc="none",
                mec="k",
                ls="none",
            )


def _plot_passes(ax, passes, animal, col, scale, *, variants, handles) -> None:
    """One panel of an animal's row: each adaptive run's passes, dotted to a cross after its answer."""
    for j, var in enumerate(variants):
        a = passes[(passes["animal"] == animal) & (passes["variant"] == var)].sort_values("wall_s")
        _line(
            handles,
            ax,
            a["wall_s"],
            a[col].astype(float) * scale,
            f"adaptive, {var}",
            marker=_MARKERS[j % len(_MARKERS)],
            color="k",
            ls="-" if j == 0 else "--",
            mfc="none",
        )
        done = a[a["converged"].astype(bool)]
        if (
            len(done) and a["wall_s"].max() > done["wall_s"].iloc[-1]
        ):  # passes spent after the answer
            y = float(done[col].iloc[-1]) * scale
            _line(
                handles,
                ax,
                [done["wall_s"].iloc[-1], a["wall_s"].max()],
                [y, y],
                "adaptive: a pass that did not converge",
                color="k",
                ls=":",
                marker="x",
                markevery=[1],
            )


def _plot_cylinder(axes_row, cyl, panels, *, colours, handles) -> None:
    """The cylinder row: per depth the fixed meshes (squares) and the adaptive passes, true errors."""
    for ax, (col, label, _, g) in zip(axes_row, panels):
        for j, d in enumerate(sorted(cyl["depth_mm"].unique())):
            at = cyl[cyl["depth_mm"] == d].sort_values("wall_s")
            f, a = at[at["kind"] == "fixed"], at[at["kind"] == "adaptive"]
            _line(
                handles,
                ax,
                f["wall_s"],
                f[_CYLINDER_TRUE[col]].astype(float).abs(),
                f"cylinder {d:g} mm, fixed mesh",
                marker="s",
                ms=8,
                mfc="none",
                color=colours[(j + 3) % len(colours)],
                ls="none",
            )
            _line(
                handles,
                ax,
                a["wall_s"],
                a[_CYLINDER_TRUE[col]].astype(float).abs(),
                f"cylinder {d:g} mm, adaptive",
                marker="o",
                color=colours[(j + 3) % len(colours)],
                ls="-",
            )
        ax.set_title(f"cylinder scene: {label}", fontsize=9)


def _finish_figure(fig, axes, panels, handles: dict) -> None:
    """Log axes, goal lines, labels, the legend below the panels and the title."""
    from matplotlib.ticker import NullFormatter

    n_rows = axes.shape[0]
    for ax, (_, label, _, g) in zip(axes.ravel(), panels * n_rows):
        ax.axhline(g, color="k", ls=":", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall time [s] (adaptive: all passes so far)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    if handles:
        fig.legend(
            list(handles.values()),
            list(handles),
            loc="lower center",
            ncol=4,
            fontsize=8,
            frameon=False,
        )
    fig.suptitle(
        "Error against the finest converged run vs wall time (dotted: goal; star: configured default)",
        fontsize=10,
    )
    legend_rows = (len(handles) + 3) // 4
    fig.tight_layout(rect=(0, min(0.35, 0.025 * legend_rows * 4 / n_rows), 1, 0.97))


def plot_error_vs_time(
    path, df, *, goal: AccuracyGoal = AccuracyGoal(), passes=None, cylinder=None
) -> None:
    """Log–log error against wall time, three panels per row (VOI, largest bin error, force), one row per
    animal and one for the cylinder scene. A limb row has one line per ladder family and variant and,
    with ``passes`` (:func:`adaptive_pass_errors`), each adaptive run's passes (black, the wall time of
    the loop so far; dotted to a cross: passes after the last converged one, which did not converge); the
    cylinder row (``cylinder``: the table of rule ``verify_cylinder_adaptive``) has the fixed mesh per
    depth (squares) and the adaptive passes per depth. The goal is a dotted line;
    references (error 0) are not drawn; a star marks the configured default."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_path

    panels = [
        ("voi_rel_error", "VOI error [%]", 100.0, 100 * goal.voi_rel_error),
        ("bin_max_error_pp", "largest bin error [pp]", 1.0, goal.bin_error_pp),
        ("force_rel_error", "force error [%]", 100.0, 100 * goal.force_rel_error),
    ]
    animals = list(dict.fromkeys(df["animal"]))
    n_rows = len(animals) + (cylinder is not None and len(cylinder) > 0)
    fig, axes = plt.subplots(n_rows, 3, figsize=(14, 3.9 * n_rows + 0.9), squeeze=False)
    ok = df[df["converged"].astype(bool) & (df["family"] != ADAPTIVE_FAMILY)]
    families = list(dict.fromkeys(ok["family"]))
    variants = list(dict.fromkeys(df["variant"]))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    handles: dict = {}
    for row, animal in enumerate(animals):
        mine = ok[ok["animal"] == animal]
        for ax, (col, label, scale, g) in zip(axes[row], panels):
            _plot_ladder(
                ax,
                mine,
                col,
                scale,
                families=families,
                variants=variants,
                colours=colours,
                handles=handles,
            )
            if passes is not None and len(passes):
                _plot_passes(ax, passes, animal, col, scale, variants=variants, handles=handles)
            ax.set_title(f"{animal}: {label}", fontsize=9)
    if n_rows > len(animals):
        _plot_cylinder(axes[-1], cylinder, panels, colours=colours, handles=handles)
    _finish_figure(fig, axes, panels, handles)
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


@dataclass(frozen=True)
class ConvergenceInputs:
    """The files rule ``convergence_aggregate`` reads.

    ``row_paths``: JSON rows of rule ``convergence_run``. ``benchmark_paths``: Snakemake ``benchmark:``
    TSVs ``<animal>/<variant>_<setting>.tsv``; their time, memory and CPU time join the row of that
    animal, variant and setting (an unreadable one is logged and left out). ``adaptive_paths``:
    passes.csv of rule ``adapt_variant`` for animals and variants of the ladder: one row each
    (:func:`adaptive_rows`) and their passes on the figure. ``cylinder_path``: the cylinder scene on
    fixed and adaptive meshes (rule ``verify_cylinder_adaptive``'s table), a row of the figure and a
    table of summary.md; None: left out.
    """

    row_paths: Sequence
    benchmark_paths: Sequence = ()
    adaptive_paths: Sequence = ()
    cylinder_path: str | Path | None = None


@dataclass(frozen=True)
class ConvergenceOutputs:
    """Where rule ``convergence_aggregate`` writes convergence.csv (:func:`convergence_table`),
    error_vs_time.png (:func:`plot_error_vs_time`) and summary.md (:func:`summary_markdown`)."""

    csv_path: str | Path
    png_path: str | Path
    md_path: str | Path


def aggregate_convergence(
    inputs: ConvergenceInputs,
    outputs: ConvergenceOutputs,
    *,
    default_name: str | None,
    goal: dict | None = None,
    notes=(),
    max_cost_ratio: float = 15.0,
    measure: str = "dofs",
):
    """Rule ``convergence_aggregate``: the rows and Snakemake's benchmarks -> the table, figure and summary.

    Parameters
    ----------
    inputs : ConvergenceInputs
        The rows, benchmarks, adaptive runs and cylinder scene read.
    outputs : ConvergenceOutputs
        Where the table, the figure and the summary go.
    default_name : str or None
        Name of the configured default setting.
    goal : dict, optional
        Config ``convergence.goal`` (keys of :class:`AccuracyGoal`).
    notes : list of str
        Lines appended to summary.md.
    max_cost_ratio : float
        The cost ratio (solve / one linear-elastic solve) the default is judged against.
    measure : {"dofs", "element_size"}
        Size measure of the Richardson extrapolation.

    Returns
    -------
    DataFrame
        The table written to ``outputs.csv_path``.
    """
    import pandas as pd

    from ..io import atomic_path, read_json

    g = AccuracyGoal(**(goal or {}))
    bench = {}
    for p in inputs.benchmark_paths:
        try:
            bench[f"{Path(p).parent.name}/{Path(p).stem}"] = read_benchmark(p)
        except Exception as exc:  # a missing or empty benchmark is not a reason to lose the table
            log.warning("benchmark %s unreadable: %s", p, exc)
    rows = []
    for p in inputs.row_paths:
        r = read_json(p)
        r.update(bench.get(f"{r['animal']}/{r['variant']}_{r['setting']}", {}))
        rows.append(r)
    passes = (
        pd.concat([pd.read_csv(p) for p in inputs.adaptive_paths], ignore_index=True)
        if inputs.adaptive_paths
        else None
    )
    if passes is not None:
        rows += adaptive_rows(passes)
        passes = adaptive_pass_errors(passes, reference_rows(rows))
    cylinder = pd.read_csv(inputs.cylinder_path) if inputs.cylinder_path else None
    df = convergence_table(rows, goal=g, measure=measure)
    with atomic_path(outputs.csv_path) as tmp:
        df.to_csv(tmp, index=False)
    plot_error_vs_time(outputs.png_path, df, goal=g, passes=passes, cylinder=cylinder)
    write_summary_md(
        outputs.md_path,
        df,
        default_name=default_name,
        goal=g,
        notes=notes,
        max_cost_ratio=max_cost_ratio,
        measure=measure,
        cylinder=cylinder,
    )
    return df
