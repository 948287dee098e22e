"""Small file helpers shared by all stages: outputs appear whole or not at all, config files are read strictly."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml

__all__ = [
    "PARTIAL_MARK",
    "STALE_FOREIGN_S",
    "ConfigError",
    "atomic_path",
    "load_config_file",
    "read_json",
    "remove_stale_partials",
    "save_npz",
    "script_log",
    "snakemake_ancestor",
    "stop_with_snakemake",
    "write_json",
]


@contextlib.contextmanager
def script_log(log_path: str | Path, job: str) -> Iterator[None]:
    """Run a workflow script's body with stderr and logging (INFO) going to ``log_path``; an exception
    is logged with its traceback as "<job> failed" and re-raised (Snakemake then marks the job failed
    and keeps the log). The body stops, as by Ctrl-C, on SIGTERM or when the Snakemake that started it
    is gone (:func:`stop_with_snakemake`), so no job goes on writing after its workflow."""
    with open(log_path, "w") as log, contextlib.redirect_stderr(log):
        root = logging.getLogger()
        handler = logging.StreamHandler(log)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s %(message)s"))
        root.addHandler(handler)
        root.setLevel(logging.INFO)
        try:
            with stop_with_snakemake(logging.getLogger(job)):
                yield
        except Exception:
            logging.getLogger(job).exception("%s failed", job)
            raise
        except KeyboardInterrupt:
            logging.getLogger(job).error(
                "%s stopped (interrupted); its outputs are not written", job
            )
            raise
        finally:
            root.removeHandler(handler)


def _start_time(pid: int) -> str | None:
    """The start time of process ``pid`` (clock ticks since boot, /proc/<pid>/stat), None if it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def snakemake_ancestor() -> tuple[int, str] | None:
    """The nearest ancestor process that runs Snakemake, as (pid, start time); None if there is none or no /proc.

    A process runs Snakemake if an argument of its command line is a file named ``snakemake`` or it is
    started as ``-m snakemake``. The start time tells the process from a later one with the same pid.
    """
    pid = os.getppid()
    while pid > 1:
        try:
            args = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
            ppid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            return None
        module = args[args.index("-m") + 1] if "-m" in args[:-1] else ""
        if module == "snakemake" or any(Path(a).name == "snakemake" for a in args[:2]):
            start = _start_time(pid)
            return None if start is None else (pid, start)
        pid = ppid
    return None


@contextlib.contextmanager
def stop_with_snakemake(
    log: logging.Logger | None = None, *, poll_s: float = 2.0, grace_s: float = 60.0
) -> Iterator[None]:
    """Run the block so that SIGTERM, or the end of the Snakemake process that started it, stops it as Ctrl-C does.

    SIGTERM raises KeyboardInterrupt in the main thread, so ``finally`` blocks run and
    :func:`atomic_path` removes its temporary file. A thread checks every ``poll_s`` seconds that the
    Snakemake ancestor (:func:`snakemake_ancestor`) still runs: when it is gone (killed with SIGKILL,
    say) the job sends itself SIGTERM, and exits ``grace_s`` seconds later if the block has not stopped
    (a long call into compiled code). Outside Snakemake or off Linux only the SIGTERM part applies.

    Parameters
    ----------
    log : logging.Logger, optional
        Where to say why the job stops.
    poll_s, grace_s : float, optional
        Seconds between checks, and before a forced exit.
    """
    log = log or logging.getLogger(__name__)
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main else None

    def on_term(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    if main and previous in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, on_term)
    done = threading.Event()
    parent = snakemake_ancestor()

    def watch():
        while not done.wait(poll_s):
            if _start_time(parent[0]) != parent[1]:
                log.error("Snakemake (pid %d) is gone: stopping this job", parent[0])
                os.kill(os.getpid(), signal.SIGTERM)
                if not done.wait(grace_s):
                    os._exit(1)
                return

    if parent is not None and main:
        threading.Thread(target=watch, name="stop_with_snakemake", daemon=True).start()
    try:
        yield
    finally:
        done.set()
        if main and previous in (signal.SIG_DFL, None):
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


#: the marker in the name of :func:`atomic_path`'s temporary files: ``.<name>.partial-<host>-<pid>-<random><suffixes>``
PARTIAL_MARK = ".partial-"
_PARTIAL = re.compile(
    r"^\.(?P<name>.+)\.partial-(?P<host>[A-Za-z0-9-]+)-(?P<pid>\d+)-[a-z0-9_]{8}"
)
#: a temporary file of another host (a cluster node) whose writer cannot be asked is stale after this long
#: without a change [s]: longer than any job's wall-time limit (config convergence.runtime_min, 4 h)
STALE_FOREIGN_S = 24 * 3600.0


def _host() -> str:
    """This machine's short host name, as it appears in temporary file names."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname().split(".")[0]) or "host"


def _writer_gone(match: re.Match, path: Path) -> bool:
    """Whether the process that wrote a temporary file is gone: on this host by its pid, on another by the
    file's age (:data:`STALE_FOREIGN_S`)."""
    if match["host"] != _host():
        try:
            return time.time() - path.stat().st_mtime > STALE_FOREIGN_S
        except OSError:
            return False
    try:
        os.kill(int(match["pid"]), 0)
    except ProcessLookupError:
        return True
    except (PermissionError, OverflowError):
        return False
    return False


