"""The findings table built from hand-made voi.csv / bins.csv tables whose answers are known."""

import numpy as np
import pandas as pd
import pytest

from deeptissue.findings import (
    CANNOT_TELL,
    DOES_NOT_HOLD,
    HOLDS,
    NOT_APPLICABLE,
    FindingsJob,
    band_verdict,
    claim_convergence,
    claim_peak_location,
    findings_table,
    peak_location,
    write_findings,
)

LABELS = ["0.3-0.4", "0.4-0.5", "0.5-0.6", "0.6-0.7", "0.7-0.8", "0.8-0.9", "0.9-1.0", ">1.0"]


def _tables(tmp_path, runs, failed=()):
    """voi.csv and bins.csv written by hand and read back as rule findings reads them.

    ``runs``: {(animal, variant): dict(voi, err, below, skin, low, bin_err)} where ``low`` is the % of the
    VOI in 0.3-0.4 (the rest in >1.0); ``failed``: (animal, variant) that did not converge.
    """
    excluded = {a for a, _ in failed}
    voi, bins = [], []
    for (a, v), r in runs.items():
        ok = (a, v) not in failed
        voi.append(
            {
                "animal": a,
                "variant": v,
                "excluded": a in excluded,
                "exclusion_reason": "not converged: bar: diverged" if a in excluded else "",
                "converged": ok,
                "voi_mm3": r.get("voi", 10.0) if ok else np.nan,
                "voi_err_mm3": r.get("err", 0.1) if ok else np.nan,
                "below_threshold_percent": r.get("below", 99.0) if ok else np.nan,
                "skin_mean_mm": r.get("skin", 0.1) if ok else np.nan,
            }
        )
        for label in LABELS:
            low = r.get("low", 85.0)
            pct = {"0.3-0.4": low, ">1.0": 100.0 - low}.get(label, 0.0)
            bins.append(
                {
                    "animal": a,
                    "variant": v,
                    "bin": label,
                    "percent": pct if ok else np.nan,
                    "err_pp": r.get("bin_err", 0.2) if ok else np.nan,
                    "excluded": a in excluded,
                }
            )
    pd.DataFrame(voi).to_csv(tmp_path / "voi.csv", index=False)
    pd.DataFrame(bins).to_csv(tmp_path / "bins.csv", index=False)
    return pd.read_csv(tmp_path / "voi.csv"), pd.read_csv(tmp_path / "bins.csv")


def _by_id(findings):
    return {f.claim_id: f for f in findings}


def _orientation_study(changes, animals=("r1", "r2", "r3"), err=0.1, **sphere):
    """Every animal: sphere VOI 10 mm³ and one run per offset with VOI 10 + change (``changes``:
    {variant: change [mm³]} or {variant: [change per animal]})."""
    runs = {}
    for i, a in enumerate(animals):
        runs[(a, "sphere")] = dict(voi=10.0, err=err, **sphere)
        for v, d in changes.items():
            runs[(a, v)] = dict(voi=10.0 + (d[i] if isinstance(d, list) else d), err=err)
    return runs


def test_band_verdict_decides_on_the_whole_interval():
    assert band_verdict(98.0, 0.5, low=97.0) == HOLDS
    assert band_verdict(96.0, 0.5, low=97.0) == DOES_NOT_HOLD
    assert band_verdict(97.2, 0.5, low=97.0) == CANNOT_TELL
    assert band_verdict(97.2, np.nan, low=97.0) == CANNOT_TELL
    assert band_verdict(85.0, 1.0, low=80.0, high=90.0) == HOLDS
    assert band_verdict(95.0, 1.0, low=80.0, high=90.0) == DOES_NOT_HOLD


def test_a_change_inside_its_errors_cannot_tell(tmp_path):
    # +0.15 and -0.15 mm³ against 0.1 + 0.1 = 0.2 mm³ of combined error: inside
    voi, bins = _tables(
        tmp_path, _orientation_study({"sphere_rx+15": 0.15, "sphere_rx-15": -0.15})
    )
    f = _by_id(findings_table(voi, bins))
    assert f["3a"].verdict == CANNOT_TELL
    assert "0 of 6 changes larger" in f["3a"].finding
    # the same changes with errors of 0.05 each (0.1 combined) are real: +15 up, -15 down
    voi, bins = _tables(
        tmp_path, _orientation_study({"sphere_rx+15": 0.15, "sphere_rx-15": -0.15}, err=0.05)
    )
    assert _by_id(findings_table(voi, bins))["3a"].verdict == HOLDS


