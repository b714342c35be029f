"""Loading and validating a capture directory (``docs/reference/capture-format.md``).

Every problem stops the run before any work with one line naming the file and the
key, e.g. ``capture.yaml: views[3].exposures[0].exposure_s: must be positive (got -1)``.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import cv2
import jsonschema
import numpy as np
import yaml

from ..errors import InputError
from .images import ImageReadError, exif_exposure_time, image_size

__all__ = [
    "Capture",
    "CaptureError",
    "Exposure",
    "View",
    "aruco_dictionary",
    "capture_schema",
    "load_capture",
    "validate_capture",
]


#: the colour chart a capture names when it does not say (the ColorChecker Classic)
DEFAULT_CHART = "MCC24"
#: the chart's bracket's id when capture.yaml gives none
DEFAULT_CHART_ID = "chart"


class CaptureError(InputError):
    """An invalid capture directory; the message names the file and key."""


@dataclass(frozen=True)
class Exposure:
    path: Path
    exposure_s: float


@dataclass(frozen=True)
class View:
    id: str
    holdout: bool
    exposures: tuple[Exposure, ...]


@dataclass
class Capture:
    """A parsed capture. Paths are absolute; lengths are millimetres."""

    root: Path
    surface_id: str
    width_mm: float
    height_mm: float
    marker_dictionary: str
    marker_ids: np.ndarray  # (M,) int
    marker_corners: np.ndarray  # (M, 4, 2) float, surface frame, OpenCV corner order
    calibration: dict[str, Any]
    calibration_images: list[Path]
    intrinsics_path: Path | None
    response: str  # "auto", "linear" or a path
    views: list[View]
    raw: dict[str, Any] = field(repr=False, default_factory=dict)
    # lights the lab measured: each ``position_mm`` (surface frame) and maybe ``size_mm``
    lights: list[dict[str, Any]] = field(default_factory=list)
    # the room's light the lab measured: ``share`` (R, G, B) of a white card's light at
    # ``at_mm`` (x, y; the surface's centre unless stated) that stays with the lamps off
    ambient: dict[str, Any] | None = None
    # white-card views (flat-field) and the colour chart's bracket, merged as views are
    flatfield: list[View] = field(default_factory=list)
    # the card's diffuse reflectance (R, G, B) where the lab states it (a calibrated
    # white standard): it makes the flat-field's irradiance absolute
    card_reflectance: tuple[float, float, float] | None = None
    chart: View | None = None
    chart_type: str = DEFAULT_CHART
    chart_reference: str | None = None  # colour-science's name; None: the chart's own

    def view(self, view_id: str) -> View:
        """A view, white-card view or the chart's bracket by id."""
        for v in [*self.views, *self.radiometry_views]:
            if v.id == view_id:
                return v
        raise KeyError(view_id)

    @property
    def radiometry_views(self) -> list[View]:
        """The white card's views and the chart's bracket (the radiometry stage's)."""
        return [*self.flatfield, *([self.chart] if self.chart else [])]

    @property
    def fitted_views(self) -> list[View]:
        return [v for v in self.views if not v.holdout]


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV ArUco dictionary by name (``DICT_4X4_50``...); ValueError if unknown."""
    code = getattr(cv2.aruco, str(name), None)
    if not str(name).startswith("DICT_") or not isinstance(code, int):
        raise InputError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(code)


class _Ctx:
    def __init__(self, yaml_path: Path):
        self.yaml_path = yaml_path
        self.root = yaml_path.parent.resolve()

    def fail(self, key: str, problem: str) -> None:
        raise CaptureError(f"{self.yaml_path}: {key}: {problem}")

    def get(self, d: Any, key: str, where: str, kind=None, required: bool = True):
        full = f"{where}.{key}" if where else key
        if not isinstance(d, dict):
            self.fail(where or "<top>", "must be a mapping")
        if key not in d or d[key] is None:
            if required:
                self.fail(full, "missing key")
            return None
        value = d[key]
        if kind is not None:
            kinds = kind if isinstance(kind, tuple) else (kind,)
            # YAML's true/false are ints to Python; never accept them as numbers.
            if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
                self.fail(full, f"must be {_kind_name(kind)} (got {value!r})")
        return value

    def positive(self, d: Any, key: str, where: str) -> float:
        v = float(self.get(d, key, where, (int, float)))
        if not np.isfinite(v) or v <= 0:
            self.fail(f"{where}.{key}", f"must be positive (got {v:g})")
        return v

    def path(self, rel: Any, key: str, must_exist: bool = True) -> Path:
        if not isinstance(rel, str) or not rel:
            self.fail(key, f"must be a relative path (got {rel!r})")
        p = (self.root / rel).resolve()
        if not p.is_relative_to(self.root):
            self.fail(key, f"path {rel!r} leaves the capture directory")
        if must_exist and not p.is_file():
            self.fail(key, f"file {rel!r} does not exist")
        return p


def _kind_name(kind) -> str:
    names = {str: "a string", list: "a list", dict: "a mapping", int: "an integer",
             bool: "true or false"}
    if isinstance(kind, tuple):
        return "a number"
    return names.get(kind, str(kind))


def capture_schema() -> dict[str, Any]:
    """The JSON schema of ``capture.yaml`` (``schemas/capture.schema.yaml``) as a dict."""
    text = resources.files("parammap").joinpath("schemas/capture.schema.yaml").read_text()
    return yaml.safe_load(text)


_TYPE_NAMES = {"string": "a string", "number": "a number", "integer": "an integer",
               "array": "a list", "object": "a mapping", "boolean": "true or false",
               "null": "empty"}


def _key(path) -> str:
    """``views[2].exposures[0].file`` from a jsonschema path."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "<top>"


