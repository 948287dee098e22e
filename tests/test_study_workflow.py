"""Study configs validate against the schema; rule aggregate runs on hand-made summaries."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from study_meshes import box_tet10

from deeptissue.config import ConfigError, validate_config
from deeptissue.pose import Pose, save_pose
from deeptissue.summary import failed_summary, summarize_solution, write_result_vtu, write_summary

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


def _load(name):
    return validate_config(
        yaml.safe_load((ROOT / "config" / name).read_text()), SCHEMA, base_dir=ROOT
    )


def test_paper_config_spans_the_study_variation():
    c = _load("paper.yaml")
    assert len(c["animals"]) == 10
    ph = [a["phantom"] for a in c["animals"].values()]
    depth = np.array([p["depth_mm"] for p in ph])
    tilt = np.array([np.hypot(*p["tilt_deg"]) for p in ph])
    rot = np.array([np.linalg.norm(p["bone_rotation_deg"]) for p in ph])
    snr = np.array([p["snr"] for p in ph])
    assert depth.min() == 1.5 and depth.max() == 3.0
    assert tilt.max() <= 20.0 + 1e-9 and tilt.max() >= 19.0 and tilt.min() == 0.0
    assert rot.max() <= 3.0 + 1e-9 and rot.max() >= 2.9
    assert snr.min() == 10 and snr.max() == 30
    assert len({p["seed"] for p in ph}) == 10
    assert c["study"]["variants"] == [
        "sphere",
        "bar",
        "sphere_rx+15",
        "sphere_rx-15",
        "sphere_rz+15",
        "sphere_rz-15",
    ]


def test_test_config_and_study_defaults():
    c = _load("test.yaml")
    assert list(c["animals"]) == ["rat01"] and c["study"]["variants"] == [
        "sphere",
        "bar",
        "sphere_rz+15",
    ]
    assert c["study"]["threshold"] == 0.3
    assert c["study"]["bin_edges"] == [0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]
    assert c["study"]["strain_measure"] == "green_lagrange" and c["study"]["figure_animal"] is None
    assert c["study"]["gamma_sampling"] == "points"
    assert (c["model"]["element_size_mm"], c["model"]["refine_size_mm"]) == (
        2.5,
        1.25,
    )  # CI's coarse mesh
    demo = _load("config.yaml")
    assert (demo["model"]["element_size_mm"], demo["model"]["refine_size_mm"]) == (1.6, 0.8)
    # the default is the accurate answer: adaptive meshes; the fixed mesh is the preview overlay's (and CI's)
    assert demo["study"]["mesh"] == "adaptive"
    # the preview is the default's first adaptive pass: the model's element size everywhere
    preview = yaml.safe_load((ROOT / "config" / "preview.yaml").read_text())
    assert preview == {"study": {"mesh": "fixed"}, "model": {"refine_size_mm": 1.6}}
    assert preview["model"]["refine_size_mm"] == demo["model"]["element_size_mm"]
    assert c["study"]["mesh"] == "fixed"
    for key, value in (("strain_measure", "hencky"), ("gamma_sampling", "nodes")):
        bad = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
        bad["study"][key] = value
        with pytest.raises(ConfigError, match=f"study.{key}"):
            validate_config(bad, SCHEMA, base_dir=ROOT)


def _snakemake(workdir, *targets_then_options, configfile=ROOT / "config" / "test.yaml"):
    """snakemake on the test config (or ``configfile``) in ``workdir``; targets must come first (options
    like --allowed-rules take several values)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        *targets_then_options,
        "-s",
        str(ROOT / "Snakefile"),
        "--directory",
        str(workdir),
        "--configfile",
        str(configfile),
    ]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)


