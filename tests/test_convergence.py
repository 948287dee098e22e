"""Speed against error: errors, Richardson, Pareto, goal, scaling, summary; one tiny run;
the SLURM profile's dry run. Known answers come from closed forms (c + k h^p), not from the code."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from deeptissue.convergence import (
    ROW_COLUMNS,
    ConvergenceInputs,
    ConvergenceOutputs,
    Discretisation,
    RunJob,
    aggregate_convergence,
    convergence_table,
    default_ladder,
    pareto_mask,
    richardson_extrapolation,
    run_discretisation,
    scaling_fit,
    setting_name,
    setting_table,
    summary_markdown,
)

ROOT = Path(__file__).resolve().parents[1]


def make_row(
    setting,
    *,
    variant="sphere",
    family="P2 uniform",
    n_dofs,
    voi,
    force,
    bins,
    wall_s,
    tolerance="default",
    rtol=1e-7,
    is_default=False,
    converged=True,
    h=1.0,
    voi_centroid=None,
    bins_centroid=None,
):
    return dict(
        animal="rat01",
        variant=variant,
        setting=setting,
        family=family,
        element_order=2,
        element_size_mm=h,
        refine_size_mm=None,
        tolerance=tolerance,
        rtol=rtol,
        gap_tol_rel=1e-3,
        mesh_key=f"p2_h{h:g}_rnone",
        is_default=is_default,
        converged=converged,
        reason=None if converged else "cut-back limit",
        n_elements=n_dofs // 10,
        n_dofs=n_dofs,
        increments=5,
        newton_iterations=20,
        voi_mm3=voi,
        bins_percent=bins,
        gamma_sampling="points",
        voi_sampled_mm3=voi,
        bins_sampled_percent=bins,
        voi_centroid_mm3=voi if voi_centroid is None else voi_centroid,
        bins_centroid_percent=bins if bins_centroid is None else bins_centroid,
        voi_err_mm3=None,
        bins_err_pp=None,
        peak_gamma=0.5,
        indenter_force_N=force,
        mesh_s=1.0,
        assembly_s=0.3 * wall_s,
        linear_solve_s=0.5 * wall_s,
        contact_s=0.05 * wall_s,
        solver_other_s=0.0,
        post_s=0.1,
        solve_s=0.85 * wall_s,
        wall_s=wall_s,
        linear_setup_s=0.1,
        linear_assembly_s=0.1,
        linear_factor_solve_s=0.1,
        linear_wall_s=0.3,
        cost_ratio=0.85 * wall_s / 0.3,
        start_rss_mb=100.0,
        peak_rss_mb=100.0 + n_dofs / 100.0,
    )


# --------------------------------------------------------------------------- Richardson


@pytest.mark.parametrize("p", [1.0, 1.5, 2.0, 3.0])
def test_richardson_recovers_limit_and_order_of_c_plus_k_h_to_the_p(p):
    c, k = 12.0, 3.5
    h = np.array([1.6, 1.1, 0.7])  # unequal ratios
    r = richardson_extrapolation(h, c + k * h**p)
    assert r.order_p == pytest.approx(p, abs=1e-9)
    assert r.extrapolated == pytest.approx(c, abs=1e-9)
    assert r.k == pytest.approx(k, rel=1e-8)
    # order of the input does not matter, and only the three finest sizes are used
    h4 = np.array([0.7, 2.5, 1.1, 1.6])
    f4 = c + k * h4**p
    f4[1] += 100.0  # the coarsest point is off the curve: ignored
    assert richardson_extrapolation(h4, f4).extrapolated == pytest.approx(c, abs=1e-9)


def test_richardson_refuses_non_monotone_or_too_few_sizes():
    assert richardson_extrapolation([1.6, 1.1, 0.7], [1.0, 2.0, 1.5]) is None  # oscillates
    assert richardson_extrapolation([1.6, 1.1], [1.0, 2.0]) is None
    assert richardson_extrapolation([1.6, 1.6, 0.7], [1.0, 2.0, 1.5]) is None
    assert (
        richardson_extrapolation([1.6, 1.1, 0.7], [1.0, 1.0, 1.0]) is None
    )  # nothing to extrapolate


# --------------------------------------------------------------------------- errors, goal, Pareto

BINS_REF = {"0.3-0.4": 60.0, "0.4-0.5": 30.0, ">0.5": 10.0}


def ladder_rows(variant="sphere", scale=1.0):
    """Uniform family with VOI = 10 + 200 h^2 and force = 0.1 (1 + 2 h^2), h = n_dofs^(-1/3)."""
    rows = []
    for n, wall in [(1000, 2.0), (8000, 10.0), (27000, 40.0), (64000, 120.0)]:
        h = n ** (-1 / 3)
        bins = {
            k: v
            + (3.0 if k == "0.3-0.4" else -3.0 if k == "0.4-0.5" else 0.0) * (h / 0.025) ** 2 * 0.1
            for k, v in BINS_REF.items()
        }
        rows.append(
            make_row(
                f"p2_n{n}",
                variant=variant,
                n_dofs=n,
                voi=scale * (10 + 200 * h**2),
                force=0.1 * (1 + 2 * h**2),
                bins=bins,
                wall_s=wall,
                h=100 * h,
            )
        )
    return rows


def test_errors_against_the_finest_run_and_richardson():
    df = convergence_table(ladder_rows())
    df = df.set_index("setting")
    assert df["is_reference"].sum() == 1 and df.loc["p2_n64000", "is_reference"]
    assert (df["reference_setting"] == "p2_n64000").all()
    f = lambda h: 10 + 200 * h**2
    g = lambda h: 0.1 * (1 + 2 * h**2)
    h1, h4 = 0.1, 0.025
    assert df.loc["p2_n1000", "voi_rel_error"] == pytest.approx((f(h1) - f(h4)) / f(h4), rel=1e-9)
    assert df.loc["p2_n1000", "force_rel_error"] == pytest.approx(
        (g(h1) - g(h4)) / g(h4), rel=1e-9
    )
    # bin errors: the 0.3-0.4 bin moved by 0.3 (h/h4)^2 pp, 0.4-0.5 by the same, reference moved 0.3 pp
    assert df.loc["p2_n1000", "bin_max_error_pp"] == pytest.approx(
        0.3 * (h1 / h4) ** 2 - 0.3, rel=1e-9
    )
    assert df.loc["p2_n64000", "voi_rel_error"] == 0.0
    # Richardson through the three finest sizes recovers the limits 10 and 0.1 exactly
    assert df.loc["p2_n1000", "voi_rel_error_richardson"] == pytest.approx(
        (f(h1) - 10) / 10, rel=1e-7
    )
    assert df.loc["p2_n64000", "force_rel_error_richardson"] == pytest.approx(2 * h4**2, rel=1e-6)
    # goal: VOI error of n27000 is 200 (1/900 - 1/1600) / f(h4) = 0.96 % (< 2 %), of n8000 3.7 %
    assert df.loc["p2_n27000", "voi_rel_error"] == pytest.approx(
        200 * (1 / 900 - 1 / 1600) / f(h4), rel=1e-9
    )
    assert df.loc["p2_n27000", "meets_goal"] and not df.loc["p2_n8000", "meets_goal"]
    assert df.loc["p2_n27000", "bin_max_error_pp"] == pytest.approx(
        0.3 * (1600 / 900) - 0.3, rel=1e-9
    )
    # each row costs more and is more accurate than the previous: all on the front
    assert df["pareto"].all()


def test_errors_of_both_gamma_samplings():
    """The sampled and centroid estimates get their own errors against the reference's same estimate."""
    rows = ladder_rows()
    for i, r in enumerate(
        rows
    ):  # centroid VOI 10 % low on the coarsest mesh, 5 % on the next, exact after
        r["voi_centroid_mm3"] = r["voi_mm3"] * (1 - [0.10, 0.05, 0.0, 0.0][i])
        r["bins_centroid_percent"] = {
            k: v + [4.0, 2.0, 0.0, 0.0][i] * (1 if k == "0.3-0.4" else 0)
            for k, v in r["bins_percent"].items()
        }
    df = convergence_table(rows).set_index("setting")
    ref = df.loc["p2_n64000"]
    for name, off_voi, off_bin in [("p2_n1000", 0.10, 4.0), ("p2_n8000", 0.05, 2.0)]:
        r = df.loc[name]
        assert r["voi_sampled_rel_error"] == pytest.approx(r["voi_rel_error"], rel=1e-12)
        assert r["voi_centroid_rel_error"] == pytest.approx(
            abs(r["voi_mm3"] * (1 - off_voi) / ref["voi_mm3"] - 1), rel=1e-12
        )
        assert r["bin_centroid_max_error_pp"] >= off_bin - r["bin_max_error_pp"] - 1e-12
    assert df.loc["p2_n27000", "meets_goal_sampled"] == df.loc["p2_n27000", "meets_goal"]
    assert not df.loc["p2_n8000", "meets_goal_centroid"]
    assert {"bin_centroid_0.3-0.4", "bin_sampled_>0.5", "goal_error_centroid"} <= set(df.columns)
    st = setting_table(df.reset_index()).set_index("setting")
    assert (
        st.loc["p2_n27000", "meets_goal_sampled"] and not st.loc["p2_n8000", "meets_goal_centroid"]
    )
    text = summary_markdown(df.reset_index(), default_name="p2_n8000")
    assert "γ at element centroids (`voi_centroid_mm3`)" in text


