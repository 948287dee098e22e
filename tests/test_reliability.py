"""Reliability: bad configs are refused before anything runs, files appear whole and readable, studies keep
their own tables, and a job stops with its Snakemake."""

import gzip
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import yaml

from deeptissue.config import RESERVED_ANIMAL_NAMES, study_name, validate_config
from deeptissue.fem.indenters import Indenter
from deeptissue.fem.solver import (
    BoneState,
    EndState,
    SolverSettings,
    load_bone_state,
    load_end_state,
    save_bone_state,
    save_end_state,
)
from deeptissue.imaging import ImagingError, load_nifti, write_nifti
from deeptissue.io import (
    PARTIAL_MARK,
    STALE_FOREIGN_S,
    ConfigError,
    atomic_path,
    load_config_file,
    remove_stale_partials,
    save_npz,
    write_json,
)
from deeptissue.phantom import PhantomSpec, _fluid_in_image, _Scene, check_indenter
from deeptissue.rigid import BoneMotion

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src")}

GOOD = """\
animals:
  rat01:
    phantom: {seed: 1, depth_mm: 2.0}
  rat02:
    phantom: {seed: 2, depth_mm: 2.5}
study:
  variants: [sphere]
"""


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _dry_run(workdir: Path, *targets_then_options: str) -> subprocess.CompletedProcess:
    """``snakemake -n`` of the real Snakefile in ``workdir`` (targets first: --configfile takes every word after it)."""
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        *targets_then_options,
        "-n",
        "--cores",
        "1",
        "-s",
        str(ROOT / "Snakefile"),
        "--directory",
        str(workdir),
    ]
    return subprocess.run(cmd, env=ENV, capture_output=True, text=True, timeout=300)


def _validate(text: str, name="study.yaml") -> dict:
    return validate_config(yaml.safe_load(text), SCHEMA, base_dir=ROOT, config_files=[name])


# --- configs that passed validation and then crashed or misled ---


def test_a_key_given_twice_is_refused_with_both_lines(tmp_path):
    f = _write(tmp_path / "study.yaml", GOOD + "animals:\n  rat03:\n    phantom: {seed: 3}\n")
    with pytest.raises(
        ConfigError, match=r"study.yaml, line 8: key 'animals' is given twice \(lines 1 and 8\)"
    ):
        load_config_file(f)
    f = _write(tmp_path / "animal.yaml", GOOD.replace("  rat02:", "  rat01:"))
    with pytest.raises(ConfigError, match=r"line 4: key 'rat01' is given twice \(lines 2 and 4\)"):
        load_config_file(f)


def test_an_unquoted_numeric_animal_name_says_to_quote_it(tmp_path):
    f = _write(tmp_path / "study.yaml", GOOD.replace("rat01:", "01:"))
    with pytest.raises(
        ConfigError,
        match=r"line 2: animal name 01 is read by YAML as an int, not a name; quote it: '01'",
    ):
        load_config_file(f)
    with pytest.raises(
        ConfigError, match=r"config key animals: animal name 1 is read by YAML as an int.*quote it"
    ):
        _validate(GOOD.replace("rat01:", "01:"))
    assert list(
        load_config_file(_write(tmp_path / "q.yaml", GOOD.replace("rat01:", "'01':")))["animals"]
    ) == ["01", "rat02"]


def test_a_yaml_syntax_error_names_file_line_and_column(tmp_path):
    f = _write(
        tmp_path / "study.yaml",
        GOOD.replace("{seed: 2, depth_mm: 2.5}", "{seed: 2, depth_mm: 2.5"),
    )
    with pytest.raises(
        ConfigError,
        match=r"study.yaml, line 6, column 6: YAML syntax error: expected ',' or '}', but got ':'",
    ):
        load_config_file(f)


