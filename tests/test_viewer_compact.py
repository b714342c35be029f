"""The viewer's compact payload (issue 17): 8-bit planes, their size and the error they
add to renders, without a browser (the page's decoder is checked against
:func:`decode_layers` in ``test_viewer.py``)."""

from __future__ import annotations

import numpy as np
import yaml

from parammap.cli import main
from parammap.conventions import mh_dir, mh_ks
from parammap.stores.camera import load_intrinsics
from parammap.stores.params import read_param_map
from parammap.viewer import payload_script, read_payload_script
from parammap.viewer.compact import (
    SH_ERROR_LEVELS,
    _filter,
    _unfilter,
    decode_layers,
    encode_layers,
    layers_to_params,
)
from parammap.viewer.layers import viewer_layers


def test_payload_script_carries_15_bits_per_code_unit_and_round_trips():
    """Any payload survives the UTF-16 script (lengths around the 15-bit groups
    included); the file is a BOM, UTF-16LE text and about 16 bits per 15 of payload
    (base64: 32 per 24); no code unit is a quote, backslash, line break or surrogate."""
    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 14, 15, 16, 29, 30, 31, 4097):
        b = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        s = payload_script('(window.P = window.P || {})["m-1"]', b)
        assert s[:2] == b"\xff\xfe"
        assert read_payload_script(s) == b
    big = rng.integers(0, 256, 30000, dtype=np.uint8).tobytes()
    s = payload_script("x", big)
    assert len(s) <= 30000 * 16 / 15 + 64
    body = s.decode("utf-16")
    body = body[body.index('"') + 1:body.rindex('"')]
    units = np.array([ord(c) for c in body])
    assert not np.isin(units, [0x22, 0x5C, 0x0A, 0x0D, 0x2028, 0x2029]).any()
    assert not ((units >= 0xD800) & (units <= 0xDFFF)).any()


def test_plane_filters_invert_and_shrink_smooth_planes():
    """Every filter inverts exactly (mod 256, at the plane's edges too); a smooth ramp
    with texel noise deflates smaller under the filter encode_layers picks, and pure
    noise stays unfiltered."""
    import zlib

    from parammap.viewer.compact import _best_filter

    rng = np.random.default_rng(1)
    q = rng.integers(0, 256, (37, 53)).astype(np.uint8)
    for code in range(4):
        np.testing.assert_array_equal(_unfilter(_filter(q, code), code), q)
    assert _best_filter(q) == 0
    r, c = np.mgrid[0:64, 0:64]
    smooth = ((r * 2 + c * 3 + rng.integers(0, 2, r.shape)) % 256).astype(np.uint8)
    code = _best_filter(smooth)
    assert code != 0
    assert len(zlib.compress(_filter(smooth, code).tobytes(), 9)) \
        < 0.5 * len(zlib.compress(smooth.tobytes(), 9))


def _round_trip(pm):
    layers, info = viewer_layers(pm)
    entry, payloads = encode_layers(layers, info)
    back = decode_layers(entry, payloads, layers.shape[:3])
    return layers, info, back, b"".join(payloads)


def test_mh_planes_round_trip_within_their_quantisation(tiny_work):
    """MH-2 of the tiny capture: Kd and Ks within half a square-root level, m within half
    a log level, lobe directions within 0.75 deg (half a level of two hemi-octahedral
    planes); the layer layout survives
    (``layers_to_params`` inverts ``viewer_layers``); at most 16 bytes per texel on this
    small, noisy map (5x less than float32; 9-11 on the demo and pbr-bench maps)."""
    cap, _, out = tiny_work
    assert main(["fit-mh", str(cap), "--out", str(out), "--lobes", "2", "--workers", "1"]) == 0
    assert main(["export", str(cap), "--out", str(out), "--model", "mh-2"]) == 0
    pm = read_param_map(out / "params" / "mh-2.exr")
    layers, info, back, payload = _round_trip(pm)
    np.testing.assert_array_equal(layers_to_params(layers, info), np.nan_to_num(pm.params))
    p, q = layers_to_params(layers, info), layers_to_params(back, info)
    for sl in (slice(0, 3), mh_ks(0), mh_ks(1)):
        r = np.sqrt(np.maximum(p[..., sl], 0))
        half = (r.max((0, 1)) - r.min((0, 1))) / 255 / 2 + 1e-7
        assert (np.abs(np.sqrt(q[..., sl]) - r) <= half).all()
    lm = np.log(p[..., 3])
    assert (np.abs(np.log(q[..., 3]) - lm) <= (lm.max() - lm.min()) / 510 + 1e-6).all()
    for k in (0, 1):
        cos = np.clip((p[..., mh_dir(k)] * q[..., mh_dir(k)]).sum(-1), -1, 1)
        ang = np.degrees(np.arccos(cos))
        assert ang.max() < 0.75 and np.median(ang) < 0.3, (ang.max(), np.median(ang))
    T, S = pm.shape
    assert len(payload) * 16 / 15 / (T * S) <= 16