def _with_own_variants(tmp_path, own, **model):
    """config/test.yaml (rat01: study.variants sphere, bar, sphere_rz+15) with more phantoms, each solving
    its own variants: ``own`` {animal: (depth_mm, variants)}; written to tmp_path/study.yaml."""
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    for k, (animal, (depth, variants)) in enumerate(own.items()):
        phantom = dict(cfg["animals"]["rat01"]["phantom"], seed=2 + k, depth_mm=depth)
        cfg["animals"][animal] = {"phantom": phantom, "variants": variants}
    cfg["model"].update(model)
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _dry_run_jobs(stdout):
    """{rule: [{'input': [...], 'wildcards': {...}, 'priority': float}]} of a dry run's job list."""
    import re

    jobs = {}
    for block in re.split(r"\n\[[^\]\n]+\]\n", stdout)[1:]:
        rule = re.match(r"(?:local)?rule (\w+):", block)
        if not rule:
            continue
        fields = dict(re.findall(r"^\s+(input|wildcards|priority): (.*)$", block, re.M))
        jobs.setdefault(rule.group(1), []).append(
            {
                "input": fields.get("input", "").split(", "),
                "wildcards": dict(w.split("=", 1) for w in fields["wildcards"].split(", "))
                if "wildcards" in fields
                else {},
                "priority": float(fields.get("priority", 0)),
            }
        )
    return jobs


@pytest.mark.slow
def test_each_animal_solves_meshes_and_aggregates_its_own_variants(tmp_path):
    # rat01 has study.variants (sphere, bar, sphere_rz+15); rat02 its own sphere and sphere_rx-15, which no
    # other animal has; rat03 only the bar. One mesh per indenter of each animal (model.mesh_groups)
    f = _with_own_variants(
        tmp_path,
        {"rat02": (2.5, ["sphere", "sphere_rx-15"]), "rat03": (2.2, ["bar"])},
        mesh_groups="indenter",
    )
    r = _snakemake(tmp_path, "-n", "--cores", "2", configfile=f)
    assert r.returncode == 0, r.stderr[-2000:]
    jobs = _dry_run_jobs(r.stdout)
    runs = [("rat01", v) for v in ("sphere", "bar", "sphere_rz+15")] + [
        ("rat02", "sphere"),
        ("rat02", "sphere_rx-15"),
        ("rat03", "bar"),
    ]
    solves = {(j["wildcards"]["animal"], j["wildcards"]["variant"]): j for j in jobs["solve"]}
    assert sorted(solves) == sorted(runs)
    meshes = {(j["wildcards"]["animal"], j["wildcards"]["group"]) for j in jobs["mesh"]}
    assert meshes == {("rat01", "sphere"), ("rat01", "bar"), ("rat02", "sphere"), ("rat03", "bar")}
    # a turned variant starts from its own animal's sphere, on that animal's sphere mesh
    turned = solves[("rat02", "sphere_rx-15")]["input"]
    assert "results/rat02/sphere/end_state.npz" in turned
    assert "results/rat02/model/sphere/mesh.npz" in turned
    assert not any(p.endswith("end_state.npz") for p in solves[("rat03", "bar")]["input"])
    # 5 more for a sphere others are turned from; rat03's bar is no base (10 + its depth)
    assert solves[("rat02", "sphere")]["priority"] == pytest.approx(5 + 2.5)
    assert solves[("rat01", "sphere")]["priority"] == pytest.approx(5 + 2.0)
    assert solves[("rat03", "bar")]["priority"] == pytest.approx(10 + 2.2)
    (aggregate,) = jobs["aggregate"]
    summaries = [p for p in aggregate["input"] if p.endswith("summary.json")]
    assert summaries == [f"results/{a}/{v}/summary.json" for a, v in runs]
    (findings,) = jobs["findings"]
    vtus = {p for p in findings["input"] if p.endswith("result.vtu")}
    assert vtus == {
        f"results/{a}/{v}/result.vtu"
        for a, v in [("rat01", "sphere"), ("rat01", "bar"), ("rat02", "sphere"), ("rat03", "bar")]
    }