def test_element_size_measure_and_bin_columns():
    rows = ladder_rows()
    df = convergence_table(
        rows, measure="element_size"
    )  # h column = 100 n^(-1/3): same extrapolation
    assert df["voi_rel_error_richardson"].iloc[0] == pytest.approx(200 * 0.01 / 10, rel=1e-6)
    assert {"bin_0.3-0.4", "bin_0.4-0.5", "bin_>0.5"} <= set(df.columns)


def test_pareto_mask_and_dominated_setting():
    cost = [1, 2, 3, 4, 5, np.nan]
    err = [5, 3, 4, 1, 1, 0]
    assert pareto_mask(cost, err).tolist() == [True, True, False, True, False, False]
    rows = ladder_rows()
    rows.append(
        make_row(
            "slow_bad",
            n_dofs=9000,
            voi=10 + 200 * 9000 ** (-2 / 3) * 1.5,
            force=0.1,
            bins=BINS_REF,
            wall_s=50.0,
            h=4.8,
        )
    )
    df = convergence_table(rows).set_index("setting")
    assert not df.loc["slow_bad", "pareto"]  # n27000 is faster and more accurate


def test_failed_run_has_no_error_and_is_never_the_reference():
    rows = ladder_rows()
    rows.append(
        make_row(
            "p2_fail",
            n_dofs=200000,
            voi=None,
            force=None,
            bins=None,
            wall_s=999.0,
            converged=False,
            h=0.2,
        )
    )
    df = convergence_table(rows).set_index("setting")
    assert df.loc["p2_n1000", "reference_setting"] == "p2_n64000"
    assert np.isnan(df.loc["p2_fail", "voi_rel_error"]) and not df.loc["p2_fail", "meets_goal"]
    assert not df.loc["p2_fail", "pareto"]