def remove_stale_partials(folder: str | Path, *, name: str | None = None) -> list[Path]:
    """Remove the temporary files of :func:`atomic_path` under ``folder`` whose writing process is gone (a
    job killed with SIGKILL, by the out-of-memory killer say, leaves one holding part of the data).

    Parameters
    ----------
    folder : str or Path
        Searched recursively (``results/`` at the start of a workflow run).
    name : str, optional
        Only the temporaries of this output (its file name), searched in ``folder`` alone: what
        :func:`atomic_path` does before it writes that output again.

    Returns
    -------
    list of Path
        The files removed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    pattern = f".{name}{PARTIAL_MARK}*" if name is not None else f".*{PARTIAL_MARK}*"
    found = folder.glob(pattern) if name is not None else folder.rglob(pattern)
    removed = []
    for path in found:
        match = _PARTIAL.match(path.name)
        if match is None or not path.is_file() or not _writer_gone(match, path):
            continue
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
            removed.append(path)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it onto ``path`` only if the block succeeds.

    The temporary is named ``.<name>.partial-<host>-<pid>-<random><suffixes>`` (:data:`PARTIAL_MARK`): it keeps
    the suffix(es) of ``path`` so that writers that dispatch on the extension (nibabel, matplotlib,
    meshio) still work, and says which process writes it, so that :func:`remove_stale_partials` can tell
    the temporaries of a killed job from those being written; the stale ones of ``path`` are removed before
    it is written. The file gets the mode ``open`` would give it (0666 less the umask), not the 0600 of a
    temporary file, so colleagues can read it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_partials(path.parent, name=path.name)
    suffix = "".join(path.suffixes)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}{PARTIAL_MARK}{_host()}-{os.getpid()}-",
        suffix=suffix,
        dir=path.parent,
    )
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, _new_file_mode())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _new_file_mode() -> int:
    """0666 less the process's umask: the mode ``open`` gives a new file."""
    try:  # Linux: read it without changing it (os.umask sets it for every thread)
        status = Path("/proc/self/status").read_text()
        mask = int(
            next(line.split()[1] for line in status.splitlines() if line.startswith("Umask:")), 8
        )
    except (OSError, StopIteration, ValueError, IndexError):
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: str | Path, data: dict) -> None:
    """Write ``data`` (numpy values allowed) as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=True) + "\n")


def read_json(path: str | Path) -> dict:
    """Read a JSON file; invalid JSON raises a ValueError naming the file."""
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc


def save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """``np.savez_compressed`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)


class ConfigError(ValueError):
    """A configuration problem; the message is one line and names the key (or the file and line)."""


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (YAML would keep the last)."""

    def construct_mapping(self, node, deep=False):
        first_line = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            line = key_node.start_mark.line + 1
            try:
                seen = first_line.get(key)
            except TypeError:  # an unhashable key: the base class reports it
                break
            if seen is not None:
                raise ConfigError(
                    f"config file {self.name}, line {line}: key {key_node.value!r} is given twice "
                    f"(lines {seen} and {line}); YAML would keep only the second"
                )
            first_line[key] = line
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _StrictLoader.construct_mapping
)


def _numeric_animal_names(node: yaml.Node, path: str) -> None:
    """Refuse an animal name that YAML reads as a number (``01``, ``1e3``), with its line and the quoted form."""
    if not isinstance(node, yaml.MappingNode):
        return
    for key_node, value_node in node.value:
        if key_node.value == "animals" and isinstance(value_node, yaml.MappingNode):
            for name_node, _ in value_node.value:
                if (
                    isinstance(name_node, yaml.ScalarNode)
                    and name_node.tag != "tag:yaml.org,2002:str"
                ):
                    kind = name_node.tag.rsplit(":", 1)[-1]
                    raise ConfigError(
                        f"config file {path}, line {name_node.start_mark.line + 1}: animal name {name_node.value} "
                        f"is read by YAML as {'an' if kind[:1] in 'aeiou' else 'a'} {kind}, not a name; quote it: "
                        f"'{name_node.value}'"
                    )


def load_config_file(path: str | Path) -> dict:
    """Read a YAML (or JSON) config file, refusing what YAML would read silently or report without a place.

    The study's config files (:func:`deeptissue.config.check_config_files`) and the manual segmentation
    overrides (:func:`deeptissue.segment.load_overrides`) are read with it.

    Parameters
    ----------
    path : str or Path
        The config file.

    Returns
    -------
    dict
        Its contents (an empty file gives an empty dict).

    Raises
    ------
    ConfigError
        A YAML syntax error (with file, line and column), a key given twice in one mapping (with the key and
        both lines), or an animal name that YAML reads as a number (with the line and the quoted form).
    """
    loader = _StrictLoader(Path(path).read_text(encoding="utf-8"))
    loader.name = str(path)
    try:
        node = loader.get_single_node()
        data = None if node is None else loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f", line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(
            f"config file {path}{where}: YAML syntax error: {exc.problem or exc.context}"
        ) from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path}: YAML syntax error: {exc}") from exc
    finally:
        loader.dispose()
    if node is not None:
        _numeric_animal_names(node, str(path))
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"config file {path}: the top level must be a mapping of keys, got {type(data).__name__}"
        )
    return data
