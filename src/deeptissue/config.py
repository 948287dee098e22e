"""Validation of the workflow configuration against its JSON schema, and the schema's reference page.

The schema (``workflow/schemas/config.schema.yaml``) gives every key a description, unit and
default. Validation fills in defaults, checks the rules that span several keys, and turns the
first problem into a one-line error that names the key, so a typo in a 40-line config is found at
once. Config files are read again strictly (:func:`deeptissue.io.load_config_file`): a key given twice, an animal
name YAML reads as a number and a syntax error are refused with file and line. ``docs/config.md`` is rendered from the same schema; regenerate it with::

    python -m deeptissue.config docs/config.md
"""

from __future__ import annotations

import argparse
import copy
import functools
import json
import math
import re
from collections import Counter
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from .io import ConfigError, atomic_path, load_config_file
from .phantom import PhantomSpec, check_indenter
from .variants import parse_variant

__all__ = [
    "ANIMAL_NAME_MAX_CHARS",
    "ORDERED_KEYS",
    "REGENERATE_COMMAND",
    "SCHEMA_PATH",
    "RESERVED_ANIMAL_NAMES",
    "ConfigError",
    "animal_variants",
    "check_config",
    "check_config_files",
    "convergence_animals",
    "figure_animal",
    "has_during_scan",
    "load_schema",
    "main",
    "schema_markdown",
    "study_name",
    "validate_config",
]

#: the schema's path inside the repository, and the command that renders it into docs/config.md
SCHEMA_PATH = Path("workflow") / "schemas" / "config.schema.yaml"
REGENERATE_COMMAND = "python -m deeptissue.config docs/config.md"


#: folders of results/ that hold the study's own outputs, not an animal's: no animal may be named so
RESERVED_ANIMAL_NAMES = ("convergence", "logs", "summary", "verification")

#: the longest animal name: it names folders and, with a variant and a ladder setting, log files
#: (``results/convergence/logs/<animal>_<variant>_<setting>.log``), which must stay under the 255 bytes
#: of a file name; the schema's ``animals.propertyNames.maxLength`` says the same
ANIMAL_NAME_MAX_CHARS = 64

#: keys whose values must not decrease in the order given (within one section), as the solver's
#: settings require (deeptissue.fem.solver.NewtonSettings, IncrementSettings)
ORDERED_KEYS = (
    ("fem.solver.newton", ("rtol", "rtol_intermediate")),
    ("fem.solver.increments", ("min_increment", "initial_increment", "max_increment")),
    ("fem.solver.increments", ("min_increment", "turn_initial_increment")),
)


def _a(kind: str) -> str:
    """``kind`` with its indefinite article (``an int``, ``a float``)."""
    return f"{'an' if kind[:1] in 'aeiou' else 'a'} {kind}"


def check_config_files(paths) -> None:
    """Read every config file of a run with :func:`deeptissue.io.load_config_file`, so that the first problem is refused.

    Snakemake reads the files itself (and keeps the last of two equal keys); the workflow calls this
    before it uses the configuration. A path that does not exist is skipped (Snakemake reports it).

    Parameters
    ----------
    paths : iterable of str or Path
        The config files, in the order given.

    Raises
    ------
    ConfigError
        See :func:`deeptissue.io.load_config_file`.
    """
    for path in paths:
        if Path(path).is_file():
            load_config_file(path)


def _key_path(path) -> str:
    """A validation error's path as the dotted key a user writes (``animals.rat01.phantom``, ``x[0]``)."""
    parts = []
    for p in path:
        parts.append(f"[{p}]" if isinstance(p, int) else (f".{p}" if parts else str(p)))
    return "".join(parts) or "<top level>"


def _extend_with_default(validator_class):
    """A validator that also fills in ``default`` values of properties (JSON Schema recipe)."""
    validate_properties = validator_class.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for prop, sub in properties.items():
                if isinstance(sub, dict) and "default" in sub and prop not in instance:
                    instance[prop] = copy.deepcopy(sub["default"])
        yield from validate_properties(validator, properties, instance, schema)

    return jsonschema.validators.extend(validator_class, {"properties": set_defaults})


_DefaultFilling = _extend_with_default(jsonschema.Draft7Validator)


