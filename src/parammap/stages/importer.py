"""A lab's camera folder becomes a capture: ``parammap import``.

The photos' headers say everything the capture format needs but the layout: exposure
time, aperture, ISO, focal length and when each was taken (EXIF, or a RAW's own header;
:func:`parammap.stores.images.photo_meta`). A folder of RAW files becomes a capture with
a linear response (``camera.response: linear``); where the camera wrote a JPEG beside
each RAW, the RAWs are used. Photos are ordered by the time they were
taken (then by name) and grouped into brackets: a bracket is a run of photos whose
exposure times are all different; a photo repeating a time already in the run, or
taken after a pause, starts the next. What a pause is comes from the capture's own
intervals between consecutive photos: bracketed frames follow each other at the
camera's frame rate and moving the camera to the next view takes far longer, so the
intervals fall into two groups; the widest break between them, where it is at least
:data:`PAUSE_FACTOR` wide, separates them (:func:`_pause`).

Each bracket is a view of the surface or a photo of the calibration board, told apart
by what its best-exposed photo shows: the board's markers (the ids of the board's
dictionary that a ChArUco board of that size uses) or the surface's (the layout's ids).
Board photos go to ``calibration/``, views to ``views/``; held-out views are those of
the photos the user names, or drawn reproducibly (``holdout`` of them, by a seeded
generator). Photos are hard-linked
into the capture where the file system allows (copied otherwise), the capture written
under a temporary name, checked by the capture loader, then renamed.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import InputError
from ..parallel import progress
from ..stores.capture import DEFAULT_CHART, DEFAULT_CHART_ID, load_capture
from ..stores.images import (
    PHOTO_SUFFIXES,
    ImageReadError,
    PhotoMeta,
    is_raw,
    photo_meta,
    read_image,
)
from ..vision.markers import detect_markers, to_gray8

logger = logging.getLogger(__name__)

__all__ = ["PAUSE_FACTOR", "CameraFolderError", "brackets_of", "default_holdout",
           "run_import"]

PAUSE_FACTOR = 10.0  # frame intervals and pauses at least this far apart
HOLDOUT_SHARE = 0.05  # views held out by default (at least one once there are ten)


class CameraFolderError(InputError):
    """A camera folder that cannot become a capture."""


def default_holdout(n_views: int) -> int:
    """Views held out when the user does not say: about 5 %, one from ten views up."""
    return 0 if n_views < 10 else max(1, round(HOLDOUT_SHARE * n_views))


def _files(photos: Path) -> list[Path]:
    """The camera files of a folder; where the camera wrote a RAW and a JPEG of each shot,
    the RAWs (linear, no response to recover). One kind only otherwise."""
    if not photos.is_dir():
        raise CameraFolderError(f"{photos}: not a folder of photos")
    files = sorted(p for p in photos.rglob("*") if p.is_file()
                   and p.suffix.lower() in PHOTO_SUFFIXES)
    if not files:
        raise CameraFolderError(f"{photos}: no photos ({', '.join(PHOTO_SUFFIXES)})")
    raws = [f for f in files if is_raw(f)]
    if raws and len(raws) < len(files):
        stems = {f.with_suffix("") for f in raws}
        others = [f for f in files if not is_raw(f)]
        unpaired = [f for f in others if f.with_suffix("") not in stems]
        if unpaired:
            raise CameraFolderError(
                f"mixed RAW and other photos: {raws[0].name} and {unpaired[0].name} (no RAW "
                "of that shot); import one kind at a time")
        logger.info(f"import: {len(raws)} RAW files, the {len(others)} JPEG/TIFF files the "
                    "camera wrote beside them are not used")
        files = raws
    return files


def _check_camera(metas: list[PhotoMeta]) -> None:
    """One camera and one image size; every photo with an exposure time."""
    for what, key in (("cameras", lambda m: m.camera), ("image sizes", lambda m: m.size)):
        values = {}
        for m in metas:
            values.setdefault(key(m), m.path)
        if len(values) > 1:
            first, *rest = values.items()
            raise CameraFolderError(
                f"mixed {what}: {first[1].name} ({first[0]}) and {rest[0][1].name} "
                f"({rest[0][0]}); import one camera's photos at a time")
    missing = [m.path.name for m in metas if m.exposure_s is None or m.exposure_s <= 0]
    if missing:
        raise CameraFolderError(f"no EXIF ExposureTime in {', '.join(missing[:5])}"
                           + (f" and {len(missing) - 5} more" if len(missing) > 5 else ""))


def _pause(gaps: np.ndarray) -> float | None:
    """The interval (s) beyond which the next photo starts a new bracket: the middle (in
    log) of the widest break between the intervals sorted, where that break is at least
    :data:`PAUSE_FACTOR` wide (the camera's frame interval and the time it takes to move
    it are two populations); None where the intervals show no such break."""
    lg = np.sort(np.log(gaps[gaps > 0]))
    if len(lg) < 2:
        return None
    jump = np.diff(lg)
    k = int(np.argmax(jump))
    if jump[k] < np.log(PAUSE_FACTOR):
        return None
    return float(np.exp(0.5 * (lg[k] + lg[k + 1])))


def brackets_of(metas: Sequence[PhotoMeta]) -> list[list[PhotoMeta]]:
    """Photos grouped into brackets (module docstring), in the order they were taken.

    Raises
    ------
    InputError
        For a bracket whose aperture, ISO or focal length changes (named by its files).
    """
    order = sorted(metas, key=lambda m: (m.taken_s if m.taken_s is not None else np.inf,
                                         m.path.name))
    pause_s = _pause(np.diff([m.taken_s for m in order if m.taken_s is not None]))
    groups: list[list[PhotoMeta]] = []
    for k, m in enumerate(order):
        prev = order[k - 1] if k else None
        pause = (pause_s is not None and prev is not None and m.taken_s is not None
                 and prev.taken_s is not None and m.taken_s - prev.taken_s > pause_s)
        repeat = bool(groups) and any(np.isclose(m.exposure_s, o.exposure_s, rtol=1e-3)
                                      for o in groups[-1])
        if not groups or pause or repeat:
            groups.append([m])
        else:
            groups[-1].append(m)
    for g in groups:
        for what, key in (("aperture", "f_number"), ("ISO", "iso"),
                          ("focal length", "focal_mm")):
            vals = {getattr(m, key) for m in g}
            if len(vals) > 1:
                raise CameraFolderError(
                    f"bracket {g[0].path.name} .. {g[-1].path.name}: the {what} changes "
                    f"({', '.join(str(v) for v in sorted(vals, key=str))}); a bracket "
                    "keeps everything but the exposure time")
    return groups


def _load_yaml(path: Path, what: str) -> dict:
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise CameraFolderError(f"{path}: cannot read the {what} ({exc})") from None
    if not isinstance(data, dict):
        raise CameraFolderError(f"{path}: not a {what} (a mapping is expected)")
    return data


def _board_ids(calibration: dict) -> set[int]:
    """Marker ids a ChArUco board of that size carries (0 .. n - 1, OpenCV's layout)."""
    if calibration.get("board") != "charuco":
        return set()
    n = (int(calibration["squares_x"]) * int(calibration["squares_y"])) // 2
    return set(range(n))


def _shows_board(group: list[PhotoMeta], markers: dict, calibration: dict | None) -> bool:
    """Whether a bracket's best-exposed photo shows the board rather than the surface."""
    if not calibration:
        return False
    best = sorted(group, key=lambda m: m.exposure_s)[len(group) // 2]
    try:
        gray = to_gray8(read_image(best.path))
    except ImageReadError as exc:
        raise CameraFolderError(str(exc)) from None
    surface = {int(it["id"]) for it in markers.get("items") or []}
    board = _board_ids(calibration)
    ids_s, _ = detect_markers(gray, markers["dictionary"])
    on_surface = len(surface & set(ids_s.tolist()))
    if calibration.get("board") == "charuco":
        ids_b, _ = detect_markers(gray, calibration["dictionary"])
        hits = set(ids_b.tolist()) & board
        if calibration["dictionary"] == markers["dictionary"]:
            hits -= surface  # ids both use say nothing
        return len(hits) >= 4 and len(hits) > on_surface
    return on_surface == 0  # a chessboard has no markers


def _listed(views: list[list[PhotoMeta]], names: Sequence[str]) -> set[int]:
    """Indices of the views holding the named camera files; an unknown name is an error."""
    where = {m.path.name: k for k, g in enumerate(views) for m in g}
    missing = [n for n in names if Path(n).name not in where]
    if missing:
        raise CameraFolderError(f"held-out photos not among the views' photos: "
                                f"{', '.join(missing)}")
    return {where[Path(n).name] for n in names}


def _place(src: Path, dst: Path) -> None:
    """Hard-link a photo into the capture (copy across file systems)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def run_import(photos: str | Path, out: str | Path, *, layout: str | Path,
               board: str | Path | None = None, holdout: int | None = None, seed: int = 0,
               surface_id: str | None = None,
               holdout_photos: Sequence[str] = (), flatfield: str | Path | None = None,
               chart: str | Path | None = None,
               ambient_share: float | Sequence[float] | None = None,
               card_reflectance: float | Sequence[float] | None = None) -> dict[str, Any]:
    """Build the capture ``out`` from a folder of camera files.

    Parameters
    ----------
    photos : folder (searched recursively) of JPEG, TIFF or PNG files with EXIF, or of
        camera RAW files (DNG, CR2, NEF, ARW, ...: a capture with a linear response).
    layout : the markers' layout (``parammap markers`` writes it: ``surface`` and
        ``markers`` in the capture format).
    board : the board's layout (``parammap board``: the ``calibration`` section); without
        it every bracket is a view and the capture needs saved intrinsics.
    holdout : views held out (default :func:`default_holdout`), drawn with ``seed``.
    holdout_photos : camera file names (any photo of a bracket) whose views are held
        out instead of drawn ones.
    surface_id : default the capture folder's name.
    flatfield : folder of photos of a uniform white card lying where the surface lies,
        under the capture's light, from a few places (brackets as the views'); the
        capture's ``flatfield`` section.
    chart : folder of one bracket of a ColorChecker Classic under the capture's light;
        the capture's ``colour_chart`` section.
    ambient_share : the room's own light, as the share (one value or R, G, B in [0, 1))
        of a white card's light at the surface's centre that stays with the lamps off;
        the capture's ``ambient`` section (the relightable map keeps it off the albedo).
    card_reflectance : the white card's diffuse reflectance (one value or R, G, B in
        (0, 1]; a calibrated white standard's certificate), which sets the relightable
        map's albedo scale; with ``flatfield`` only.

    Returns
    -------
    dict of counts: photos, views, held out, board photos, exposures per view.
    """
    photos, out = Path(photos), Path(out)
    lay = _load_yaml(Path(layout), "markers' layout")
    if "markers" not in lay or "surface" not in lay:
        raise CameraFolderError(f"{layout}: a markers' layout has surface and markers sections "
                           "(parammap markers writes one)")
    calib = _load_yaml(Path(board), "board layout").get("calibration") if board else None
    if board and not calib:
        raise CameraFolderError(f"{board}: a board layout has a calibration section "
                           "(parammap board writes one)")
    if card_reflectance is not None and not flatfield:
        raise CameraFolderError("--card-reflectance: the white card's reflectance needs its "
                                "photos (--flatfield)")
    extra = [Path(p).resolve() for p in (flatfield, chart) if p]
    files = [f for f in _files(photos)
             if not any(f.resolve().is_relative_to(e) for e in extra)]
    metas = _headers(files, "import: headers")
    card = brackets_of(_headers(_files(Path(flatfield)), "import: white card")) \
        if flatfield else []
    chart_groups = brackets_of(_headers(_files(Path(chart)), "import: colour chart")) \
        if chart else []
    if chart and len(chart_groups) != 1:
        raise CameraFolderError(f"{chart}: {len(chart_groups)} brackets; the colour chart's "
                                "folder holds one")
    _check_camera(metas + [m for g in card + chart_groups for m in g])
    groups = brackets_of(metas)
    kinds = [_shows_board(g, lay["markers"], calib)
             for g in progress(groups, len(groups), "import: views and board photos", logger)]
    views = [g for g, b in zip(groups, kinds, strict=True) if not b]
    boards = [g for g, b in zip(groups, kinds, strict=True) if b]
    if not views:
        raise CameraFolderError(f"{photos}: no photo shows the surface's markers "
                           f"({lay['markers']['dictionary']})")
    if holdout_photos:
        held = _listed(views, holdout_photos)
        n_hold = len(held)
    else:
        n_hold = default_holdout(len(views)) if holdout is None else int(holdout)
        held = set(np.random.default_rng(seed).choice(len(views), max(n_hold, 0),
                                                      replace=False).tolist()) \
            if 0 <= n_hold < len(views) else set()
    if not 0 <= n_hold < len(views):
        raise CameraFolderError(f"{n_hold} views held out: must leave at least one of the "
                                f"{len(views)} views to fit")
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        doc = _write(tmp, views, boards, held, lay, calib, surface_id or out.name)
        _write_radiometry(tmp, doc, card, chart_groups[0] if chart_groups else None,
                          ambient_share, card_reflectance)
        load_capture(tmp, check_images=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    tmp.replace(out)
    summary = {"photos": len(files), "views": len(views), "held_out": n_hold,
               "board_photos": len(boards), "card_views": len(card),
               "chart": bool(chart_groups),
               "exposures_per_view": sorted({len(g) for g in views})}
    logger.info(f"import: {out}: {summary['views']} views ({n_hold} held out) of "
                f"{'/'.join(map(str, summary['exposures_per_view']))} exposures, "
                f"{len(boards)} board photos, from {len(files)} photos")
    return summary | {"capture": doc}


def _headers(files: list[Path], what: str) -> list[PhotoMeta]:
    """The camera metadata of each file; one line naming an unreadable one."""
    metas = []
    for f in progress(files, len(files), what, logger):
        try:
            metas.append(photo_meta(f))
        except ImageReadError as exc:
            raise CameraFolderError(str(exc)) from None
    return metas


def _bracket_doc(root: Path, name: str, g: list[PhotoMeta]) -> list[dict[str, Any]]:
    """A bracket's photos placed under ``radiometry/`` as ``<name>_<k>``, longest
    exposure first; their capture-format entries."""
    exps = []
    for j, m in enumerate(sorted(g, key=lambda m: -m.exposure_s)):
        rel = Path("radiometry") / f"{name}_{j}{m.path.suffix.lower()}"
        _place(m.path, root / rel)
        exps.append({"file": rel.as_posix(), "exposure_s": float(m.exposure_s)})
    return exps


def _write_radiometry(root: Path, doc: dict, card: list[list[PhotoMeta]],
                      chart: list[PhotoMeta] | None,
                      ambient_share: float | Sequence[float] | None = None,
                      card_reflectance: float | Sequence[float] | None = None) -> None:
    """The white card's views, the chart's bracket and the room's stated light into
    ``root`` and its ``capture.yaml`` (``doc``, updated)."""
    if ambient_share is not None:
        doc["ambient"] = {"share": _one_or_rgb(ambient_share)}
    if card:
        doc["flatfield"] = {"views": [{"id": f"card{k:02d}",
                                       "exposures": _bracket_doc(root, f"card{k:02d}", g)}
                                      for k, g in enumerate(card)]}
        if card_reflectance is not None:
            doc["flatfield"] = {"reflectance": _one_or_rgb(card_reflectance),
                                **doc["flatfield"]}
    if chart:
        doc["colour_chart"] = {"id": DEFAULT_CHART_ID, "chart": DEFAULT_CHART,
                               "exposures": _bracket_doc(root, DEFAULT_CHART_ID, chart)}
    if card or chart or ambient_share is not None:
        (root / "capture.yaml").write_text(
            "# written by parammap import\n"
            + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))


def _one_or_rgb(value: float | Sequence[float]) -> float | list[float]:
    """A stated value as capture.yaml holds it: one number, or R, G, B."""
    v = np.atleast_1d(np.asarray(value, float)).tolist()
    return v[0] if len(v) == 1 else v


def _camera_settings(metas: list[PhotoMeta]) -> dict[str, Any]:
    """The camera and the settings every view's photo shares (provenance)."""
    out: dict[str, Any] = {"model": metas[0].camera} if metas[0].camera else {}
    for key in ("f_number", "iso", "focal_mm"):
        vals = {getattr(m, key) for m in metas}
        if len(vals) == 1 and None not in vals:
            out[key] = float(vals.pop())
    return out


