"""deeptissue.status: one line per solve job, read from hand-made logs in the format the solver writes."""

import os

from deeptissue.fem.progress import NEXT_PASS, Progress, format_progress, parse_end, parse_progress
from deeptissue.status import collect, format_status, main, read_solve_log

_T = "2026-12-06 18:15:{:02d},000 INFO deeptissue.fem.solver "


def _lines(*msgs):
    return "".join(_T.format(i) + m + "\n" for i, m in enumerate(msgs))


RUNNING = _lines(
    "step 4 t 3.0000->3.2500 ok it 0 changes 0 F 0 N pen 0.0263 mm",
    "progress: load 3.2500/4 increments 1/1 newton 0 elapsed 4.6 s",
    "step 4 t 3.2500->4.0000 cut (too many iterations) it 25 changes 80 F 0 N pen nan mm",
    "progress: load 3.2500/4 increments 1/2 newton 25 elapsed 61.0 s",
)
STALLED = RUNNING + _lines(
    "progress: load 3.2507/4 increments 9/21 newton 240 elapsed 700.2 s",
    "solve not converged (stalled: the load advanced 0.00072 in the last 12 increments "
    "(stall_load 0.001) at t = 3.2507) in 700.3 s: 21 increments, 240 Newton iterations, 900 active-set changes",
)
CONVERGED = _lines(
    "progress: load 4.0000/4 increments 9/9 newton 15 elapsed 99.8 s",
    "solve converged in 99.9 s: 9 increments, 15 Newton iterations, 183 active-set changes",
)


def test_the_progress_line_reads_back_what_was_written():
    p = Progress(3.6029, 3, 4, 8, 52.25)
    line = format_progress(p)
    assert line == "progress: load 3.6029/4 increments 3/4 newton 8 elapsed 52.2 s"
    assert parse_progress(_T.format(0) + line) == Progress(3.6029, 3, 4, 8, 52.2)
    assert parse_progress("step 4 t 3.0000->3.2500 ok") is None
    assert parse_end(CONVERGED.splitlines()[-1]) == (True, "")


def test_a_log_reads_as_running_stalled_converged_failed_or_waiting():
    state, p, reason = read_solve_log(RUNNING)
    assert state == "running" and (p.load, p.increments, p.attempts, p.newton_iterations) == (
        3.25,
        1,
        2,
        25,
    )
    assert p.elapsed_s == 61.0 and reason == ""
    state, p, reason = read_solve_log(STALLED)
    assert state == "not converged" and p.load == 3.2507 and reason.startswith("stalled:")
    assert read_solve_log(CONVERGED)[0] == "converged"
    # a turned variant whose turn failed goes on from the start: running again after the first end line
    assert read_solve_log(STALLED + RUNNING)[0] == "running"
    failed = RUNNING + "2026-12-06 18:16:00,000 ERROR solve solve failed\nTraceback ...\n"
    assert read_solve_log(failed)[:1] == ("failed",)
    assert read_solve_log(_lines("Initializing CellBasis"))[0] == "waiting"
    # an adaptive run between two passes: its first solve converged, the next pass is being meshed
    between = CONVERGED + (
        "2026-12-06 18:16:00,000 INFO deeptissue.adapt_limb rat01/sphere adaptive pass 1: "
        f"{NEXT_PASS}\n"
    )
    after_pass = CONVERGED + _lines("adaptive pass 0: 18180 DOFs, goal met: False")
    assert read_solve_log(after_pass)[0] == "converged"
    state, p, _ = read_solve_log(between)
    assert state == "running" and p.load == 4.0
    assert read_solve_log(between + RUNNING)[0] == "running"
    assert read_solve_log(between + CONVERGED)[0] == "converged"


def test_status_prints_one_line_per_solve_job(tmp_path, capsys):
    logs = tmp_path / "rat01" / "logs"
    logs.mkdir(parents=True)
    (logs / "solve_sphere.log").write_text(RUNNING)
    (logs / "solve_bar.log").write_text(CONVERGED)
    (logs / "bone_state_all.log").write_text(CONVERGED)
    (logs / "mesh_all.log").write_text("not a solve\n")  # not a solve job: left out
    os.utime(logs / "solve_sphere.log", (1000.0, 1000.0))
    rows = collect(tmp_path, now=1030.0)
    assert [(r.job, r.state) for r in rows] == [
        ("bone_state_all", "converged"),
        ("solve_bar", "converged"),
        ("solve_sphere", "running"),
    ]
    assert rows[2].idle_s == 30.0
    assert format_status(rows[2]) == (
        "rat01      solve_sphere             running        "
        "load 3.250/4  increments 1/2  newton 25  61 s  (log idle 30 s)"
    )
    assert main([str(tmp_path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 3 and "solve_bar" in out[1] and "load 4.000/4" in out[1]
    assert main([str(tmp_path / "nowhere")]) == 2
