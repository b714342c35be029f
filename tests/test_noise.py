"""Noise-aware fitting (issue 15, item 3): the merge's noise model, observation
weights, weighted fits and the chi-square."""

from __future__ import annotations

import numpy as np

from parammap.conventions import FitStatus
from parammap.models.mh import fit_mh_tile
from parammap.models.sh import fit_sh_tile
from parammap.models.weights import MAX_RATIO, noise_weights, reduced_chi2
from parammap.stages.hdr import level_noise, merge_bracket, merge_noise, reexposure_error
from parammap.synth.cases import phong_case


def _bracket(E, times, sd_levels, rng):
    """8-bit photos of radiance E (H, W, 3) through a gamma 2.2 response with Gaussian
    noise of ``sd_levels`` before rounding."""
    g = np.log(np.maximum(np.arange(256) / 255.0, 1e-4) ** 2.2)
    g = np.repeat(g[:, None], 3, 1)
    stack = []
    for t in times:
        x = 255 * np.clip(E * t, 0, 1) ** (1 / 2.2) + rng.normal(0, sd_levels, E.shape)
        stack.append(np.clip(np.round(x), 0, 255).astype(np.uint8))
    return np.stack(stack), g


def test_merge_noise_predicts_the_spread_of_merged_radiance():
    rng = np.random.default_rng(0)
    times = np.array([1.0, 0.25, 1 / 16])
    # four constant radiance levels, 4000 pixels each: toe, middle, bright, very bright
    levels = np.array([0.02, 0.2, 1.5, 8.0])
    E = np.repeat(levels, 4000)[None, :, None] * np.ones((1, 1, 3))
    stack, g = _bracket(E, times, 1.5, rng)
    rad, sat, dark = merge_bracket(stack, times, g)
    sd_lv = level_noise(reexposure_error(stack, times, rad, g).mean(), len(times))
    assert 1.1 < sd_lv < 2.0, sd_lv  # 1.53 with rounding, from the re-exposure errors
    pred = merge_noise(stack, times, g, sd_lv)
    for k, e in enumerate(levels):
        sl = slice(4000 * k, 4000 * (k + 1))
        actual = np.std(rad[0, sl].mean(-1) / e)
        predicted = np.median(pred[0, sl])
        assert 0.6 < predicted / (actual * np.sqrt(3)) < 1.7, (e, predicted, actual)


def test_noise_weights_are_normalised_and_bounded():
    valid = np.ones((2, 6), bool)
    valid[1, 5] = False
    noise = np.array([[0.01, 0.02, 0.01, 0.01, 0.5, 1e-6], [0.01] * 5 + [np.nan]])
    w = noise_weights(noise, valid)
    assert np.allclose(w[valid].reshape(-1)[:6].mean(), 1.0) and w[1, 5] == 0
    assert np.allclose(w[1, :5], 1.0)
    ratio = w[0].max() / np.median(w[0])
    assert ratio <= MAX_RATIO * 1.0001  # one view cannot dominate
    assert w[0, 1] < w[0, 0] and w[0, 4] < w[0, 1]
    assert np.array_equal(noise_weights(None, valid), valid.astype(float))
    partial = noise_weights(np.array([[0.01, np.nan, 0.01, 0.01, 0.01, 0.01]]),
                            np.ones((1, 6), bool))
    assert np.array_equal(partial, np.ones((1, 6)))  # unknown sd: unweighted


def test_weighted_fit_ignores_the_noisy_views_and_chi2_is_about_one():
    rng = np.random.default_rng(2)
    case = phong_case(texels=4, level=2, m=30, ks=0.8)
    L, V, valid = case.radiance.astype(float), case.direction, case.valid
    N = L.shape[2]
    sd = np.full(L.shape[:3], 0.01)
    bad = rng.random(N) < 0.25  # a quarter of the views ten times noisier
    sd[..., bad] = 0.1
    Ln = L * (1 + sd[..., None] * rng.standard_normal(L.shape))
    plain = fit_mh_tile(Ln.astype(np.float32), V, valid, 1)
    weighted = fit_mh_tile(Ln.astype(np.float32), V, valid, 1, noise=sd.astype(np.float32))
    assert (weighted["status"] == FitStatus.OK).all()
    truth = case.truth[..., :3]
    err_p = np.abs(plain["params"][..., :3] - truth).mean()
    err_w = np.abs(weighted["params"][..., :3] - truth).mean()
    assert err_w < 0.7 * err_p, (err_w, err_p)
    chi2 = weighted["chi2"]
    assert np.median(chi2) > 0.7 and np.median(chi2) < 1.4 and chi2.max() < 3, chi2
    assert np.isnan(plain["chi2"]).all()  # no noise recorded: no chi-square
    sh = fit_sh_tile(Ln.astype(np.float32), V, valid, 6, "rlsop", noise=sd.astype(np.float32))
    assert np.isfinite(sh["chi2"]).all() and (sh["chi2"] > 0.5).all()


def test_reduced_chi2_of_exact_noise():
    rng = np.random.default_rng(5)
    fitted = rng.uniform(0.5, 2.0, (50, 200, 3))
    sd = np.full((50, 200), 0.02)
    meas = fitted * (1 + sd[..., None] * rng.standard_normal(fitted.shape))
    chi2 = reduced_chi2(meas, fitted, sd, np.ones((50, 200), bool), 0)
    assert abs(np.median(chi2) - 1) < 0.05