_BOUND_SIGNS = {"minimum": ">=", "exclusiveMinimum": ">", "maximum": "<=", "exclusiveMaximum": "<"}


def _bound_message(where: str, err: jsonschema.ValidationError) -> str:
    """``must be a non-negative integer, got -1``: a bound a value breaks, in words, with the unit."""
    kinds = err.schema.get("type", "number")
    integer = "integer" in (kinds if isinstance(kinds, list) else [kinds])
    sign, bound = _BOUND_SIGNS[err.validator], err.validator_value
    if integer and err.validator == "minimum" and bound in (0, 1):
        kind = "a non-negative integer" if bound == 0 else "a positive integer"
    else:
        kind = f"{'an integer' if integer else 'a number'} {sign} {bound}"
    unit = err.schema.get("unit")
    unit = f" [{unit}]" if unit not in (None, "1", "-") else ""
    return f"config key {where}: must be {kind}{unit}, got {err.instance!r}"


def _message(
    err: jsonschema.ValidationError, parent: jsonschema.ValidationError | None = None
) -> str:
    """One line for a schema violation that names the key (``parent``: the oneOf it is a form of)."""
    where = _key_path(err.absolute_path)
    if err.validator == "additionalProperties":
        allowed = sorted(err.schema.get("properties", {}))
        extra = sorted(set(err.instance) - set(allowed))
        return f"config key {where}: unknown key(s) {extra}; allowed: {allowed}"
    if err.validator in _BOUND_SIGNS:
        return _bound_message(where, err)
    if err.validator == "not" and isinstance(err.instance, dict):
        rule = parent.schema.get("description", "") if parent is not None else ""
        given = sorted(k for k in err.instance if k in _FORM_KEYS)
        return f"config key {where}: {given} do not go together; {' '.join(rule.split())}"
    if err.validator == "not" and "const" in err.validator_value:
        return f"config key {where}: must not be {err.validator_value['const']!r}"
    if err.validator == "required":
        return f"config key {where}: {err.message}"
    if err.validator in ("oneOf", "anyOf"):
        return f"config key {where}: does not match any allowed form ({err.schema.get('description', err.message)})"
    return f"config key {where}: {err.message}"


#: the keys of an animal that choose its form (a phantom, or scans)
_FORM_KEYS = ("phantom", "pre", "during")


def _schema_node(schema: dict, path: tuple) -> dict:
    """The schema node of a config key (``("animals", "rat01", "phantom", "snr")``), {} if it has none."""
    node = _resolve(schema, schema)
    for part in path:
        if isinstance(part, int):
            node = node.get("items", {})
        elif part in node.get("properties", {}):
            node = node["properties"][part]
        elif isinstance(node.get("additionalProperties"), dict):
            node = node["additionalProperties"]
        else:
            return {}
        node = _resolve(node, schema) if isinstance(node, dict) else {}
    return node


def _check_finite(value: Any, schema: dict, path: tuple = ()) -> None:
    """Refuse NaN and ±Inf anywhere in a config (YAML's ``.nan``, ``.inf``): NaN passes every bound, since
    every comparison with it is false, and no key takes an infinite value (a limit that can be switched off
    takes null)."""
    if isinstance(value, dict):
        for key, sub in value.items():
            _check_finite(sub, schema, (*path, key))
    elif isinstance(value, (list, tuple)):
        for i, sub in enumerate(value):
            _check_finite(sub, schema, (*path, i))
    elif isinstance(value, float) and not math.isfinite(value):
        kinds = _schema_node(schema, path).get("type", [])
        off = " (or null to switch it off)" if "null" in kinds else ""
        raise ConfigError(
            f"config key {_key_path(path)}: {value} is not a finite number; give a finite number{off} "
            f"in the key's range (docs/config.md)"
        )


#: libyaml's safe loader where PyYAML has it: it reads the schema ten times faster than the Python one
_FAST_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load_schema(schema_path: str | Path) -> dict:
    """Read the configuration schema.

    Parameters
    ----------
    schema_path : str or Path
        The YAML file of the JSON schema (draft 7, with an extra ``unit`` keyword per key).

    Returns
    -------
    dict
        The schema as loaded by ``yaml.safe_load`` (a copy of its own: the file is parsed once while it
        is unchanged).
    """
    path = Path(schema_path).resolve()
    return copy.deepcopy(_parsed_schema(path, path.stat().st_mtime_ns))