def test_viewer_stage_measures_payload_error_below_half_a_level(tiny_work, tmp_path):
    """The viewer stage writes ``manifest.json`` with every model's payload size and the
    error its quantisation adds to renders of the held-out views at the report's gamma:
    below 0.5 mean 8-bit levels for MH, SH (PCA) and diffuse; SH near the budget its
    steps were chosen for."""
    import json

    cap, _, out = tiny_work
    assert main(["fit-mh", str(cap), "--out", str(out), "--lobes", "2", "--workers", "1"]) == 0
    assert main(["fit-sh", str(cap), "--out", str(out), "--model", "sh-rlsop-36",
                 "--workers", "1"]) == 0
    models = ["mh-2", "sh-rlsop-36", "diffuse"]
    assert main(["export", str(cap), "--out", str(out), *[x for m in models
                                                         for x in ("--model", m)]]) == 0
    vdir = tmp_path / "viewer"
    assert main(["viewer", str(cap), "--out", str(out), "--figures", str(vdir),
                 *[x for m in models for x in ("--model", m)]]) == 0
    man = json.loads((vdir / "manifest.json").read_text())
    got = {m["name"]: m for m in man["models"]}
    assert set(got) == set(models)
    for name, m in got.items():
        assert 0 <= m["quantisation_error_8bit"] < 0.5, (name, m["quantisation_error_8bit"])
        assert sum((vdir / f).stat().st_size for f in m["files"]) == m["bytes"]
    assert got["mh-2"]["bytes_per_texel"] <= 16
    sh = got["sh-rlsop-36"]
    assert sh["compact"]["pca"]["components"] >= 1
    # the SH payload spends the error budget it was given (its estimate of the render
    # error is neither blind nor far too cautious)
    assert 0.5 * SH_ERROR_LEVELS < sh["quantisation_error_8bit"] < 0.5, sh
    # the float maps would have been 16 bytes per texel and layer
    assert got["sh-rlsop-36"]["bytes_per_texel"] < 0.5 * 16 * got["sh-rlsop-36"]["nlayers"]
    intr = load_intrinsics(out / "camera" / "intrinsics.yaml")
    assert yaml.safe_load((out / "camera" / "poses.yaml").read_text())["views"]
    assert intr.image_size


def test_sh_map_in_tiles_decodes_as_in_one_payload():
    """An SH-16 map encoded from its parameters (:func:`encode_map`) in tiles of 16
    texels decodes as in one payload (PCA, steps and int16 basis are the map's), every
    tile recorded once; the decoding stays within the steps' error of the float map
    (the int16 basis adds nothing visible)."""
    from parammap.stores.params import ParamMap
    from parammap.viewer.compact import encode_map, tile_grid

    rng = np.random.default_rng(3)
    T, S, nc = 40, 50, 16
    r, c = np.mgrid[0:T, 0:S] / 10.0
    a, b, d = rng.normal(size=(3, 3 * nc)) * np.r_[1.0, 0.3 * np.ones(3 * nc - 1)]
    params = (a + b * np.sin(r)[..., None] + d * np.cos(c)[..., None]
              + 0.01 * rng.normal(size=(T, S, 3 * nc))).astype(np.float32)
    pm = ParamMap("sh", params, 100.0, 80.0)
    layers, info = viewer_layers(pm)
    one, p1 = encode_map(pm, 2.0)
    tiled, pt = encode_map(pm, 2.0, tile=16)
    assert len(p1) == 1 and len(pt) == len(tile_grid(T, S, 16)) == 12
    assert [(t["r"], t["c"], t["T"], t["S"]) for t in tiled["tiles"]] == tile_grid(T, S, 16)
    x1 = decode_layers(one, p1, layers.shape[:3])
    xt = decode_layers(tiled, pt, layers.shape[:3])
    np.testing.assert_allclose(xt, x1, atol=1e-5)
    # each coefficient within the summed half steps of the weights that build it
    half = sum(0.5 * p["step"] for p in one["planes"])
    assert np.abs(x1[..., :3] - layers[..., :3]).max() < half


def test_decoding_every_nth_texel_matches_the_full_decoding():
    """``decode_layers(..., every=s)`` (how a map above ERROR_TEXELS is judged) keeps
    exactly the full decoding's every s-th row and column, across tile edges that are
    not multiples of s."""
    from parammap.stores.params import ParamMap
    from parammap.viewer.compact import encode_map

    rng = np.random.default_rng(4)
    pm = ParamMap("diffuse", rng.uniform(0, 1, (37, 45, 3)).astype(np.float32), 90.0, 74.0)
    entry, payloads = encode_map(pm, 1.0, tile=10)
    full = decode_layers(entry, payloads, (1, 37, 45))
    for s in (2, 3, 7):
        np.testing.assert_array_equal(decode_layers(entry, payloads, (1, 37, 45), s),
                                      full[:, ::s, ::s])