def test_offset_direction_allows_one_animal_but_not_two(tmp_path):
    wrong_one = {"sphere_rz+15": [1.0, 1.0, -1.0], "sphere_rz-15": -1.0}
    voi, bins = _tables(tmp_path, _orientation_study(wrong_one))
    assert _by_id(findings_table(voi, bins))["3a"].verdict == HOLDS
    wrong_two = {"sphere_rz+15": [1.0, -1.0, -1.0], "sphere_rz-15": -1.0}
    voi, bins = _tables(tmp_path, _orientation_study(wrong_two))
    assert _by_id(findings_table(voi, bins))["3a"].verdict == DOES_NOT_HOLD


def test_increases_against_decreases(tmp_path):
    # equal across animals: no spread, the uncertainty is the mean combined error 0.2 + 0.2
    voi, bins = _tables(tmp_path, _orientation_study({"sphere_rx+15": 2.0, "sphere_rx-15": -0.5}))
    f = _by_id(findings_table(voi, bins))["3b"]
    assert f.verdict == HOLDS
    assert (f.value, f.uncertainty) == (pytest.approx(1.5), pytest.approx(0.4))
    voi, bins = _tables(tmp_path, _orientation_study({"sphere_rx+15": 0.5, "sphere_rx-15": -2.0}))
    assert _by_id(findings_table(voi, bins))["3b"].verdict == DOES_NOT_HOLD
    voi, bins = _tables(tmp_path, _orientation_study({"sphere_rx+15": 1.0, "sphere_rx-15": -0.8}))
    assert _by_id(findings_table(voi, bins))["3b"].verdict == CANNOT_TELL


def test_an_excluded_animal_is_left_out_of_the_shares(tmp_path):
    # r1-r3 change by 1 % (certainly below 15 %); r4 by 50 %, but its bar failed: excluded
    runs = _orientation_study({"sphere_rx+15": 0.1, "sphere_rx-15": -0.1}, err=0.01)
    runs.update(_orientation_study({"sphere_rx+15": 5.0, "sphere_rx-15": -5.0}, animals=["r4"]))
    runs[("r4", "sphere")]["low"] = 50.0  # would also fail claim 5
    runs[("r4", "bar")] = {}
    for a in ("r1", "r2", "r3"):
        runs[(a, "bar")] = {}
    voi, bins = _tables(tmp_path, runs, failed=[("r4", "bar")])
    f = _by_id(findings_table(voi, bins))
    assert f["4a"].verdict == HOLDS and f["4a"].value == pytest.approx(100.0)
    assert f["4a"].n_animals == 3 and "of 6 models" in f["4a"].finding
    assert f["5"].verdict == HOLDS and f["5"].n_animals == 3
    assert f["7"].finding.startswith("3 of 4 animals") and "r4: not converged" in f["7"].finding
    assert f["7"].verdict == HOLDS  # 75 % >= 70 %
    # with r4 included its changes of 50 % take the share to 75 %, below the paper's 83 %
    voi, bins = _tables(tmp_path, runs)
    f = _by_id(findings_table(voi, bins))
    assert f["4a"].verdict == DOES_NOT_HOLD and f["4a"].value == pytest.approx(75.0)
    assert f["5"].verdict == DOES_NOT_HOLD


def test_a_missing_variant_is_not_applicable(tmp_path):
    voi, bins = _tables(tmp_path, {("r1", "sphere"): {}, ("r2", "sphere"): {}})
    f = _by_id(findings_table(voi, bins))
    for cid in ("2b", "3a", "3b", "4a", "4b", "6"):
        assert f[cid].verdict == NOT_APPLICABLE, cid
    assert "no 'bar' variant" in f["2b"].reason
    assert f["1"].verdict == HOLDS and f["5"].verdict == HOLDS
    # only + offsets: the comparison of increases and decreases needs both
    voi, bins = _tables(tmp_path, _orientation_study({"sphere_rx+15": 1.0}))
    assert _by_id(findings_table(voi, bins))["3b"].verdict == NOT_APPLICABLE
    # no sphere at all: every claim on it
    voi, bins = _tables(tmp_path, {("r1", "bar"): {}})
    f = _by_id(findings_table(voi, bins))
    assert {f[c].verdict for c in ("1", "2a", "3a", "4a", "5", "6")} == {NOT_APPLICABLE}
    assert "no 'sphere' variant" in f["1"].reason