# --------------------------------------------------------------------------- scaling and summary


def test_scaling_fit_recovers_exponent_and_prefactor():
    n = np.array([1e3, 5e3, 2e4, 1e5])
    fit = scaling_fit(n, 3.0 * n**1.5, quantity="solve_s")
    assert fit.exponent == pytest.approx(1.5, abs=1e-12)
    assert fit.prefactor == pytest.approx(3.0, rel=1e-9)
    assert fit.r2 == pytest.approx(1.0) and fit.n_points == 4
    assert scaling_fit([1e3, 1e3], [1.0, 2.0]) is None


def test_summary_names_cheapest_setting_meeting_goal_and_judges_default():
    rows = ladder_rows("sphere") + ladder_rows("bar", scale=1.1)
    for r in rows:
        r["is_default"] = r["setting"] == "p2_n8000"
    df = convergence_table(rows)
    st = setting_table(df)
    assert st.set_index("setting").loc["p2_n27000", "meets_goal"]
    text = summary_markdown(df, default_name="p2_n8000", notes=["element order 1 left out"])
    assert "Cheapest setting meeting the goal: `p2_n27000`" in text
    assert "`p2_n8000` does NOT meet the goal" in text and "sits on the" in text
    assert "reference for rat01 `bar`: `p2_n64000`" in text
    assert "Note: element order 1 left out" in text
    assert "is the reference itself" in summary_markdown(df, default_name="p2_n64000")
    # memory above the start grows exactly linearly in n_dofs in these rows
    assert "`rss_above_start_mb` ∝ n_dofs^1.00" in text
    assert (
        "Each sampling:\n\n- γ at 64 points per element (`voi_sampled_mm3`): cheapest setting"
        in text
    )
    # rows without the VOI of each sampling: no heading over an empty list
    for r in rows:
        r["voi_sampled_mm3"] = r["voi_centroid_mm3"] = None
    assert "Each sampling" not in summary_markdown(
        convergence_table(rows), default_name="p2_n8000"
    )