def test_config_files_are_checked_without_snakemake(tmp_path, capsys, monkeypatch):
    # Snakemake reads a --configfile itself and reports a syntax error without its place: --check names it
    from deeptissue.config import main

    monkeypatch.chdir(ROOT)
    overlay = _write(tmp_path / "overlay.yaml", "study: {variants: [bar]}\n")
    main(
        [
            "--check",
            str(_write(tmp_path / "paper2.yaml", GOOD)),
            str(overlay),
            "--schema",
            str(SCHEMA),
        ]
    )
    assert "config OK: study paper2, animals ['rat01', 'rat02']" in capsys.readouterr().out
    bad = _write(tmp_path / "bad.yaml", GOOD.replace("[sphere]", "[sphere"))
    with pytest.raises(SystemExit) as exit_:
        main(["--check", str(bad), "--schema", str(SCHEMA)])
    assert exit_.value.code == 1
    assert "bad.yaml, line 8, column 1: YAML syntax error" in capsys.readouterr().err


def test_animals_named_like_a_folder_of_results_are_refused():
    for name in RESERVED_ANIMAL_NAMES:
        with pytest.raises(
            ConfigError, match=f"config key animals.{name}: '{name}' is a folder of results/"
        ):
            _validate(GOOD.replace("rat02:", f"{name}:"))


def test_the_reserved_names_are_every_study_folder_of_results():
    # every results/<folder>/ the rules write that is not an animal's is reserved
    folders = set()
    for smk in (ROOT / "workflow" / "rules").glob("*.smk"):
        folders |= set(re.findall(r'"results/([A-Za-z_]+)/', smk.read_text()))
    assert folders == set(RESERVED_ANIMAL_NAMES)


def test_phantom_values_it_cannot_render_are_refused_with_the_range_that_works():
    with pytest.raises(
        ConfigError,
        match=r"animals.rat01.phantom.depth_mm: must be a number > 0 \[mm\], got 0",
    ):
        _validate(GOOD.replace("depth_mm: 2.0", "depth_mm: 0"))
    with pytest.raises(
        ConfigError,
        match=r"animals.rat01.phantom: tilt_deg \[89.0, 0.0\]: .* tilt about X works "
        r"from -\d+\.\d to \d+\.\d deg",
    ):
        _validate(GOOD.replace("depth_mm: 2.0", "depth_mm: 2.0, tilt_deg: [89, 0]"))
    with pytest.raises(
        ConfigError,
        match=r"animals.rat02.phantom: depth_mm 5 mm: .* works from 0 to below \d\.\d\d mm",
    ):
        _validate(GOOD.replace("depth_mm: 2.5", "depth_mm: 5"))


@pytest.mark.slow
def test_the_ranges_check_indenter_states_are_what_the_phantom_renders():
    # inside the stated range the phantom builds its scene; outside it fails as check_indenter says
    with pytest.raises(ValueError) as tilt:
        check_indenter(PhantomSpec(tilt_deg=(89.0, 0.0)))
    lo, hi = map(float, re.search(r"from (\S+) to (\S+) deg", str(tilt.value)).groups())
    assert -80 < lo < -30 and 30 < hi < 80
    slab = (-9.5, 9.5)  # the default 20 slices 1 mm apart
    for t in (lo + 0.5, hi - 0.5):
        scene = _Scene(
            PhantomSpec(tilt_deg=(t, 0.0))
        )  # renders, with the indenter inside the slab
        assert all(slab[0] <= p[2] <= slab[1] for p in (scene.skin_point, scene.tip_end))
    # past the range the indenter leaves the slab, or too little of its fluid column stays in the image
    # for the pose stage to find its axis (LIMITS' fluid_column_length_mm, 5 mm)
    outside = PhantomSpec(tilt_deg=(hi + 1.0, 0.0))
    scene = _Scene(outside)
    leaves = not all(slab[0] <= p[2] <= slab[1] for p in (scene.skin_point, scene.tip_end))
    front = scene.tip_end - outside.indenter_wall_mm * scene.axis
    assert leaves or _fluid_in_image(outside, front, scene.axis, slab) < 5.0
    with pytest.raises(ValueError, match="does not leave the leg"):
        _Scene(PhantomSpec(tilt_deg=(89.0, 0.0)))
    with pytest.raises(ValueError) as depth:
        check_indenter(PhantomSpec(depth_mm=5.0))
    below = float(re.search(r"below (\S+) mm", str(depth.value)).group(1))
    gap = _Scene(PhantomSpec(depth_mm=below - 0.05)).bone_gap()
    assert 0 < gap < 0.1  # the scene's own clearance at the stated limit
    with pytest.raises(ValueError, match="reaches the tibia"):
        _Scene(PhantomSpec(depth_mm=below + 0.05))