def test_decoding_in_row_blocks_matches_whole_tiles(monkeypatch):
    """``decode_layers`` decodes a tile a block of rows at a time (its memory bounded
    for a lab's SH tiles): with blocks of a few rows, every texel as with whole tiles,
    for an SH map (PCA weights) and an MH map (planes and derived directions), also
    at every s-th texel."""
    from parammap.stores.params import ParamMap
    from parammap.viewer import compact

    rng = np.random.default_rng(5)
    T, S = 37, 45
    sh = ParamMap("sh", rng.normal(0, 1, (T, S, 27)).astype(np.float32), 90.0, 74.0)
    mh = rng.uniform(0.1, 1, (T, S, 10)).astype(np.float32)
    d = rng.normal(0, 1, (T, S, 3))
    d[..., 2] = np.abs(d[..., 2]) + 0.5
    mh[..., 7:10] = d / np.linalg.norm(d, axis=-1, keepdims=True)
    for pm in (sh, ParamMap("mh", mh, 90.0, 74.0)):
        entry, payloads = compact.encode_map(pm, 1.0, tile=16)
        L = compact.layer_info(pm)[1]
        whole = [compact.decode_layers(entry, payloads, (L, T, S), s) for s in (1, 3)]
        with monkeypatch.context() as mp:
            mp.setattr(compact, "DECODE_BLOCK_VALUES", 3 * 16 * L * 4)  # 3 rows a block
            for s, want in zip((1, 3), whole, strict=True):
                np.testing.assert_array_equal(
                    compact.decode_layers(entry, payloads, (L, T, S), s), want)


def test_quantisation_error_camera_is_scaled_with_pixel_centres_kept():
    """A camera above ERROR_PIXELS renders at a scale that fits, its pixel centres
    where the full camera's fall: a point seen at pixel u is seen at (u + 0.5) / s -
    0.5 (s per axis: the image's edges kept exactly)."""
    import cv2

    from parammap.geometry import Intrinsics
    from parammap.viewer.compact import _scaled_camera

    K = np.array([[3000.0, 0, 2011.3], [0, 3010.0, 1497.8], [0, 0, 1]])
    intr = Intrinsics(K, np.array([0.05, -0.1, 0.001, 0.002, 0.0]), (4000, 3000))
    small = _scaled_camera(intr, 1 << 20)
    W, H = small.image_size
    s = np.array([4000 / W, 3000 / H])
    assert W * H <= 1 << 20 and abs(s[0] - s[1]) < 0.01
    assert _scaled_camera(small, 1 << 20) is small
    X = np.array([[10.0, -20.0, 300.0], [-50.0, 30.0, 250.0]])
    uv = [cv2.projectPoints(X, np.zeros(3), np.zeros(3), c.K, c.dist)[0].reshape(-1, 2)
          for c in (intr, small)]
    np.testing.assert_allclose(uv[1], (uv[0] + 0.5) / s - 0.5, atol=1e-9)


def test_sh_map_stores_the_level_the_page_shows():
    """An SH map whose float layers pass the page's budget also carries the page's
    reduction (:func:`page_reduction`), each block's mean weights quantised with the
    map's steps: its decoding is the block average of the full decoding to within
    those steps, and far closer than the map's own quantisation allows."""
    from parammap.stores.params import ParamMap
    from parammap.viewer.compact import encode_map, page_reduction

    rng = np.random.default_rng(5)
    T, S, nc = 40, 50, 16
    r, c = np.mgrid[0:T, 0:S] / 10.0
    a, b, d = rng.normal(size=(3, 3 * nc))
    params = (a + b * np.sin(r)[..., None] + d * np.cos(c)[..., None]
              + 0.01 * rng.normal(size=(T, S, 3 * nc))).astype(np.float32)
    pm = ParamMap("sh", params, 100.0, 80.0)
    assert "level" not in encode_map(pm, 2.0, tile=16)[0]  # fits the default budget
    f = page_reduction(T, S, nc, 0.1)
    entry, payloads = encode_map(pm, 2.0, tile=16, budget_mb=0.1)
    lvl = entry["level"]
    assert (lvl["f"], lvl["T"], lvl["S"]) == (f, T // f, S // f) and f > 1
    assert len(payloads) == len(entry["tiles"]) + len(lvl["tiles"])
    full = decode_layers(entry, payloads, (nc, T, S))
    want = full[:, :T // f * f, :S // f * f].reshape(nc, T // f, f, S // f, f, 4).mean((2, 4))
    got = decode_layers(entry, payloads, (nc, T, S), level=True)
    half = sum(0.5 * p["step"] for p in entry["planes"])
    err = np.abs(got - want)[..., :3]
    assert err.max() < half and err.mean() < 0.1 * half