def test_aggregate_writes_csv_figure_and_summary_with_benchmarks(tmp_path):
    from deeptissue.io import write_json

    paths, benches = [], []
    for r in ladder_rows():
        p = tmp_path / "rows" / f"{r['setting']}.json"
        write_json(p, r)
        paths.append(p)
        b = tmp_path / "bench" / "rat01" / f"sphere_{r['setting']}.tsv"
        b.parent.mkdir(parents=True, exist_ok=True)
        b.write_text(
            "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
            f"{r['wall_s'] + 2}\t0:00:01\t{r['peak_rss_mb'] + 5}\t1\t1\t1\t0\t0\t90\t{r['wall_s']}\n"
        )
        benches.append(b)
    out = tmp_path / "out"
    df = aggregate_convergence(
        ConvergenceInputs(row_paths=paths, benchmark_paths=benches),
        ConvergenceOutputs(
            csv_path=out / "convergence.csv",
            png_path=out / "error_vs_time.png",
            md_path=out / "summary.md",
        ),
        default_name="p2_n27000",
    )
    back = pd.read_csv(out / "convergence.csv")
    # flattened to bin_* columns, or reduced to bin_err_max_pp
    dict_columns = {"bins_percent", "bins_sampled_percent", "bins_centroid_percent", "bins_err_pp"}
    assert len(back) == 4 and set(ROW_COLUMNS) - dict_columns <= set(back.columns)
    assert np.allclose(back["benchmark_max_rss_mb"], back["peak_rss_mb"] + 5)
    assert (out / "error_vs_time.png").read_bytes()[:4] == b"\x89PNG"
    assert "`p2_n27000` meets the goal" in (out / "summary.md").read_text()
    assert df["meets_goal"].sum() == 2


# --------------------------------------------------------------------------- ladder


def test_default_ladder_contains_default_families_of_both_orders():
    lad = default_ladder(
        {
            "element_orders": [1, 2],
            "element_sizes_mm": [1.6, 0.9],
            "refined_element_sizes_mm": [1.2, 1.0],
            "refine_ratio": 0.5,
            "tolerances": [{"name": "loose", "rtol": 1e-5}, {"name": "default"}],
        },
        model_cfg={"element_size_mm": 1.0, "refine_size_mm": 0.5},
        solver_cfg={"newton": {"rtol": 1e-7}, "contact": {"gap_tol_rel": 1e-3}},
    )
    names = lad.names
    assert len(names) == len(set(names))
    assert lad.default_name == "p2_h1_r0.5" and lad.default_name in names
    p2 = {"p2_h1.6", "p2_h0.9", "p2_h1.2_r0.6", "p2_h1_r0.5", "p2_h1_r0.5_loose"}
    assert p2 | {n.replace("p2_", "p1_") for n in p2} == set(names)
    assert (
        lad.by_name("p2_h1_r0.5_loose").rtol == 1e-5
        and lad.by_name("p2_h1_r0.5_loose").gap_tol_rel == 1e-3
    )
    assert lad.by_name("p2_h1.6").model_settings({"refine_radius_mm": 4.0}) == {
        "refine_radius_mm": 4.0,
        "element_size_mm": 1.6,
        "refine_size_mm": 1.6,
        "element_order": 2,
    }
    assert lad.by_name("p1_h1.6").model_settings({"element_order": 2})["element_order"] == 1
    assert lad.by_name("p1_h0.9").family == "P1 uniform" and not lad.notes
    assert (
        setting_name(element_size_mm=0.7, refine_size_mm=0.35, tolerance="tight")
        == "p2_h0.7_r0.35_tight"
    )
    assert (
        default_ladder({"element_orders": [1]}).default_name == "p1_h1.6_r0.8"
    )  # the model defaults
    with pytest.raises(ValueError, match="element_orders"):
        default_ladder({"element_orders": [3]})


