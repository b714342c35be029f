"""The synthetic capture generator against its own ground truth."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import yaml

from parammap.geometry import pixel_to_plane, plane_to_texel, project_points, texel_centres
from parammap.stores.capture import validate_capture
from parammap.stores.images import read_image
from parammap.synth.generate import PRESETS, Response, generate
from parammap.synth.sampling import icosahedron, latlong, spiral, stratified
from parammap.synth.scene import PHONG, build_scene, load_scene, mh_truth, true_radiance


def _digest(root):
    h = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return h


def test_same_seed_same_bytes(tiny_capture, tmp_path):
    cap, truth = tiny_capture
    again = generate(tmp_path / "cap", tmp_path / "truth", preset="tiny", seed=0, workers=1)
    assert _digest(again) == _digest(cap)
    assert _digest(tmp_path / "truth") == _digest(truth)


def test_other_seed_other_photos(tmp_path, tiny_capture):
    other = generate(tmp_path / "c", tmp_path / "t", preset="tiny", seed=1, workers=2)
    a, b = _digest(tiny_capture[0]), _digest(other)
    assert a["views/v000_0.png"] != b["views/v000_0.png"]


def test_generated_capture_validates(tiny_capture):
    cap = validate_capture(tiny_capture[0])
    assert len(cap.views) >= 10
    assert sum(v.holdout for v in cap.views) == PRESETS["tiny"].holdout
    assert len(cap.calibration_images) == PRESETS["tiny"].calib_images
    assert all(len(v.exposures) == PRESETS["tiny"].exposures for v in cap.views)


def _truth(truth):
    cam = yaml.safe_load((truth / "camera.yaml").read_text())
    poses = np.load(truth / "poses.npz")
    return np.array(cam["K"]), np.array(cam["dist"]), poses


def test_texel_centres_project_onto_their_texels(tiny_capture):
    cap_dir, truth = tiny_capture
    K, dist, poses = _truth(truth)
    scene = load_scene(truth / "scene.npz")
    T, S = scene.shape
    ctr = texel_centres(S, T, scene.width_mm, scene.height_mm).reshape(-1, 3)
    rr, cc = np.divmod(np.arange(S * T), S)
    for R, t in zip(poses["R"], poses["t"], strict=True):
        uv = project_points(ctr, K, dist, R, t)
        P, hit = pixel_to_plane(uv, K, dist, R, t)
        assert hit.all()
        np.testing.assert_allclose(P, ctr, atol=1e-6)
        r, c = plane_to_texel(P[:, 0], P[:, 1], S, T, scene.width_mm, scene.height_mm)
        assert np.array_equal(np.floor(r).astype(int), rr)
        assert np.array_equal(np.floor(c).astype(int), cc)


def test_photo_at_projected_centre_shows_that_texel(tiny_capture):
    """The rendered photo at a texel centre's projection has the level the true
    radiance of that texel predicts: checks the texel mapping (row 0 at the top)."""
    cap_dir, truth = tiny_capture
    K, dist, poses = _truth(truth)
    scene = load_scene(truth / "scene.npz")
    cap = validate_capture(cap_dir)
    T, S = scene.shape
    ctr = texel_centres(S, T, scene.width_mm, scene.height_mm).reshape(-1, 3)
    rr, cc = np.divmod(np.arange(S * T), S)
    resp = Response()
    errs, flipped = [], []
    for k, view in enumerate(cap.views):
        R, t = poses["R"][k], poses["t"][k]
        C = -R.T @ t
        uv = project_points(ctr, K, dist, R, t)
        v = (C - ctr) / np.linalg.norm(C - ctr, axis=1, keepdims=True)
        # Only texels at least 2.5 px wide in this view, away from where it changes.
        foot = np.linalg.norm(project_points(ctr + [scene.width_mm / S, 0, 0], K, dist, R, t)
                              - uv, axis=1)
        ok = foot > 2.5
        ex = view.exposures[-1]
        img = read_image(ex.path).astype(float)
        px = np.round(uv).astype(int)
        L = true_radiance(scene, rr, cc, v)
        Lf = true_radiance(scene, T - 1 - rr, cc, v)  # what a row flip would show
        want = resp(L * ex.exposure_s)
        got = img[px[:, 1], px[:, 0]]
        good = ok & (want.max(1) < 240) & (got.max(1) < 240)
        errs.append(np.abs(got - want)[good])
        flipped.append(np.abs(got - resp(Lf * ex.exposure_s))[good])
    errs = np.concatenate(errs)
    assert np.median(errs) < 2.0
    assert np.median(np.concatenate(flipped)) > 2 * np.median(errs)


def test_response_monotonic_and_every_radiance_well_exposed_somewhere(tiny_capture):
    cap_dir, truth = tiny_capture
    resp = np.load(truth / "response.npz")
    X = resp["exposure"]
    assert X.shape == (256, 3)
    assert np.all(np.diff(X, axis=0) > 0)
    K, dist, poses = _truth(truth)
    scene = load_scene(truth / "scene.npz")
    cap = validate_capture(cap_dir)
    T, S = scene.shape
    for k, view in enumerate(cap.views):
        R, t = poses["R"][k], poses["t"][k]
        uv = project_points(texel_centres(S, T, scene.width_mm, scene.height_mm).reshape(-1, 3),
                            K, dist, R, t)
        px = np.round(uv).astype(int)
        levels = np.stack([read_image(e.path)[px[:, 1], px[:, 0]] for e in view.exposures])
        well = ((levels > 10) & (levels < 245)).any(axis=0)
        assert well.all(), f"{view.id}: {np.sum(~well)} texel samples never well exposed"


def test_sampling_schemes():
    assert len(icosahedron(1)) == 17 and len(icosahedron(2)) == 73 and len(icosahedron(3)) == 305
    for d in (icosahedron(2, 70), latlong(5, 24, 80), spiral(60, 5, 80), stratified(6, 80)):
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-12)
        assert d[:, 2].min() >= np.cos(np.radians(80.0)) - 1e-9
        assert len(np.unique(np.round(d, 9), axis=0)) == len(d)


def test_exact_mh_truth_matches_scene():
    scene = build_scene(16, 16, 80.0, 80.0, seed=3)
    params, mask = mh_truth(scene)
    assert mask.any() and (scene.kind[mask] == PHONG).all()
    rng = np.random.default_rng(0)
    r, c = np.nonzero(mask)
    v = rng.normal(size=(len(r), 3))
    v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p = params[r, c]
    L = p[:, :3].copy()
    for k in range((p.shape[1] - 4) // 6):
        d = p[:, 7 + 6 * k: 10 + 6 * k]
        L += p[:, 4 + 6 * k: 7 + 6 * k] * (np.clip((d * v).sum(1), 0, None) ** p[:, 3])[:, None]
    np.testing.assert_allclose(true_radiance(scene, r, c, v), L, rtol=1e-12)


@pytest.mark.parametrize("name", ["tiny", "demo", "paper"])
def test_presets_exist(name):
    assert PRESETS[name].texels > 0