@functools.lru_cache(maxsize=4)
def _parsed_schema(path: Path, mtime_ns: int) -> dict:
    """The schema file parsed (cached by path and modification time)."""
    with open(path) as fh:
        return yaml.load(fh, Loader=_FAST_SAFE_LOADER)


def validate_config(
    config: dict[str, Any], schema_path: str | Path, *, base_dir: str | Path = ".", config_files=()
) -> dict:
    """Validate a configuration in place: schema, defaults, named input files and cross-key rules.

    Parameters
    ----------
    config : dict
        The configuration as loaded from YAML; missing keys get the schema's defaults.
    schema_path : str or Path
        The YAML file of the configuration schema.
    base_dir : str or Path, optional
        Directory the input files of ``animals.<name>.pre``, ``during`` and ``overrides`` are relative to.
    config_files : sequence of str or Path, optional
        The config files the configuration was read from; a ``study.name`` left null becomes the first
        one's name without its suffix (``config/paper.yaml`` -> ``paper``), else ``config``.

    Returns
    -------
    dict
        The same ``config``, with defaults filled in.

    Raises
    ------
    ConfigError
        On the first problem, with a one-line message that names the key.
    """
    _check_animal_keys(config)
    schema = load_schema(schema_path)
    _check_finite(config, schema)
    validator = _DefaultFilling(schema)
    errors = sorted(
        validator.iter_errors(config),
        key=lambda e: (len(e.absolute_path), list(map(str, e.absolute_path))),
    )
    if errors:
        # the deepest error is the most specific; oneOf errors carry their context
        err = parent = errors[-1]
        if err.context:
            # the allowed form the value comes closest to: fewest errors, then deepest, not a plain type mismatch
            per_form = Counter(e.relative_schema_path[0] for e in err.context)
            err = min(
                err.context,
                key=lambda e: (
                    e.validator == "type",
                    per_form[e.relative_schema_path[0]],
                    -len(e.absolute_path),
                ),
            )
        raise ConfigError(_message(err, parent if err is not parent else None))
    _check_files(config, Path(base_dir))
    if config["study"]["name"] is None:
        config["study"]["name"] = study_name(config_files)
    check_config(config)
    return config


def study_name(config_files) -> str:
    """The default name of a study: its first config file's name without the suffix, else ``config``.

    Parameters
    ----------
    config_files : sequence of str or Path
        The config files of the run, in the order given (overlays come after the study's file).

    Returns
    -------
    str
    """
    files = list(config_files)
    return Path(files[0]).stem if files else "config"


_ANIMAL_NAME = re.compile(r"[A-Za-z0-9_-]+")


def _check_animal_keys(config: dict[str, Any]) -> None:
    """Refuse an animal name that is not a string (YAML reads ``01`` as the number 1), is longer than
    :data:`ANIMAL_NAME_MAX_CHARS` or holds a character other than letters, digits, ``_`` and ``-``
    (it names folders and files)."""
    animals = config.get("animals")
    if not isinstance(animals, dict):
        return
    for name in animals:
        if not isinstance(name, str):
            raise ConfigError(
                f"config key animals: animal name {name!r} is read by YAML as {_a(type(name).__name__)}, not a name; "
                f"quote it in the config file (as written there, e.g. '01')"
            )
        shown = name if len(name) <= 24 else f"{name[:20]}..."
        if len(name) > ANIMAL_NAME_MAX_CHARS or not _ANIMAL_NAME.fullmatch(name):
            raise ConfigError(
                f"config key animals: animal name {shown!r} ({len(name)} characters) names folders and files of "
                f"results/: use 1 to {ANIMAL_NAME_MAX_CHARS} letters, digits, '_' or '-'"
            )


_FILE_KEYS = ("pre", "during", "overrides")


