"""The flat-field and colour correction of a capture (``camera/radiometry.json``).

Written by the radiometry stage from the capture's white-card and colour-chart photos;
an identity (nothing measured) when the capture has neither. Every stage that reads
radiance from a merged frame divides it through :func:`parammap.radiometry.correct_frame`
with this record.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..models.radiometry import (
    COLOUR_INTEROP_IDS,
    VIGNETTING_TERMS,
    Radiometry,
    describe_radiometry,
)
from .capture import Capture
from .common import read_document
from .paths import Processed

__all__ = ["INTEROP_ATTR", "RADIOMETRY_VERSION", "RadiometryError", "colour_interop",
           "describe_radiometry", "merged_frame_radiometry", "radiometry_for",
           "read_radiometry", "write_radiometry"]

RADIOMETRY_VERSION = 1

_VIGNETTING, _IRRADIANCE, _MATRIX, _SPACE, _FIELD, _MODEL, _SCALE = (
    "vignetting", "irradiance", "colour_matrix", "colour_space", "field_max", "colour_model",
    "irradiance_scale")


#: the OpenEXR header attribute that names the colour space of an image's RGB
INTEROP_ATTR = "colorInteropID"


class RadiometryError(InputError):
    """A missing or malformed ``camera/radiometry.json``."""


def _array(v: Any) -> np.ndarray | None:
    return None if v is None else np.asarray(v, float)


def write_radiometry(path: str | Path, rad: Radiometry, info: dict[str, Any]) -> Path:
    """Write ``camera/radiometry.json``: the correction and ``info`` (how it was
    measured), via a temporary name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"version": RADIOMETRY_VERSION,
           _VIGNETTING: None if rad.vignetting is None else np.asarray(rad.vignetting).tolist(),
           _IRRADIANCE: None if rad.irradiance is None else np.round(
               np.asarray(rad.irradiance), 6).tolist(),
           _MATRIX: None if rad.colour_matrix is None else np.asarray(
               rad.colour_matrix).tolist(),
           _SPACE: rad.colour_space, _FIELD: rad.field_max,
           _MODEL: rad.colour_model, _SCALE: rad.irradiance_scale, "info": info}
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    tmp.replace(path)
    return path


def read_radiometry(path: str | Path | None) -> Radiometry:
    """Read :func:`write_radiometry`'s file; None reads as the identity."""
    if path is None:
        return Radiometry()
    path = Path(path)
    doc = read_document(path, RadiometryError, "radiometry")
    try:
        rad = Radiometry(_array(doc[_VIGNETTING]), _array(doc[_IRRADIANCE]),
                         _array(doc[_MATRIX]), doc[_SPACE], doc.get(_FIELD),
                         doc.get(_MODEL), doc.get(_SCALE))
    except (KeyError, TypeError, ValueError):
        raise RadiometryError(f"{path}: not a radiometry record") from None
    if rad.vignetting is not None and (rad.vignetting.shape != (VIGNETTING_TERMS,)
                                       or rad.field_max is None):
        raise RadiometryError(f"{path}: vignetting must have {VIGNETTING_TERMS} terms and "
                              "a field_max")
    if rad.colour_matrix is not None and (rad.colour_matrix.shape[0] != 3
                                          or rad.colour_model is None):
        raise RadiometryError(f"{path}: colour_matrix must have 3 rows and a colour_model")
    if rad.irradiance is not None and (rad.irradiance.ndim != 2
                                       or not np.all(rad.irradiance > 0)):
        raise RadiometryError(f"{path}: irradiance must be a grid of positive values")
    return rad


def radiometry_for(cap: Capture, processed: str | Path | Processed) -> Radiometry:
    """The correction a stage applies to this capture's frames: read from
    ``camera/radiometry.json`` when the capture has a card or a chart (a clear error
    when the radiometry stage has not run), the identity otherwise."""
    if not cap.radiometry_views:
        return Radiometry()
    path = Processed(processed).radiometry
    if not path.is_file():
        raise RadiometryError(f"{path}: missing; the capture has a white card or a colour "
                                "chart, run `parammap radiometry` first")
    return read_radiometry(path)


def colour_interop(desc: dict[str, Any]) -> dict[str, str]:
    """The EXR header's ``colorInteropID`` for radiance described by ``desc``
    (:func:`describe_radiometry`): the colour space a chart's correction mapped it to;
    nothing for camera RGB, whose primaries no one measured."""
    space = desc.get("colour_space")
    return {INTEROP_ATTR: COLOUR_INTEROP_IDS[space]} if space in COLOUR_INTEROP_IDS else {}


def merged_frame_radiometry(cap: Capture) -> dict[str, str]:
    """What a merged frame (``hdr/<view>.exr``) says of its flat-field and colour: a
    frame is merged as the camera saw it (the card and the chart are measured from
    merged frames), and the capture's correction is applied as frames are read."""
    rec = "camera/radiometry.json"
    return {
        "flatfield": (f"not applied: divided out as the frame is read ({rec}, from the "
                      "white card)" if cap.flatfield else "none (no white card)"),
        "colour": (f"camera RGB: corrected as the frame is read ({rec}, from the colour "
                   "chart)" if cap.chart else "camera RGB (no colour chart)")}
