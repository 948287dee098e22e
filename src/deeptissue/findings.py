"""The paper's claims answered by a study: one :class:`Finding` per claim, with its uncertainty and verdict.

The claims are those of Traa et al., CMBBE 2018, for the spherical indenter unless said otherwise
(:data:`CLAIMS`). Each is decided from the study's tables (``voi.csv``, ``bins.csv``: per-number error
estimates) and, for where the highest strains lie, from the ``result.vtu`` of the sphere and the bar.

How a verdict is decided (docs/method.md, section 9):

- **Only included animals count.** An animal with a variant that did not converge is excluded
  (:func:`deeptissue.report.exclusions`) and left out of every share, mean and count of claims 1–6.
- **A change is real only when it exceeds the combined error estimates of the two numbers it
  compares**, combined as their *sum* (:data:`COMBINATION`): the two solutions' errors may have
  either sign and be correlated, and the sum bounds the error of their difference whatever the
  correlation.
- **A number against a limit or a band** (97 %, 80–90 %, ±15 %): ``holds`` when the whole interval
  value ± error lies on the claim's side, ``does not hold`` when the whole interval lies on the other
  side, ``cannot tell at this accuracy`` when the interval straddles the limit or the error is unknown.
- **A mean across animals** carries the mean of the per-number error estimates plus twice the standard
  error of the mean across the animals (the spread; none with one animal). A number without a
  per-number estimate (``skin_mean_mm``) carries the spread alone and needs two animals.
- **A claim that needs an input the study lacks** (a variant, the bins edge at 0.6, skin contours, any
  included animal) is ``not applicable``, with the reason.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .fem.indenters import Indenter
from .io import atomic_path
from .pose import load_pose
from .report import pyplot, save_figure, voi_changes, write_csv
from .study import variant_indenter
from .summary import read_result_vtu
from .variants import parse_variant

__all__ = [
    "CANNOT_TELL",
    "CLAIMS",
    "COMBINATION",
    "DOES_NOT_HOLD",
    "HOLDS",
    "NOT_APPLICABLE",
    "VERDICTS",
    "Finding",
    "FindingsJob",
    "PeakLocation",
    "band_verdict",
    "findings_frame",
    "findings_markdown",
    "findings_table",
    "orientation_changes",
    "peak_location",
    "write_findings",
]

HOLDS = "holds"
DOES_NOT_HOLD = "does not hold"
CANNOT_TELL = "cannot tell at this accuracy"
NOT_APPLICABLE = "not applicable"
VERDICTS = (HOLDS, DOES_NOT_HOLD, CANNOT_TELL, NOT_APPLICABLE)
COMBINATION = "sum"  # how two numbers' error estimates combine into the error of their difference

# the claims as the paper states them (Traa et al., CMBBE 2018), by id
CLAIMS = {
    "1": "At least 97 % of the leg's volume has γmax < 0.3 (sphere).",
    "2a": "The highest strains lie in the section through the middle of the spherical indenter.",
    "2b": "For the bar the highest strains lie near its hemispherical ends, not centrally under it.",
    "3a": "A +15° offset about X or Z increases the VOI and a −15° offset decreases it, in all animals "
    "but one.",
    "3b": "The increases are larger than the decreases.",
    "4a": "The offsets change the VOI by less than 15 % in 83 % of the models.",
    "4b": "The offsets change the strain distribution within the VOI very little.",
    "5": "About 85 % of the VOI has γmax ≤ 0.6 within an animal, similar between animals (sphere).",
    "6": "Every offset fits the MRI skin contours worse than the measured orientation.",
    "7": "7 of 10 animals had all their models converge; animals with a failed model are excluded.",
}
PAPER = {
    "1": "≥ 97 % of the leg below 0.3",
    "2a": "highest strains in the middle section (Fig. 5)",
    "2b": "highest strains near the bar's ends, at one or both (Fig. 5)",
    "3a": "+15° increases, −15° decreases the VOI in all animals but one",
    "3b": "increases up to 12.8 mm³ (20 %), decreases up to 7.0 mm³ (13 %); mean change 1.40 mm³",
    "4a": "|change| < 15 % in 83 % of the models",
    "4b": "the bins change very little",
    "5": "about 85 % of the VOI has γmax ≤ 0.6, similar between animals",
    "6": "every offset fits worse (compared by eye)",
    "7": "7 of 10 animals converged in every model; the others excluded",
}

LEG_BELOW_MIN_PERCENT = 97.0  # claim 1
MIDDLE_HALF_WIDTH_MM = 0.5  # claim 2a: half the 1 mm spacing of the paper's sections
TOP_VOI_SHARE = (
    0.1  # claim 2: "the highest strains" are the tenth of the VOI with the largest γmax
)
END_SHARE_MIN = 0.5  # claim 2b: more than half of the highest strains lie near the bar's ends
SMALL_CHANGE_PERCENT = 15.0  # claim 4a
SMALL_CHANGE_SHARE = 0.83  # claim 4a: the paper's share of models
LITTLE_BIN_CHANGE_PP = 5.0  # claim 4b: "very little": no bin moves by 5 percentage points
LOW_STRAIN_EDGE = 0.6  # claim 5
LOW_STRAIN_BAND_PERCENT = (80.0, 90.0)  # claim 5: "about 85 %", ± 5 pp
CONVERGED_SHARE_MIN = 0.7  # claim 7: 7 of 10


@dataclass(frozen=True)
class Finding:
    """One claim of the paper answered by the study (a row of ``findings.csv``).

    ``value`` ± ``uncertainty`` [``unit``] is the study's headline number for the claim; ``finding``
    says it in words with the per-animal detail; ``verdict`` is one of :data:`VERDICTS` and ``reason``
    how it was decided; ``n_animals`` the included animals it rests on; ``figure`` the file name of its
    figure ("" when none).
    """

    claim_id: str
    claim: str
    paper: str
    finding: str
    value: float
    uncertainty: float
    unit: str
    verdict: str
    reason: str
    n_animals: int
    figure: str = ""

    def __post_init__(self):
        if self.verdict not in VERDICTS:
            raise ValueError(
                f"finding {self.claim_id}: verdict {self.verdict!r} not in {VERDICTS}"
            )


def _finding(claim_id: str, verdict: str, reason: str, **kw) -> Finding:
    base = dict(finding="", value=np.nan, uncertainty=np.nan, unit="", n_animals=0, figure="")
    base.update(kw)
    return Finding(
        claim_id=claim_id,
        claim=CLAIMS[claim_id],
        paper=PAPER[claim_id],
        verdict=verdict,
        reason=reason,
        **base,
    )


def _not_applicable(claim_id: str, reason: str) -> Finding:
    return _finding(claim_id, NOT_APPLICABLE, reason)


# --- decision rules ---------------------------------------------------------------------------------


def band_verdict(value: float, error: float, low: float = -np.inf, high: float = np.inf) -> str:
    """Whether ``value`` ± ``error`` lies in the band [low, high]: :data:`HOLDS` if the whole
    interval does, :data:`DOES_NOT_HOLD` if none of it does, :data:`CANNOT_TELL` if it straddles an
    edge or the value or its error is unknown (NaN)."""
    if not (np.isfinite(value) and np.isfinite(error)):
        return CANNOT_TELL
    lo, hi = value - abs(error), value + abs(error)
    if lo >= low and hi <= high:
        return HOLDS
    if hi < low or lo > high:
        return DOES_NOT_HOLD
    return CANNOT_TELL


def _all_of(verdicts: Sequence[str]) -> str:
    """A claim over several items: does not hold if any item does not, holds if every item does."""
    if any(v == DOES_NOT_HOLD for v in verdicts):
        return DOES_NOT_HOLD
    if verdicts and all(v == HOLDS for v in verdicts):
        return HOLDS
    return CANNOT_TELL


def _mean_with_uncertainty(values, errors=None) -> tuple[float, float]:
    """Mean across animals and its uncertainty: mean per-number error plus twice the standard error of
    the mean (NaN spread term with one value and no errors)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return np.nan, np.nan
    spread = 2.0 * v.std(ddof=1) / np.sqrt(v.size) if v.size > 1 else 0.0
    if errors is None:
        return float(v.mean()), float(spread) if v.size > 1 else np.nan
    e = np.asarray(errors, float)
    return float(v.mean()), float(np.mean(e) + spread) if np.isfinite(e).all() else np.nan