def _check_files(config: dict, base_dir: Path) -> None:
    for animal, cfg in (config.get("animals") or {}).items():
        for key in _FILE_KEYS:
            val = cfg.get(key)
            if isinstance(
                val, dict
            ):  # a scanner's folder: {dicom: folder, ...} or {bruker: study, ...}
                folder = val.get("dicom", val.get("bruker"))
                if not (base_dir / folder).is_dir():
                    raise ConfigError(
                        f"config key animals.{animal}.{key}: folder not found: {folder}"
                    )
            elif isinstance(val, str) and not (
                (base_dir / val).is_file() or (key != "overrides" and (base_dir / val).is_dir())
            ):
                raise ConfigError(f"config key animals.{animal}.{key}: file not found: {val}")


def has_during_scan(animal: dict[str, Any]) -> bool:
    """Whether an animal has a during scan: a phantom always, a real animal if ``during`` is given.

    Parameters
    ----------
    animal : dict
        One entry of ``config["animals"]``.

    Returns
    -------
    bool
    """
    return "phantom" in animal or "during" in animal


def animal_variants(config: dict[str, Any], animal: str) -> list[str]:
    """The variants solved for one animal: its own ``animals.<animal>.variants``, else ``study.variants``.

    Parameters
    ----------
    config : dict
        A validated configuration.
    animal : str
        A configured animal.

    Returns
    -------
    list of str
        Variant names (:func:`deeptissue.variants.parse_variant`), in the order given.
    """
    own = config["animals"][animal].get("variants")
    return list(own if own is not None else config["study"]["variants"])


def figure_animal(config: dict[str, Any]) -> str | None:
    """The animal drawn in the study's section figures: ``study.figure_animal``, or the first configured animal
    with a during scan (None if there is none: a study of pre-only animals has no FE results to draw).

    Parameters
    ----------
    config : dict
        A validated configuration.

    Returns
    -------
    str or None
    """
    named = config["study"]["figure_animal"]
    if named is not None:
        return named
    return next((a for a, c in config["animals"].items() if has_during_scan(c)), None)


def convergence_animals(config: dict[str, Any], *, required: bool = False) -> list[str]:
    """The animals of the speed-against-error ladder.

    Parameters
    ----------
    config : dict
        A validated configuration.
    required : bool, optional
        Raise instead of leaving animals out (for the inputs of the ``convergence`` target).

    Returns
    -------
    list of str
        The animals of ``convergence.animals`` that have a during scan, or with ``convergence.animals`` null the
        first configured animal with one; empty if there is none (a study of pre-only animals: only the
        convergence target needs one).

    Raises
    ------
    ConfigError
        If ``required`` and a named animal has no during scan, or none qualifies.
    """
    named = config["convergence"]["animals"]
    animals = config["animals"]
    if named is not None:
        without = [a for a in named if not has_during_scan(animals[a])]
        if without and required:
            raise ConfigError(
                f"config key convergence.animals: {without} have no during scan; the convergence target solves an "
                f"indentation and needs animals with one {list(animals)}"
            )
        return [a for a in named if a not in without]
    found = next((a for a, cfg in animals.items() if has_during_scan(cfg)), None)
    if found is None and required:
        raise ConfigError(
            f"config key convergence.animals: null, and no configured animal has a during scan {list(animals)}"
        )
    return [] if found is None else [found]


def _check_bin_edges(config: dict[str, Any]) -> None:
    study = config["study"]
    edges = study["bin_edges"]
    if abs(edges[0] - study["threshold"]) > 1e-12:
        raise ConfigError(
            f"config key study.bin_edges: must start at study.threshold ({study['threshold']}), got {edges[0]}"
        )
    if any(b <= a for a, b in zip(edges, edges[1:])):
        raise ConfigError(f"config key study.bin_edges: not strictly increasing: {edges}")


def _section(config: dict[str, Any], dotted: str) -> dict:
    """The config section at a dotted path (``fem.solver.newton``), with its defaults filled in."""
    node = config
    for part in dotted.split("."):
        node = node[part]
    return node


