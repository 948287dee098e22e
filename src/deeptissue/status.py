"""Where the study's solves are: one line per solve job, read from the jobs' logs.

``python -m deeptissue.status [results]`` prints, for every ``results/{animal}/logs/solve_{variant}.log``,
``bone_state_{mesh}.log`` and ``adapt_{variant}.log``: the job, its state (running, converged, not converged,
failed, waiting), the load reached of 4 (full depth), the converged / attempted increments, the Newton
iterations, the solve's elapsed time and how long ago its log last changed. A job that runs several solves (a
turned variant solved again from the start, the passes of an adaptive run) shows its last one; an adaptive run
meshing its next pass is running. The solver logs
one progress line per increment (:mod:`deeptissue.fem.progress`).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .fem.progress import NEXT_PASS, Progress, parse_end, parse_progress

__all__ = ["SolveStatus", "collect", "format_status", "main", "read_solve_log"]

_JOBS = ("solve_", "bone_state_", "adapt_")  # log name prefixes of the jobs that solve


@dataclass(frozen=True)
class SolveStatus:
    """One solve job: ``animal``, ``job`` (log name without .log), ``state`` ('running', 'converged',
    'not converged', 'failed', 'waiting': no increment yet), ``progress`` (the last Progress, or None),
    ``reason`` (why it did not converge or failed), ``idle_s`` (seconds since its log last changed)."""

    animal: str
    job: str
    state: str
    progress: Progress | None
    reason: str
    idle_s: float


def read_solve_log(text: str) -> tuple[str, Progress | None, str]:
    """(state, last progress, reason) of one job's log text (see :class:`SolveStatus`)."""
    state, progress, reason = "waiting", None, ""
    for line in text.splitlines():
        p = parse_progress(line)
        if p is not None:
            state, progress, reason = "running", p, ""
            continue
        if NEXT_PASS in line:  # an adaptive run goes on to its next pass
            state, reason = "running", ""
            continue
        end = parse_end(line)
        if end is not None:
            state, reason = ("converged", "") if end[0] else ("not converged", end[1])
        elif " failed" in line and " ERROR " in line or "stopped (interrupted)" in line:
            state, reason = "failed", line.split(" ERROR ", 1)[-1].strip()
    return state, progress, reason


def collect(results: str | Path, now: float | None = None) -> list[SolveStatus]:
    """The status of every solve job with a log under ``results`` (sorted by animal and job)."""
    now = time.time() if now is None else now
    out = []
    for path in sorted(Path(results).glob("*/logs/*.log")):
        if not path.name.startswith(_JOBS):
            continue
        state, progress, reason = read_solve_log(path.read_text(errors="replace"))
        out.append(
            SolveStatus(
                animal=path.parent.parent.name,
                job=path.stem,
                state=state,
                progress=progress,
                reason=reason,
                idle_s=max(now - path.stat().st_mtime, 0.0),
            )
        )
    return out


def format_status(s: SolveStatus) -> str:
    """One line: animal, job, state, load, increments, Newton iterations, elapsed, idle time, reason."""
    head = f"{s.animal:<10} {s.job:<24} {s.state:<14}"
    p = s.progress
    body = (
        f"load {p.load:.3f}/4  increments {p.increments}/{p.attempts}  newton {p.newton_iterations}  "
        f"{p.elapsed_s:.0f} s"
        if p is not None
        else ("no increment yet" if s.state == "waiting" else "-")
    )
    tail = f"  (log idle {s.idle_s:.0f} s)" if s.state in ("running", "waiting") else ""
    why = f"  {s.reason}" if s.reason else ""
    return f"{head} {body}{tail}{why}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m deeptissue.status",
        description="One line per solve job of a study, read from results/{animal}/logs/.",
    )
    parser.add_argument("results", nargs="?", default="results", help="the results folder")
    args = parser.parse_args(argv)
    if not Path(args.results).is_dir():
        print(
            f"{args.results}: no such folder (run from the checkout, or name it)", file=sys.stderr
        )
        return 2
    rows = collect(args.results)
    if not rows:
        print(f"{args.results}: no solve logs yet")
    for s in rows:
        print(format_status(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