def _count(verdicts: Sequence[str]) -> str:
    n = len(verdicts)
    parts = [f"{sum(v == k for v in verdicts)} {k}" for k in (HOLDS, DOES_NOT_HOLD, CANNOT_TELL)]
    return f"of {n}: " + ", ".join(p for p in parts if not p.startswith("0 "))


def _pm(value: float, error: float, unit: str = "", digits: int = 1) -> str:
    u = f" {unit}" if unit else ""
    if not np.isfinite(value):
        return "undefined"
    if not np.isfinite(error):
        return f"{value:.{digits}f}{u} (error unknown)"
    return f"{value:.{digits}f} ± {error:.{digits}f}{u}"


# --- the tables the claims read -----------------------------------------------------------------------


def _numbers(df: pd.DataFrame, column: str) -> np.ndarray:
    if column not in df:
        return np.full(len(df), np.nan)
    return pd.to_numeric(df[column], errors="coerce").to_numpy(float)


def _flags(df: pd.DataFrame, column: str) -> np.ndarray:
    """A true/false column as bools (also when read from CSV as strings)."""
    return df[column].astype(str).str.lower().isin(["true", "1", "1.0"]).to_numpy()


def _included(voi: pd.DataFrame) -> pd.DataFrame:
    return voi[~_flags(voi, "excluded")] if "excluded" in voi else voi


def _offsets(variants: Sequence[str], reference: str, axes: str = "xz") -> list[str]:
    """The turned variants of the reference indenter (``sphere_rx+15`` …) about the given axes."""
    ref = parse_variant(reference)
    out = []
    for v in variants:
        try:
            p = parse_variant(str(v))
        except ValueError:
            continue
        if p.indenter == ref.indenter and (p.turn_axis or "-") in axes and p.turn_deg != 0:
            out.append(str(v))
    return out


def orientation_changes(voi: pd.DataFrame, *, reference: str = "sphere") -> pd.DataFrame:
    """:func:`deeptissue.report.voi_changes` of the included animals' offsets of the reference (about X
    or Z), with ``turn_deg`` (signed offset [deg]) and ``direction`` (the verdict that the VOI moves the
    way the offset's sign says: up for +, down for −, beyond the change's error)."""
    ch = voi_changes(_included(voi), reference=reference)
    ch = ch[ch["variant"].isin(_offsets(ch["variant"].unique(), reference))].copy()
    ch["turn_deg"] = [parse_variant(v).turn_deg for v in ch["variant"]]
    ch["direction"] = [
        band_verdict(np.sign(t) * c, e, low=0.0)
        for t, c, e in zip(
            ch["turn_deg"], _numbers(ch, "change_mm3"), _numbers(ch, "change_err_mm3")
        )
    ]
    return ch.reset_index(drop=True)


def _no_input(voi: pd.DataFrame, reference: str) -> str | None:
    """Why claims on the reference variant cannot be applied (None: they can)."""
    if reference not in set(voi["variant"]):
        return f"the study has no '{reference}' variant"
    if _included(voi).empty:
        return "no animal is included: every animal has a variant that did not converge"
    return None


# --- claims 1, 5: one number per animal against a limit ---------------------------------------------