def test_limits_per_animal_hold_and_do_not_hold(tmp_path):
    # claim 1: the leg below threshold; the error is voi_err over the leg volume: 1 mm³ of a
    # 1000 mm³ leg (VOI 10 mm³ = 1 %) is 0.1 pp
    voi, bins = _tables(tmp_path, {("r1", "sphere"): dict(voi=10.0, err=1.0, below=99.0)})
    f = _by_id(findings_table(voi, bins))["1"]
    assert f.verdict == HOLDS and f.uncertainty == pytest.approx(0.1)
    voi, bins = _tables(tmp_path, {("r1", "sphere"): dict(voi=50.0, err=1.0, below=95.0)})
    assert _by_id(findings_table(voi, bins))["1"].verdict == DOES_NOT_HOLD
    # 97.05 % ± 0.1 pp straddles the limit
    voi, bins = _tables(tmp_path, {("r1", "sphere"): dict(voi=29.5, err=1.0, below=97.05)})
    assert _by_id(findings_table(voi, bins))["1"].verdict == CANNOT_TELL
    # claim 5: 85 % in the band, 95 % outside; 89.5 % ± (3 bins x 0.2 pp) straddles 90 %
    for low, verdict in [(85.0, HOLDS), (95.0, DOES_NOT_HOLD), (89.5, CANNOT_TELL)]:
        voi, bins = _tables(tmp_path, {(a, "sphere"): dict(low=low) for a in ("r1", "r2")})
        assert _by_id(findings_table(voi, bins))["5"].verdict == verdict, low


def test_bin_changes_little_or_not(tmp_path):
    runs = _orientation_study({"sphere_rx+15": 1.0}, low=85.0)
    for a in ("r1", "r2", "r3"):
        runs[(a, "sphere_rx+15")]["low"] = 86.0
    voi, bins = _tables(tmp_path, runs)
    f = _by_id(findings_table(voi, bins))["4b"]
    assert f.verdict == HOLDS and abs(f.value) == pytest.approx(1.0)
    assert f.uncertainty == pytest.approx(0.4)
    runs[("r2", "sphere_rx+15")]["low"] = 70.0  # 15 pp out of the first bin
    voi, bins = _tables(tmp_path, runs)
    assert _by_id(findings_table(voi, bins))["4b"].verdict == DOES_NOT_HOLD


def test_skin_fit_by_the_spread_across_animals(tmp_path):
    def study(deltas):
        runs = {}
        for i, d in enumerate(deltas):
            runs[(f"r{i}", "sphere")] = dict(skin=0.10)
            runs[(f"r{i}", "sphere_rx+15")] = dict(skin=0.10 + d)
        return runs

    voi, bins = _tables(tmp_path, study([0.05, 0.06, 0.055]))
    assert _by_id(findings_table(voi, bins))["6"].verdict == HOLDS
    voi, bins = _tables(tmp_path, study([-0.05, -0.06, -0.055]))
    assert _by_id(findings_table(voi, bins))["6"].verdict == DOES_NOT_HOLD
    voi, bins = _tables(tmp_path, study([0.05, -0.06, 0.01]))
    assert _by_id(findings_table(voi, bins))["6"].verdict == CANNOT_TELL
    voi, bins = _tables(tmp_path, study([0.05]))  # one animal: no spread to judge by
    assert _by_id(findings_table(voi, bins))["6"].verdict == CANNOT_TELL


def test_convergence_share_against_seven_of_ten(tmp_path):
    runs = {(f"r{i}", v): {} for i in range(10) for v in ("sphere", "bar")}
    voi, _ = _tables(tmp_path, runs, failed=[("r0", "bar"), ("r1", "bar"), ("r2", "bar")])
    f = claim_convergence(voi)
    assert f.verdict == HOLDS and f.value == pytest.approx(70.0) and f.n_animals == 7
    voi, _ = _tables(tmp_path, runs, failed=[(f"r{i}", "bar") for i in range(4)])
    assert claim_convergence(voi).verdict == DOES_NOT_HOLD


