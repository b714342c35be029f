"""Camera RAW input (issue 45 item 3): DNGs of a simulated sensor, read through LibRaw,
merged with a noise model measured from the bracket itself, imported from a camera
folder with no YAML typed."""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np
import pytest

from parammap.errors import InputError
from parammap.stages.hdr import fit_sensor_noise, merge_linear
from parammap.stores.images import RAW_FULL, image_size, photo_meta, read_image
from parammap.synth.raw import Sensor, expose_raw, write_dng

T0 = datetime(2026, 11, 20, 9, 0, 0)


def _scene(H: int = 180, W: int = 240) -> np.ndarray:
    """Smooth linear radiance over 5 stops, three tints."""
    y, x = np.mgrid[0:H, 0:W]
    X = np.exp(1.7 * np.sin(x / 23.0) * np.cos(y / 31.0))[..., None] * [1.0, 0.8, 0.5]
    return X / X.max()


def _bracket(tmp_path, sensor: Sensor, times, X, seed=0):
    rng = np.random.default_rng(seed)
    files = []
    for k, t in enumerate(times):
        f = tmp_path / f"IMG_{k:04d}.DNG"
        write_dng(f, expose_raw(X * t, sensor, rng), sensor, float(t),
                  T0 + timedelta(seconds=k), iso=400, f_number=5.6)
        files.append(f)
    return files


def _error(rad: np.ndarray, X: np.ndarray) -> tuple[float, float]:
    inner = (slice(3, -3), slice(3, -3))  # the demosaic's reflected border
    e = np.abs(rad[inner] / RAW_FULL / X[inner] - 1)
    return float(np.median(e)), float(np.percentile(e, 95))


@pytest.mark.parametrize("pattern, stops, read_e", [("RGGB", 1, 5.0), ("GBRG", 2, 5.0),
                                                    ("BGGR", 2, 40.0), ("GRBG", 1, 40.0)])
def test_raw_merge_is_within_a_tenth_of_the_oracle(tmp_path, pattern, stops, read_e):
    """The merge of a DNG bracket, weighted by the noise it measures in the bracket
    itself, is within 1.1x of the oracle merge (same photos, the sensor's true noise
    model) in median and 95th percentile; with a read noise that matters, inverse-
    variance weights beat shot-noise weights (sum v / sum t) in the shadows."""
    sensor = Sensor(pattern=pattern, read_noise_e=read_e)
    X = _scene()
    times = 3.0 * 2.0 ** (-stops * np.arange(4))  # the longest saturates the top stop
    files = _bracket(tmp_path, sensor, times, X)
    m = photo_meta(files[1])
    assert m.exposure_s == pytest.approx(times[1], rel=1e-4) and m.iso == 400
    assert m.f_number == pytest.approx(5.6) and m.camera == "Parammap SynthRaw"
    assert m.size == (X.shape[1], X.shape[0]) and image_size(files[0]) == X.shape[:2]
    stack = np.stack([read_image(f) for f in files])
    assert stack.dtype == np.uint16 and stack.shape == (4, *X.shape)
    ours = merge_linear(stack, times, RAW_FULL)
    oracle = merge_linear(stack, times, RAW_FULL, noise_model=sensor.noise_model)
    e_ours, e_oracle = _error(ours[0], X), _error(oracle[0], X)
    assert e_ours[0] <= 1.1 * e_oracle[0] and e_ours[1] <= 1.1 * e_oracle[1], (e_ours, e_oracle)
    assert e_ours[0] < 0.02
    # the bright stop saturates the longest exposure only: nothing saturated in all
    assert not ours[1].any()
    if read_e > 20:
        shot = merge_linear(stack, times, RAW_FULL, noise_model=(1 / RAW_FULL, 1e-12))
        dark = X.mean(-1) < np.percentile(X.mean(-1), 10)
        e_dark = np.median(np.abs(ours[0] / RAW_FULL / X - 1)[dark])
        e_shot = np.median(np.abs(shot[0] / RAW_FULL / X - 1)[dark])
        assert e_dark < 0.97 * e_shot, (e_dark, e_shot)
    # the recorded noise follows the measured model: over pixels alike, the relative sd
    # of the merge against the truth is the noise it records (within 35 %)
    rel = (ours[0] / RAW_FULL / X - 1)[3:-3, 3:-3].mean(-1)
    rec = ours[3][3:-3, 3:-3]
    assert 0.65 < np.std(rel) / np.sqrt(np.mean(rec ** 2)) < 1.35


