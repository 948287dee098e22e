"""Validation of the workflow configuration against its JSON schema.

The schema (``workflow/schemas/config.schema.yaml``) gives every key a description, unit and
default. Validation fills in defaults and turns the first problem into a one-line error that
names the key, so a typo in a 40-line config is found at once.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import jsonschema
import yaml


class ConfigError(ValueError):
    """A configuration problem; the message is one line and names the key."""


def _key_path(path) -> str:
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


def _message(err: jsonschema.ValidationError) -> str:
    where = _key_path(err.absolute_path)
    if err.validator == "additionalProperties":
        allowed = sorted(err.schema.get("properties", {}))
        extra = sorted(set(err.instance) - set(allowed))
        return f"config key {where}: unknown key(s) {extra}; allowed: {allowed}"
    if err.validator == "required":
        return f"config key {where}: {err.message}"
    if err.validator in ("oneOf", "anyOf"):
        return f"config key {where}: does not match any allowed form ({err.schema.get('description', err.message)})"
    return f"config key {where}: {err.message}"


def load_schema(schema_path: str | Path) -> dict:
    with open(schema_path) as fh:
        return yaml.safe_load(fh)


def validate_config(config: dict[str, Any], schema_path: str | Path, *, base_dir: str | Path = ".") -> dict:
    """Validate ``config`` in place (defaults filled) and check that every named input file exists.

    Returns the same dict. Raises :class:`ConfigError` with a one-line message naming the key.
    """
    schema = load_schema(schema_path)
    validator = _DefaultFilling(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: (len(e.absolute_path), list(map(str, e.absolute_path))))
    if errors:
        # the deepest error is the most specific; oneOf errors carry their context
        err = errors[-1]
        if err.context:
            err = max(err.context, key=lambda e: len(e.absolute_path))
        raise ConfigError(_message(err))
    # a second pass: defaults inside oneOf branches are not filled by the first
    _check_files(config, Path(base_dir))
    return config


_FILE_KEYS = ("pre", "during", "overrides")


def _check_files(config: dict, base_dir: Path) -> None:
    for animal, cfg in (config.get("animals") or {}).items():
        for key in _FILE_KEYS:
            val = cfg.get(key)
            if isinstance(val, str) and not (base_dir / val).is_file():
                raise ConfigError(f"config key animals.{animal}.{key}: file not found: {val}")
