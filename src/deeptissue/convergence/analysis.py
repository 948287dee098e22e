"""Errors of the ladder's runs: against the finest converged run, Richardson, the Pareto front, scaling.

:func:`convergence_table` turns the rows into errors against the finest converged run of the same
variant (and a Richardson extrapolation where three sizes of one family allow it), the accuracy
goal and the Pareto front; :func:`setting_table` sums them per setting; :func:`scaling_fits` fits the
growth of time and memory with the number of DOFs.

Percentages in %, bin errors in percentage points (pp).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ladder import AccuracyGoal

# The two γ samplings whose errors are always tabulated (summary.GAMMA_SAMPLINGS: 'points' is 'sampled')
ESTIMATES = {"sampled": "γ at 64 points per element", "centroid": "γ at element centroids"}


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
    return Richardson(
        order_p=float(p),
        extrapolated=float(f[2] - k * h[2] ** p),
        k=float(k),
        sizes=tuple(h.tolist()),
    )


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


ADAPTIVE_FAMILY = (
    "adaptive"  # the family of runs on adaptive meshes: compared with the reference, never one
)


def _run(r: dict) -> tuple:
    """The (animal, variant) a row belongs to."""
    return (r.get("animal"), r["variant"])


def reference_rows(rows) -> dict:
    """{(animal, variant): the finest converged row of the ladder}: most DOFs, then tightest rtol and gap
    tolerance. Runs on adaptive meshes (family :data:`ADAPTIVE_FAMILY`) are measured against it, not
    candidates: their sizes are not one step of the ladder."""
    ref = {}
    for r in rows:
        if not _ok(r) or r.get("family") == ADAPTIVE_FAMILY:
            continue
        key = (
            r.get("n_dofs") or 0,
            -float(r.get("rtol") or 1.0),
            -float(r.get("gap_tol_rel") or 1.0),
        )
        cur = ref.get(_run(r))
        if cur is None or key > cur[0]:
            ref[_run(r)] = (key, r)
    return {v: k_r[1] for v, k_r in ref.items()}


def richardson_by_family(rows, *, measure: str = "dofs") -> list[dict]:
    """Richardson extrapolation of VOI and force for every animal x variant x family with >= 3 converged
    sizes at one tolerance. One dict per (animal, variant, family, quantity): order_p, extrapolated,
    sizes, settings."""
    out = []
    groups: dict = {}
    for r in rows:
        if _ok(r) and r.get("family") != ADAPTIVE_FAMILY:
            groups.setdefault(
                (r.get("animal"), r["variant"], r["family"], r.get("tolerance")), []
            ).append(r)
    for (animal, variant, family, tol), rs in sorted(
        groups.items(), key=lambda kv: tuple(str(x) for x in kv[0])
    ):
        if len({r["mesh_key"] for r in rs}) < 3:
            continue
        for q in ("voi_mm3", "voi_sampled_mm3", "voi_centroid_mm3", "indenter_force_N"):
            if all(r.get(q) is None for r in rs):
                continue
            h = [size_measure(r, measure=measure) for r in rs]
            f = [float(r[q]) if r.get(q) is not None else np.nan for r in rs]
            res = richardson_extrapolation(h, f)
            finest = sorted(rs, key=lambda r: -size_measure(r, measure=measure))[-3:]
            out.append(
                dict(
                    animal=animal,
                    variant=variant,
                    family=family,
                    tolerance=tol,
                    quantity=q,
                    order_p=None if res is None else res.order_p,
                    extrapolated=None if res is None else res.extrapolated,
                    sizes=None if res is None else list(res.sizes),
                    settings=[r["setting"] for r in finest],
                    n_sizes=len(rs),
                )
            )
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


def goal_error(
    voi_rel: float, bin_pp: float, force_rel: float, goal: AccuracyGoal = AccuracyGoal()
) -> float:
    """The largest error as a multiple of its goal: <= 1 means the goal is met (NaN if any is unknown)."""
    v = [
        voi_rel / goal.voi_rel_error,
        bin_pp / goal.bin_error_pp,
        force_rel / goal.force_rel_error,
    ]
    return (
        float("nan") if any(not np.isfinite(x) and not np.isinf(x) for x in v) else float(max(v))
    )


def convergence_table(rows, *, goal: AccuracyGoal = AccuracyGoal(), measure: str = "dofs"):
    """One row per run with its errors against the finest converged run of its animal and variant.

    Parameters
    ----------
    rows : iterable of dict
        Rows of :func:`deeptissue.convergence.runs.run_discretisation` (keys ``ROW_COLUMNS``) and of
        :func:`adaptive_rows` (family :data:`ADAPTIVE_FAMILY`).
    goal : AccuracyGoal
        The limits that ``goal_error`` divides by.
    measure : {"dofs", "element_size"}
        Size measure of the Richardson extrapolation (:func:`size_measure`).

    Returns
    -------
    DataFrame
        The rows, plus ``reference_setting`` (the finest converged run of the animal and variant, see
        :func:`reference_rows`), ``is_reference``, ``voi_rel_error`` (|VOI − VOI_ref| / VOI_ref),
        ``bin_max_error_pp`` (largest |bin % − bin %_ref|, percentage points), ``force_rel_error``,
        ``goal_error`` (largest error over its goal), ``meets_goal``, ``voi_rel_error_richardson`` and
        ``force_rel_error_richardson`` (against the Richardson extrapolation of the reference's family,
        or of the family with the most sizes, where it exists), ``meets_goal_richardson``, ``pareto``
        (not dominated in (wall_s, goal_error) among the converged runs of the animal and variant), one
        ``bin_<label>`` column per VOI bin [%], and the same errors for each γ sampling of
        :data:`ESTIMATES`. Rows that did not converge keep NaN errors.
    """
    import pandas as pd

    rows = [dict(r) for r in rows]
    refs = reference_rows(rows)
    rich_ref = _richardson_references(rows, refs, measure=measure)
    labels = []
    for r in rows:
        for k in r.get("bins_percent") or {}:
            if k not in labels:
                labels.append(k)
    for r in rows:
        ref = refs.get(_run(r))
        ok = _ok(r) and ref is not None
        _add_reference_errors(r, ref, ok=ok, rich_ref=rich_ref, goal=goal, labels=labels)
        for est in ESTIMATES:  # the errors of both γ samplings, whichever voi_mm3 is
            _add_sampling_errors(r, ref, est, ok=ok, rich_ref=rich_ref, goal=goal, labels=labels)
    df = pd.DataFrame(rows)
    df = df.drop(
        columns=[
            c
            for c in ("bins_percent", "bins_err_pp", *(f"bins_{e}_percent" for e in ESTIMATES))
            if c in df
        ]
    )
    df["pareto"] = False
    for _, idx in df.groupby(["animal", "variant"], dropna=False).groups.items():
        sub = df.loc[idx]
        conv = sub["converged"].astype(bool).to_numpy()
        m = pareto_mask(
            np.where(conv, sub["wall_s"].astype(float), np.nan), sub["goal_error"].astype(float)
        )
        df.loc[idx, "pareto"] = m
    return df


def _richardson_references(rows, refs: dict, *, measure: str) -> dict:
    """Per (animal, variant, quantity) the Richardson extrapolation the errors are taken against: that
    of the reference's family and tolerance, else that of the family with the most sizes."""
    rich = richardson_by_family(rows, measure=measure)
    rich_ref: dict = {}
    for run, ref in refs.items():
        cands = [
            x for x in rich if (x["animal"], x["variant"]) == run and x["extrapolated"] is not None
        ]
        for q in ("voi_mm3", "voi_sampled_mm3", "voi_centroid_mm3", "indenter_force_N"):
            qc = [x for x in cands if x["quantity"] == q]
            same = [
                x
                for x in qc
                if x["family"] == ref["family"] and x["tolerance"] == ref.get("tolerance")
            ]
            pick = same[0] if same else (max(qc, key=lambda x: x["n_sizes"]) if qc else None)
            if pick is not None:
                rich_ref[(*run, q)] = pick
    return rich_ref