def _check_schema(c: _Ctx, raw: Any) -> None:
    """Stop at the first value (in document order) that breaks the capture schema,
    naming its key: a missing key, a wrong type, or the node's ``x-message``."""
    validator = jsonschema.Draft202012Validator(capture_schema())
    errors = sorted(validator.iter_errors(raw), key=lambda e: [str(p) for p in e.path])
    if not errors:
        return
    e = errors[0]
    if e.validator == "required":
        missing = e.message.split("'")[1]
        c.fail(_key([*e.path, missing]), "missing key")
    got = e.instance if not isinstance(e.instance, dict | list) or e.validator in (
        "minItems", "maxItems") else None
    got = "" if got is None else f" (got {got!r})" if not isinstance(got, list) else \
        f" (got {len(got)})"
    if e.validator == "type" and e.schema.get("type") == e.validator_value:
        kinds = e.validator_value if isinstance(e.validator_value, list) else [
            e.validator_value]
        c.fail(_key(e.path), "must be " + " or ".join(_TYPE_NAMES.get(k, k) for k in kinds)
               + f" (got {e.instance!r})")
    if "x-message" in e.schema:
        c.fail(_key(e.path), e.schema["x-message"] + got)
    c.fail(_key(e.path), e.message)


def _markers(c: _Ctx, raw: dict) -> tuple[str, np.ndarray, np.ndarray]:
    """Dictionary name, ids (M,) and corners (M, 4, 2) mm of the surface markers.

    A capture may have no markers yet (a bracket alone): the HDR stage still runs and
    the pose stage drops every view with that reason."""
    markers = raw.get("markers") or {}
    dict_name = markers.get("dictionary", "DICT_4X4_50")
    try:
        dictionary = aruco_dictionary(dict_name)
    except ValueError as exc:
        c.fail("markers.dictionary", str(exc))
    items = markers.get("items") or []
    if 0 < len(items) < 4:
        c.fail("markers.items", f"needs at least 4 markers (got {len(items)})")
    ids, corners = [], []
    n_dict = dictionary.bytesList.shape[0]
    for k, item in enumerate(items):
        where = f"markers.items[{k}]"
        mid = item["id"]
        if mid >= n_dict:
            c.fail(f"{where}.id", f"{mid} is not in {dict_name} (ids 0..{n_dict - 1})")
        if mid in ids:
            c.fail(f"{where}.id", f"duplicate marker id {mid}")
        arr = np.asarray(item["corners_mm"], float)
        if not np.all(np.isfinite(arr)):
            c.fail(f"{where}.corners_mm", "must be 4 corners of [x, y] in mm")
        ids.append(mid)
        corners.append(arr)
    return dict_name, np.asarray(ids, int), np.asarray(corners, float).reshape(-1, 4, 2)