def _field(peaks_at_mm, n=201, size_mm=0.1):
    """Elements on a line along n = +z every ``size_mm``, γ peaked (1.0) at the given positions and
    0.35 elsewhere (inside the VOI), volumes of regular tets of edge ``size_mm``."""
    s = np.linspace(-5, 5, n)
    g = 0.35 + 0.65 * np.max([np.exp(-(((s - p) / 0.3) ** 2)) for p in peaks_at_mm], axis=0)
    vol = np.full(n, size_mm**3 / (6 * np.sqrt(2)))
    return np.column_stack([0 * s, 0 * s, s]), g, vol


def test_peak_location_finds_the_highest_strains():
    c, g, v = _field([0.2])
    loc = peak_location(c, g, v, tip_mm=[0, 0, 0], normal=[0, 0, 1], half_length_mm=3.5)
    assert loc.centre_mm == pytest.approx(0.2, abs=0.01)
    assert loc.uncertainty_mm == pytest.approx(0.05)  # half the edge of the regular tet
    c, g, v = _field([-3.0, 3.0])
    loc = peak_location(c, g, v, tip_mm=[0, 0, 0], normal=[0, 0, 1], half_length_mm=3.5)
    assert loc.end_share == pytest.approx(1.0) and loc.ends == "both"
    assert abs(loc.centre_mm) < 0.5  # both ends: the mean lies between them, hence the end share
    empty = peak_location(c, 0 * g, v, tip_mm=[0, 0, 0], normal=[0, 0, 1])
    assert np.isnan(empty.centre_mm)


def test_peak_claims_hold_and_do_not_hold(tmp_path):
    voi, _ = _tables(tmp_path, {("r1", "sphere"): {}, ("r1", "bar"): {}})

    def peaks(sphere_at, bar_at):
        rows = []
        for variant, at in (("sphere", sphere_at), ("bar", bar_at)):
            loc = peak_location(
                *_field(at), tip_mm=[0, 0, 0], normal=[0, 0, 1], half_length_mm=3.5
            )
            rows.append({"animal": "r1", "variant": variant, **loc.__dict__})
        return pd.DataFrame(rows)

    good = peaks([0.0], [3.0])
    assert claim_peak_location(voi, good, shape="sphere").verdict == HOLDS
    assert claim_peak_location(voi, good, shape="bar").verdict == HOLDS
    bad = peaks([1.5], [0.0])
    assert claim_peak_location(voi, bad, shape="sphere").verdict == DOES_NOT_HOLD
    assert claim_peak_location(voi, bad, shape="bar").verdict == DOES_NOT_HOLD
    assert claim_peak_location(voi, None, shape="bar").verdict == NOT_APPLICABLE


def test_write_findings_writes_the_table_and_the_figures(tmp_path):
    _tables(tmp_path, _orientation_study({"sphere_rx+15": 1.0, "sphere_rx-15": -0.5}))
    keys = ["tissue_png", "peaks_png", "orientation_png", "bins_png", "skin_png"]
    outs = {k: tmp_path / f"{k}.png" for k in keys}
    outs.update(findings_csv=tmp_path / "findings.csv", findings_md=tmp_path / "findings.md")
    job = FindingsJob(tmp_path / "voi.csv", tmp_path / "bins.csv", outputs=outs, study="hand")
    findings = write_findings(job)
    table = pd.read_csv(outs["findings_csv"])
    assert list(table["claim_id"].astype(str)) == [f.claim_id for f in findings]
    assert len(table) == 10 and set(table["verdict"]) <= {
        HOLDS,
        DOES_NOT_HOLD,
        CANNOT_TELL,
        NOT_APPLICABLE,
    }
    md = outs["findings_md"].read_text()
    assert "| 3a." in md and "**holds**" in md and "study 'hand'" in md
    for k in keys:
        assert outs[k].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", k
    bad = tmp_path / "bad.csv"
    pd.DataFrame({"animal": ["r1"]}).to_csv(bad, index=False)
    with pytest.raises(ValueError, match="bad.csv: no column"):
        write_findings(FindingsJob(bad, tmp_path / "bins.csv", outputs=outs, study="hand"))