def _add_reference_errors(r: dict, ref, *, ok: bool, rich_ref: dict, goal, labels) -> None:
    """Add to row ``r`` its errors against ``ref`` and the Richardson extrapolation, its bins
    (``bin_<label>``) and the effectivity of its own error estimate; NaN where not ``ok``."""
    r["reference_setting"] = ref["setting"] if ref is not None else None
    r["is_reference"] = ref is not None and r["setting"] == ref["setting"]
    r["voi_rel_error"] = _rel(r["voi_mm3"], ref["voi_mm3"]) if ok else float("nan")
    r["bin_max_error_pp"] = (
        _bin_error(r.get("bins_percent"), ref.get("bins_percent")) if ok else float("nan")
    )
    r["force_rel_error"] = (
        _rel(r["indenter_force_N"], ref["indenter_force_N"]) if ok else float("nan")
    )
    r["goal_error"] = (
        goal_error(r["voi_rel_error"], r["bin_max_error_pp"], r["force_rel_error"], goal)
        if ok
        else float("nan")
    )
    r["meets_goal"] = bool(ok and r["goal_error"] <= 1.0)
    rv, rf = rich_ref.get((*_run(r), "voi_mm3")), rich_ref.get((*_run(r), "indenter_force_N"))
    r["voi_rel_error_richardson"] = (
        _rel(r["voi_mm3"], rv["extrapolated"]) if (ok and rv) else float("nan")
    )
    r["force_rel_error_richardson"] = (
        _rel(r["indenter_force_N"], rf["extrapolated"]) if (ok and rf) else float("nan")
    )
    if ok and rv and rf:
        r["meets_goal_richardson"] = bool(
            goal_error(
                r["voi_rel_error_richardson"],
                r["bin_max_error_pp"],
                r["force_rel_error_richardson"],
                goal,
            )
            <= 1.0
        )
    else:
        r["meets_goal_richardson"] = None
    for k in labels:
        r[f"bin_{k}"] = (r.get("bins_percent") or {}).get(k)
    # the run's own error estimate against its error from the reference: effectivity = estimate / error
    # (the estimate bounds the error within 2 x where the effectivity is 0.5 or more)
    est_bins = [v for v in (r.get("bins_err_pp") or {}).values() if v is not None]
    r["bin_err_max_pp"] = max(est_bins) if est_bins else float("nan")
    voi_err = r.get("voi_err_mm3")
    voi_abs = abs(r["voi_mm3"] - ref["voi_mm3"]) if ok else float("nan")
    r["voi_effectivity"] = (
        voi_err / voi_abs if (ok and voi_err is not None and voi_abs > 0) else float("nan")
    )
    r["bin_effectivity"] = (
        r["bin_err_max_pp"] / r["bin_max_error_pp"]
        if ok and r["bin_max_error_pp"] > 0
        else float("nan")
    )


