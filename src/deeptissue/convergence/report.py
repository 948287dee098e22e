"""The convergence report: summary.md, the error-vs-time figure, and rule ``convergence_aggregate``.

:func:`aggregate_convergence` reads the rows (JSON) and Snakemake's benchmark TSVs, and writes
convergence.csv (:func:`deeptissue.convergence.analysis.convergence_table`), error_vs_time.png
(:func:`plot_error_vs_time`) and summary.md (:func:`summary_markdown`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .analysis import ESTIMATES, convergence_table, richardson_by_family, scaling_fits, setting_table
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
    from ..io import atomic_path

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

    from ..io import atomic_path

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
    """Rule ``convergence_aggregate``: the rows and Snakemake's benchmarks -> the table, figure and summary.

    Parameters
    ----------
    row_paths : list of path
        JSON rows of rule ``convergence_run``.
    benchmark_paths : list of path
        Snakemake ``benchmark:`` TSVs named ``<variant>_<setting>.tsv``; their time, memory and CPU
        time join the row of that variant and setting (an unreadable one is logged and left out).
    csv_path, png_path, md_path : path
        Where convergence.csv (:func:`convergence_table`), error_vs_time.png
        (:func:`plot_error_vs_time`) and summary.md (:func:`summary_markdown`) go.
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
        The table written to ``csv_path``.
    """
    from ..io import atomic_path, read_json

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
