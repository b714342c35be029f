"""A synthetic capture written as a lab's camera would leave it: JPEG files (or DNGs of
a simulated sensor) named in the order they were taken, with exposure time, aperture,
ISO, focal length, time and camera in their headers and no YAML, plus the layouts
`parammap markers` and `parammap board` would have printed. `parammap import` reads it
back (issue 45's path with no YAML typed)."""

from __future__ import annotations

from datetime import datetime, timedelta
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from PIL import Image, TiffImagePlugin

from ..stores.capture import load_capture
from ..stores.images import read_image
from .generate import true_view_radiance
from .pbr import read_truth_radiance
from .raw import Sensor, expose_raw, write_dng

__all__ = ["write_camera_folder", "write_jpeg_exif"]

START = datetime(2026, 11, 20, 9, 0, 0)
FRAME_S = 0.4  # between the frames of a bracket (the camera's burst rate)
MOVE_S = 30.0  # moving the camera to the next view or board pose


def write_jpeg_exif(path: str | Path, rgb: np.ndarray, exposure_s: float | None,
                    taken: datetime, iso: int = 100, f_number: float = 8.0,
                    focal_mm: float = 35.0, camera: tuple[str, str] = ("Parammap", "Synth"),
                    size: tuple[int, int] | None = None, quality: int = 95) -> None:
    """One photo as a camera writes it: (H, W, 3) uint8 RGB as JPEG with EXIF (no
    ``ExposureTime`` where ``exposure_s`` is None; resized to ``size`` (w, h) if given)."""
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = camera
    ifd = exif.get_ifd(0x8769)
    if exposure_s is not None:
        ifd[0x829A] = TiffImagePlugin.IFDRational(Fraction(exposure_s).limit_denominator(100000))
    ifd[0x829D] = TiffImagePlugin.IFDRational(Fraction(f_number).limit_denominator(100))
    ifd[0x8827] = int(iso)
    ifd[0x920A] = TiffImagePlugin.IFDRational(Fraction(focal_mm).limit_denominator(100))
    ifd[0x9003] = taken.strftime("%Y:%m:%d %H:%M:%S")
    ifd[0x9291] = f"{taken.microsecond // 10000:02d}"
    im = Image.fromarray(np.ascontiguousarray(rgb[..., :3]).astype(np.uint8))
    if size is not None:
        im = im.resize(size)
    im.save(path, quality=quality, exif=exif.tobytes())


def _truth_response(truth: Path) -> tuple[np.ndarray, np.ndarray]:
    """The generator's response: 8-bit levels (256,) and their normalised exposure
    (256, 3)."""
    with np.load(truth / "response.npz") as r:
        return np.asarray(r["levels"], float), np.asarray(r["exposure"], float)


def _view_radiance(capture: Path, truth: Path, view_id: str) -> np.ndarray:
    """The radiance (H, W, 3) a generated view's photos were exposed from."""
    if (truth / "radiance" / f"{view_id}.exr").is_file():  # the physically based generator
        return read_truth_radiance(truth, view_id)
    return true_view_radiance(capture, truth, view_id)


def write_camera_folder(capture: str | Path, out: str | Path, seed: int = 0,
                        raw: Sensor | None = None, truth: str | Path | None = None,
                        ) -> dict[str, Any]:
    """Write ``capture``'s photos into ``out`` as a camera folder (``out/DCIM``: board
    photos first, then each view's bracket in a shuffled order, ``MOVE_S`` between
    poses and ``FRAME_S`` between frames) and its layouts (``out/markers.yaml``,
    ``out/board.yaml``). 16-bit photos are written as 8-bit JPEGs.

    With ``raw`` (a :class:`~parammap.synth.raw.Sensor`) the photos are DNGs that sensor
    records of each view's radiance (``truth``: the generator's truth folder) exposed
    for the bracket's times, the white level at the response's level 255; board photos
    from their 8-bit photos through the generator's response.

    A capture's white-card views and colour chart go to ``out/FLATFIELD`` and
    ``out/CHART`` (the import's ``--flatfield`` and ``--chart``).

    Returns
    -------
    ``{"photos": folder, "layout": markers.yaml, "board": board.yaml or None, "views":
    count, "board_photos": count}`` and ``flatfield`` and ``chart`` folders if written.
    """
    cap = load_capture(capture)
    out = Path(out)
    dcim = out / "DCIM"
    dcim.mkdir(parents=True, exist_ok=False)
    rng = np.random.default_rng(seed)
    when, n = START, 0
    if raw is not None:
        if truth is None:
            raise ValueError("a RAW camera folder needs the generator's truth folder")
        levels, exposure = _truth_response(Path(truth))
        white = float(exposure[255].mean())

    def shoot(path: Path, exposure_s: float, radiance: np.ndarray | None = None,
              folder: Path = dcim) -> None:
        nonlocal when, n
        n += 1
        folder.mkdir(parents=True, exist_ok=True)
        if raw is not None:
            if radiance is None:  # a board photo: its exposure from its levels
                img = read_image(path).astype(float)
                img = img / 257.0 if img.max() > 255 else img
                radiance = np.stack([np.interp(img[..., c], levels, exposure[:, c])
                                     for c in range(3)], -1) / exposure_s
            write_dng(folder / f"IMG_{n:04d}.DNG", expose_raw(radiance * exposure_s / white,
                                                            raw, rng), raw, exposure_s, when)
            return
        img = read_image(path)
        if img.dtype != np.uint8:
            img = (img >> 8).astype(np.uint8)
        write_jpeg_exif(folder / f"IMG_{n:04d}.JPG", img, exposure_s, when)

    for p in cap.calibration_images:
        shoot(p, 1 / 60)
        when += timedelta(seconds=MOVE_S)
    for v in cap.views:
        rad = _view_radiance(cap.root, Path(truth), v.id) if raw is not None else None
        for k in rng.permutation(len(v.exposures)):
            shoot(v.exposures[k].path, v.exposures[k].exposure_s, rad)
            when += timedelta(seconds=FRAME_S)
        when += timedelta(seconds=MOVE_S)
    # the white card's views and the chart's bracket, each in its own folder, as a lab
    # keeps them apart from the surface's (the card shows the surface's markers)
    extra = {"flatfield": out / "FLATFIELD", "chart": out / "CHART"}
    for v in cap.radiometry_views:
        folder = extra["chart"] if v is cap.chart else extra["flatfield"]
        for k in rng.permutation(len(v.exposures)):
            shoot(v.exposures[k].path, v.exposures[k].exposure_s, folder=folder)
            when += timedelta(seconds=FRAME_S)
        when += timedelta(seconds=MOVE_S)
    doc = cap.raw
    layout = out / "markers.yaml"
    layout.write_text(yaml.safe_dump(
        {"surface": {k: v for k, v in doc["surface"].items() if k != "id"},
         "markers": doc["markers"]}, sort_keys=False))
    board = None
    if doc.get("calibration"):
        board = out / "board.yaml"
        board.write_text(yaml.safe_dump({"calibration": {
            k: v for k, v in doc["calibration"].items() if k not in ("images", "intrinsics")}},
            sort_keys=False))
    return {"photos": dcim, "layout": layout, "board": board, "views": len(cap.views),
            "board_photos": len(cap.calibration_images),
            **{k: p for k, p in extra.items() if p.is_dir()}}