def _add_sampling_errors(
    r: dict, ref, est: str, *, ok: bool, rich_ref: dict, goal, labels
) -> None:
    """Add to row ``r`` the errors of γ sampling ``est`` (a key of :data:`ESTIMATES`) against ``ref``
    and its bins (``bin_<est>_<label>``); NaN where not ``ok`` or the sampling is missing."""
    voi, bins = f"voi_{est}_mm3", f"bins_{est}_percent"
    ok_e = ok and r.get(voi) is not None and ref.get(voi) is not None
    r[f"voi_{est}_rel_error"] = _rel(r.get(voi), ref[voi]) if ok_e else float("nan")
    r[f"bin_{est}_max_error_pp"] = _bin_error(r.get(bins), ref.get(bins)) if ok_e else float("nan")
    r[f"goal_error_{est}"] = (
        goal_error(
            r[f"voi_{est}_rel_error"],
            r[f"bin_{est}_max_error_pp"],
            r["force_rel_error"],
            goal,
        )
        if ok_e
        else float("nan")
    )
    r[f"meets_goal_{est}"] = bool(ok_e and r[f"goal_error_{est}"] <= 1.0)
    rs = rich_ref.get((*_run(r), voi))
    r[f"voi_{est}_rel_error_richardson"] = (
        _rel(r.get(voi), rs["extrapolated"]) if (ok_e and rs) else float("nan")
    )
    for k in labels:
        r[f"bin_{est}_{k}"] = (r.get(bins) or {}).get(k)


