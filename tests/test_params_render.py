"""Parameter-map EXRs, the renderer and the held-out comparison (issue 7)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from parammap.geometry import plane_to_texel
from parammap.render import render, surface_points, tone_map
from parammap.stages.calibration import Intrinsics
from parammap.stages.holdout import choose_gamma, compare
from parammap.stores.exr import ExrError, read_exr, write_exr
from parammap.stores.params import (
    ParamMap,
    ParamMapError,
    channel_names,
    read_param_map,
    write_param_map,
)
from parammap.synth.generate import true_view_radiance


@pytest.mark.parametrize("model,P,hemi", [("mh", 16, None), ("sh", 3 * 36, "lsop"),
                                          ("diffuse", 3, None)])
def test_param_map_round_trip_is_exact(tmp_path, model, P, hemi):
    rng = np.random.default_rng(1)
    pm = ParamMap(model, rng.random((5, 7, P)).astype(np.float32), 120.0, 80.0, hemi)
    pm.params[0, 0, 0] = np.nan  # failed texels stay NaN
    write_param_map(tmp_path / "m.exr", pm)
    back = read_param_map(tmp_path / "m.exr")
    assert back.model == model and back.hemisphere == hemi
    assert (back.width_mm, back.height_mm) == (120.0, 80.0)
    np.testing.assert_array_equal(back.params, pm.params)
    chans, head = read_exr(tmp_path / "m.exr")
    assert sorted(chans) == sorted(channel_names(model, P))
    assert head["S"] == 7 and head["T"] == 5


def test_channel_names_follow_conventions():
    assert channel_names("mh", 16)[:10] == ["Kd.R", "Kd.G", "Kd.B", "m", "lobe1.Ks.R",
                                            "lobe1.Ks.G", "lobe1.Ks.B", "lobe1.d.X",
                                            "lobe1.d.Y", "lobe1.d.Z"]
    sh = channel_names("sh", 3 * 16)
    assert sh[0] == "sh.R.00" and sh[15] == "sh.R.15" and sh[16] == "sh.G.00"
    assert channel_names("sh", 300)[99] == "sh.R.99"


def test_half_on_request(tmp_path):
    pm = ParamMap("diffuse", np.full((2, 2, 3), 0.5, np.float32), 1.0, 1.0)
    write_param_map(tmp_path / "h.exr", pm, half=True)
    chans, _ = read_exr(tmp_path / "h.exr")
    assert chans["Kd.R"].dtype == np.float16
    np.testing.assert_array_equal(read_param_map(tmp_path / "h.exr").params, pm.params)


def test_bad_exr_input_is_a_clear_error(tmp_path):
    with pytest.raises(ExrError, match="no such EXR"):
        read_param_map(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(ExrError, match="not a readable EXR"):
        read_param_map(tmp_path / "junk.exr")
    write_exr(tmp_path / "photo.exr", {"R": np.zeros((2, 2))})
    with pytest.raises(ParamMapError, match="unknown parameter-map model None"):
        read_param_map(tmp_path / "photo.exr")
    write_exr(tmp_path / "odd.exr", {"Kd.R": np.zeros((2, 2)), "x": np.zeros((2, 2))},
              {"parammap_model": "mh", "parammap_model_version": 1,
               "parammap_layout": "Kd.R x", "S": 2, "T": 2, "width_mm": 1.0,
               "height_mm": 1.0})
    with pytest.raises(ParamMapError, match="4 \\+ 6K"):
        read_param_map(tmp_path / "odd.exr")
    write_exr(tmp_path / "v2.exr", {"Kd.R": np.zeros((2, 2))},
              {"parammap_model": "mh", "parammap_model_version": 2})
    with pytest.raises(ParamMapError, match="version 2"):
        read_param_map(tmp_path / "v2.exr")
    # an svbrdf map from before its coat (version 1, seven channels): refit, one line
    old = "Kd.R Kd.G Kd.B Ks.R Ks.G Ks.B alpha"
    write_exr(tmp_path / "svbrdf-v1.exr", {c: np.zeros((2, 2)) for c in old.split()},
              {"parammap_model": "svbrdf", "parammap_model_version": 1,
               "parammap_layout": old, "S": 2, "T": 2, "width_mm": 1.0, "height_mm": 1.0})
    with pytest.raises(ParamMapError, match="svbrdf-v1.exr: svbrdf map version 1 .*rerun"):
        read_param_map(tmp_path / "svbrdf-v1.exr")


def test_renderer_reproduces_generator_photo_of_exact_mh_patch(tiny_capture):
    cap, truth = tiny_capture
    z = np.load(truth / "mh_params.npz")
    params, mask = z["params"], z["mask"]
    cam = yaml.safe_load((truth / "camera.yaml").read_text())
    intr = Intrinsics(np.array(cam["K"]), np.array(cam["dist"]), tuple(cam["image_size"]))
    poses = np.load(truth / "poses.npz")
    T, S = mask.shape
    w = h = yaml.safe_load((cap / "capture.yaml").read_text())["surface"]["width_mm"]
    pm = ParamMap("mh", np.nan_to_num(params).astype(np.float32), w, h)
    for k in (0, 5):
        vid = str(poses["view_ids"][k])
        R, t = poses["R"][k], poses["t"][k]
        img, inside = render(pm, intr, R, t, interpolation="nearest")
        true = true_view_radiance(cap, truth, vid)
        P, _ = surface_points(intr, R, t, w, h)
        r, c = plane_to_texel(P[..., 0], P[..., 1], S, T, w, h)
        # pixels well inside exact-MH texels (the photo box-filters across texel edges)
        central = (np.abs(r % 1 - 0.5) < 0.25) & (np.abs(c % 1 - 0.5) < 0.25)
        ri, ci = np.clip(r.astype(int), 0, T - 1), np.clip(c.astype(int), 0, S - 1)
        sel = inside & central & mask[ri, ci] & (params[ri, ci, 3] <= 150)
        assert sel.sum() > 50
        rel = np.abs(img[sel] / true[sel] - 1)
        assert np.percentile(rel, 95) < 0.02, np.percentile(rel, 95)


def test_comparison_figures():
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.1, 1.0, (20, 30, 3)).astype(np.float32)
    mask = np.ones((20, 30), bool)
    g = choose_gamma(photo, mask)
    assert tone_map(np.percentile(photo, 99), g) == round(255 * 0.95)
    same = compare(photo, photo, mask, g)
    assert same["mean_diff_8bit"] == 0 and same["psnr_db"] is None
    worse = compare(photo, photo * 1.2, mask, g)
    better = compare(photo, photo * 1.05, mask, g)
    assert worse["mean_diff_8bit"] > better["mean_diff_8bit"] > 0
    assert better["psnr_db"] > worse["psnr_db"]


def test_mh_interpolates_radiance_not_lobes():
    """Two texels with the same two lobes in opposite order (fitters sort by strength,
    and neighbours differ) must render between them as the model they share."""
    from parammap.models.mh import mh_eval
    from parammap.render import evaluate_bilinear

    d1, d2 = np.array([0.6, 0.0, 0.8]), np.array([-0.6, 0.0, 0.8])
    a = np.r_[0.1, 0.1, 0.1, 40.0, 1.0, 1.0, 1.0, d1, 0.8, 0.8, 0.8, d2]
    b = np.r_[0.1, 0.1, 0.1, 40.0, 0.8, 0.8, 0.8, d2, 1.0, 1.0, 1.0, d1]
    params = np.stack([a, b])[None]  # (T=1, S=2, 16)
    v = np.array([d1, d2, [0.0, 0.0, 1.0]])
    got = evaluate_bilinear("mh", params, np.full(3, 0.5), np.full(3, 1.0), v)
    want = mh_eval(a[None], v[None])[0]
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert got[0, 0] > 1.0  # the lobes survive (interpolated parameters lose them)


def test_maps_read_without_their_sds_or_one_at_a_time(tmp_path):
    """A stage that holds many maps of a lab capture reads them without their standard
    deviations (half their memory), or from their files as each is needed
    (``ParamMapFiles``: nothing kept); a missing map is named before any work."""
    from parammap.stores.params import ParamMapFiles

    rng = np.random.default_rng(0)
    params = rng.uniform(0.1, 1.0, (6, 8, 10)).astype(np.float32)
    params[..., 7:10] = [0.0, 0.0, 1.0]
    sd = rng.uniform(0.0, 0.1, (6, 8, 8)).astype(np.float32)
    write_param_map(tmp_path / "mh-1.exr", ParamMap("mh", params, 20.0, 15.0, sd=sd))
    full = read_param_map(tmp_path / "mh-1.exr")
    lean = read_param_map(tmp_path / "mh-1.exr", with_sd=False)
    np.testing.assert_array_equal(full.sd, sd)
    assert lean.sd is None
    np.testing.assert_array_equal(lean.params, full.params)
    files = ParamMapFiles({"mh-1": tmp_path / "mh-1.exr"})
    assert list(files) == ["mh-1"] and len(files) == 1 and "mh-1" in files
    a, b = files["mh-1"], files["mh-1"]
    assert a is not b and a.sd is None
    np.testing.assert_array_equal(a.params, full.params)
    with pytest.raises(ParamMapError, match="sh-rlsop-36.exr"):
        ParamMapFiles({"mh-1": tmp_path / "mh-1.exr", "sh": tmp_path / "sh-rlsop-36.exr"})