def claim_tissue_below_threshold(voi: pd.DataFrame, *, reference: str = "sphere") -> Finding:
    """Claim 1: the share of the leg with γmax ≤ threshold, ≥ 97 % in every included animal; its error
    is ``voi_err_mm3`` over the leg's volume (VOI / (1 − share))."""
    why = _no_input(voi, reference)
    if why:
        return _not_applicable("1", why)
    ref = _included(voi)[lambda d: d["variant"] == reference]
    below, v, e = (_numbers(ref, c) for c in ("below_threshold_percent", "voi_mm3", "voi_err_mm3"))
    with np.errstate(divide="ignore", invalid="ignore"):
        leg = np.where(below < 100.0, 100.0 * v / (100.0 - below), np.nan)
        err = np.where(e == 0, 0.0, 100.0 * e / leg)
    verdicts = [band_verdict(b, x, low=LEG_BELOW_MIN_PERCENT) for b, x in zip(below, err)]
    worst = int(np.nanargmin(below)) if np.isfinite(below).any() else 0
    animals = list(ref["animal"])
    mean, u = _mean_with_uncertainty(below, err)
    return _finding(
        "1",
        _all_of(verdicts),
        f"each animal's share ± its error against {LEG_BELOW_MIN_PERCENT:g} %, "
        f"{_count(verdicts)}; the claim holds only if it holds in every included animal",
        finding=f"lowest {_pm(below[worst], err[worst], '%', 2)} ({animals[worst]}); "
        f"mean {_pm(mean, u, '%', 2)} over {len(animals)} animals",
        value=float(below[worst]),
        uncertainty=float(err[worst]),
        unit="%",
        n_animals=len(animals),
        figure="findings_tissue.png",
    )


def _bin_upper(label: str) -> float:
    return np.inf if label.startswith(">") else float(label.rsplit("-", 1)[1])


def low_strain_shares(bins: pd.DataFrame, *, edge: float = LOW_STRAIN_EDGE) -> pd.DataFrame:
    """Per animal × variant: the % of the VOI with γmax ≤ ``edge`` (the bins up to it) and its error,
    the smaller of the summed bin errors below and above the edge (either sum bounds it)."""
    labels = list(dict.fromkeys(bins["bin"]))
    upper = {b: _bin_upper(b) for b in labels}
    if not any(np.isclose(u, edge) for u in upper.values()):
        raise ValueError(f"the bins {labels} have no edge at {edge:g}")
    rows = []
    for (a, v), sub in bins.groupby(["animal", "variant"], sort=False):
        low = sub["bin"].map(lambda b: upper[b] <= edge + 1e-9).to_numpy()
        pct, err = _numbers(sub, "percent"), _numbers(sub, "err_pp")
        rows.append(
            {
                "animal": a,
                "variant": v,
                "share_percent": pct[low].sum() if np.isfinite(pct).all() else np.nan,
                "err_pp": min(err[low].sum(), err[~low].sum()),
            }
        )
    return pd.DataFrame(rows, columns=["animal", "variant", "share_percent", "err_pp"])


def claim_low_strain_share(
    voi: pd.DataFrame, bins: pd.DataFrame, *, reference="sphere"
) -> Finding:
    """Claim 5: the share of the VOI with γmax ≤ 0.6 lies within 80–90 % ("about 85 %") in every
    included animal, which also makes it similar between animals."""
    why = _no_input(voi, reference)
    if why:
        return _not_applicable("5", why)
    try:
        shares = low_strain_shares(bins)
    except ValueError as exc:
        return _not_applicable("5", str(exc))
    keep = set(_included(voi)["animal"])
    ref = shares[(shares["variant"] == reference) & shares["animal"].isin(keep)]
    s, e = _numbers(ref, "share_percent"), _numbers(ref, "err_pp")
    lo, hi = LOW_STRAIN_BAND_PERCENT
    verdicts = [band_verdict(x, y, low=lo, high=hi) for x, y in zip(s, e)]
    mean, u = _mean_with_uncertainty(s, e)
    return _finding(
        "5",
        _all_of(verdicts),
        f"each animal's share ± its error (summed bin errors) within {lo:g}–{hi:g} %, "
        f"{_count(verdicts)}",
        finding=f"mean {_pm(mean, u, '%')}, animals {np.nanmin(s):.1f}–{np.nanmax(s):.1f} % "
        f"(errors up to {np.nanmax(e):.1f} pp) over {len(s)} animals",
        value=mean,
        uncertainty=u,
        unit="%",
        n_animals=len(s),
        figure="findings_bins.png",
    )


# --- claim 2: where the highest strains lie ----------------------------------------------------------


@dataclass(frozen=True)
class PeakLocation:
    """Where the highest strains of one solution lie along the section normal ``n`` (the bar's long
    axis: the leg axis projected perpendicular to the indenter axis), measured from the final tip [mm].

    ``centre_mm``: volume-weighted mean position of the highest strains (the :data:`TOP_VOI_SHARE` of
    the VOI with the largest centroid γmax); ``uncertainty_mm``: half their mean element size (the
    edge of a regular tetrahedron of the element's volume), the resolution of a position the mesh gives;
    ``end_share``: the share of that volume at ``|s| ≥ half_length_mm / 2`` (the outer half of the bar's
    straight part and beyond), with its bounds when every position moves by the uncertainty toward or
    away from the axis; ``ends``: which ends hold at least a quarter of it (``both``, ``one``, ``none``).
    """

    centre_mm: float
    uncertainty_mm: float
    end_share: float
    end_share_low: float
    end_share_high: float
    ends: str
    n_elements: int


def peak_location(
    centroids_mm, gamma, volume_mm3, *, tip_mm, normal, threshold: float = 0.3, half_length_mm=3.5
) -> PeakLocation:
    """:class:`PeakLocation` of per-element ``gamma`` (n,) at ``centroids_mm`` (n, 3) with volumes
    ``volume_mm3`` (n,); ``normal`` the unit section normal; ``half_length_mm`` the bar's straight
    half length (the end-share boundary is half of it). NaN fields for an empty VOI."""
    g, vol = np.asarray(gamma, float), np.asarray(volume_mm3, float)
    inside = g > threshold
    if not inside.any():
        return PeakLocation(np.nan, np.nan, np.nan, np.nan, np.nan, "none", 0)
    order = np.argsort(-g[inside])
    v_sorted = vol[inside][order]
    n_top = int(np.searchsorted(np.cumsum(v_sorted), TOP_VOI_SHARE * v_sorted.sum()) + 1)
    top = np.flatnonzero(inside)[order[:n_top]]
    w = vol[top] / vol[top].sum()
    s = (np.asarray(centroids_mm, float)[top] - np.asarray(tip_mm, float)) @ np.asarray(
        normal, float
    )
    u = 0.5 * float(w @ np.cbrt(6.0 * np.sqrt(2.0) * vol[top]))
    b = 0.5 * half_length_mm
    ends = [w[s >= b].sum() >= 0.25, w[s <= -b].sum() >= 0.25]
    return PeakLocation(
        centre_mm=float(w @ s),
        uncertainty_mm=u,
        end_share=float(w[np.abs(s) >= b].sum()),
        end_share_low=float(w[np.abs(s) - u >= b].sum()),
        end_share_high=float(w[np.abs(s) + u >= b].sum()),
        ends="both" if all(ends) else ("one" if any(ends) else "none"),
        n_elements=n_top,
    )