def setting_table(df, *, goal: AccuracyGoal = AccuracyGoal()):
    """Per setting over all animals and variants: converged everywhere, largest goal_error, summed wall time and
    solve time, largest cost_ratio and peak memory, meets_goal (in every variant) and the Pareto
    flag on (total wall, largest goal_error). A pandas DataFrame sorted by total wall time."""
    import pandas as pd

    n_var = len(df[["animal", "variant"]].drop_duplicates())
    out = []
    for name, g in df.groupby("setting", sort=False):
        conv = bool(g["converged"].astype(bool).all()) and len(g) == n_var
        out.append(
            dict(
                setting=name,
                family=g["family"].iloc[0],
                is_default=bool(g["is_default"].astype(bool).any()),
                is_reference=bool(g["is_reference"].astype(bool).any()),
                converged=conv,
                n_dofs=g["n_dofs"].max(),
                wall_s=float(g["wall_s"].astype(float).sum()),
                solve_s=float(g["solve_s"].astype(float).sum()),
                goal_error=float(g["goal_error"].astype(float).max()) if conv else float("nan"),
                **{
                    f"goal_error_{e}": (
                        float(g[f"goal_error_{e}"].astype(float).max())
                        if conv and f"goal_error_{e}" in g
                        else float("nan")
                    )
                    for e in ESTIMATES
                },
                cost_ratio=float(g["cost_ratio"].astype(float).max()),
                peak_rss_mb=float(g["peak_rss_mb"].astype(float).max()),
            )
        )
    st = pd.DataFrame(out)
    st["meets_goal"] = st["converged"] & (st["goal_error"] <= 1.0)
    for e in ESTIMATES:
        st[f"meets_goal_{e}"] = st["converged"] & (st[f"goal_error_{e}"] <= 1.0)
    st["pareto"] = pareto_mask(np.where(st["converged"], st["wall_s"], np.nan), st["goal_error"])
    return st.sort_values("wall_s", kind="stable").reset_index(drop=True)


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
    return ScalingFit(
        quantity=quantity,
        exponent=float(coef[1]),
        prefactor=float(np.exp(coef[0])),
        r2=r2,
        n_points=int(len(n)),
    )


def scaling_fits(df) -> list:
    """Growth with n_dofs of the solver wall time, the linear reference, the whole run and the memory
    (peak RSS above the process's start), over the converged runs at the default tolerance."""
    sel = df[df["converged"].astype(bool) & (df["tolerance"] == "default")]
    n = sel["n_dofs"].astype(float)
    fits = [
        scaling_fit(n, sel["solve_s"].astype(float), quantity="solve_s"),
        scaling_fit(n, sel["linear_wall_s"].astype(float), quantity="linear_wall_s"),
        scaling_fit(n, sel["wall_s"].astype(float), quantity="wall_s"),
        scaling_fit(
            n,
            sel["peak_rss_mb"].astype(float) - sel["start_rss_mb"].astype(float),
            quantity="rss_above_start_mb",
        ),
        scaling_fit(n, sel["peak_rss_mb"].astype(float), quantity="peak_rss_mb"),
    ]
    return [f for f in fits if f is not None]