def _calibration(c: _Ctx, raw: dict) -> tuple[dict, list[Path], Path | None]:
    """The calibration section, its board photos and a saved intrinsics file.

    Calibration may be absent for a bracket-only capture; the calibrate stage then
    stops with a clear message."""
    calib = raw.get("calibration") or {}
    if not calib:
        return {}, [], None
    board = c.get(calib, "board", "calibration", str)
    for key in ("squares_x", "squares_y"):
        c.get(calib, key, "calibration")
    square = c.positive(calib, "square_mm", "calibration")
    if board == "charuco":
        if c.positive(calib, "marker_mm", "calibration") >= square:
            c.fail("calibration.marker_mm", "must be smaller than square_mm")
        try:
            aruco_dictionary(c.get(calib, "dictionary", "calibration", str))
        except ValueError as exc:
            c.fail("calibration.dictionary", str(exc))
    intr = calib.get("intrinsics")
    intr_path = c.path(intr, "calibration.intrinsics") if intr else None
    pattern = calib.get("images")
    if intr_path is None:
        pattern = c.get(calib, "images", "calibration", str)
    images: list[Path] = []
    if pattern:
        if Path(pattern).is_absolute() or ".." in Path(pattern).parts:
            c.fail("calibration.images", f"pattern {pattern!r} leaves the capture directory")
        images = sorted(Path(p).resolve() for p in glob.glob(str(c.root / pattern)))
        if not images and intr_path is None:
            c.fail("calibration.images", f"pattern {pattern!r} matches no file")
    return dict(calib), images, intr_path


def _exposures(c: _Ctx, items: list, where: str) -> tuple[Exposure, ...]:
    """A bracket's exposures (times from capture.yaml, or from EXIF)."""
    exps = []
    for e, ex in enumerate(items):
        ew = f"{where}.exposures[{e}]"
        p = c.path(ex["file"], f"{ew}.file")
        t = ex.get("exposure_s")
        if t is None:
            # EXIF is read from the header only, cheap enough for every load.
            t = exif_exposure_time(p) if p.is_file() else None
            if t is None:
                c.fail(f"{ew}.exposure_s", f"missing, and {p.name} has no EXIF ExposureTime")
        elif not np.isfinite(float(t)):
            c.fail(f"{ew}.exposure_s", f"must be positive (got {t})")
        exps.append(Exposure(p, float(t)))
    return tuple(exps)


def _views(c: _Ctx, items: list, key: str, seen: set[str]) -> list[View]:
    """Every view of ``items`` (``capture.yaml``'s list ``key``) with its exposures;
    ids must be new to ``seen``, which gathers them."""
    views = []
    for k, v in enumerate(items):
        where = f"{key}[{k}]"
        vid = str(v["id"])
        if vid in seen:
            c.fail(f"{where}.id", f"duplicate view id {vid!r}")
        seen.add(vid)
        views.append(View(vid, bool(v.get("holdout", False)),
                          _exposures(c, v["exposures"], where)))
    return views


def _radiometry_views(c: _Ctx, raw: dict, seen: set[str]) -> tuple[list[View], View | None]:
    """The white card's views and the colour chart's bracket (ids new to ``seen``)."""
    card = _views(c, (raw.get("flatfield") or {}).get("views") or [], "flatfield.views", seen)
    chart_raw = raw.get("colour_chart")
    if not chart_raw:
        return card, None
    cid = str(chart_raw.get("id", DEFAULT_CHART_ID))
    if cid in seen:
        c.fail("colour_chart.id", f"duplicate view id {cid!r}")
    return card, View(cid, False, _exposures(c, chart_raw["exposures"], "colour_chart"))