@pytest.mark.slow
def test_the_bone_at_indenter_config_turns_the_sphere_of_deep3_only(tmp_path):
    r = _snakemake(
        tmp_path, "-n", "--cores", "2", configfile=ROOT / "config" / "bone_at_indenter.yaml"
    )
    assert r.returncode == 0, r.stderr[-2000:]
    jobs = _dry_run_jobs(r.stdout)
    solves = sorted((j["wildcards"]["animal"], j["wildcards"]["variant"]) for j in jobs["solve"])
    pinch = ["gap030", "gap010", "gap005", "tilt030", "tilt010", "tilt005"]
    turns = ["sphere_rx+15", "sphere_rx-15", "sphere_rz+15", "sphere_rz-15"]
    assert solves == sorted(
        [(a, "sphere") for a in pinch + ["deep3"]] + [("deep3", v) for v in turns]
    )
    for j in jobs["solve"]:
        if j["wildcards"]["variant"] in turns:
            assert "results/deep3/sphere/end_state.npz" in j["input"]
    # one mesh per animal (model.mesh_groups: animal)
    assert sorted(j["wildcards"]["animal"] for j in jobs["mesh"]) == sorted(pinch + ["deep3"])


@pytest.mark.slow
def test_a_turned_adaptive_variant_rides_its_base_variants_passes(tmp_path):
    # the demo (study.mesh: adaptive): each turned sphere reads its sphere's converged passes; the
    # sphere and the bar mesh their own
    r = _snakemake(tmp_path, "-n", "--cores", "2", configfile=ROOT / "config" / "config.yaml")
    assert r.returncode == 0, r.stderr[-2000:]
    jobs = _dry_run_jobs(r.stdout)["adapt_variant"]
    assert len(jobs) == 18
    for j in jobs:
        a, v = j["wildcards"]["animal"], j["wildcards"]["variant"]
        states = f"results/{a}/adaptive/sphere/states"
        assert (states in j["input"]) == v.startswith("sphere_r"), (a, v, j["input"])


@pytest.mark.slow
def test_the_solve_rule_schedules_the_longest_solves_first(tmp_path):
    # the dry run shows each solve job with its priority (deeptissue.variants.solve_priority): 10 for a bar
    # plus the phantom's depth, and 5 more for a variant others are turned from (they wait for it, after
    # the bars: the longest job starts first)
    import re

    r = _snakemake(tmp_path, "-n", "--cores", "2")
    assert r.returncode == 0, r.stderr[-2000:]
    jobs = re.findall(r"wildcards: animal=(\w+), variant=(\S+)\n\s+priority: ([\d.]+)", r.stdout)
    cfg = _load("test.yaml")
    depth = {a: c["phantom"]["depth_mm"] for a, c in cfg["animals"].items()}
    assert sorted((a, v) for a, v, _ in jobs) == sorted(
        (a, v) for a in depth for v in cfg["study"]["variants"]
    )
    for animal, variant, prio in jobs:
        base = 5.0 if variant == "sphere" else 0.0
        assert float(prio) == pytest.approx(
            (10.0 if variant.startswith("bar") else 0.0) + depth[animal] + base
        )
    # the turned variant waits for its base's end state
    turned = re.search(
        r"rule solve:\n\s+input: ([^\n]+)\n(?:.*\n){0,6}?\s+wildcards: animal=rat01, variant=sphere_rz\+15",
        r.stdout,
    )
    assert turned and "results/rat01/sphere/end_state.npz" in turned.group(1)