def _bins_of(row) -> dict:
    """{bin label: %} from the ``bins_percent.<label>`` columns of a passes.csv row."""
    return {
        k[len("bins_percent.") :]: float(v)
        for k, v in row.items()
        if k.startswith("bins_percent.") and v is not None and np.isfinite(float(v))
    }


def adaptive_rows(passes) -> list[dict]:
    """One row per adaptive run (rule ``adapt_variant``'s passes.csv, concatenated) in the ladder's form.

    The run's answer is its last converged pass (its DOFs, VOI, bins and force; ``voi_err_mm3`` and
    ``bins_err_pp`` its own estimates); its cost is the whole loop (``wall_s``: every pass's meshing, solve
    and estimate; ``solve_s`` the passes' solves). Family :data:`ADAPTIVE_FAMILY`, setting 'adaptive'; also
    ``adapt_passes``, ``adapt_stop_reason``, ``adapt_goal_met`` and the estimates ``est_voi_percent``,
    ``est_bins_pp`` and ``est_force_percent`` (NaN where no previous pass gives the force's). A run with
    no converged pass is a row with ``converged`` false and its stop reason.
    """
    rows = []
    for (animal, variant), g in passes.groupby(["animal", "variant"], sort=False):
        g = g.sort_values("index")
        done = g[g["converged"].astype(bool)]
        stop = str(g["stop_reason"].iloc[-1]) if "stop_reason" in g else ""
        row = dict(
            animal=animal,
            variant=variant,
            setting="adaptive",
            family=ADAPTIVE_FAMILY,
            element_order=2,
            tolerance="default",
            mesh_key=f"adaptive_{animal}_{variant}",
            is_default=False,
            converged=len(done) > 0,
            reason=f"adaptive loop stopped: {stop}",
            wall_s=float(g["wall_s"].astype(float).max()),
            solve_s=float(g["solve_s"].astype(float).sum()),
            adapt_passes=len(g),
            adapt_stop_reason=stop,
            adapt_goal_met=bool(len(done) and done["goal_met"].iloc[-1]),
        )
        if len(done):
            last = done.iloc[-1].to_dict()
            voi = float(last["voi_mm3"])
            row.update(
                n_dofs=int(last["n_dofs"]),
                n_elements=int(last["n_tets"]),
                voi_mm3=voi,
                bins_percent=_bins_of(last),
                indenter_force_N=float(last["force_N"]),
                voi_err_mm3=voi * float(last["voi_err_percent"]) / 100.0,
                bins_err_pp={"largest": float(last["bins_err_pp"])},
                est_voi_percent=float(last["voi_err_percent"]),
                est_bins_pp=float(last["bins_err_pp"]),
                est_force_percent=float(last["force_err_percent"]),
            )
        rows.append(row)
    return rows


def adaptive_pass_errors(passes, refs: dict):
    """Every adaptive pass's true error against the ladder's reference of its animal and variant
    (``refs``: :func:`reference_rows`): ``voi_rel_error``, ``bin_max_error_pp`` and ``force_rel_error``
    beside the pass's own estimates (passes.csv); NaN where the pass did not converge or no reference."""
    out = passes.copy()
    cols = {"voi_rel_error": [], "bin_max_error_pp": [], "force_rel_error": []}
    for r in passes.to_dict("records"):
        ref = refs.get((r["animal"], r["variant"]))
        ok = ref is not None and bool(r["converged"])
        cols["voi_rel_error"].append(_rel(r["voi_mm3"], ref["voi_mm3"]) if ok else float("nan"))
        cols["bin_max_error_pp"].append(
            _bin_error(_bins_of(r), ref.get("bins_percent")) if ok else float("nan")
        )
        cols["force_rel_error"].append(
            _rel(r["force_N"], ref["indenter_force_N"]) if ok else float("nan")
        )
    for k, v in cols.items():
        out[k] = v
    return out