def _check_ordered(config: dict[str, Any]) -> None:
    """The keys of :data:`ORDERED_KEYS` do not decrease, and a ladder's Newton tolerance
    (``convergence.tolerances[].rtol``) is not looser than ``fem.solver.newton.rtol_intermediate``."""
    for dotted, keys in ORDERED_KEYS:
        section = _section(config, dotted)
        for low, high in zip(keys, keys[1:]):
            if section[low] > section[high]:
                chain = " <= ".join(f"{dotted}.{k} ({section[k]})" for k in keys)
                raise ConfigError(
                    f"config key {dotted}.{low}: {section[low]} is larger than {dotted}.{high} "
                    f"({section[high]}); the solver needs {chain}"
                )
    loosest = config["fem"]["solver"]["newton"]["rtol_intermediate"]
    for i, pair in enumerate(config["convergence"]["tolerances"]):
        if pair.get("rtol", 0.0) > loosest:
            raise ConfigError(
                f"config key convergence.tolerances[{i}].rtol: {pair['rtol']} is larger than "
                f"fem.solver.newton.rtol_intermediate ({loosest}); give a tighter rtol or loosen that one"
            )


def _check_figure_animal(config: dict[str, Any]) -> None:
    name = config["study"]["figure_animal"]
    animals = list(config["animals"])
    if name is not None and name not in animals:
        raise ConfigError(
            f"config key study.figure_animal: {name!r} is not a configured animal {animals}"
        )
    if name is not None and not has_during_scan(config["animals"][name]):
        raise ConfigError(
            f"config key study.figure_animal: {name!r} has no during scan: it has no FE results to draw"
        )


def _check_convergence_animals(config: dict[str, Any]) -> None:
    """Named ``convergence.animals`` must be configured; one without a during scan is refused only by the
    ``convergence`` target (:func:`convergence_animals` with ``required``), so a study of pre-only animals runs."""
    named = config["convergence"]["animals"] or []
    animals = list(config["animals"])
    unknown = [a for a in named if a not in animals]
    if unknown:
        raise ConfigError(
            f"config key convergence.animals: {unknown} are not configured animals {animals}"
        )


def _check_leg_points(config: dict[str, Any]) -> None:
    """``animals.<a>.leg_point_mm`` must lie inside the animal's ``crop_mm`` box, where the leg is looked for."""
    for animal, cfg in config["animals"].items():
        point, box = cfg.get("leg_point_mm"), cfg.get("crop_mm")
        if point is None or box is None:
            continue
        if not all(lo <= p <= hi for p, (lo, hi) in zip(point, box)):
            raise ConfigError(
                f"config key animals.{animal}.leg_point_mm: {list(point)} lies outside animals.{animal}.crop_mm {box}"
            )


def _check_reserved_names(config: dict[str, Any]) -> None:
    for name in config["animals"]:
        if name in RESERVED_ANIMAL_NAMES:
            raise ConfigError(
                f"config key animals.{name}: {name!r} is a folder of results/ that holds the study's own outputs "
                f"(reserved: {', '.join(RESERVED_ANIMAL_NAMES)}); rename the animal"
            )


def _check_phantoms(config: dict[str, Any]) -> None:
    """Refuse a phantom whose indenter cannot be imaged (tilt, depth), with the range that works."""
    phantoms = {a: cfg["phantom"] for a, cfg in config["animals"].items() if "phantom" in cfg}
    if not phantoms:
        return
    for animal, cfg in phantoms.items():
        try:
            check_indenter(PhantomSpec.from_config(cfg))
        except ValueError as exc:
            raise ConfigError(f"config key animals.{animal}.{exc}") from exc


def _check_animal_variants(config: dict[str, Any]) -> None:
    """An animal's own ``variants`` name the unturned variant of every turned one they list (``sphere`` for
    ``sphere_rx+15``): a turned variant is compared with, and solved from, the unturned one of its animal."""
    for animal, cfg in config["animals"].items():
        own = cfg.get("variants")
        if own is None:
            continue
        if not has_during_scan(cfg):
            raise ConfigError(
                f"config key animals.{animal}.variants: {animal!r} has no during scan, so none of its variants is "
                f"solved; remove the key or give the animal its during scan"
            )
        for name in own:
            v = parse_variant(name)
            if v.turn_axis is not None and v.indenter not in own:
                raise ConfigError(
                    f"config key animals.{animal}.variants: {name!r} is turned from {v.indenter!r}, which the list "
                    f"{list(own)} does not name; add {v.indenter!r} (a turned variant is compared with its unturned "
                    f"one of the same animal) or remove {name!r}"
                )


