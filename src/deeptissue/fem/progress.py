"""The one-line progress record a solve logs after each attempted increment, and its parser.

A solve (:mod:`deeptissue.fem.solver`) logs ``progress: load 3.6029/4 increments 3/4 newton 8 elapsed 52.3 s``
(the load parameter reached of 4 = full depth, converged / attempted increments, Newton iterations, wall time
[s] since the solve started), and at its end ``solve converged in ...`` or ``solve not converged (reason) in
...``. An adaptive run (:func:`deeptissue.adapt.adapt`) logs :data:`NEXT_PASS` when it goes on to mesh and solve
another pass. :mod:`deeptissue.status` reads these lines from the jobs' logs.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["NEXT_PASS", "Progress", "format_progress", "parse_end", "parse_progress"]

#: what an adaptive run logs when it goes on to another pass
NEXT_PASS = "meshing to the refined sizes"

_PROGRESS = re.compile(
    r"progress: load (?P<load>[-\d.]+)/4 increments (?P<ok>\d+)/(?P<all>\d+) "
    r"newton (?P<newton>\d+) elapsed (?P<elapsed>[\d.]+) s"
)
_END = re.compile(r"solve (?P<state>converged|not converged \((?P<reason>.*)\)) in [\d.]+ s")


@dataclass(frozen=True)
class Progress:
    """A solve's state after an increment: load (0-4, 4 = full depth), increments converged and attempted,
    Newton iterations, elapsed wall time [s]."""

    load: float
    increments: int
    attempts: int
    newton_iterations: int
    elapsed_s: float


def format_progress(p: Progress) -> str:
    """The log line of ``p`` (the text after the logger's timestamp and name)."""
    return (
        f"progress: load {p.load:.4f}/4 increments {p.increments}/{p.attempts} "
        f"newton {p.newton_iterations} elapsed {p.elapsed_s:.1f} s"
    )


def parse_progress(line: str) -> Progress | None:
    """The Progress in a log line, None if the line has none."""
    m = _PROGRESS.search(line)
    if m is None:
        return None
    return Progress(
        load=float(m["load"]),
        increments=int(m["ok"]),
        attempts=int(m["all"]),
        newton_iterations=int(m["newton"]),
        elapsed_s=float(m["elapsed"]),
    )


def parse_end(line: str) -> tuple[bool, str] | None:
    """(converged, reason) of a solve's last log line, None if the line is not one."""
    m = _END.search(line)
    if m is None:
        return None
    return m["state"] == "converged", m["reason"] or ""