def claim_peak_location(voi: pd.DataFrame, peaks: pd.DataFrame | None, *, shape: str) -> Finding:
    """Claim 2a (``shape`` 'sphere': the highest strains' centre within ±0.5 mm of the middle section,
    with its uncertainty) or 2b ('bar': more than half of them near the bar's ends, the bounds of that
    share on the same side of one half), in every included animal."""
    cid = "2a" if shape == "sphere" else "2b"
    why = _no_input(voi, shape)
    if why:
        return _not_applicable(cid, why)
    keep = set(_included(voi)["animal"])
    rows = (
        None if peaks is None else peaks[(peaks["variant"] == shape) & peaks["animal"].isin(keep)]
    )
    if rows is None or rows.empty:
        return _not_applicable(cid, f"no strain field (result.vtu) of '{shape}' was given")
    c, u = _numbers(rows, "centre_mm"), _numbers(rows, "uncertainty_mm")
    if shape == "sphere":
        h = MIDDLE_HALF_WIDTH_MM
        verdicts = [band_verdict(x, y, low=-h, high=h) for x, y in zip(c, u)]
        worst = int(np.nanargmax(np.abs(c))) if np.isfinite(c).any() else 0
        return _finding(
            cid,
            _all_of(verdicts),
            f"centre ± half the element size within ±{h:g} mm (the middle of seven sections 1 mm "
            f"apart), {_count(verdicts)}",
            finding=f"centre of the highest {TOP_VOI_SHARE:.0%} of the VOI {np.nanmin(c):+.2f} to "
            f"{np.nanmax(c):+.2f} mm from the middle section (resolution ± {np.nanmax(u):.2f} mm)",
            value=float(c[worst]),
            uncertainty=float(u[worst]),
            unit="mm",
            n_animals=len(c),
            figure="findings_peaks.png",
        )
    share, lo, hi = (_numbers(rows, k) for k in ("end_share", "end_share_low", "end_share_high"))
    verdicts = [
        CANNOT_TELL
        if not np.isfinite(s)
        else (
            HOLDS if a > END_SHARE_MIN else (DOES_NOT_HOLD if b <= END_SHARE_MIN else CANNOT_TELL)
        )
        for s, a, b in zip(share, lo, hi)
    ]
    ends = ", ".join(f"{a}: {e}" for a, e in zip(rows["animal"], rows["ends"]))
    return _finding(
        cid,
        _all_of(verdicts),
        f"share of the highest {TOP_VOI_SHARE:.0%} of the VOI in the outer half of the bar or beyond, "
        f"its bounds for positions moved by half the element size against {END_SHARE_MIN:.0%}, "
        f"{_count(verdicts)}",
        finding=f"share near the ends {np.nanmin(share):.0%}–{np.nanmax(share):.0%} "
        f"(bounds {np.nanmin(lo):.0%}–{np.nanmax(hi):.0%}); ends with a quarter of it: {ends}",
        value=float(np.nanmean(share)) if np.isfinite(share).any() else np.nan,
        uncertainty=float(np.nanmax(hi - lo) / 2) if np.isfinite(share).any() else np.nan,
        unit="share",
        n_animals=len(share),
        figure="findings_peaks.png",
    )


# --- claims 3, 4: the orientation offsets -------------------------------------------------------------


def claim_offset_direction(ch: pd.DataFrame) -> Finding:
    """Claim 3a: per animal, every offset moves the VOI the way its sign says beyond the change's
    error; all included animals but one (none with fewer than three) must."""
    if ch.empty:
        return _not_applicable("3a", "the study has no ±offset of the sphere about X or Z")
    per_animal = ch.groupby("animal", sort=False)["direction"].apply(lambda d: _all_of(list(d)))
    n = len(per_animal)
    spare = 1 if n >= 3 else 0
    n_hold, n_not = int((per_animal == HOLDS).sum()), int((per_animal == DOES_NOT_HOLD).sum())
    verdict = HOLDS if n_hold >= n - spare else (DOES_NOT_HOLD if n_not > spare else CANNOT_TELL)
    real = int((ch["larger_than_error"] == True).sum())  # noqa: E712 (None: undefined)
    return _finding(
        "3a",
        verdict,
        f"a change counts only beyond the sum of the two VOIs' error estimates; animals "
        f"{_count(list(per_animal))}; all but {spare} must hold",
        finding=f"{real} of {len(ch)} changes larger than their errors; "
        + "; ".join(f"{a}: {v}" for a, v in per_animal.items()),
        value=float(n_hold),
        uncertainty=float(n - n_hold - n_not),
        unit="animals",
        n_animals=n,
        figure="findings_orientation.png",
    )


