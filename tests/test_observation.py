"""Observation map (issue 4): accuracy against the generator's truth, store layout,
atomic writes, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
import zarr

from parammap.stages.observation import COMPLETE_ATTR, build_observation_map, marker_texel_mask
from parammap.stores.capture import load_capture
from parammap.stores.observation import ObservationError, open_observation_map
from parammap.synth.generate import true_observations


@pytest.mark.parametrize("zenith_deg", [0.0, 60.0])
def test_texel_pixels_is_the_frontal_width_at_the_views_distance(zenith_deg):
    """10 mm texels 1000 mm from a camera of focal length 800 px are 8 px across,
    frontal or not: the foreshortening of an oblique view is undone."""
    from parammap.stages.observation import texel_pixels

    _, intr, R, t = _checker_photo(zenith_deg, 8, 6, 1.0, 1.0)
    assert texel_pixels(intr, R, t, 8, 6, 80.0, 60.0) == pytest.approx(8.0, rel=0.01)


def test_blend_check_follows_the_maps_resolution_not_one_views():
    """Texels 2.4 px across in this view (under the 3 px a frontal read needs), 1.2 px
    across its columns at 60 deg, in a map
    the other views resolve: with ``resolved`` the grazing view's blended reads are
    left out all the same (judged from this view alone, it would keep them), and a
    uniform surface keeps every read."""
    from parammap.stages.observation import sample_view

    S, T = 27, 20  # 2.96 mm texels, 1000 mm away: 2.4 px
    frame, intr, R, t = _checker_photo(60.0, S, T, 1.0, 3.0)  # 1.2 px across
    noise = np.full(frame.shape[:2], 0.01, np.float32)
    sat = np.zeros(frame.shape[:2], bool)
    args = (frame, sat, intr, R, t, slice(0, T), S, T, 80.0, 60.0)
    _, _, own, _ = sample_view(*args, noise=noise, max_blend=2.0)
    _, _, mapwide, _ = sample_view(*args, noise=noise, max_blend=2.0, resolved=True)
    assert own.all()
    assert (~mapwide).mean() > 0.9
    flat, intr, R, t = _checker_photo(60.0, S, T, 1.0, 1.0)
    _, _, uniform, _ = sample_view(flat, sat, intr, R, t, slice(0, T), S, T, 80.0, 60.0,
                                   noise=noise, max_blend=2.0, resolved=True)
    assert uniform.all()


def test_observations_match_truth(tiny_processed):
    _, truth, out = tiny_processed
    g = open_observation_map(out / "observation.zarr")
    T, S, N = g["valid"].shape
    assert (T, S) == (24, 24) and N == len(g.attrs["view_ids"])
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(T), np.arange(S), indexing="ij"))
    d_true, L_true = true_observations(truth, g.attrs["view_ids"], rows, cols)
    v = g["valid"][:].reshape(T * S, N)
    d = g["direction"][:].reshape(T * S, N, 3)
    L = g["radiance"][:].reshape(T * S, N, 3)
    m = yaml.safe_load((out / "metrics" / "observation.json").read_text())
    # the tiny capture's texels are resolved (over 3 px at the median view): its
    # grazing reads at material edges are left out, a few per cent
    assert m["texel_px"] > 3 and m["blend_check"]
    assert 0 < m["blended_fraction"] < 0.1
    assert v.mean() > 0.9
    ang = np.degrees(np.arccos(np.clip((d * d_true).sum(-1), -1, 1)))[v]
    assert np.median(ang) < 0.2, np.median(ang)
    np.testing.assert_allclose(np.linalg.norm(d[v], axis=-1), 1, atol=1e-5)
    ok = v[..., None] & (L_true > 1e-3)
    scale = np.median(L_true[ok] / L[ok])
    rel = np.abs(L[ok] * scale - L_true[ok]) / L_true[ok]
    assert np.median(rel) < 0.02, np.median(rel)
    # what the blend check leaves out are reads far from their texel's truth
    out_ = ~v[..., None] & np.isfinite(L) & (L_true > 1e-3) & np.isfinite(d).all(-1)[..., None]
    rel_out = np.abs(L[out_] * scale - L_true[out_]) / L_true[out_]
    assert np.median(rel_out) > 3 * np.median(rel), (np.median(rel_out), np.median(rel))


def test_store_layout_and_metrics(tiny_processed):
    cap, _, out = tiny_processed
    g = open_observation_map(out / "observation.zarr")
    N = len(g.attrs["view_ids"])
    assert g["radiance"].chunks == (8, 8, N, 3) and g["radiance"].dtype == np.float32
    assert g["valid"].chunks == (8, 8, N)
    # lean on disk: radiance codes, no directions, half-float noise
    raw = zarr.open_group(out / "observation.zarr", mode="r")
    assert raw["radiance"].dtype == np.uint16 and "direction" not in raw
    assert raw["noise"].dtype == np.float16
    held = [v.id for v in load_capture(cap).views if v.holdout]
    assert g.attrs["held_out_view_ids"] == held
    assert not set(held) & set(g.attrs["view_ids"])
    m = yaml.safe_load((out / "metrics" / "observation.json").read_text())
    assert m["texels"] == 576 and m["views"] == N and 0 < m["bytes_on_disk"]
    assert m["bytes_per_observation"] <= 10, m["bytes_per_observation"]
    assert (out / "fig" / "observation_valid_count.png").is_file()
    assert (out / "fig" / "observation_lobes.png").is_file()


def test_directions_follow_from_the_camera_centres(tiny_processed):
    """The directions a map hands out are the unit vectors from each texel centre to
    its view's camera centre, as the build stored them before (within 1e-6 rad), by
    every way of indexing the readers use."""
    from parammap.geometry import texel_centres, unit
    from parammap.stores.observation import tile_reader

    _, _, out = tiny_processed
    g = open_observation_map(out / "observation.zarr")
    T, S, N = g.shape
    C = np.asarray(g.attrs["camera_centres_mm"])
    ref = unit(C[None, None] - texel_centres(S, T, g.width_mm, g.height_mm)[:, :, None])
    d = g.direction[...]
    assert d.shape == (T, S, N, 3) and d.dtype == np.float32
    ang = np.arctan2(np.linalg.norm(np.cross(d, ref), axis=-1), (d * ref).sum(-1))
    assert ang.max() < 1e-6, ang.max()
    np.testing.assert_array_equal(g.direction[3:9, 5:7], d[3:9, 5:7])
    np.testing.assert_array_equal(g.direction[4, 6], d[4, 6])
    np.testing.assert_array_equal(g.direction[4, 2:5, :, 2], d[4, 2:5, :, 2])
    rows, cols = np.array([0, 5, 23]), np.array([1, 2])
    np.testing.assert_array_equal(g.direction.oindex[rows, cols], d[np.ix_(rows, cols)])
    np.testing.assert_array_equal(tile_reader(str(out / "observation.zarr")).direction[:8, 8:16],
                                  d[:8, 8:16])
    with pytest.raises(IndexError):
        g.direction[rows, cols]  # numpy's pointwise meaning is not what a map means


def test_radiance_codes_hold_a_tenth_of_the_noise(tiny_processed):
    """log2 codes over 48 stops: any radiance in range comes back within 2.6e-4
    (relative), below a tenth of the smallest noise the tiny capture's merge records;
    NaN and non-positive values are 'no observation'; out of range is clipped."""
    from parammap.stores.observation import LOG2_RANGE, decode_radiance, encode_radiance

    rng = np.random.default_rng(0)
    L = np.exp2(rng.uniform(*LOG2_RANGE, 200_000))
    rel = np.abs(decode_radiance(encode_radiance(L)) / L - 1)
    assert rel.max() < 2.6e-4 and 1.3e-4 < np.sqrt(np.mean(rel ** 2)) < 1.6e-4
    code = encode_radiance(np.array([np.nan, 0.0, -1.0, 2.0 ** 30]))
    assert list(code[:3]) == [0, 0, 0] and code[3] == 65535
    assert np.isnan(decode_radiance(code[:3])).all()
    g = open_observation_map(tiny_processed[2] / "observation.zarr")
    noise = g.noise[...][g.valid[...]]
    assert 10 * rel.max() < np.nanmin(noise), np.nanmin(noise)


def test_maps_written_before_the_lean_store_read_as_they_did(tmp_path):
    """A map with float32 radiance and stored directions (before the lean store) and
    one written from in-memory set-ups read the same through every reader."""
    from parammap.stores.observation import tile_observations, write_observation_arrays

    rng = np.random.default_rng(1)
    T, S, N = 4, 5, 6
    L = rng.uniform(0.1, 3, (T, S, N, 3)).astype(np.float32)
    D = rng.normal(size=(T, S, N, 3))
    D = (D / np.linalg.norm(D, axis=-1, keepdims=True)).astype(np.float32)
    D[..., 2] = np.abs(D[..., 2])
    W = rng.random((T, S, N)) > 0.2
    old = zarr.open_group(tmp_path / "old.zarr", mode="w")
    for name, a in (("radiance", L), ("direction", D), ("valid", W)):
        old.create_array(name, shape=a.shape, dtype=a.dtype, chunks=(2, 2) + a.shape[2:])[...] = a
    old.attrs.update({"S": S, "T": T, "tile": 2, "width_mm": 10.0, "height_mm": 8.0,
                      "view_ids": [f"v{n}" for n in range(N)], COMPLETE_ATTR: True})
    new = write_observation_arrays(tmp_path / "new.zarr", L, D, W, 10.0, 8.0, tile=2)
    a, b = open_observation_map(tmp_path / "old.zarr"), open_observation_map(new)
    assert a.noise is None and b.noise is not None
    np.testing.assert_array_equal(a["direction"][...], D)
    np.testing.assert_array_equal(b.direction[1:3, 2:4], D[1:3, 2:4])
    np.testing.assert_array_equal(a.radiance[...], L)
    np.testing.assert_allclose(b.radiance[...], L, rtol=2.6e-4)
    Va, La, Wa, _ = tile_observations(a, slice(0, 2), slice(2, 4))
    Vb, Lb, Wb, _ = tile_observations(b, slice(0, 2), slice(2, 4))
    np.testing.assert_array_equal(Va, Vb)
    np.testing.assert_array_equal(Wa, Wb)
    np.testing.assert_allclose(La, Lb, rtol=2.6e-4)
    with pytest.raises(ObservationError, match="camera_centres_mm"):
        write_observation_arrays(tmp_path / "none.zarr", L, None, W, 10.0, 8.0)


def test_the_transpose_in_column_blocks_writes_the_same_map(tiny_processed, tmp_path):
    """Issue 47: the build's transpose bounded in memory (blocks of tile columns) writes
    the map the whole-band transpose writes."""
    from parammap.stages.observation import band_columns

    assert band_columns(4096, 32, 300, 32, 512) == 2048  # 3 x 32 x 300 x 9 B a column
    assert band_columns(24, 8, 13, 8, 1e-3) == 8 and band_columns(24, 8, 13, 8, 1e6) == 24
    cap, _, out = tiny_processed
    work = tmp_path / "proc"
    (work / "camera").mkdir(parents=True)
    (work / "hdr").symlink_to(out / "hdr")
    for f in (out / "camera").iterdir():
        (work / "camera" / f.name).write_bytes(f.read_bytes())
    build_observation_map(load_capture(cap), work, work / "observation.zarr", 24, tile=8,
                          max_blend=2.0, max_band_mib=1e-3)
    a = open_observation_map(out / "observation.zarr")
    b = open_observation_map(work / "observation.zarr")
    for name in ("radiance", "valid", "noise"):
        np.testing.assert_array_equal(a[name][...], b[name][...])


def test_incomplete_store_is_refused(tmp_path):
    g = zarr.open_group(tmp_path / "half.zarr", mode="w")
    for name in ("radiance", "direction", "valid"):
        g.create_array(name, shape=(2, 2, 1), dtype="float32")
    with pytest.raises(ObservationError, match="incomplete"):
        open_observation_map(tmp_path / "half.zarr")
    g.attrs[COMPLETE_ATTR] = True
    open_observation_map(tmp_path / "half.zarr")
    with pytest.raises(ObservationError, match="no observation map"):
        open_observation_map(tmp_path / "missing.zarr")


def test_failed_build_leaves_previous_store_and_no_temporary(tiny_processed, tmp_path):
    cap, _, out = tiny_processed
    target = tmp_path / "observation.zarr"
    (tmp_path / "camera").mkdir()
    for f in ("intrinsics.yaml", "poses.yaml"):
        (tmp_path / "camera" / f).write_text((out / "camera" / f).read_text())
    # No HDR frames here: the build must stop naming the missing frame.
    with pytest.raises(ObservationError, match=r"hdr/.*\.exr.*missing"):
        build_observation_map(load_capture(cap), tmp_path, target, 8)
    assert not target.exists()
    assert not list(tmp_path.glob(".observation.zarr.tmp*"))


def test_marker_texels_are_masked(tiny_capture):
    cap = load_capture(tiny_capture[0])
    assert not marker_texel_mask(cap, 24, 24).any()  # generator markers lie outside
    cap.marker_corners = np.array([[[10, 40], [20, 40], [20, 30], [10, 30]]], float)
    m = marker_texel_mask(cap, 24, 24)
    tw = cap.width_mm / 24
    rows, cols = np.nonzero(m)
    assert cols.min() == int(10 // tw) and cols.max() == int(np.ceil(20 / tw)) - 1
    assert m.sum() == (rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1)


def _checker_photo(zenith_deg: float, S: int, T: int, a: float, b: float,
                   w_mm: float = 80.0, h_mm: float = 60.0):
    """A texel-aligned checkerboard of values ``a`` and ``b`` on an S x T map,
    photographed from ``zenith_deg`` (tilted about the map's y axis) with box-filtered
    pixels (the mean of 8 x 8 points over each pixel): the (300, 400, 3) frame, the
    intrinsics and the pose."""
    from parammap.geometry import Intrinsics, look_at, pixel_to_plane

    K = np.array([[800.0, 0, 199.5], [0, 800.0, 149.5], [0, 0, 1]])
    intr = Intrinsics(K, np.zeros(5), (400, 300))
    z = np.radians(zenith_deg)
    target = np.array([w_mm / 2, h_mm / 2, 0.0])
    R, t = look_at(target + 1000.0 * np.array([np.sin(z), 0.0, np.cos(z)]), target)
    u, v = np.meshgrid(np.arange(400.0), np.arange(300.0))
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    img = np.zeros((300, 400))
    for du in sub:
        for dv in sub:
            P, _ = pixel_to_plane(np.stack([u + du, v + dv], -1), K, intr.dist, R, t)
            col = np.floor(P[..., 0] * S / w_mm).astype(int)
            row = np.floor((h_mm - P[..., 1]) * T / h_mm).astype(int)
            img += np.where((row + col) % 2 == 0, a, b) / 64
    return np.repeat(img[..., None], 3, -1).astype(np.float32), intr, R, t


@pytest.mark.parametrize("zenith_deg", [0.0, 60.0])
def test_texels_read_only_their_own_surface(zenith_deg):
    """A texel-aligned checkerboard photographed with box-filtered pixels (texels of
    5-10 pixels, frontal and foreshortened to about half): every texel's observation
    is its own value, not a blend with its neighbours across the texel edges."""
    from parammap.stages.observation import sample_view

    S, T, w_mm, h_mm = 8, 6, 80.0, 60.0
    a, b = 1.0, 3.0
    frame, intr, R, t = _checker_photo(zenith_deg, S, T, a, b, w_mm, h_mm)
    rad, _, valid, _ = sample_view(frame, np.zeros((300, 400), bool), intr, R, t,
                                   slice(0, T), S, T, w_mm, h_mm)
    assert valid.all()
    rr, cc = np.meshgrid(np.arange(T), np.arange(S), indexing="ij")
    expect = np.where((rr + cc) % 2 == 0, a, b)
    np.testing.assert_allclose(rad[..., 0], expect, rtol=2e-3)


@pytest.mark.parametrize("S, T, zenith_deg, contrast, left_out", [
    (8, 6, 82.0, 3.0, True),  # 8 px texels foreshortened to about 1: a blend
    (8, 6, 82.0, 1.0, False),  # the same view of a uniform surface: no bias
    (8, 6, 82.0, 1.01, False),  # a contrast within the noise
    (8, 6, 0.0, 3.0, False),  # frontal: each texel read on its own
    (64, 48, 0.0, 3.0, False),  # texels of one pixel: every view blurs them alike
    (64, 48, 75.0, 3.0, False),  # ... a grazing one too: the photos do not resolve them
])
def test_reads_blended_with_the_neighbours_by_foreshortening_are_left_out(
        S, T, zenith_deg, contrast, left_out):
    """A texel the photo resolves, seen so obliquely that its read takes in the texels
    beside it, is not observed there, where its neighbours differ from it by more than
    the noise; a map as fine as the photos (texels a pixel across) keeps its reads,
    which every view blurs. The rows of a band are read with their neighbours in the
    next band, and the map's edge texels with what lies beyond."""
    from parammap.stages.observation import sample_view

    frame, intr, R, t = _checker_photo(zenith_deg, S, T, 1.0, contrast)
    noise = np.full(frame.shape[:2], 0.01, np.float32)  # 1 % relative sd
    sat = np.zeros(frame.shape[:2], bool)
    stats: dict[str, int] = {}
    bands = [sample_view(frame, sat, intr, R, t, slice(r0, min(r0 + 4, T)), S, T, 80.0,
                         60.0, noise=noise, max_blend=2.0, stats=stats)
             for r0 in range(0, T, 4)]
    valid = np.concatenate([b[2] for b in bands])
    _, _, kept, _ = sample_view(frame, sat, intr, R, t, slice(0, T), S, T, 80.0, 60.0,
                                noise=noise, max_blend=None)
    assert kept.all() and valid.shape == (T, S)
    # the band-by-band reads see the same neighbours as one read of the whole map
    whole = sample_view(frame, sat, intr, R, t, slice(0, T), S, T, 80.0, 60.0, noise=noise,
                        max_blend=2.0)
    np.testing.assert_array_equal(valid, whole[2])
    assert stats.get("blended", 0) == int((~valid).sum())
    if left_out:
        assert (~valid).mean() > 0.9
    else:
        assert valid.all()


@pytest.mark.parametrize("w", [1.2, 1.6, 2.2])
def test_blend_bias_of_a_line_a_texel_wide_matches_its_blend(w):
    """Reads of a printed line one texel wide, blended with their neighbours as the
    read model says (each takes ``f`` of its share from the two texels beside it): the
    estimated bias of the line's read, from the blended reads alone, is its true error
    within 25 % (the blended reads' own second difference understates the line's by
    1 - 2f), and a linear gradient has none."""
    from parammap.stages.observation import blend_bias, outside_fraction

    f = float(outside_fraction(np.array(w)))
    x = np.full((3, 9), 1.0)
    x[:, 4] = 3.0
    r = x.copy()
    r[:, 1:-1] = x[:, 1:-1] + f * (0.5 * (x[:, :-2] + x[:, 2:]) - x[:, 1:-1])
    rad = np.repeat(r[..., None], 3, -1)
    wx, wy = np.full(x.shape, w), np.full(x.shape, 50.0)
    frontal = np.full(x.shape, 50.0)
    near = np.zeros(x.shape, bool)
    bias = blend_bias(rad, wx, wy, near, frontal)[0, :, 0]  # core columns 1..7
    true = np.abs(r - x)[1, 1:-1]
    assert bias[3] == pytest.approx(true[3], rel=0.25)
    grad = np.repeat(np.linspace(1, 2, 9)[None, :, None], 3, 0).repeat(3, -1)
    assert np.abs(blend_bias(grad, wx, wy, near, frontal)).max() < 1e-9


@pytest.mark.parametrize("zenith_deg", [0.0, 40.0])
def test_a_raw_frames_texels_are_read_from_their_own_photosites(zenith_deg):
    """A RAW frame's texels (3.2 px across, dark beside bright, a Bayer mosaic) read
    from their own photosites (:func:`photosite_planes`) are within 2 % of their value
    at the median; read from the demosaiced frame, whose interpolation reaches a
    photosite further, the dark ones take in their bright neighbours. Seen from 40 deg
    the texels are 2.5 px across one axis and read by whole pixels: each point's own
    photosite (0.008 % off at the median; the demosaiced pixel there: 310 %)."""
    from parammap.stages.observation import photosite_planes, sample_view
    from parammap.stores.images import RAW_FULL, demosaic
    from parammap.synth.raw import Sensor

    S, T = 20, 15
    a, b = 0.05, 0.8
    frame, intr, R, t = _checker_photo(zenith_deg, S, T, a, b)
    colors = Sensor(pattern="GBRG").colors(*frame.shape[:2])
    mosaic = np.round(np.take_along_axis(frame, colors[..., None], 2)[..., 0]
                      * RAW_FULL).astype(np.uint16)
    rgb = demosaic(mosaic, colors).astype(np.float32)
    sat = np.zeros(frame.shape[:2], bool)
    args = (rgb, sat, intr, R, t, slice(0, T), S, T, 80.0, 60.0)
    demosaiced = sample_view(*args)[0]
    own = sample_view(*args, sites=photosite_planes((mosaic.astype(np.float32), colors)))[0]
    rr, cc = np.meshgrid(np.arange(T), np.arange(S), indexing="ij")
    expect = RAW_FULL * np.where((rr + cc) % 2 == 0, a, b)[..., None]
    dark = np.broadcast_to(((rr + cc) % 2 == 0)[..., None], own.shape) & np.isfinite(own)
    e_own, e_dem = (np.abs(x / expect - 1)[dark] for x in (own, demosaiced))
    assert np.median(e_own) < 0.02 and np.median(e_dem) > 2 * np.median(e_own), \
        (np.median(e_own), np.median(e_dem))