def check_config(config: dict[str, Any]) -> None:
    """Check the rules of a configuration that span several keys (the schema checks each key alone).

    No animal is named like a folder of the study's own outputs (:data:`RESERVED_ANIMAL_NAMES`); every
    phantom's indenter can be imaged (:func:`deeptissue.phantom.check_indenter`);
    ``study.bin_edges`` starts at ``study.threshold`` and increases strictly; the keys of
    :data:`ORDERED_KEYS` do not decrease; ``study.figure_animal``
    is a configured animal; ``convergence.animals`` are configured animals (the ``convergence`` target
    asks for a during scan); an animal's ``leg_point_mm`` lies inside its ``crop_mm``; an animal's own
    ``variants`` name the unturned variant of every turned one they list.

    Parameters
    ----------
    config : dict
        A configuration whose defaults are filled in (as :func:`validate_config` leaves it).

    Raises
    ------
    ConfigError
        Naming the key whose value breaks a rule.
    """
    _check_reserved_names(config)
    _check_phantoms(config)
    _check_bin_edges(config)
    _check_ordered(config)
    _check_figure_animal(config)
    _check_convergence_animals(config)
    _check_leg_points(config)
    _check_animal_variants(config)


# --- the reference page docs/config.md, rendered from the schema ---


def _resolve(node: dict, schema: dict) -> dict:
    """``node`` with a local ``$ref`` (``#/definitions/x``) replaced by its target."""
    ref = node.get("$ref")
    if ref is None:
        return node
    target = schema
    for part in ref.lstrip("#/").split("/"):
        target = target[part]
    return _resolve(target, schema)


def _text(value: Any) -> str:
    """A description on one line, safe inside a Markdown table cell."""
    return " ".join(str(value).split()).replace("|", "\\|")


def _literal(value: Any) -> str:
    """A value as JSON in backticks (null, true, lists as written in YAML's flow style)."""
    return f"`{json.dumps(value, ensure_ascii=False)}`"


def _type(node: dict) -> str:
    """The JSON type(s) of a key, with the item type of an array."""
    kind = node.get("type")
    if kind is None:
        return "enum" if "enum" in node else ""
    kinds = kind if isinstance(kind, list) else [kind]
    text = " or ".join(kinds)
    items = node.get("items")
    if "array" in kinds and isinstance(items, dict) and "type" in items:
        text = text.replace("array", f"array of {items['type']}")
    return text


_BOUNDS = (
    ("minimum", "≥"),
    ("exclusiveMinimum", ">"),
    ("maximum", "≤"),
    ("exclusiveMaximum", "<"),
)


def _range(node: dict) -> str:
    """The allowed values of a key: enum, bounds, list length and bounds of the items."""
    parts = []
    if "enum" in node:
        parts.append("one of " + ", ".join(_literal(v) for v in node["enum"]))
    parts.extend(f"{sign} {node[key]}" for key, sign in _BOUNDS if key in node)
    if isinstance(node.get("not"), dict) and "const" in node["not"]:
        parts.append(f"≠ {node['not']['const']}")
    n_min, n_max = node.get("minItems"), node.get("maxItems")
    if n_min is not None and n_min == n_max:
        parts.append(f"{n_min} items")
    elif n_min is not None and n_max is not None:
        parts.append(f"{n_min}-{n_max} items")
    elif n_min is not None:
        parts.append(f"≥ {n_min} items")
    elif n_max is not None:
        parts.append(f"≤ {n_max} items")
    items = node.get("items")
    if isinstance(items, dict):
        inner = [f"{sign} {items[key]}" for key, sign in _BOUNDS if key in items]
        if "enum" in items:
            inner.append("one of " + ", ".join(_literal(v) for v in items["enum"]))
        if inner:
            parts.append("each " + ", ".join(inner))
    return "; ".join(parts)


def _is_section(node: dict) -> bool:
    """Whether a schema node is an object with its own keys (rendered as a section of its own)."""
    return isinstance(node.get("properties"), dict)