def test_a_study_is_named_after_its_first_config_file():
    assert study_name(["/x/config/paper.yaml", "config/preview.yaml"]) == "paper"
    assert study_name([]) == "config"
    assert _validate(GOOD, name="config/test.yaml")["study"]["name"] == "test"
    assert _validate(GOOD.replace("study:\n", "study:\n  name: mine\n"))["study"]["name"] == "mine"


@pytest.mark.slow
@pytest.mark.parametrize(
    "change, message",
    [
        (
            lambda t: t.replace("  rat02:", "  rat01:"),
            r"line 4: key 'rat01' is given twice \(lines 2 and 4\)",
        ),
        (
            lambda t: t.replace("rat01:", "01:"),
            r"animal name 01 is read by YAML as an int, not a name; quote it: '01'",
        ),
        (
            lambda t: t.replace("rat02:", "summary:"),
            r"config key animals.summary: 'summary' is a folder of results/",
        ),
        (
            lambda t: t.replace("depth_mm: 2.0", "depth_mm: 0"),
            r"animals.rat01.phantom.depth_mm: must be a number > 0",
        ),
        (
            lambda t: t.replace("depth_mm: 2.0", "depth_mm: 2.0, tilt_deg: [89, 0]"),
            r"tilt about X works from",
        ),
    ],
    ids=["duplicate", "numeric", "reserved", "depth0", "tilt89"],
)
def test_the_workflow_refuses_each_bad_config_before_it_runs(tmp_path, change, message):
    f = _write(tmp_path / "study.yaml", change(GOOD))
    r = _dry_run(tmp_path, "--configfile", str(f))
    assert r.returncode != 0
    assert re.search(message, r.stdout + r.stderr), (r.stdout + r.stderr)[-2000:]
    assert not (tmp_path / "results").exists()


@pytest.mark.slow
def test_a_syntax_error_in_the_default_config_names_line_and_column(tmp_path):
    _write(tmp_path / "config" / "config.yaml", GOOD.replace("[sphere]", "[sphere"))
    r = _dry_run(tmp_path)
    assert r.returncode != 0
    assert (
        "config file config/config.yaml, line 8, column 1: YAML syntax error"
        in r.stdout + r.stderr
    )


@pytest.mark.slow
def test_targets_come_before_configfile_as_the_readme_says(tmp_path):
    f = _write(tmp_path / "study.yaml", GOOD)
    assert _dry_run(tmp_path, "study", "--configfile", str(f)).returncode == 0
    assert _dry_run(tmp_path, f"--configfile={f}", "study").returncode == 0
    r = _dry_run(tmp_path, "--configfile", str(f), "study")  # 'study' is read as a config file
    assert r.returncode != 0 and "No such file or directory: 'study'" in r.stdout + r.stderr


@pytest.mark.slow
def test_two_studies_in_one_checkout_write_their_own_tables(tmp_path):
    a, b = (
        _write(tmp_path / "a.yaml", GOOD),
        _write(tmp_path / "b.yaml", GOOD.replace("[sphere]", "[sphere, bar]")),
    )
    ra, rb = (
        _dry_run(tmp_path, "study", "--configfile", str(a)),
        _dry_run(tmp_path, "study", "--configfile", str(b)),
    )
    assert ra.returncode == 0 and rb.returncode == 0, ra.stderr[-2000:] + rb.stderr[-2000:]
    assert (
        "results/summary/a/voi.csv" in ra.stdout and "results/summary/b/voi.csv" not in ra.stdout
    )
    assert (
        "results/summary/b/voi.csv" in rb.stdout and "results/summary/a/voi.csv" not in rb.stdout
    )


# --- files whole, readable and not lost ---