@pytest.mark.slow
def test_rule_aggregate_runs_on_hand_made_summaries(tmp_path):
    """sphere and sphere_rz+15 converged, bar failed (its summary says why): the animal is excluded, the study completes,
    and a second run has nothing to do."""
    for variant, k in [("sphere", 0.9), ("bar", 1.3), ("sphere_rz+15", 1.0)]:
        failed = "no convergence at 85% depth" if variant == "bar" else None
        _hand_made_run(tmp_path, "rat01", variant, k, failed=failed)
    _hand_made_pose(tmp_path, "rat01")
    # the study's tables go to results/summary/<study.name>, here "test" from config/test.yaml
    targets = [
        "results/summary/test/voi.csv",
        "results/summary/test/sections.png",
        "results/summary/test/orientations.png",
    ]
    r = _snakemake(tmp_path, *targets, "--cores", "1", "--allowed-rules", "aggregate")
    assert r.returncode == 0, r.stderr[-3000:]
    voi = pd.read_csv(tmp_path / "results" / "summary" / "test" / "voi.csv")
    assert list(voi["variant"]) == ["sphere", "bar", "sphere_rz+15"] and voi[
        "converged"
    ].tolist() == [True, False, True]
    assert voi["excluded"].all()
    assert voi["exclusion_reason"].iloc[0] == "not converged: bar: no convergence at 85% depth"
    bins = pd.read_csv(tmp_path / "results" / "summary" / "test" / "bins.csv").groupby(
        "variant", sort=False
    )["percent"]
    assert bins.sum(min_count=1).round(9).tolist()[0] == 100.0 and bins.count().tolist() == [
        8,
        0,
        8,
    ]
    for name in [
        "bins.csv",
        "voi.png",
        "bins.png",
        "voi_change.png",
        "sections.png",
        "orientations.png",
    ]:
        assert (tmp_path / "results" / "summary" / "test" / name).stat().st_size > 0
    r = _snakemake(tmp_path, *targets, "-n", "--allowed-rules", "aggregate")
    assert r.returncode == 0 and "Nothing to be done" in r.stdout + r.stderr


def _hand_made_run(root, animal, variant, k, *, failed=None):
    """A box's summary.json and result.vtu under ``root``/results/animal/variant: u_x = k y² / 10 [mm] (a
    shear that grows with k), or a failed run's summary with the reason ``failed``."""
    m = box_tet10(np.linspace(-3, 3, 7), np.linspace(0, 5, 6), np.linspace(-3, 3, 7))
    y = m.nodes_mm[:, 1]
    u = np.column_stack([k * y**2 / 10, 0 * y, 0 * y])
    s, strain = summarize_solution(m, u, animal=animal, variant=variant, indenter_force_N=0.1)
    if failed:
        s = failed_summary(animal=animal, variant=variant, reason=failed, increments=9)
    write_summary(root / "results" / animal / variant / "summary.json", s)
    write_result_vtu(root / "results" / animal / variant / "result.vtu", m, u, strain)
    return s


def _hand_made_pose(root, animal):
    save_pose(
        root / "results" / animal / "pose.json",
        Pose(
            indenter_axis=[0, -1, 0],
            tip_start_mm=[0, 5, 0],
            tip_end_mm=[0, 3, 0],
            depth_mm=2.0,
            bone_com_mm=[0, 1, 0],
            bone_rotation_deg=[0, 0, 0],
            bone_translation_mm=[0, 0, 0],
        ),
    )


def test_the_tables_hold_each_animals_own_variants_and_ask_for_no_other(tmp_path):
    from deeptissue.report import summary_tables

    runs = [("ratA", "sphere", 0.9), ("ratA", "sphere_rx+15", 1.0), ("ratB", "bar", 1.3)]
    made = [_hand_made_run(tmp_path, a, v, k) for a, v, k in runs]
    own = {"ratA": ["sphere", "sphere_rx+15"], "ratB": ["bar"]}
    voi, bins = summary_tables(made, animals=["ratA", "ratB"], variants=own)
    assert list(zip(voi["animal"], voi["variant"])) == [(a, v) for a, v, _ in runs]
    assert voi["voi_mm3"].tolist() == pytest.approx([s.voi_mm3 for s in made])
    assert bins.groupby(["animal", "variant"], sort=False).size().index.tolist() == [
        (a, v) for a, v, _ in runs
    ]
    # one list for every animal asks for ratB's sphere, which it does not have
    with pytest.raises(
        ValueError, match=r"no summary for ratA/bar, ratB/sphere, ratB/sphere_rx\+15$"
    ):
        summary_tables(made, animals=["ratA", "ratB"], variants=["sphere", "bar", "sphere_rx+15"])
    with pytest.raises(ValueError, match=r"no variants given for animal\(s\) ratB"):
        summary_tables(made, animals=["ratA", "ratB"], variants={"ratA": ["sphere"]})