def _write(root: Path, views: list[list[PhotoMeta]], boards: list[list[PhotoMeta]],
           held: set[int], lay: dict, calib: dict | None, surface_id: str) -> dict:
    """Photos into ``root`` and its ``capture.yaml``; returns the document."""
    vlist = []
    width = len(str(max(len(views) - 1, 1)))
    for k, g in enumerate(views):
        vid = f"v{k:0{max(3, width)}d}"
        exps = []
        for j, m in enumerate(sorted(g, key=lambda m: -m.exposure_s)):
            rel = Path("views") / f"{vid}_{j}{m.path.suffix.lower()}"
            _place(m.path, root / rel)
            exps.append({"file": rel.as_posix(), "exposure_s": float(m.exposure_s)})
        vlist.append({"id": vid, "holdout": k in held, "exposures": exps,
                      "source": [m.path.name for m in g]})
    doc: dict[str, Any] = {
        "surface": {"id": surface_id, **{k: v for k, v in lay["surface"].items()
                                         if k != "id"}},
        "markers": lay["markers"]}
    if calib:
        for k, g in enumerate(boards):
            # one photo per board pose: the bracket's best exposed
            m = sorted(g, key=lambda m: m.exposure_s)[len(g) // 2]
            _place(m.path, root / "calibration" / f"board_{k:03d}{m.path.suffix.lower()}")
        doc["calibration"] = {**calib, "images": "calibration/*", "intrinsics": None}
    # a RAW is linear: nothing to recover
    response = "linear" if is_raw(views[0][0].path) else "auto"
    doc["camera"] = {"response": response, **_camera_settings([m for g in views for m in g])}
    doc["views"] = vlist
    root.mkdir(parents=True, exist_ok=True)
    (root / "capture.yaml").write_text(
        "# written by parammap import\n"
        + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    return doc