def _bone_state(n=30):
    return BoneState(
        displacement_mm=np.arange(n, dtype=float),
        contact={"cast": (np.arange(3), np.ones(3))},
        strain_energy_mJ=1.5,
        history=(),
        newton_iterations=4,
        wall_s=1.0,
        assembly_s=0.5,
        linear_solve_s=0.3,
        contact_s=0.1,
        settings=SolverSettings(),
    )


def _end_state(n=30):
    return EndState(
        displacement_mm=np.arange(n, dtype=float),
        contact={"indenter": (np.arange(2), np.ones(2))},
        indenter=Indenter(),
        bone_motion=BoneMotion(),
        settings=SolverSettings(),
    )


class _Interrupted(KeyboardInterrupt):
    pass


def _interrupt_after_some_bytes(monkeypatch, name):
    """Make ``numpy.<name>`` write a few bytes, then stop as Ctrl-C does."""

    def partial(file, *args, **kwargs):
        file.write(b"PK\x03\x04 half an archive")
        raise _Interrupted

    monkeypatch.setattr(np, name, partial)


@pytest.mark.parametrize(
    "write, numpy_writer",
    [
        (lambda p: save_bone_state(p, _bone_state()), "savez"),
        (lambda p: save_end_state(p, _end_state()), "savez"),
        (lambda p: save_npz(p, failed=np.array("not converged")), "savez_compressed"),
    ],
    ids=["bone_state", "end_state", "failure_marker"],
)
def test_an_interrupted_writer_leaves_no_file(tmp_path, monkeypatch, write, numpy_writer):
    path = tmp_path / "out" / "state.npz"
    with monkeypatch.context() as m:
        _interrupt_after_some_bytes(m, numpy_writer)
        with pytest.raises(_Interrupted):
            write(path)
    assert list(path.parent.iterdir()) == []  # neither the file nor a temporary one
    write(path)  # and uninterrupted, a whole file
    assert list(path.parent.iterdir()) == [path]


def test_the_states_read_back_after_an_atomic_write(tmp_path):
    save_bone_state(tmp_path / "bone_state.npz", _bone_state())
    save_end_state(tmp_path / "end_state.npz", _end_state())
    assert load_bone_state(tmp_path / "bone_state.npz").newton_iterations == 4
    assert np.array_equal(
        load_end_state(tmp_path / "end_state.npz").displacement_mm, np.arange(30.0)
    )


def test_the_study_failure_markers_are_written_atomically(tmp_path, monkeypatch):
    # run_bone_state records a failed set-up (no mesh file) in its output; interrupted, it leaves nothing
    from deeptissue.study import run_bone_state

    out = tmp_path / "bone_state.npz"
    kw = dict(
        mesh_path=tmp_path / "missing.npz",
        cast_path=None,
        pose_path=tmp_path / "pose.json",
        state_path=out,
        fem_cfg={},
    )
    with monkeypatch.context() as m:
        _interrupt_after_some_bytes(m, "savez_compressed")
        with pytest.raises(_Interrupted):
            run_bone_state(**kw)
    assert list(tmp_path.iterdir()) == []
    assert run_bone_state(**kw) is None
    with np.load(out) as d:
        assert "missing.npz" in str(d["failed"])