def _sections(node: dict, path: str, schema: dict):
    """Yield ``(path, node, rows)`` for ``node`` and every object with properties below it."""
    rows, below = [], []
    for key, sub in node["properties"].items():
        sub = _resolve(sub, schema)
        child = f"{path}.{key}" if path else key
        if _is_section(sub):
            below.append((child, sub))
            continue
        items = sub.get("items")
        if isinstance(items, dict) and _is_section(items):
            rows.append((child, sub))
            below.append((f"{child}[]", items))
            continue
        extra = sub.get("additionalProperties")
        if isinstance(extra, dict):
            extra = _resolve(extra, schema)
            if _is_section(extra):
                rows.append((child, sub))
                below.append((f"{child}.<name>", extra))
                continue
        rows.append((child, sub))
    yield path, node, rows
    for child, sub in below:
        yield from _sections(sub, child, schema)


def schema_markdown(schema: dict) -> str:
    """Render a configuration schema as a Markdown reference page.

    Every object with properties becomes a section (heading = its dotted path, ``<name>`` for a
    map's key, ``[]`` for a list's items) with its description and one table row per key:
    dotted path, type, default, unit, allowed range and description.

    Parameters
    ----------
    schema : dict
        A JSON schema as loaded by :func:`load_schema`; local ``$ref`` s are followed.

    Returns
    -------
    str
        The page, ending with a newline.
    """
    lines = [
        "# Configuration reference",
        "",
        f"Generated from `{SCHEMA_PATH.as_posix()}` by `{REGENERATE_COMMAND}`; do not edit by hand.",
        "",
        _text(schema.get("description", "")),
        "",
        "Unit `1` is a dimensionless number, `-` a name or a switch. A key left out takes its default.",
    ]
    for path, node, rows in _sections(schema, "", schema):
        lines += ["", f"## `{path}`" if path else "## Top level", ""]
        if path and node.get("description"):
            lines += [_text(node["description"]), ""]
        if not rows:
            lines.append("Only the sections below.")
            continue
        lines += [
            "| key | type | default | unit | range | description |",
            "|---|---|---|---|---|---|",
        ]
        required = set(node.get("required", ()))
        for key, sub in rows:
            if "default" in sub:
                default = _literal(sub["default"])
            else:
                default = "required" if key.rsplit(".", 1)[-1] in required else ""
            unit = f"`{sub['unit']}`" if "unit" in sub else ""
            cells = [
                f"`{key}`",
                _type(sub),
                _text(default),
                unit,
                _text(_range(sub)),
                _text(sub.get("description", "")),
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _merged(base: dict, overlay: dict) -> dict:
    """``base`` updated by ``overlay``, nested mappings key by key (as Snakemake merges config files)."""
    out = dict(base)
    for key, value in overlay.items():
        out[key] = (
            _merged(out[key], value)
            if isinstance(value, dict) and isinstance(out.get(key), dict)
            else value
        )
    return out


def main(argv: list[str] | None = None) -> None:
    """Write the reference page rendered from the schema (``python -m deeptissue.config docs/config.md``),
    or check config files without running the workflow (``--check config/my_study.yaml``).

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments: the output file and ``--schema PATH`` (default
        ``workflow/schemas/config.schema.yaml``, relative to the working directory); or ``--check`` and the
        config files of a run in the order Snakemake is given them (the study's file, then overlays), whose
        input files are relative to the working directory.
    """
    parser = argparse.ArgumentParser(
        prog="python -m deeptissue.config", description=main.__doc__.splitlines()[0]
    )
    parser.add_argument(
        "output", type=Path, nargs="?", help="the Markdown file to write, e.g. docs/config.md"
    )
    parser.add_argument(
        "--schema", type=Path, default=SCHEMA_PATH, help="the configuration schema (YAML)"
    )
    parser.add_argument(
        "--check",
        type=Path,
        nargs="+",
        metavar="CONFIG",
        help="check these config files (merged in order) instead of writing the page",
    )
    args = parser.parse_args(argv)
    if args.check:
        try:
            config = {}
            for path in args.check:
                config = _merged(config, load_config_file(path))
            validate_config(config, args.schema, base_dir=".", config_files=args.check)
        except (ConfigError, OSError) as exc:
            parser.exit(1, f"{exc}\n")
        print(f"config OK: study {config['study']['name']}, animals {list(config['animals'])}")
        return
    if args.output is None:
        parser.error("give the Markdown file to write, or --check CONFIG")
    with atomic_path(args.output) as tmp:
        tmp.write_text(schema_markdown(load_schema(args.schema)))


if __name__ == "__main__":
    main()