# --------------------------------------------------------------------------- one real run


@pytest.mark.slow
def test_run_discretisation_on_a_tiny_synthetic_leg():
    from model_synth import leg_contours, leg_pose

    c = leg_contours(n_slices=12, n_points=60)
    pose = leg_pose(c, depth_mm=0.5)
    s = Discretisation(name="p2_h2.5", family="P2 uniform", element_size_mm=2.5)
    study = {"variants": ["sphere"], "threshold": 0.05, "bin_edges": [0.05, 0.1, 0.2]}
    row = run_discretisation(
        RunJob(animal="synth", variant="sphere", setting=s, is_default=True),
        contours=c,
        pose=pose,
        cast=False,
        study_cfg=study,
    )
    assert set(ROW_COLUMNS) <= set(row)
    assert row["converged"], row["reason"]
    assert row["n_elements"] > 100 and row["n_dofs"] > 3 * row["n_elements"]
    assert row["voi_mm3"] > 0 and sum(row["bins_percent"].values()) == pytest.approx(100.0)
    assert row["indenter_force_N"] > 0 and row["newton_iterations"] >= row["increments"] > 0
    # the solver's parts add up to its wall time; the run's wall time holds meshing, solve and post
    parts = row["assembly_s"] + row["linear_solve_s"] + row["contact_s"] + row["solver_other_s"]
    assert parts == pytest.approx(row["solve_s"], rel=1e-6)
    assert row["wall_s"] == pytest.approx(row["mesh_s"] + row["solve_s"] + row["post_s"], rel=1e-6)
    # a nonlinear contact solve takes several Newton iterations: more than one linear solve
    assert row["cost_ratio"] > 1 and row["linear_wall_s"] > 0
    assert row["peak_rss_mb"] >= row["start_rss_mb"] > 0


# --------------------------------------------------------------------------- SLURM profile