def test_sensor_noise_is_measured_from_the_bracket():
    """Without demosaicing (one colour), the fitted shot and read noise are the
    sensor's: a within 15 %, b within a factor 2 (read noise is small beside shot)."""
    sensor = Sensor(read_noise_e=30.0)
    rng = np.random.default_rng(3)
    X = _scene(256, 256)
    times = 2.0 ** -np.arange(4)
    v = np.stack([np.repeat(((expose_raw(np.repeat(X[..., :1] * t, 3, -1), sensor, rng)
                              .astype(float) - sensor.black) / (sensor.white - sensor.black)
                             )[..., None], 3, -1) for t in times])
    stack = np.round(np.clip(v, 0, 1) * RAW_FULL).astype(np.uint16)
    a, b = fit_sensor_noise(stack, times, RAW_FULL)
    ta, tb = sensor.noise_model
    assert abs(a / ta - 1) < 0.15 and 0.5 < b / tb < 2, (a, ta, b, tb)


def test_a_saturated_photosite_saturates_its_pixels(tmp_path):
    sensor = Sensor()
    mosaic = np.full((40, 60), 3000, np.uint16)
    mosaic[10, 15] = sensor.white
    write_dng(tmp_path / "a.dng", mosaic, sensor, 0.01, T0)
    img = read_image(tmp_path / "a.dng")
    full = img == RAW_FULL
    assert full[9:12, 14:17].all() and full.sum() == 27  # its 3 x 3 pixels, every channel
    lin = (3000 - sensor.black) / (sensor.white - sensor.black)
    np.testing.assert_allclose(img[0, 0] / RAW_FULL, lin, atol=1 / RAW_FULL)


def test_raw_folder_faults_name_the_file(tmp_path):
    """A corrupt RAW, and RAWs mixed with JPEGs of other shots, fail in one line naming
    a file; a JPEG the camera wrote beside each RAW is set aside for the RAW."""
    from parammap.stages.importer import _files
    from parammap.synth.camera_folder import write_jpeg_exif

    sensor = Sensor()
    X = _scene(40, 60)
    files = _bracket(tmp_path, sensor, [0.5, 0.25], X)
    for f in files:  # RAW + JPEG of each shot
        write_jpeg_exif(f.with_suffix(".JPG"), np.full((40, 60, 3), 99, np.uint8), 0.5, T0)
    assert _files(tmp_path) == files
    write_jpeg_exif(tmp_path / "OTHER.JPG", np.full((40, 60, 3), 99, np.uint8), 0.5, T0)
    with pytest.raises(InputError, match="mixed RAW and other photos.*OTHER.JPG"):
        _files(tmp_path)
    bad = tmp_path / "BAD.DNG"
    bad.write_bytes(files[0].read_bytes()[:300])
    with pytest.raises(InputError, match="BAD.DNG"):
        image_size(bad)
    # through import: one line naming the file, nothing written
    from parammap.stages.importer import run_import

    folder = tmp_path / "folder"
    folder.mkdir()
    for f in [*files, bad]:
        (folder / f.name).write_bytes(f.read_bytes())
    layout = tmp_path / "markers.yaml"
    layout.write_text("surface: {width_mm: 100, height_mm: 80}\n"
                      "markers: {dictionary: DICT_4X4_50, items: []}\n")
    with pytest.raises(InputError, match="BAD.DNG"):
        run_import(folder, tmp_path / "surface", layout=layout)
    assert not (tmp_path / "surface").exists()


