"""parammap import (issue 45 item 2): a folder of camera files (JPEG with EXIF, no YAML
typed) becomes a capture; bad folders fail in one line naming the file, writing
nothing."""

from __future__ import annotations

import shutil
from datetime import datetime, timedelta
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image, TiffImagePlugin

from parammap.cli import main
from parammap.errors import InputError
from parammap.stages.importer import brackets_of, run_import
from parammap.stores.capture import load_capture
from parammap.stores.images import photo_meta, read_image

T0 = datetime(2026, 11, 20, 9, 0, 0)


def _jpeg(path: Path, rgb: np.ndarray, t_s: float | None, when: datetime, iso: int = 100,
          size: tuple[int, int] | None = None) -> None:
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "Parammap", "Test Camera"
    ifd = exif.get_ifd(0x8769)
    if t_s is not None:
        ifd[0x829A] = TiffImagePlugin.IFDRational(Fraction(t_s).limit_denominator(100000))
    ifd[0x829D] = TiffImagePlugin.IFDRational(8, 1)
    ifd[0x8827] = iso
    ifd[0x920A] = TiffImagePlugin.IFDRational(35, 1)
    ifd[0x9003] = when.strftime("%Y:%m:%d %H:%M:%S")
    ifd[0x9291] = f"{when.microsecond // 10000:02d}"
    im = Image.fromarray(rgb)
    if size is not None:
        im = im.resize(size)
    im.save(path, quality=95, exif=exif.tobytes())


def _camera_folder(cap_dir: Path, out: Path, rng: np.random.Generator) -> tuple[list, int]:
    """The capture's photos as a camera would leave them: JPEGs named in the order they
    were taken, exposure times and times in EXIF; board photos first, then each view's
    bracket in a shuffled order, views 30 s apart, frames 0.4 s apart."""
    cap = load_capture(cap_dir)
    out.mkdir()
    when, n = T0, 0
    for p in cap.calibration_images:
        n += 1
        _jpeg(out / f"IMG_{n:04d}.JPG", read_image(p), 1 / 60, when)
        when += timedelta(seconds=30)
    for v in cap.views:
        for k in rng.permutation(len(v.exposures)):
            e = v.exposures[k]
            n += 1
            _jpeg(out / f"IMG_{n:04d}.JPG", read_image(e.path), e.exposure_s, when)
            when += timedelta(seconds=0.4)
        when += timedelta(seconds=30)
    return cap.views, len(cap.calibration_images)


def _layouts(cap_dir: Path, tmp: Path) -> tuple[Path, Path]:
    doc = yaml.safe_load((cap_dir / "capture.yaml").read_text())
    lay, board = tmp / "markers.yaml", tmp / "board.yaml"
    lay.write_text(yaml.safe_dump({"surface": {k: v for k, v in doc["surface"].items()
                                               if k != "id"}, "markers": doc["markers"]}))
    calib = {k: v for k, v in doc["calibration"].items() if k not in ("images", "intrinsics")}
    board.write_text(yaml.safe_dump({"calibration": calib}))
    return lay, board


@pytest.fixture(scope="module")
def camera_folder(tiny_capture, tmp_path_factory):
    root = tmp_path_factory.mktemp("camera")
    views, boards = _camera_folder(tiny_capture[0], root / "DCIM",
                                   np.random.default_rng(0))
    lay, board = _layouts(tiny_capture[0], root)
    return root / "DCIM", lay, board, views, boards


def test_import_builds_the_capture_the_generator_described(camera_folder, tmp_path):
    photos, lay, board, views, boards = camera_folder
    out = tmp_path / "surface"
    assert main(["import", str(photos), "--layout", str(lay), "--board", str(board),
                 "--holdout", "2", "--out", str(out)]) == 0
    cap = load_capture(out, check_images=True)
    assert len(cap.views) == len(views) and len(cap.calibration_images) == boards
    assert sum(v.holdout for v in cap.views) == 2
    for got, want in zip(cap.views, views, strict=True):
        t_got = sorted(e.exposure_s for e in got.exposures)
        t_want = sorted(e.exposure_s for e in want.exposures)
        np.testing.assert_allclose(t_got, t_want, rtol=1e-4)
        # longest first, and each photo is that exposure's (JPEG: within its noise)
        assert [e.exposure_s for e in got.exposures] == sorted(t_got, reverse=True)
        for e in got.exposures:
            src = min(want.exposures, key=lambda w: abs(w.exposure_s - e.exposure_s))
            diff = np.abs(read_image(e.path).astype(int) - read_image(src.path).astype(int))
            assert diff.mean() < 2.0
    assert cap.surface_id == "surface"
    # the same seed draws the same held-out views
    again = run_import(photos, tmp_path / "again", layout=lay, board=board, holdout=2)
    assert [v["holdout"] for v in again["capture"]["views"]] == [v.holdout for v in cap.views]


def test_brackets_split_on_a_repeated_time_and_on_a_pause(tmp_path):
    img = np.full((40, 60, 3), 120, np.uint8)
    shots = [(0.0, 1 / 10), (0.5, 1 / 40), (1.0, 1 / 160),  # a bracket
             (1.5, 1 / 10), (2.0, 1 / 40),  # the next, its first time repeated: no pause
             (40.0, 1 / 160)]  # after a pause: a third, though its time is new
    for k, (dt, t) in enumerate(shots):
        _jpeg(tmp_path / f"a{k}.jpg", img, t, T0 + timedelta(seconds=dt))
    groups = brackets_of([photo_meta(p) for p in sorted(tmp_path.glob("*.jpg"))])
    assert [[m.path.name for m in g] for g in groups] == [
        ["a0.jpg", "a1.jpg", "a2.jpg"], ["a3.jpg", "a4.jpg"], ["a5.jpg"]]


@pytest.mark.parametrize("fault, message", [
    ("size", "mixed image sizes"),
    ("iso", "the ISO changes"),
    ("time", "no EXIF ExposureTime in IMG_0"),
    ("corrupt", "IMG_9999.JPG: not a readable image"),
])
def test_a_bad_camera_folder_fails_naming_the_file_and_writes_nothing(
        camera_folder, tmp_path, fault, message):
    photos, lay, board, views, boards = camera_folder
    bad = tmp_path / "DCIM"
    shutil.copytree(photos, bad)
    first_view = sorted(bad.glob("*.JPG"))[boards]  # the first view's first frame
    rgb = read_image(first_view)
    when = datetime.fromtimestamp(photo_meta(first_view).taken_s)
    if fault == "size":
        _jpeg(first_view, rgb, photo_meta(first_view).exposure_s, when,
              size=(rgb.shape[1] // 2, rgb.shape[0] // 2))
    elif fault == "iso":
        _jpeg(first_view, rgb, photo_meta(first_view).exposure_s, when, iso=400)
    elif fault == "time":
        _jpeg(first_view, rgb, None, when)
    else:
        (bad / "IMG_9999.JPG").write_bytes(b"\xff\xd8 not really a photo")
    out = tmp_path / "surface"
    with pytest.raises(InputError, match=message):
        run_import(bad, out, layout=lay, board=board)
    assert not out.exists() and not list(tmp_path.glob(".surface*"))
