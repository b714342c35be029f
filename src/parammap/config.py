"""Workflow configuration: load, fill defaults and validate against the JSON schema.

The schema lives in ``parammap/schemas/config.schema.yaml`` (``workflow/schemas`` links to
it), so the Snakefile and the CLI check the same rules.
"""

from __future__ import annotations

import copy
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from .errors import InputError

__all__ = ["ConfigError", "default", "load_config", "schema", "surface_config", "validate_config"]


class ConfigError(InputError):
    """A configuration value that breaks the schema; the message names the key."""


def schema() -> dict[str, Any]:
    """The configuration schema as a dict."""
    text = resources.files("parammap").joinpath("schemas/config.schema.yaml").read_text()
    return yaml.safe_load(text)


def _fill_defaults(instance: Any, sch: dict[str, Any]) -> None:
    if not isinstance(instance, dict):
        return
    for key, sub in sch.get("properties", {}).items():
        if key not in instance and "default" in sub:
            instance[key] = copy.deepcopy(sub["default"])
        if key in instance:
            _fill_defaults(instance[key], sub)
    extra = sch.get("additionalProperties")
    if isinstance(extra, dict):
        for key, value in instance.items():
            if key not in sch.get("properties", {}):
                _fill_defaults(value, extra)


def _allowed_types(sch: dict[str, Any]) -> set[str]:
    """JSON types a schema node accepts (through oneOf / anyOf)."""
    types = sch.get("type", [])
    out = set([types] if isinstance(types, str) else types)
    for alt in sch.get("oneOf", []) + sch.get("anyOf", []):
        out |= _allowed_types(alt)
    return out


def _coerce(value: Any, sch: dict[str, Any]) -> Any:
    """A number or boolean that arrived as text (Snakemake's ``--config`` hands nested
    values over as strings: ``observation={"texels_x": 512}`` gives '512') as what the
    schema asks for; anything else unchanged, for the validation to judge."""
    if not isinstance(value, str):
        return value
    allowed = _allowed_types(sch)
    if "integer" in allowed or "number" in allowed:
        try:
            return int(value)
        except ValueError:
            if "number" in allowed:
                try:
                    return float(value)
                except ValueError:
                    pass
    if "boolean" in allowed and value.lower() in ("true", "false"):
        return value.lower() == "true"
    return value


def _coerce_numbers(instance: Any, sch: dict[str, Any]) -> None:
    if isinstance(instance, list) and isinstance(sch.get("items"), dict):
        for i, v in enumerate(instance):
            instance[i] = _coerce(v, sch["items"])
            _coerce_numbers(instance[i], sch["items"])
        return
    if not isinstance(instance, dict):
        return
    props = sch.get("properties", {})
    extra = sch.get("additionalProperties")
    for key in list(instance):
        sub = props.get(key, extra if isinstance(extra, dict) else None)
        if sub is not None:
            instance[key] = _coerce(instance[key], sub)
            _coerce_numbers(instance[key], sub)


def validate_config(config: dict[str, Any]) -> dict[str, Any]:
    """Return a validated copy of ``config`` with defaults filled in.

    Raises
    ------
    ConfigError
        Naming the first offending key, e.g. ``config: hdr.samples: 3 is less than
        the minimum of 20``.
    """
    sch = schema()
    cfg = copy.deepcopy(dict(config))
    _coerce_numbers(cfg, sch)
    _fill_defaults(cfg, sch)
    validator = jsonschema.Draft202012Validator(sch)
    errors = sorted(validator.iter_errors(cfg), key=lambda e: list(e.absolute_path))
    if errors:
        err = errors[0]
        key = ".".join(str(p) for p in err.absolute_path) or "<top>"
        raise ConfigError(f"config: {key}: {err.message}")
    return cfg


def load_config(path: str | Path, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Read a YAML config file, apply top-level ``overrides`` and validate it."""
    path = Path(path)
    try:
        cfg = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read config ({exc})") from None
    cfg.update(overrides or {})
    return validate_config(cfg)


def apply_settings(cfg: dict[str, Any], settings: list[str]) -> dict[str, Any]:
    """Apply ``section.key=value`` settings (value parsed as YAML) and re-validate,
    e.g. ``observation.texels_x=512``."""
    cfg = copy.deepcopy(cfg)
    for item in settings or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"config: --set {item!r}: expected section.key=value")
        node = cfg
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"config: --set {item!r}: {part} is not a section")
        node[leaf] = yaml.safe_load(value)
    return validate_config(cfg)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else copy.deepcopy(v)
    return out


def surface_config(cfg: dict[str, Any], surface_id: str) -> dict[str, Any]:
    """The configuration one surface runs with: ``overrides[surface_id]`` merged over
    the sections, validated again (so a bad override names its key)."""
    over = (cfg.get("overrides") or {}).get(surface_id)
    if not over:
        return cfg
    try:
        return validate_config(_merge(cfg, over))
    except ConfigError as exc:
        raise ConfigError(f"{exc} (from overrides.{surface_id})") from None


@lru_cache(maxsize=1)
def _defaults() -> dict[str, Any]:
    sch = schema()
    cfg: dict[str, Any] = {}
    _fill_defaults(cfg, sch)
    return cfg


def default(key: str) -> Any:
    """The schema's default of a dotted config key, e.g. ``default("hdr.low")``: where a
    function's parameter defaults to a config setting, it reads it here, so that every
    default is written once, in the schema."""
    node: Any = _defaults()
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(f"config schema has no default for {key!r}")
        node = node[part]
    return copy.deepcopy(node)