def test_a_raw_camera_folder_imports_to_the_generators_poses(tiny_capture, tiny_processed,
                                                             tmp_path):
    """The tiny capture as a camera folder of DNGs (``parammap synth --camera-folder
    --raw``; a sensor whose red and blue photosites collect less of the white light than
    its green ones) -> import (a linear capture) -> HDR, poses: the merged frames within
    2 % of the generator's radiance at the median, channel by channel; every view the
    generator's capture keeps is kept, its pose within 2x of the generator's 8-bit
    photos' at the median. Measured 0.016 mm / 0.0034 deg against 0.011 / 0.0025: the
    poses are measured on the white-balanced photosites (``marker_image``). On the
    demosaiced frame they were 0.096 / 0.022: at 320 x 240 a Bayer mosaic leaves the
    markers' edges a few pixels of red and blue samples."""
    import yaml

    from parammap.stages.importer import run_import
    from parammap.stores.hdr import read_hdr
    from parammap.synth import testsupport as ev
    from parammap.synth.camera_folder import _view_radiance, write_camera_folder

    from .conftest import poses_with_true_intrinsics

    cap_dir, truth = tiny_capture
    w = write_camera_folder(cap_dir, tmp_path / "folder", truth=truth,
                            raw=Sensor(pattern="GRBG", gains=(0.45, 1.0, 0.7)))
    photos = sorted(w["photos"].iterdir())
    assert all(p.suffix == ".DNG" for p in photos)
    # the tiny preset's 320 x 240 board photos are too small to calibrate (the poses
    # use the true intrinsics), and behind a Bayer filter too small to classify
    for p in photos[:w["board_photos"]]:
        p.unlink()
    imported = tmp_path / "surface"
    run_import(w["photos"], imported, layout=w["layout"], holdout=0)
    doc = yaml.safe_load((imported / "capture.yaml").read_text())
    assert doc["camera"]["response"] == "linear"
    from parammap.stores.capture import load_capture

    views = load_capture(cap_dir).views
    for v, want in zip(doc["views"], views, strict=True):
        v["holdout"] = want.holdout
    (imported / "capture.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    out = tmp_path / "proc"
    poses_with_true_intrinsics(imported, truth, out)
    # the workflow's response file exists for a linear capture too, and says so
    from parammap.cli import main
    from parammap.stores.hdr import is_linear_response

    assert is_linear_response(out / "camera" / "response.csv")
    assert main(["figures", "response", str(imported), "--out", str(out), "--figures",
                 str(tmp_path / "fig")]) == 0
    assert (tmp_path / "fig" / "response.png").is_file()
    rad = read_hdr(out / "hdr" / "v000.exr")[0]
    true = _view_radiance(cap_dir, truth, views[0].id)
    ok = true.mean(-1) > np.percentile(true.mean(-1), 20)
    scale = np.median(true[ok] / rad[ok], axis=0)  # each filter's own gain
    assert np.median(np.abs(rad[ok] * scale / true[ok] - 1)) < 0.02
    _, _, proc = tiny_processed
    ours, theirs = ev.pose_errors(truth, out), ev.pose_errors(truth, proc)
    kept = [k for k in theirs if theirs[k]["kept"]]
    assert all(ours[k]["kept"] for k in kept)
    for key in ("centre_mm", "rotation_deg"):
        a, b = (np.median([e[k][key] for k in kept]) for e in (ours, theirs))
        assert a <= 2 * b, (key, a, b)


def test_a_raw_bracket_keeps_its_white_balanced_photosites(tmp_path):
    """The HDR frame of a RAW bracket keeps its merged photosites and their filters
    (a Bayer and a 6 x 6 pattern round trip through the frame), and the filters' gains
    are read from a grey marker's white: divided by them, every photosite samples the
    grey scene within its noise."""
    from parammap.stages.hdr import merge_mosaic
    from parammap.stores.hdr import read_hdr_mosaic, write_hdr
    from parammap.vision.markers import neutral_gains

    sensor = Sensor(pattern="BGGR", gains=(0.5, 1.0, 0.8))
    H, W = 120, 160
    X = np.full((H, W, 3), 0.8)
    X[40:80, 60:100] = 0.05  # a black marker on white paper
    files = _bracket(tmp_path, sensor, [1.0, 0.5, 0.25], X)
    from parammap.stores.images import read_raw_mosaic

    mosaic, colors = merge_mosaic([read_raw_mosaic(f) for f in files],
                                  np.array([1.0, 0.5, 0.25]))
    np.testing.assert_array_equal(colors, sensor.colors(H, W))
    z = np.zeros((H, W))
    write_hdr(tmp_path / "f.exr", np.zeros((H, W, 3)), z > 0, z > 0, z, "v",
              mosaic=(mosaic, colors))
    got, got_colors = read_hdr_mosaic(tmp_path / "f.exr")
    np.testing.assert_array_equal(got_colors, colors)
    np.testing.assert_allclose(got, mosaic)
    quad = np.array([[[59.5, 39.5], [99.5, 39.5], [99.5, 79.5], [59.5, 79.5]]])  # 8 cells
    gains = neutral_gains(mosaic, colors, quad, 8)
    np.testing.assert_allclose(gains, np.array(sensor.gains) / sensor.gains[1], rtol=0.01)
    grey = mosaic / gains[colors] / RAW_FULL
    assert np.median(np.abs(grey[5:35, 5:-5] / 0.8 - 1)) < 0.01
    assert np.median(np.abs(grey[45:75, 65:95] / 0.05 - 1)) < 0.03
    xtrans = np.random.default_rng(1).integers(0, 3, (6, 6)).astype(np.uint8)
    tiled = np.tile(xtrans, (H // 6, W // 6 + 1))[:, :W]
    write_hdr(tmp_path / "x.exr", np.zeros((H, W, 3)), z > 0, z > 0, z, "v",
              mosaic=(mosaic, tiled))
    np.testing.assert_array_equal(read_hdr_mosaic(tmp_path / "x.exr")[1], tiled)
    write_hdr(tmp_path / "n.exr", np.zeros((H, W, 3)), z > 0, z > 0, z, "v")
    assert read_hdr_mosaic(tmp_path / "n.exr") is None
