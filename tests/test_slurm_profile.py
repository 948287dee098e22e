"""The SLURM profile: every rule that runs a job asks for its resources, and the user guide's commands work as written."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PROFILE = yaml.safe_load((ROOT / "profiles/slurm/config.yaml").read_text())


def _job_rules() -> set[str]:
    """Rules of workflow/rules/*.smk with an action (script, shell, run): those the cluster runs as jobs."""
    rules = set()
    for smk in sorted((ROOT / "workflow/rules").glob("*.smk")):
        for block in re.split(r"^(?=rule \w+:)", smk.read_text(), flags=re.M):
            m = re.match(r"rule (\w+):", block)
            if m and re.search(r"^    (script|shell|run|notebook|wrapper):", block, flags=re.M):
                rules.add(m.group(1))
    return rules


def test_every_job_rule_has_its_own_memory_time_and_cpus():
    rules = _job_rules()
    assert {
        "solve",
        "bone_state",
        "aggregate",
        "verify_locking",
        "config_docs",
    } <= rules  # the parse finds them
    entries = PROFILE["set-resources"]
    assert rules <= set(entries), (
        f"rules without a set-resources entry: {sorted(rules - set(entries))}"
    )
    assert set(entries) <= rules, f"entries of no rule: {sorted(set(entries) - rules)}"
    for rule in rules:
        assert {"mem_mb", "runtime", "cpus_per_task"} <= set(entries[rule]), rule
    for rule, threads in PROFILE["set-threads"].items():
        assert entries[rule]["cpus_per_task"] == threads, rule


def test_job_states_come_from_squeue_which_needs_no_accounting():
    assert PROFILE["slurm-status-command"] == "squeue"
    # the plugin falls back to sacct when MinJobAge (300 s by default) < 3 x the first wait
    assert 3 * PROFILE["slurm-init-seconds-before-status-checks"] <= 300


def _guide_cluster_commands() -> list[str]:
    text = (ROOT / "docs" / "usage.md").read_text()
    section = text.split("## On a SLURM cluster", 1)[1].split("\n## ", 1)[0]
    return [
        line.split("#")[0].strip()
        for line in section.splitlines()
        if line.startswith(".venv/bin/snakemake") and "--profile profiles/slurm" in line
    ]


@pytest.mark.slow
def test_the_user_guides_cluster_commands_plan_every_job_with_its_resources():
    commands = _guide_cluster_commands()
    assert any("--default-resources slurm_account=" in c for c in commands)
    job_rules = _job_rules()
    exe = Path(sys.executable).with_name("snakemake")
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    for command in commands:
        args = command.split()[1:]
        if (
            "slurm_account=" in command
        ):  # every target: the account replaces default-resources for all rules
            args = ["convergence", "verify", *args]
        if "-n" not in args:
            args.append("-n")
        # --forceall: plan every job whatever results/ already holds
        p = subprocess.run(
            [str(exe), *args, "--forceall"],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        out = p.stdout + p.stderr
        assert p.returncode == 0, f"{command}\n{out[-3000:]}"
        jobs = [
            (rule, resources)
            for rule, resources in re.findall(
                r"^rule (\w+):\n(?:    .*\n)*?    resources: (.*)$", out, flags=re.M
            )
            if rule in job_rules
        ]
        assert jobs, out[-2000:]  # (target rules such as study have no action and run no job)
        if "slurm_account=" in command:
            assert {"verify_locking", "convergence_run", "adapt_variant"} <= {
                rule for rule, _ in jobs
            }
        for rule, resources in jobs:
            assert "mem_mb=" in resources and "runtime=" in resources, (command, rule, resources)
            if "slurm_account=" in command:
                assert "slurm_account=ACCT" in resources and "slurm_partition=PART" in resources, (
                    rule,
                    resources,
                )