def claim_increases_vs_decreases(ch: pd.DataFrame) -> Finding:
    """Claim 3b: the mean change of the + offsets against the mean |change| of the − offsets, each
    mean with its uncertainty (:func:`_mean_with_uncertainty`), compared with the sum of the two."""
    plus, minus = ch[ch["turn_deg"] > 0], ch[ch["turn_deg"] < 0]
    if plus.empty or minus.empty:
        return _not_applicable("3b", "the study needs both + and − offsets of the sphere")
    inc, u_inc = _mean_with_uncertainty(
        _numbers(plus, "change_mm3"), _numbers(plus, "change_err_mm3")
    )
    dec, u_dec = _mean_with_uncertainty(
        -_numbers(minus, "change_mm3"), _numbers(minus, "change_err_mm3")
    )
    diff, u = inc - dec, u_inc + u_dec
    c, e = _numbers(ch, "change_mm3"), _numbers(ch, "change_err_mm3")
    mean_all, u_all = _mean_with_uncertainty(c, e)
    k_up, k_down = int(np.nanargmax(c)), int(np.nanargmin(c))
    pct = _numbers(ch, "voi_change_percent")
    return _finding(
        "3b",
        band_verdict(diff, u, low=0.0),
        "mean increase of the + offsets minus mean decrease of the − offsets against the sum of "
        "their uncertainties (mean error estimate + 2 standard errors across animals each)",
        finding=f"mean + change {_pm(inc, u_inc, 'mm³', 2)}, mean − change {_pm(-dec, u_dec, 'mm³', 2)};"
        f" largest increase {_pm(c[k_up], e[k_up], 'mm³', 2)} ({pct[k_up]:+.0f} %), largest decrease "
        f"{_pm(c[k_down], e[k_down], 'mm³', 2)} ({pct[k_down]:+.0f} %); mean change "
        f"{_pm(mean_all, u_all, 'mm³', 2)}",
        value=diff,
        uncertainty=u,
        unit="mm³",
        n_animals=ch["animal"].nunique(),
        figure="findings_orientation.png",
    )


def claim_small_voi_change(ch: pd.DataFrame) -> Finding:
    """Claim 4a: the share of offset models with |change| < 15 % (each ± its error): its lower bound
    (models certainly below) at least 83 % holds, its upper bound below 83 % does not hold."""
    if ch.empty:
        return _not_applicable("4a", "the study has no offset of the sphere about X or Z")
    lim = SMALL_CHANGE_PERCENT
    per = [
        band_verdict(c, e, low=-lim, high=lim)
        for c, e in zip(_numbers(ch, "voi_change_percent"), _numbers(ch, "change_err_percent"))
    ]
    n = len(per)
    lo, hi = sum(v == HOLDS for v in per) / n, (n - sum(v == DOES_NOT_HOLD for v in per)) / n
    point = float(np.mean(np.abs(_numbers(ch, "voi_change_percent")) < lim))
    verdict = (
        HOLDS
        if lo >= SMALL_CHANGE_SHARE
        else (DOES_NOT_HOLD if hi < SMALL_CHANGE_SHARE else CANNOT_TELL)
    )
    return _finding(
        "4a",
        verdict,
        f"each model's |change| ± its error against {lim:g} %: the share lies in [{lo:.0%}, {hi:.0%}]"
        f" against the paper's {SMALL_CHANGE_SHARE:.0%}",
        finding=f"{point:.0%} of {n} models below {lim:g} % (between {lo:.0%} and {hi:.0%} with the "
        f"errors)",
        value=100 * point,
        uncertainty=100 * max(point - lo, hi - point),
        unit="%",
        n_animals=ch["animal"].nunique(),
        figure="findings_orientation.png",
    )


def bin_changes(
    bins: pd.DataFrame, ch: pd.DataFrame, *, reference: str = "sphere"
) -> pd.DataFrame:
    """Per offset model of ``ch`` and bin: the change of the bin's % against the reference [pp] and
    its error (the sum of the two bins' ``err_pp``)."""
    key = ["animal", "bin"]
    ref = bins[bins["variant"] == reference].set_index(key)
    rows = []
    for a, v in zip(ch["animal"], ch["variant"]):
        sub = bins[(bins["animal"] == a) & (bins["variant"] == v)].set_index(key)
        for k in sub.index:
            if k not in ref.index:
                continue
            d = _numbers(sub.loc[[k]], "percent")[0] - _numbers(ref.loc[[k]], "percent")[0]
            e = _numbers(sub.loc[[k]], "err_pp")[0] + _numbers(ref.loc[[k]], "err_pp")[0]
            rows.append({"animal": a, "variant": v, "bin": k[1], "change_pp": d, "err_pp": e})
    return pd.DataFrame(rows, columns=["animal", "variant", "bin", "change_pp", "err_pp"])


def claim_little_bin_change(
    bins: pd.DataFrame, ch: pd.DataFrame, *, reference="sphere"
) -> Finding:
    """Claim 4b: in every offset model every bin's % moves by less than 5 pp, each change ± the sum of
    the two bins' errors."""
    if ch.empty:
        return _not_applicable("4b", "the study has no offset of the sphere about X or Z")
    bc = bin_changes(bins, ch, reference=reference)
    if bc.empty:
        return _not_applicable("4b", "bins.csv has no bins of the offsets and the reference")
    lim = LITTLE_BIN_CHANGE_PP
    bc["verdict"] = [
        band_verdict(d, e, low=-lim, high=lim) for d, e in zip(bc["change_pp"], bc["err_pp"])
    ]
    per_model = bc.groupby(["animal", "variant"], sort=False)["verdict"].apply(
        lambda d: _all_of(list(d))
    )
    k = int(np.nanargmax(np.abs(bc["change_pp"].to_numpy(float))))
    worst = bc.iloc[k]
    return _finding(
        "4b",
        _all_of(list(per_model)),
        f"each bin's change ± the sum of the two bins' errors against ±{lim:g} pp; models "
        f"{_count(list(per_model))}",
        finding=f"largest bin change {_pm(worst['change_pp'], worst['err_pp'], 'pp')} "
        f"({worst['animal']} {worst['variant']}, bin {worst['bin']})",
        value=float(worst["change_pp"]),
        uncertainty=float(worst["err_pp"]),
        unit="pp",
        n_animals=ch["animal"].nunique(),
        figure="findings_bins.png",
    )


# --- claims 6, 7 ------------------------------------------------------------------------------------