def load_capture(directory: str | Path, check_images: bool = False) -> Capture:
    """Parse and check ``<directory>/capture.yaml``: first against its JSON schema
    (:func:`capture_schema`), then what a schema cannot express (files, dictionaries,
    duplicate ids, EXIF exposure times).

    Parameters
    ----------
    directory : the capture directory.
    check_images : also decode every photo, check sizes agree within the views and
        within the calibration set.

    Raises
    ------
    CaptureError
        On the first problem, naming the file and key.
    """
    directory = Path(directory)
    yaml_path = directory / "capture.yaml"
    if not yaml_path.is_file():
        raise CaptureError(f"{yaml_path}: missing (a capture directory holds capture.yaml)")
    try:
        raw = yaml.safe_load(yaml_path.read_text())
    except yaml.YAMLError as exc:
        raise CaptureError(f"{yaml_path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    c = _Ctx(yaml_path)
    if not isinstance(raw, dict):
        c.fail("<top>", "must be a mapping")
    _check_schema(c, raw)
    surface = raw["surface"]
    dict_name, ids, corners = _markers(c, raw)
    calib, calib_images, intr_path = _calibration(c, raw)
    seen: set[str] = set()
    views = _views(c, raw["views"], "views", seen)
    card, chart = _radiometry_views(c, raw, seen)
    chart_raw = raw.get("colour_chart") or {}
    response = (raw.get("camera") or {}).get("response", "auto")
    if response not in ("auto", "linear"):
        response = str(c.path(response, "camera.response"))
    cap = Capture(
        root=c.root, surface_id=str(surface["id"]),
        width_mm=c.positive(surface, "width_mm", "surface"),
        height_mm=c.positive(surface, "height_mm", "surface"),
        marker_dictionary=dict_name, marker_ids=ids,
        marker_corners=corners, calibration=calib, calibration_images=calib_images,
        intrinsics_path=intr_path, response=response, views=views, raw=raw,
        lights=[dict(lt) for lt in raw.get("lights") or []], ambient=_ambient(raw),
        flatfield=card, card_reflectance=_card_reflectance(raw), chart=chart,
        chart_type=chart_raw.get("chart", DEFAULT_CHART),
        chart_reference=chart_raw.get("reference"),
    )
    if check_images:
        _check_images(c, cap, raw["views"])
    return cap


def _ambient(raw: dict) -> dict[str, Any] | None:
    """The capture's ``ambient`` (schema-checked) with its share as (R, G, B) and where
    it was read (default the surface's centre)."""
    a = raw.get("ambient")
    if not a:
        return None
    s = raw["surface"]
    return {"share": np.broadcast_to(np.asarray(a["share"], float), (3,)).tolist(),
            "at_mm": [float(x) for x in a.get("at_mm") or (s["width_mm"] / 2,
                                                            s["height_mm"] / 2)]}


def _card_reflectance(raw: dict) -> tuple[float, float, float] | None:
    """The white card's stated reflectance (schema-checked) as (R, G, B), or None."""
    r = (raw.get("flatfield") or {}).get("reflectance")
    return None if r is None else tuple(
        float(x) for x in np.broadcast_to(np.asarray(r, float), (3,)))


def _check_images(c: _Ctx, cap: Capture, views_raw: list) -> None:
    view_size = None
    keyed = ([(f"views[{k}]", v) for k, v in enumerate(cap.views)]
             + [(f"flatfield.views[{k}]", v) for k, v in enumerate(cap.flatfield)]
             + ([("colour_chart", cap.chart)] if cap.chart else []))
    for where, v in keyed:
        for e, ex in enumerate(v.exposures):
            key = f"{where}.exposures[{e}].file"
            try:
                size = image_size(ex.path)
            except ImageReadError as exc:
                c.fail(key, str(exc))
            if view_size is None:
                view_size, first = size, f"{key} ({ex.path.relative_to(c.root)})"
            elif size != view_size:
                c.fail(key, f"{ex.path.relative_to(c.root)}: image size {size[1]}x"
                            f"{size[0]} differs from {view_size[1]}x{view_size[0]} of "
                            f"{first}")
    calib_size = None
    for p in cap.calibration_images:
        try:
            size = image_size(p)
        except ImageReadError as exc:
            c.fail("calibration.images", str(exc))
        if calib_size is None:
            calib_size, first = size, p.name
        elif size != calib_size:
            c.fail("calibration.images", f"{p.name}: image size differs from {first}")


def validate_capture(directory: str | Path) -> Capture:
    """Full check of a capture, images included (``parammap validate-capture``)."""
    return load_capture(directory, check_images=True)