@pytest.mark.slow
def test_slurm_profile_dry_run_plans_the_study_and_the_ladder():
    import yaml

    from deeptissue.config import validate_config

    cfg = validate_config(
        yaml.safe_load((ROOT / "config/config.yaml").read_text()),
        ROOT / "workflow/schemas/config.schema.yaml",
        base_dir=ROOT,
    )
    n_solve = len(cfg["animals"]) * len(cfg["study"]["variants"])
    n_ladder = (
        len(cfg["convergence"]["animals"])
        * len(cfg["convergence"]["variants"])
        * len(
            default_ladder(
                cfg["convergence"], model_cfg=cfg["model"], solver_cfg=cfg["fem"]["solver"]
            ).settings
        )
    )
    exe = Path(sys.executable).with_name("snakemake")
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    # --forceall: plan every job whatever results/ already holds; without the plugin installed, snakemake
    # refuses the profile ("--executor: invalid choice: 'slurm'")
    p = subprocess.run(
        [str(exe), "-n", "--forceall", "--profile", "profiles/slurm", "study", "convergence"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = p.stdout + p.stderr
    assert p.returncode == 0, out[-3000:]
    # every animal x variant on adaptive meshes (the default; the ladder's adaptive runs are among them)
    # and every convergence run, each with the profile's resources
    stats = [line.split() for line in out.splitlines()]
    assert ["adapt_variant", str(n_solve)] in stats, out[-2000:]
    assert n_ladder // len(default_ladder(cfg["convergence"]).settings) <= n_solve
    assert ["convergence_run", str(n_ladder)] in stats, out[-2000:]
    # Snakemake prints a job's resources in no fixed order (disk_mb before or after mem_mb): compare them as maps
    resources = _planned_resources(out)
    assert {(r["mem_mb"], r["runtime"]) for r in resources["adapt_variant"]} == {("4000", "120")}
    assert {(r["mem_mb"], r["runtime"]) for r in resources["convergence_run"]} == {("8000", "240")}
    assert ["verify_cylinder_adaptive", "1"] in stats, out[-2000:]


def _planned_resources(out):
    """{rule: [{resource: value} per planned job]} from the jobs a dry run of Snakemake lists."""
    planned, rule = {}, None
    for line in out.splitlines():
        if line.startswith(("rule ", "localrule ")):
            rule = line.split()[1].rstrip(":")
        elif line.strip().startswith("resources:") and rule is not None:
            pairs = (item.split("=", 1) for item in line.split(":", 1)[1].split(","))
            planned.setdefault(rule, []).append({k.strip(): v.strip() for k, v in pairs})
            rule = None
    return planned


def _passes(bins_last, *, voi_last, force_last, n_last, converged_last=True):
    """passes.csv of an adaptive run of rat01's sphere: a coarse pass, then one with the given answer."""
    bins0 = {"0.3-0.4": 70.0, "0.4-0.5": 25.0, ">0.5": 5.0}
    rows = []
    for k, (n, voi, force, bins, ok) in enumerate(
        [
            (2000, 14.0, 0.11, bins0, True),
            (n_last, voi_last, force_last, bins_last, converged_last),
        ]
    ):
        rows.append(
            dict(
                animal="rat01",
                variant="sphere",
                index=k,
                n_dofs=n,
                n_tets=n // 5,
                converged=ok,
                mesh_s=1.0,
                solve_s=5.0 * (k + 1),
                estimate_s=0.5,
                wall_s=7.0 * (k + 1) ** 2,
                voi_mm3=voi if ok else np.nan,
                voi_err_percent=1.0 if ok else np.nan,
                bins_err_pp=0.2 if ok else np.nan,
                force_N=force if ok else np.nan,
                force_err_percent=np.nan if k == 0 else 3.0,
                goal_met=k == 1 and ok,
                stop_reason="goal",
                **{f"bins_percent.{b}": (v if ok else np.nan) for b, v in bins.items()},
            )
        )
    return pd.DataFrame(rows)


def test_adaptive_runs_are_measured_against_the_ladders_reference_and_never_are_it(tmp_path):
    from deeptissue.convergence import adaptive_pass_errors, adaptive_rows, reference_rows

    ref = ladder_rows()[-1]  # p2_n64000
    bins = {k: v + 0.5 for k, v in ref["bins_percent"].items()}
    passes = _passes(
        bins,
        voi_last=1.01 * ref["voi_mm3"],
        force_last=1.03 * ref["indenter_force_N"],
        n_last=90000,
    )
    rows = ladder_rows() + adaptive_rows(passes)
    assert (
        reference_rows(rows)[("rat01", "sphere")]["setting"] == "p2_n64000"
    )  # more DOFs, still not the reference
    df = convergence_table(rows).set_index("setting")
    a = df.loc["adaptive"]
    assert a["voi_rel_error"] == pytest.approx(0.01) and a["force_rel_error"] == pytest.approx(
        0.03
    )
    assert (
        a["bin_max_error_pp"] == pytest.approx(0.5)
        and a["wall_s"] == 28.0
        and a["n_dofs"] == 90000
    )
    assert not a["meets_goal"] and not a["is_reference"]
    # every pass's true error, for the figure
    errs = adaptive_pass_errors(passes, reference_rows(rows))
    assert (
        errs.loc[1, "voi_rel_error"] == pytest.approx(0.01) and errs.loc[0, "voi_rel_error"] > 0.1
    )
    text = summary_markdown(convergence_table(rows), default_name="p2_n27000")
    # VOI 1 % against an estimate of 1 %, bins 0.5 pp against 0.2 pp, force 3 % against 3 %
    assert (
        "| rat01 | sphere | 2, goal | 90000 (64000) | 28 | 1.00 / 1.00 | 0.50 / 0.20 | 3.00 / 3.00 | yes, no, yes | –, – |"
        in text
    )
    # a run whose last pass failed answers with its last converged pass; one with none converged is a failed row
    failed = _passes(bins, voi_last=1.0, force_last=1.0, n_last=90000, converged_last=False)
    row = adaptive_rows(failed)[0]
    assert row["converged"] and row["n_dofs"] == 2000 and row["wall_s"] == 28.0
    none = failed.assign(converged=False)
    assert not adaptive_rows(none)[0]["converged"]
    # the aggregate: the adaptive run in the table, and the cylinder scene in the summary
    from deeptissue.io import write_json

    paths = []
    for r in ladder_rows():
        write_json(tmp_path / "rows" / f"{r['setting']}.json", r)
        paths.append(tmp_path / "rows" / f"{r['setting']}.json")
    passes.to_csv(tmp_path / "passes.csv", index=False)
    cyl = pd.DataFrame(
        [
            dict(
                kind="fixed",
                mesh="1.6 / 0.8 mm",
                depth_mm=2.0,
                n_dofs=29577,
                wall_s=18.0,
                est_voi_percent=12.0,
                est_bins_pp=4.2,
                true_voi_percent=2.1,
                true_bins_pp=1.06,
                true_force_percent=0.73,
            ),
            dict(
                kind="adaptive",
                mesh="adaptive",
                depth_mm=2.0,
                n_dofs=10809,
                wall_s=2.9,
                est_voi_percent=38.0,
                est_bins_pp=16.9,
                true_voi_percent=22.4,
                true_bins_pp=8.2,
                true_force_percent=5.8,
                pass_index=0,
            ),
            dict(
                kind="adaptive",
                mesh="adaptive",
                depth_mm=2.0,
                n_dofs=77433,
                wall_s=37.7,
                est_voi_percent=1.0,
                est_bins_pp=0.18,
                true_voi_percent=-0.09,
                true_bins_pp=0.15,
                true_force_percent=0.07,
                pass_index=3,
                est_force_percent=0.1,
            ),
        ]
    )
    cyl.to_csv(tmp_path / "cylinder.csv", index=False)
    out = tmp_path / "out"
    df = aggregate_convergence(
        ConvergenceInputs(
            row_paths=paths,
            adaptive_paths=[tmp_path / "passes.csv"],
            cylinder_path=tmp_path / "cylinder.csv",
        ),
        ConvergenceOutputs(
            csv_path=out / "convergence.csv",
            png_path=out / "error_vs_time.png",
            md_path=out / "summary.md",
        ),
        default_name="p2_n27000",
    )
    assert "adaptive" in set(df["setting"])
    md = (out / "summary.md").read_text()
    assert "| 2 | 1.6 / 0.8 mm | 29577 | 18.0 | 2.10 / 12.00 | 1.06 / 4.20 | 0.73 / – | no |" in md
    assert (
        "| 2 | adaptive, 4 passes | 77433 | 37.7 | 0.09 / 1.00 | 0.15 / 0.18 | 0.07 / 0.10 | yes |"
        in md
    )
    assert (out / "error_vs_time.png").read_bytes()[:4] == b"\x89PNG"


def test_effectivity_of_the_runs_own_error_estimate():
    rows = ladder_rows()
    for r in rows:  # an estimate of half the true VOI error of n1000 and twice its bin error
        r["voi_err_mm3"], r["bins_err_pp"] = 1.0, {"0.3-0.4": 0.5, "0.4-0.5": 2.0, ">0.5": None}
    df = convergence_table(rows).set_index("setting")
    voi_abs = abs(df.loc["p2_n1000", "voi_mm3"] - df.loc["p2_n64000", "voi_mm3"])
    assert df.loc["p2_n1000", "voi_effectivity"] == pytest.approx(1.0 / voi_abs, rel=1e-12)
    assert df.loc["p2_n1000", "bin_err_max_pp"] == 2.0
    assert df.loc["p2_n1000", "bin_effectivity"] == pytest.approx(
        2.0 / df.loc["p2_n1000", "bin_max_error_pp"], rel=1e-12
    )
    # the reference has no error to compare with; rows without an estimate have none either
    assert np.isnan(df.loc["p2_n64000", "voi_effectivity"])
    assert "bins_err_pp" not in df.columns
    assert np.isnan(
        convergence_table(ladder_rows()).set_index("setting").loc["p2_n1000", "voi_effectivity"]
    )