def skin_changes(voi: pd.DataFrame, *, reference: str = "sphere") -> pd.DataFrame:
    """Per included animal and offset of the reference (any axis): ``skin_mean_mm`` of the offset
    minus that of the reference [mm] (> 0: the offset fits the skin contours worse)."""
    inc = _included(voi)
    rows = []
    for a, sub in inc.groupby("animal", sort=False):
        sub = sub.set_index("variant")
        if reference not in sub.index:
            continue
        ref = _numbers(sub.loc[[reference]], "skin_mean_mm")[0]
        for v in _offsets(sub.index, reference, axes="xyz"):
            d = _numbers(sub.loc[[v]], "skin_mean_mm")[0] - ref
            rows.append({"animal": a, "variant": v, "skin_change_mm": d})
    return pd.DataFrame(rows, columns=["animal", "variant", "skin_change_mm"])


def claim_skin_fit(voi: pd.DataFrame, *, reference: str = "sphere") -> Finding:
    """Claim 6: per offset, the mean across animals of its ``skin_mean_mm`` minus the reference's,
    ± twice its standard error (``skin_mean_mm`` has no per-number estimate): > 0 beyond it is worse."""
    why = _no_input(voi, reference)
    if why:
        return _not_applicable("6", why)
    sk = skin_changes(voi, reference=reference)
    if sk.empty:
        return _not_applicable("6", "the study has no offset of the sphere")
    if not np.isfinite(sk["skin_change_mm"]).any():
        return _not_applicable("6", "no skin_mean_mm in voi.csv (no during-scan skin contours)")
    per, text = [], []
    for v, sub in sk.groupby("variant", sort=False):
        m, u = _mean_with_uncertainty(sub["skin_change_mm"])
        per.append(band_verdict(m, u, low=0.0) if np.isfinite(u) else CANNOT_TELL)
        text.append(f"{v} {_pm(m, u, 'mm', 3)}")
    worse = int((sk["skin_change_mm"] > 0).sum())
    m_all, u_all = _mean_with_uncertainty(sk["skin_change_mm"])
    return _finding(
        "6",
        _all_of(per),
        "per offset, the mean change of skin_mean_mm against ± 2 standard errors across animals "
        f"(no per-number error estimate exists; one animal cannot tell), offsets {_count(per)}",
        finding=f"{worse} of {len(sk)} models fit worse; mean change by offset: "
        + ", ".join(text),
        value=m_all,
        uncertainty=u_all,
        unit="mm",
        n_animals=sk["animal"].nunique(),
        figure="findings_skin.png",
    )


def claim_convergence(voi: pd.DataFrame) -> Finding:
    """Claim 7: the share of animals whose every variant converged, at least 7 of 10 (a count: exact),
    and the others excluded from claims 1–6."""
    animals = list(dict.fromkeys(voi["animal"]))
    if not animals:
        return _not_applicable("7", "the study has no animal")
    excluded = (
        voi[_flags(voi, "excluded")].drop_duplicates("animal") if "excluded" in voi else voi[:0]
    )
    n_ok = len(animals) - len(excluded)
    reasons = "; ".join(
        f"{a}: {r}" for a, r in zip(excluded["animal"], excluded["exclusion_reason"])
    )
    share = n_ok / len(animals)
    return _finding(
        "7",
        HOLDS if share >= CONVERGED_SHARE_MIN else DOES_NOT_HOLD,
        f"a count, without uncertainty, against {CONVERGED_SHARE_MIN:.0%}; the excluded animals are "
        "left out of claims 1–6",
        finding=f"{n_ok} of {len(animals)} animals had every model converge"
        + (f"; excluded: {reasons}" if reasons else ""),
        value=100 * share,
        uncertainty=0.0,
        unit="%",
        n_animals=n_ok,
    )


# --- the table ---------------------------------------------------------------------------------------


def findings_table(
    voi: pd.DataFrame,
    bins: pd.DataFrame,
    peaks: pd.DataFrame | None = None,
    *,
    reference: str = "sphere",
) -> list[Finding]:
    """Every claim of :data:`CLAIMS` answered from the study's ``voi.csv`` and ``bins.csv`` tables
    (:func:`deeptissue.report.summary_tables`) and the ``peaks`` table (animal, variant and the fields
    of :class:`PeakLocation`, for claim 2; None: claim 2 not applicable)."""
    ch = (
        orientation_changes(voi, reference=reference) if reference in set(voi["variant"]) else None
    )
    ch = ch if ch is not None else pd.DataFrame(columns=["animal", "variant", "turn_deg"])
    return [
        claim_tissue_below_threshold(voi, reference=reference),
        claim_peak_location(voi, peaks, shape="sphere"),
        claim_peak_location(voi, peaks, shape="bar"),
        claim_offset_direction(ch),
        claim_increases_vs_decreases(ch),
        claim_small_voi_change(ch),
        claim_little_bin_change(bins, ch, reference=reference),
        claim_low_strain_share(voi, bins, reference=reference),
        claim_skin_fit(voi, reference=reference),
        claim_convergence(voi),
    ]


def findings_frame(findings: Sequence[Finding]) -> pd.DataFrame:
    """``findings.csv``: one row per finding, the fields of :class:`Finding` as columns."""
    return pd.DataFrame([asdict(f) for f in findings])


def findings_markdown(findings: Sequence[Finding], *, study: str) -> str:
    """``findings.md``: the table of claims, what the paper reports, what the study finds, the verdict
    and its reason, and how the verdicts are decided."""
    esc = lambda t: str(t).replace("|", "\\|")  # noqa: E731
    lines = [
        f"# Findings of study '{study}' against Traa et al., CMBBE 2018",
        "",
        "Each number carries its uncertainty: the runs' own error estimates (`voi_err_mm3`, "
        "`bins_err_pp`) and, for means across animals, twice their standard error. A change counts "
        "only when it exceeds the sum of the error estimates of the two numbers compared; animals "
        "with a variant that did not converge are left out of claims 1–6 (docs/method.md, section 9).",
        "",
        "| claim | paper | this study | verdict | how decided |",
        "| --- | --- | --- | --- | --- |",
    ]
    for f in findings:
        fig = f" ({f.figure})" if f.figure else ""
        lines.append(
            f"| {f.claim_id}. {esc(f.claim)} | {esc(f.paper)} | {esc(f.finding)}{fig} | "
            f"**{f.verdict}** | {esc(f.reason)} |"
        )
    figures = list(dict.fromkeys(f.figure for f in findings if f.figure))
    if figures:
        lines += ["", "## Figures", ""]
        lines += [f"![{name}]({name})" for name in figures]
    return "\n".join(lines) + "\n"


