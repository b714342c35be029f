"""The lights found from the highlights (``camera/lights.yaml``), and a capture's measured
ones."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import InputError
from ..models.radiometry import IrradianceGrid
from ..models.svbrdf import LightRig
from .common import read_document

__all__ = ["LIGHTS_VERSION", "LightsError", "light_doc", "parse_lamps", "parse_light_doc",
           "read_lights", "write_lights"]

LIGHTS_VERSION = 1


class LightsError(InputError):
    """A missing or malformed ``camera/lights.yaml``."""


# the lights a relightable map carries (fit-store attribute, EXR header as JSON)
_POSITION, _INTENSITY, _IRRADIANCE, _AMBIENT = ("position_mm", "intensity", "irradiance",
                                                 "ambient")
_NORMAL, _LAMPS, _EXTENT = "emitter_normal", "lamps", "extent"


def light_doc(position_mm: np.ndarray, intensity: np.ndarray,
              irradiance: IrradianceGrid | None = None,
              ambient: np.ndarray | None = None,
              lamps: tuple[np.ndarray, np.ndarray, list] | None = None) -> dict[str, Any]:
    """The lights of a relightable map as stored with it: positions (J, 3) mm, surface
    frame, or (P, 6) with the emitters' normals (an area light's points,
    :func:`parammap.models.lights.expand_lights`), relative RGB intensities (J, 3) (or
    (P, 3)), with area lights the ``lamps`` they are points of (centres (L, 3), RGB
    intensities (L, 3), extents), the room's ambient irradiance (3,) where the
    capture stated it (:func:`parammap.models.svbrdf.ambient_irradiance`) and, when the
    capture's frames had the lights' fall-off divided out (a white card,
    :mod:`parammap.models.radiometry`), that relative irradiance, which the map's renders
    of the capture divide out too."""
    p = np.asarray(position_mm, float)
    p = p.reshape(-1, p.shape[-1] if p.ndim > 1 else 3)
    doc = {_POSITION: np.round(p[:, :3], 4).tolist(),
           _INTENSITY: np.round(np.asarray(intensity, float), 6).reshape(-1, 3).tolist()}
    if p.shape[1] == 6:
        doc[_NORMAL] = np.round(p[:, 3:], 6).tolist()
    if lamps is not None:
        doc[_LAMPS] = [{_POSITION: np.round(c, 4).tolist(), _INTENSITY: np.round(w, 6).tolist(),
                        _EXTENT: e} for c, w, e in zip(*lamps, strict=True)]
    if ambient is not None:
        doc[_AMBIENT] = np.round(np.asarray(ambient, float), 8).reshape(3).tolist()
    if irradiance is not None:
        doc[_IRRADIANCE] = {"grid": np.round(np.asarray(irradiance.grid), 6).tolist(),
                            "width_mm": irradiance.width_mm,
                            "height_mm": irradiance.height_mm}
    return doc


def parse_light_doc(doc: dict[str, Any] | str) -> LightRig:
    """The :class:`~parammap.models.svbrdf.LightRig` of :func:`light_doc` (or its
    JSON)."""
    doc = json.loads(doc) if isinstance(doc, str) else doc
    try:
        irr, amb = doc.get(_IRRADIANCE), doc.get(_AMBIENT)
        pos = np.asarray(doc[_POSITION], float).reshape(-1, 3)
        if _NORMAL in doc:
            pos = np.c_[pos, np.asarray(doc[_NORMAL], float).reshape(-1, 3)]
        return LightRig(
            pos,
            np.asarray(doc[_INTENSITY], float).reshape(-1, 3),
            None if irr is None else IrradianceGrid(
                np.asarray(irr["grid"], float), float(irr["width_mm"]),
                float(irr["height_mm"])),
            None if amb is None else np.asarray(amb, float).reshape(3))
    except (KeyError, TypeError, ValueError):
        raise LightsError(f"malformed lights of a relightable map: {str(doc)[:80]}") from None


def parse_lamps(doc: dict[str, Any] | str) -> tuple[np.ndarray, np.ndarray] | None:
    """The centres (L, 3) mm and RGB intensities (L, 3) of the area lights whose points
    a relightable map's lights are (:func:`light_doc`'s ``lamps``); None for point
    lights."""
    doc = json.loads(doc) if isinstance(doc, str) else doc
    lamps = doc.get(_LAMPS)
    if not lamps:
        return None
    return (np.array([lp[_POSITION] for lp in lamps], float).reshape(-1, 3),
            np.array([lp[_INTENSITY] for lp in lamps], float).reshape(-1, 3))


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
    doc = read_document(path, LightsError, "lights")
    if not isinstance(doc, dict) or not isinstance(doc.get("lights"), list):
        raise LightsError(f"{path}: no list of lights")
    return doc