_KILLED_WRITER = """
import os, signal, sys
from deeptissue.io import atomic_path
with atomic_path(sys.argv[1]) as tmp:
    tmp.write_bytes(b"PK half an archive")
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_writer_killed_mid_write_leaves_a_partial_the_next_write_removes(tmp_path):
    """SIGKILL (the out-of-memory killer) runs no finally block: the temporary stays, named by its pattern;
    writing the same output again removes it, and the output appears whole."""
    path = tmp_path / "results" / "rat01" / "end_state.npz"
    r = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(path)], env=ENV, timeout=60)
    assert r.returncode == -signal.SIGKILL
    (partial,) = path.parent.iterdir()
    assert partial.name.startswith(f".end_state.npz{PARTIAL_MARK}") and partial.name.endswith(
        ".npz"
    )
    save_end_state(path, _end_state())
    assert list(path.parent.iterdir()) == [path]


def test_stale_partials_are_found_under_results_and_live_ones_kept(tmp_path):
    """remove_stale_partials (the workflow's onstart): a partial of a killed process on this host, and one of
    another host unchanged for longer than STALE_FOREIGN_S, go; one being written, and a recent one of another
    host, stay, as do ordinary hidden files."""
    results = tmp_path / "results"
    r = subprocess.run(
        [sys.executable, "-c", _KILLED_WRITER, str(results / "rat01" / "qc" / "model_all.png")],
        env=ENV,
        timeout=60,
    )
    assert r.returncode == -signal.SIGKILL
    (killed,) = (results / "rat01" / "qc").iterdir()
    old = _write(results / "rat02" / f".mesh.npz{PARTIAL_MARK}node07-4242-abcdefgh.npz", "x")
    os.utime(old, (time.time() - STALE_FOREIGN_S - 60,) * 2)
    recent = _write(results / "rat02" / f".pose.json{PARTIAL_MARK}node07-4243-abcdefgh.json", "x")
    hidden = _write(results / ".keep", "")
    with atomic_path(results / "rat03" / "pose.json") as live:
        live.write_text("{}")
        assert sorted(remove_stale_partials(results)) == sorted([killed, old])
        assert live.exists() and recent.exists() and hidden.exists()
    assert (results / "rat03" / "pose.json").read_text() == "{}"


@pytest.mark.slow
def test_a_run_from_the_workflow_folder_works_in_the_repository(tmp_path):
    """``snakemake -s ../Snakefile`` started in workflow/ works in the repository (workdir): its
    .snakemake (and results/) are the repository's, none appear in workflow/."""
    repo = tmp_path / "repo"
    (repo / "workflow").mkdir(parents=True)
    (repo / "Snakefile").write_text((ROOT / "Snakefile").read_text())
    for d in ("rules", "scripts", "schemas", "envs", "report"):
        (repo / "workflow" / d).symlink_to(ROOT / "workflow" / d)
    _write(repo / "config" / "config.yaml", GOOD)
    cmd = [sys.executable, "-m", "snakemake", "-n", "--cores", "1", "-s", "../Snakefile"]
    r = subprocess.run(
        cmd, cwd=repo / "workflow", env=ENV, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "results/rat01/mri/pre.nii.gz" in r.stdout
    assert (repo / ".snakemake").is_dir()
    assert sorted(p.name for p in (repo / "workflow").iterdir()) == sorted(
        ["rules", "scripts", "schemas", "envs", "report"]
    )


@pytest.mark.slow
def test_an_incomplete_output_is_made_again_by_the_same_command(tmp_path):
    """An output a killed job left (marked incomplete in .snakemake/) is redone by the plain command, through
    the workflow's default profile (profiles/default: rerun-incomplete), with no extra flag."""
    from base64 import urlsafe_b64encode

    f = _write(tmp_path / "study.yaml", GOOD)
    target = "results/rat01/mri/pre.nii.gz"
    _write(tmp_path / target, "half a file")
    marker = tmp_path / ".snakemake" / "incomplete" / urlsafe_b64encode(target.encode()).decode()
    _write(marker, '{"external_jobid": null}')
    r = _dry_run(tmp_path, target, "--configfile", str(f))
    assert r.returncode == 0, (r.stdout + r.stderr)[-2000:]
    assert re.search(r"rule phantom:", r.stdout)
    r = _dry_run(tmp_path, target, "--configfile", str(f), "--workflow-profile", "none")
    assert r.returncode != 0 and "incomplete" in (r.stdout + r.stderr).lower()


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_written_files_honour_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        write_json(tmp_path / "pose.json", {"a": 1})
        save_bone_state(tmp_path / "bone_state.npz", _bone_state())
        with atomic_path(tmp_path / "x.png") as tmp:
            tmp.write_bytes(b"png")
    finally:
        os.umask(old)
    for name in ("pose.json", "bone_state.npz", "x.png"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode


def _truncated_nifti(tmp_path) -> Path:
    path = tmp_path / "during.nii.gz"
    write_nifti(path, np.random.default_rng(0).random((16, 16, 4)), np.eye(4))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises((EOFError, gzip.BadGzipFile, OSError, ValueError)):
        np.asarray(nib.load(str(path)).dataobj)  # what nibabel alone says: no file name
    return path


def test_a_truncated_scan_names_animal_and_file(tmp_path):
    path = _truncated_nifti(tmp_path)
    with pytest.raises(
        ImagingError,
        match=rf"animal rat01, file {re.escape(str(path))}: cannot read the voxel data, "
        "the file is truncated or corrupt",
    ):
        load_nifti(path, animal="rat01")


def test_the_pose_stage_reads_the_scan_through_the_same_error(tmp_path):
    from deeptissue.pose import PoseFiles, run_pose

    path = _truncated_nifti(tmp_path)
    out = {k: tmp_path / f"{k}.png" for k in ("axis_png", "tip_png", "bone_png")}
    with pytest.raises(
        ImagingError,
        match=rf"animal rat01, file {re.escape(str(path))}: cannot read the voxel data",
    ):
        run_pose(
            PoseFiles(
                during_nifti=path,
                pre_contours=tmp_path / "pre.npz",
                during_contours=tmp_path / "during.npz",
                pose_json=tmp_path / "pose.json",
                **out,
            ),
            options={},
            override={},
            animal="rat01",
        )


# --- a job stops with its Snakemake ---

_JOB = """
import sys, time
from pathlib import Path
from deeptissue.io import atomic_path, script_log
out = Path(sys.argv[1])
with script_log(out.with_suffix(".log"), "solve"):
    with atomic_path(out) as tmp:
        tmp.write_text("half a result")
        Path(sys.argv[2]).write_text("writing")
        time.sleep(60)
"""

# stands in for Snakemake: a process whose command line runs a file named `snakemake`, that starts the job
_SNAKEMAKE = """
import subprocess, sys, time
subprocess.Popen([sys.executable, sys.argv[1], sys.argv[2], sys.argv[3]])
time.sleep(120)
"""


def _wait_for(predicate, timeout_s):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def _job_pid(marker: Path, parent: int) -> int | None:
    """The pid of the job that writes ``marker`` (the child of the stand-in ``parent``)."""
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != parent:
            try:
                if str(marker) in (proc / "cmdline").read_bytes().decode(errors="replace"):
                    return int(proc.name)
            except OSError:
                continue
    return None


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")
def test_a_job_stops_without_writing_when_its_snakemake_is_killed(tmp_path):
    job, fake = (
        _write(tmp_path / "job.py", _JOB),
        _write(tmp_path / "bin" / "snakemake", _SNAKEMAKE),
    )
    out, started = tmp_path / "results" / "summary.json", tmp_path / "started"
    out.parent.mkdir()
    parent = subprocess.Popen(
        [sys.executable, str(fake), str(job), str(out), str(started)], env=ENV
    )
    try:
        assert _wait_for(started.exists, 30)
        pid = _job_pid(started, parent.pid)
        assert pid is not None
        parent.kill()  # SIGKILL: Snakemake cannot stop its jobs itself
        parent.wait()
        assert _wait_for(
            lambda: (
                not Path(f"/proc/{pid}").exists()
                or "Z" in Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            ),
            10,
        )
    finally:
        if parent.poll() is None:
            parent.kill()
    assert list(out.parent.iterdir()) == [out.with_suffix(".log")]  # no result, no temporary file
    log = out.with_suffix(".log").read_text()
    assert (
        f"Snakemake (pid {parent.pid}) is gone: stopping this job" in log
        and "solve stopped (interrupted)" in log
    )


@pytest.mark.skipif(not hasattr(signal, "SIGTERM"), reason="needs SIGTERM")
def test_sigterm_stops_a_job_without_writing(tmp_path):
    job = _write(tmp_path / "job.py", _JOB)
    out, started = tmp_path / "results" / "summary.json", tmp_path / "started"
    out.parent.mkdir()
    proc = subprocess.Popen([sys.executable, str(job), str(out), str(started)], env=ENV)
    assert _wait_for(started.exists, 30)
    proc.terminate()
    assert proc.wait(timeout=10) != 0
    assert list(out.parent.iterdir()) == [out.with_suffix(".log")]
    assert "solve stopped (interrupted)" in out.with_suffix(".log").read_text()