# --- figures ------------------------------------------------------------------------------------------


def _per_animal_axes(ax, animals, title, ylabel):
    ax.set_xticks(range(len(animals)), animals, fontsize=7)
    ax.set_xlim(-0.6, max(len(animals), 1) - 0.4)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=8)


def plot_tissue(voi: pd.DataFrame, path, *, reference: str = "sphere") -> None:
    """Claim 1: each included animal's % of the leg with γmax ≤ threshold, ± its error; the 97 % line."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ref = _included(voi)[lambda d: d["variant"] == reference]
    below, v, e = (_numbers(ref, c) for c in ("below_threshold_percent", "voi_mm3", "voi_err_mm3"))
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.where(e == 0, 0.0, e * (100.0 - below) / v)
    ax.errorbar(range(len(ref)), below, yerr=np.nan_to_num(err), fmt="o", capsize=3)
    ax.axhline(LEG_BELOW_MIN_PERCENT, color="r", lw=0.8, ls="--", label="paper: ≥ 97 %")
    ax.legend(fontsize=7)
    _per_animal_axes(
        ax, list(ref["animal"]), "Claim 1: leg volume with γmax ≤ threshold", "% of leg"
    )
    save_figure(fig, path)


def plot_peaks(peaks: pd.DataFrame | None, path) -> None:
    """Claim 2: the sphere's highest-strain centre per animal ± its resolution (±0.5 mm band: the
    middle section), and the bar's share of them near its ends with its bounds (50 % line)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, shape in zip(axes, ("sphere", "bar")):
        rows = peaks[peaks["variant"] == shape] if peaks is not None else pd.DataFrame()
        animals = list(rows["animal"]) if len(rows) else []
        if shape == "sphere" and len(rows):
            ax.errorbar(
                range(len(rows)),
                rows["centre_mm"],
                yerr=rows["uncertainty_mm"],
                fmt="o",
                capsize=3,
            )
            ax.axhspan(-MIDDLE_HALF_WIDTH_MM, MIDDLE_HALF_WIDTH_MM, color="g", alpha=0.15)
        elif len(rows):
            s = rows["end_share"].to_numpy(float)
            yerr = np.abs(np.vstack([s - rows["end_share_low"], rows["end_share_high"] - s]))
            ax.errorbar(range(len(rows)), s, yerr=yerr, fmt="o", capsize=3)
            ax.axhline(END_SHARE_MIN, color="r", lw=0.8, ls="--")
            ax.set_ylim(-0.05, 1.05)
        else:
            ax.text(0.5, 0.5, f"no '{shape}' variant", transform=ax.transAxes, ha="center")
        title = (
            "2a sphere: centre of the highest strains\nfrom the middle section (green: ±0.5 mm)"
            if shape == "sphere"
            else "2b bar: share of the highest strains\nnear its ends (line: half)"
        )
        _per_animal_axes(ax, animals, title, "mm along the leg" if shape == "sphere" else "share")
    save_figure(fig, path)


def plot_orientation(ch: pd.DataFrame, path) -> None:
    """Claims 3 and 4a: each offset's VOI change per animal in mm³ and in %, ± the sum of the two
    VOIs' errors; filled markers: larger than it; ±15 % lines."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    animals = list(dict.fromkeys(ch["animal"]))
    variants = list(dict.fromkeys(ch["variant"]))
    colours = plt.get_cmap("tab10")
    for ax, (col, err, unit) in zip(
        axes,
        [
            ("change_mm3", "change_err_mm3", "mm³"),
            ("voi_change_percent", "change_err_percent", "%"),
        ],
    ):
        for j, v in enumerate(variants):
            sub = ch[ch["variant"] == v]
            x = (
                np.array([animals.index(a) for a in sub["animal"]])
                + 0.8 * (j + 0.5) / len(variants)
                - 0.4
            )
            real = (sub["larger_than_error"] == True).to_numpy()  # noqa: E712
            c = colours(j % 10)
            y = _numbers(sub, col)
            ax.errorbar(
                x, y, yerr=np.nan_to_num(_numbers(sub, err)), fmt="none", ecolor=c, capsize=2
            )
            ax.scatter(x[real], y[real], color=c, label=v, zorder=3)
            ax.scatter(x[~real], y[~real], facecolor="white", edgecolor=c, zorder=3)
        ax.axhline(0, color="k", lw=0.6)
        if unit == "%":
            for y in (-SMALL_CHANGE_PERCENT, SMALL_CHANGE_PERCENT):
                ax.axhline(y, color="r", lw=0.8, ls="--")
        _per_animal_axes(
            ax, animals, f"VOI change against the measured orientation [{unit}]", unit
        )
    axes[0].legend(fontsize=7)
    fig.suptitle(
        "Claims 3, 4a: filled: change larger than the sum of the two error estimates; hollow: within it",
        fontsize=8,
    )
    save_figure(fig, path)


def plot_low_strain(voi: pd.DataFrame, bins: pd.DataFrame, path, *, reference="sphere") -> None:
    """Claims 5 and 4b: % of the VOI with γmax ≤ 0.6 per included animal and sphere variant ± its error;
    the 80–90 % band."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    keep = list(dict.fromkeys(_included(voi)["animal"]))
    try:
        shares = low_strain_shares(bins)
    except ValueError as exc:
        ax.text(0.5, 0.5, str(exc), transform=ax.transAxes, ha="center")
        shares = pd.DataFrame(columns=["animal", "variant", "share_percent", "err_pp"])
    variants = [reference] + _offsets(shares["variant"].unique(), reference)
    for j, v in enumerate(v for v in variants if v in set(shares["variant"])):
        sub = shares[(shares["variant"] == v) & shares["animal"].isin(keep)]
        x = np.array([keep.index(a) for a in sub["animal"]]) + 0.1 * j
        ax.errorbar(
            x,
            sub["share_percent"],
            yerr=np.nan_to_num(_numbers(sub, "err_pp")),
            fmt="o" if v == reference else ".",
            capsize=2,
            label=v,
        )
    ax.axhspan(*LOW_STRAIN_BAND_PERCENT, color="g", alpha=0.15)
    ax.legend(fontsize=7, bbox_to_anchor=(1.01, 1), loc="upper left")
    _per_animal_axes(ax, keep, "Claims 5, 4b: VOI with γmax ≤ 0.6 (green: 80–90 %)", "% of VOI")
    save_figure(fig, path)


