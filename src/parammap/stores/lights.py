"""The lights found from the highlights (``camera/lights.yaml``), and a capture's measured
ones."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from ..errors import InputError

__all__ = ["LIGHTS_VERSION", "LightsError", "read_lights", "write_lights"]

LIGHTS_VERSION = 1


class LightsError(InputError):
    """A missing or malformed ``camera/lights.yaml``."""


def write_lights(path: str | Path, lights: list[dict[str, Any]], info: dict[str, Any]) -> None:
    """Write ``camera/lights.yaml``: ``lights`` (each ``position_mm`` (3,), ``sd_mm``
    (3,), ``rays``, ``scale``; surface frame, mm) and ``info`` (the model they came
    from, ray counts), via a temporary name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"version": LIGHTS_VERSION, **info, "lights": lights}
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
    tmp.replace(path)


def read_lights(path: str | Path) -> dict[str, Any]:
    """Read ``camera/lights.yaml`` (:func:`write_lights`)."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise LightsError(f"{path}: cannot read the lights ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise LightsError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("lights"), list):
        raise LightsError(f"{path}: no list of lights")
    return doc
