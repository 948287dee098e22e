"""The package's shape: imports point down the layers of :data:`LAYERS` and form no cycle; no function is
over :data:`MAX_LINES` lines or takes more than :data:`MAX_PARAMETERS` parameters.

Every ``import`` and ``from ... import`` in ``src/deeptissue`` counts, at module level and inside
functions (``TYPE_CHECKING`` blocks too), with relative imports resolved: ``from .pose import Pose`` in
``deeptissue.study`` is an import of ``deeptissue.pose``, ``from .fem.solver import solve_from`` one of
``deeptissue.fem.solver``.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterator
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "deeptissue"

#: The layers of the package, lowest first: each with its modules (relative to ``deeptissue``;
#: ``__init__`` is the package itself, a subpackage stands for all its modules) and the layers directly
#: below it. A module imports from its own layer and from the layers below its own, transitively; never
#: from a layer above it or beside it. Two stacks meet in ``model``: the images of an animal
#: (imaging < segment < pose) and the finite elements (mesh < fem < estimates); ``study`` solves the
#: model; the results (report, findings), the verification scenes and the convergence studies sit on
#: the study, and the entry points (config validation with its phantom checks, status) on top.
LAYERS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "base": (("__init__", "io", "elements", "geometry", "rigid", "variants", "pose_error"), ()),
    "images": (
        (
            "imaging",
            "contours",
            "scanner",
            "qc",
            "segment_checks",
            "segment_accuracy",
            "fluid",
            "bone_motion",
        ),
        ("base",),
    ),
    "segment": (("segment",), ("images",)),
    "pose": (("pose",), ("segment",)),
    "phantom": (("phantom",), ("pose",)),
    "mesh": (("mesh", "strain"), ("base",)),
    "fem": (("fem",), ("mesh",)),
    "estimates": (("errorest", "summary", "adapt"), ("fem",)),
    "model": (("model",), ("pose", "mesh")),
    "study": (("study", "adapt_limb"), ("model", "estimates")),
    "results": (("report", "findings", "verification", "convergence"), ("study",)),
    "entry": (("config", "status"), ("results", "phantom")),
}

#: Imports that do not point down the layers yet, as (importer, imported module), each with its reason.
KNOWN_UPWARD: dict[tuple[str, str], str] = {}

#: The longest function [lines, its ``def`` line to its last] and the most parameters one takes
#: (``self`` and ``cls`` not counted; ``*args`` and ``**kwargs`` count one each): beyond them a body is
#: split into named steps and a parameter list grouped in a small frozen dataclass.
MAX_LINES = 120
MAX_PARAMETERS = 8


def _modules() -> dict[str, tuple[Path, bool]]:
    """Every module of the package: dotted name -> (file, whether it is a package's ``__init__``)."""
    out = {}
    for path in sorted((SRC / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return out


MODULES = _modules()


@functools.cache
def _tree(module: str) -> ast.Module:
    """The parsed source of a package module."""
    path = MODULES[module][0]
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _targets(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> Iterator[str]:
    """The package modules an import statement of ``module`` imports (the longest module name that
    exists: ``from .fem.solver import Scene`` -> ``deeptissue.fem.solver``, ``from . import io`` ->
    ``deeptissue.io``)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        if node.level:
            here = module.split(".") if is_package else module.split(".")[:-1]
            here = here[: len(here) - (node.level - 1)]
            prefix = ".".join(here + ([node.module] if node.module else []))
        else:
            prefix = node.module or ""
        names = [f"{prefix}.{alias.name}" for alias in node.names]
    for name in names:
        while name and name not in MODULES:
            name = name.rpartition(".")[0]
        if name and name != module:
            yield name


class _ImportWalk(ast.NodeVisitor):
    """Collects a module's imports of package modules, noting those inside a function."""

    def __init__(self, module: str, is_package: bool):
        self.module, self.is_package, self.depth = module, is_package, 0
        self.found: list[tuple[str, str, int, bool]] = []

    def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_AsyncFunctionDef = visit_FunctionDef

    def visit_Import(self, node: ast.Import | ast.ImportFrom) -> None:
        for target in _targets(node, self.module, self.is_package):
            self.found.append((self.module, target, node.lineno, self.depth > 0))

    visit_ImportFrom = visit_Import


@functools.cache
def _imports() -> tuple[tuple[str, str, int, bool], ...]:
    """Every import of a package module by another: (importer, imported, line, inside a function)."""
    found = []
    for module, (_, is_package) in MODULES.items():
        walk = _ImportWalk(module, is_package)
        walk.visit(_tree(module))
        found += walk.found
    return tuple(found)


def _layer_of(module: str) -> str:
    """The layer of a module: the one whose entry is the module or its nearest enclosing package."""
    rel = "__init__" if module == PACKAGE else module.removeprefix(PACKAGE + ".")
    best, length = None, -1
    for layer, (members, _) in LAYERS.items():
        for m in members:
            if (rel == m or rel.startswith(m + ".")) and len(m) > length:
                best, length = layer, len(m)
    if best is None:
        raise AssertionError(f"{module} is in no layer of LAYERS: add it to the table")
    return best


def _below(layer: str) -> set[str]:
    """The layers below ``layer``, transitively."""
    out, todo = set(), list(LAYERS[layer][1])
    while todo:
        lower = todo.pop()
        if lower not in out:
            out.add(lower)
            todo.extend(LAYERS[lower][1])
    return out


def _not_downward() -> dict[tuple[str, str], list[int]]:
    """The imports from a layer to one that is not its own or below it: (importer, imported) -> lines."""
    bad: dict[tuple[str, str], list[int]] = {}
    for importer, imported, line, _ in _imports():
        a, b = _layer_of(importer), _layer_of(imported)
        if b != a and b not in _below(a):
            bad.setdefault((importer, imported), []).append(line)
    return bad


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each as a sorted list."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_every_module_is_in_exactly_one_layer_and_every_entry_exists():
    rel = {"__init__" if m == PACKAGE else m.removeprefix(PACKAGE + ".") for m in MODULES}
    entries = [m for members, _ in LAYERS.values() for m in members]
    assert len(entries) == len(set(entries)), "a module is listed in two layers"
    missing = [m for m in entries if not any(r == m or r.startswith(m + ".") for r in rel)]
    assert not missing, f"LAYERS lists modules that do not exist: {missing}"
    for module in MODULES:
        _layer_of(module)  # raises for a module in no layer
    for layer, (_, lower) in LAYERS.items():
        assert set(lower) <= set(LAYERS), f"layer {layer}: unknown layers below it {lower}"
        assert layer not in _below(layer), f"layer {layer} is below itself"


def test_the_import_walk_sees_relative_function_level_and_absolute_imports():
    # truths read off the source by hand: study imports the solver at its top, the phantom imports the
    # NIfTI writer inside write_phantom, config the phantom at its top
    found = {(a, b, inside) for a, b, _, inside in _imports()}
    assert ("deeptissue.study", "deeptissue.fem.solver", False) in found
    assert ("deeptissue.study", "deeptissue.pose", False) in found
    assert ("deeptissue.phantom", "deeptissue.imaging", True) in found
    assert ("deeptissue.config", "deeptissue.phantom", False) in found
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_between_modules():
    edges: dict[str, set[str]] = {}
    for importer, imported, _, _ in _imports():
        edges.setdefault(importer, set()).add(imported)
    cycles = _cycles(edges)
    assert not cycles, "modules that import each other, directly or through others:\n" + "\n".join(
        " <-> ".join(c) for c in cycles
    )


def test_imports_point_down_the_layers():
    bad = _not_downward()
    new = {
        f"{a} (layer {_layer_of(a)}, line {', '.join(map(str, lines))}) imports {b} (layer {_layer_of(b)})"
        for (a, b), lines in bad.items()
        if (a, b) not in KNOWN_UPWARD
    }
    assert not new, "imports that do not point down LAYERS:\n" + "\n".join(sorted(new))
    gone = sorted(set(KNOWN_UPWARD) - set(bad))
    assert not gone, f"KNOWN_UPWARD lists imports that no longer point up: remove {gone}"


def test_no_function_is_too_long_or_takes_too_many_parameters():
    over = []
    for module in MODULES:
        for node in ast.walk(_tree(module)):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            a = node.args
            names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
            names += [p.arg for p in (a.vararg, a.kwarg) if p is not None]
            if names[:1] in (["self"], ["cls"]):
                names = names[1:]
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_LINES or len(names) > MAX_PARAMETERS:
                over.append(
                    f"{module}.{node.name} (line {node.lineno}): {lines} lines, {len(names)} parameters"
                )
    assert not over, (
        f"functions over {MAX_LINES} lines or {MAX_PARAMETERS} parameters:\n" + "\n".join(over)
    )