def plot_skin(voi: pd.DataFrame, path, *, reference: str = "sphere") -> None:
    """Claim 6: each offset's skin_mean_mm minus the measured orientation's, per included animal."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    sk = skin_changes(voi, reference=reference)
    animals = list(dict.fromkeys(sk["animal"]))
    for j, (v, sub) in enumerate(sk.groupby("variant", sort=False)):
        x = np.array([animals.index(a) for a in sub["animal"]]) + 0.1 * j
        ax.plot(x, sub["skin_change_mm"], "o", label=v)
    ax.axhline(0, color="k", lw=0.6)
    if len(sk):
        ax.legend(fontsize=7, bbox_to_anchor=(1.01, 1), loc="upper left")
    _per_animal_axes(
        ax,
        animals,
        "Claim 6: skin distance of each offset minus the measured one (> 0: worse)",
        "mm",
    )
    save_figure(fig, path)


# --- the rule ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FindingsJob:
    """What rule ``findings`` reads and writes.

    ``voi_csv``, ``bins_csv``: the study's tables (rule ``aggregate``); ``results``: (animal, variant)
    -> ``result.vtu`` of the sphere and the bar, and ``poses``: animal -> ``pose.json``, for where the
    highest strains lie (claim 2); ``outputs``: paths by key, ``findings_csv``, ``findings_md`` and the
    figures ``tissue_png``, ``peaks_png``, ``orientation_png``, ``bins_png``, ``skin_png``;
    ``study``: its name (the title of findings.md); ``strain_measure``, ``threshold``: the VOI's;
    ``bar_length_mm``: the bar's length end to end (config fem.bar_length_mm); ``reference``: the
    measured orientation's variant.
    """

    voi_csv: str | Path
    bins_csv: str | Path
    outputs: Mapping[str, str | Path]
    study: str
    results: Mapping[tuple[str, str], str | Path] = field(default_factory=dict)
    poses: Mapping[str, str | Path] = field(default_factory=dict)
    strain_measure: str = "green_lagrange"
    threshold: float = 0.3
    bar_length_mm: float = 10.0
    reference: str = "sphere"


_CELL_FIELD = {"green_lagrange": "gamma_gl", "log": "gamma_log"}


def peak_table(job: FindingsJob, skip: Callable[[str, str], bool]) -> pd.DataFrame | None:
    """:class:`PeakLocation` of every given result.vtu whose run converged (``skip`` says which not),
    its section normal and centre from the variant's indenter at the end of travel."""
    half_length_mm = Indenter(kind="bar", bar_length_mm=job.bar_length_mm).bar_half_length_mm
    rows = []
    for (animal, variant), vtu in job.results.items():
        if skip(animal, variant):
            continue
        mesh, _, cells = read_result_vtu(vtu)
        ind = variant_indenter(
            load_pose(job.poses[animal]), variant, bar_length_mm=job.bar_length_mm
        )
        corners = mesh.nodes_mm[mesh.tets[:, :4]].mean(axis=1)
        loc = peak_location(
            corners,
            cells[_CELL_FIELD[job.strain_measure]],
            cells["volume_mm3"],
            tip_mm=ind.end_mm,
            normal=ind.bar_direction(),
            threshold=job.threshold,
            half_length_mm=half_length_mm,
        )
        rows.append({"animal": animal, "variant": variant, **asdict(loc)})
    return pd.DataFrame(rows) if rows else None


def write_findings(job: FindingsJob) -> list[Finding]:
    """Rule ``findings``: read the study's tables (and result.vtu files), write ``findings.csv``,
    ``findings.md`` and the claim figures (:class:`FindingsJob`); returns the findings."""
    voi, bins = pd.read_csv(job.voi_csv), pd.read_csv(job.bins_csv)
    for name, df, cols in [
        (job.voi_csv, voi, ("animal", "variant", "converged", "excluded")),
        (job.bins_csv, bins, ("animal", "variant", "bin", "percent")),
    ]:
        missing = [c for c in cols if c not in df]
        if missing:
            raise ValueError(f"{name}: no column(s) {missing}; rerun rule aggregate to rewrite it")
    failed = set(zip(voi["animal"], voi["variant"])) - set(
        zip(voi["animal"][_flags(voi, "converged")], voi["variant"][_flags(voi, "converged")])
    )
    peaks = peak_table(job, lambda a, v: (a, v) in failed)
    findings = findings_table(voi, bins, peaks, reference=job.reference)
    out = job.outputs
    write_csv(out["findings_csv"], findings_frame(findings))
    with atomic_path(out["findings_md"]) as tmp:
        Path(tmp).write_text(findings_markdown(findings, study=job.study), encoding="utf-8")
    ch = (
        orientation_changes(voi, reference=job.reference)
        if job.reference in set(voi["variant"])
        else None
    )
    plot_tissue(voi, out["tissue_png"], reference=job.reference)
    plot_peaks(peaks, out["peaks_png"])
    plot_orientation(
        ch if ch is not None else pd.DataFrame(columns=["animal", "variant"]),
        out["orientation_png"],
    )
    plot_low_strain(voi, bins, out["bins_png"], reference=job.reference)
    plot_skin(voi, out["skin_png"], reference=job.reference)
    return findings