@pytest.mark.slow
def test_aggregate_and_findings_run_when_an_animal_lacks_variants(tmp_path):
    """rat01 has sphere, bar and sphere_rz+15 (study.variants), rat02 only its own sphere: each animal's rows
    are its own variants, an orientation is compared with the sphere of its own animal only, and no table
    or figure asks for rat02's missing runs."""
    from deeptissue.findings import findings_table
    from deeptissue.report import voi_changes

    f = _with_own_variants(tmp_path, {"rat02": (2.5, ["sphere"])})
    made = {
        ("rat01", "sphere"): _hand_made_run(tmp_path, "rat01", "sphere", 0.9),
        ("rat01", "bar"): _hand_made_run(tmp_path, "rat01", "bar", 1.3),
        ("rat01", "sphere_rz+15"): _hand_made_run(tmp_path, "rat01", "sphere_rz+15", 1.0),
        ("rat02", "sphere"): _hand_made_run(tmp_path, "rat02", "sphere", 1.1),
    }
    for animal in ("rat01", "rat02"):
        _hand_made_pose(tmp_path, animal)
    # a summary of a variant rat02 does not have is left out, not read
    _hand_made_run(tmp_path, "rat02", "bar", 1.3, failed="not configured for rat02")
    out = tmp_path / "results" / "summary" / "study"
    targets = ["results/summary/study/voi.csv", "results/summary/study/findings.csv"]
    r = _snakemake(
        tmp_path,
        *targets,
        "--cores",
        "1",
        "--allowed-rules",
        "aggregate",
        "findings",
        configfile=f,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    voi = pd.read_csv(out / "voi.csv")
    assert list(zip(voi["animal"], voi["variant"])) == list(made)
    assert not voi["excluded"].any()  # rat02's failed bar is no variant of rat02's
    assert voi["voi_mm3"].tolist() == pytest.approx([s.voi_mm3 for s in made.values()])
    bins = pd.read_csv(out / "bins.csv")
    assert set(zip(bins["animal"], bins["variant"])) == set(made)
    # the change of sphere_rz+15 against rat01's own sphere; rat02 has nothing to compare
    ch = voi_changes(voi)
    assert list(zip(ch["animal"], ch["variant"])) == [("rat01", "bar"), ("rat01", "sphere_rz+15")]
    rz = ch.set_index("variant").loc["sphere_rz+15"]
    s_rz, s_ref = made[("rat01", "sphere_rz+15")], made[("rat01", "sphere")]
    assert rz["change_mm3"] == pytest.approx(s_rz.voi_mm3 - s_ref.voi_mm3)
    for name in ["bins.png", "voi.png", "voi_change.png", "findings_orientation.png"]:
        assert (out / name).stat().st_size > 0
    # the claims on the sphere rest on both animals, those on its orientations on rat01 alone
    findings = pd.read_csv(out / "findings.csv").set_index("claim_id")
    assert findings.loc["1", "n_animals"] == 2 and findings.loc["4a", "n_animals"] == 1
    assert findings.loc["3b", "verdict"] == findings_table(voi, bins)[4].verdict


@pytest.mark.slow
def test_inconsistent_study_config_is_a_one_line_error(tmp_path):
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["study"]["threshold"] = 0.25
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(cfg))
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "snakemake",
            "-n",
            "-s",
            str(ROOT / "Snakefile"),
            "--directory",
            str(tmp_path),
            "--configfile",
            str(tmp_path / "bad.yaml"),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode != 0
    assert (
        "config key study.bin_edges: must start at study.threshold (0.25), got 0.3"
        in r.stderr + r.stdout
    )
