"""The best model per texel (issue 20): the leave-one-view-out criterion is exact for
linear models, the composite map renders each texel with its own model, and the stage
keeps the model that explains a texel's views where another cannot."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from parammap.config import validate_config
from parammap.errors import InputError
from parammap.geometry import Intrinsics, look_at
from parammap.models.mh import MhFitConfig, fit_mh_tile, mh_outputs
from parammap.models.selection import press_linear
from parammap.render import render
from parammap.stages.best import run_best
from parammap.stages.fit import fit_map
from parammap.stores.observation import write_observation_arrays
from parammap.stores.params import (
    ParamMap,
    diffuse_map,
    param_map_from_fit,
    read_param_map,
    write_param_map,
)
from parammap.synth.cases import patches_case


def test_press_linear_is_exact_leave_one_view_out():
    rng = np.random.default_rng(0)
    n, N, q = 3, 12, 4
    J = rng.standard_normal((n, N, 3, q))
    L = rng.standard_normal((n, N, 3))
    w = rng.uniform(0.5, 2.0, (n, N))
    W = np.ones((n, N), bool)
    W[1, 3] = False
    ww = np.where(W, w, 0.0)

    def solve(i, keep):
        A = np.einsum("vcq,v,vcp->qp", J[i][keep], ww[i][keep], J[i][keep])
        b = np.einsum("vcq,v,vc->q", J[i][keep], ww[i][keep], L[i][keep])
        return np.linalg.solve(A, b)

    r = np.stack([J[i] @ solve(i, np.ones(N, bool)) - L[i] for i in range(n)])
    brute = []
    for i in range(n):
        tot = 0.0
        for v in range(N):
            if not W[i, v]:
                continue
            keep = np.arange(N) != v
            e = J[i, v] @ solve(i, keep) - L[i, v]
            tot += ww[i, v] * (e ** 2).sum()
        brute.append(tot)
    assert np.allclose(press_linear(J, np.where(W[..., None], r, 0), w, W), brute)


def test_best_map_renders_each_texel_with_its_own_models(tmp_path):
    T = S = 18
    a = ParamMap("diffuse", np.full((T, S, 3), 1.0, np.float32), 90.0, 90.0)
    b = ParamMap("diffuse", np.full((T, S, 3), 2.0, np.float32), 90.0, 90.0)
    write_param_map(tmp_path / "a.exr", a)
    write_param_map(tmp_path / "b.exr", b)
    cp = np.zeros((T, S, 2), np.float32)
    cp[:, S // 3:, 1] = 1  # middle third: the mean of a and b
    cp[:, 2 * S // 3:] = 1  # right third: b
    write_param_map(tmp_path / "best.exr", ParamMap("best", cp, 90.0, 90.0,
                                                    attrs={"candidates": "a b"}))
    best = read_param_map(tmp_path / "best.exr")
    assert list(best.parts) == ["a", "b"]
    intr = Intrinsics(np.array([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]]), np.zeros(5),
                      (320, 240))
    R, t = look_at(np.array([45.0, 45.0, 400.0]), np.array([45.0, 45.0, 0.0]))
    img, inside = render(best, intr, R, t)
    P_x = np.arange(320) - 160 + 45.0  # plane x of each column (frontal view, 1 mm a px)
    rows = slice(100, 140)
    got = [round(float(img[rows][:, (P_x > lo + 5) & (P_x < lo + 25)].mean()), 4)
           for lo in (0.0, 30.0, 60.0)]
    assert got == [1.0, 1.5, 2.0]
    # between texels, each texel's own models: a candidate's values where the texel did
    # not choose it never show (its interpolated share times its render would draw them)
    a.params[:, 2 * S // 3:] = 100.0
    b.params[:, :S // 3] = 100.0
    write_param_map(tmp_path / "a.exr", a)
    write_param_map(tmp_path / "b.exr", b)
    img, inside = render(read_param_map(tmp_path / "best.exr"), intr, R, t)
    assert 1.0 - 1e-5 < img[inside].min() and img[inside].max() < 2.0 + 1e-5
    # its candidates read from their files as the render needs them: the same image
    lazy = read_param_map(tmp_path / "best.exr", with_sd=False)
    assert not isinstance(lazy.parts, dict)
    assert np.array_equal(render(lazy, intr, R, t)[0], img, equal_nan=True)
    near, _ = render(read_param_map(tmp_path / "best.exr"), intr, R, t, interpolation="nearest")
    assert set(np.unique(np.round(near[inside], 4))) == {1.0, 1.5, 2.0}
    write_param_map(tmp_path / "bad.exr", ParamMap("best", cp, 90.0, 90.0))
    with pytest.raises(InputError, match="no candidates"):
        read_param_map(tmp_path / "bad.exr")
    with pytest.raises(InputError, match="2 channels, choice, partner"):
        write_param_map(tmp_path / "bad.exr", ParamMap("best", cp[..., :1], 90.0, 90.0))


def test_best_stage_keeps_the_lobe_where_the_views_need_it(tmp_path, monkeypatch):
    import parammap.stages.best as best_stage

    case, label = patches_case(texels=12, noise=0.01, seed=2)
    write_observation_arrays(tmp_path / "observation.zarr", case.radiance, case.direction,
                             case.valid, 1000.0, 1000.0, tile=6)
    fit_map(tmp_path / "observation.zarr", tmp_path / "fit" / "mh-1.zarr",
            partial(fit_mh_tile, K=1, cfg=MhFitConfig(), K_max=1), mh_outputs(1),
            {"model": "mh", "lobes": "1"}, "synchronous", 1)
    (tmp_path / "params").mkdir()
    write_param_map(tmp_path / "params" / "mh-1.exr",
                    param_map_from_fit(tmp_path / "fit" / "mh-1.zarr"))
    write_param_map(tmp_path / "params" / "diffuse.exr",
                    diffuse_map(tmp_path / "observation.zarr"))
    cfg = validate_config({"captures": {"x": "."}})
    m = run_best(tmp_path, tmp_path, cfg, models=["mh-1", "diffuse"], figures=tmp_path / "figs")
    best = read_param_map(tmp_path / "params" / "best.exr")
    choice = best.params[..., 0]
    lobe = read_param_map(tmp_path / "params" / "mh-1.exr").params[..., 4:7].sum(-1) > 0
    assert (label > 0).sum() > 50 and lobe[label > 0].mean() > 0.6
    assert (choice[lobe & (label > 0)] == 0).mean() > 0.95  # glossy bands keep their lobes
    assert abs(sum(m["chosen_fraction"].values()) - 1) < 1e-9
    assert m["values_per_texel_single"] == {"mh-1": 10, "diffuse": 3}
    # a texel drawn without a lobe (diffuse, or an MH fit that found none) stores Kd
    partner = best.params[..., 1]
    flat = ((choice == 1) | ~lobe) & ((partner == 1) | ~lobe)
    assert m["diffuse_fraction"] == pytest.approx(flat.mean())
    pair = choice != partner
    want = np.where(flat, 3, np.where(pair, 13, 10)).mean()
    assert m["values_per_texel"] == pytest.approx(want)
    assert (tmp_path / "figs" / "best_choice.png").is_file()
    with pytest.raises(InputError, match="at least two"):
        run_best(tmp_path, tmp_path, cfg, models=["mh-1"])
    # the same map from two worker processes, and with the sampled tiles' per-view
    # errors computed again rather than kept (a map bigger than the sample)
    run_best(tmp_path, tmp_path, cfg, models=["mh-1", "diffuse"], workers=2)
    assert np.array_equal(read_param_map(tmp_path / "params" / "best.exr").params,
                          best.params)
    monkeypatch.setattr(best_stage, "KEEP_BYTES", 0)
    assert run_best(tmp_path, tmp_path, cfg, models=["mh-1", "diffuse"]) == m
    assert np.array_equal(read_param_map(tmp_path / "params" / "best.exr").params,
                          best.params)


def test_choice_leaves_the_default_only_for_a_significant_gain():
    from parammap.stages.best import candidates, choose, resolve, significance_z

    # four texels, candidates a (the default: least mean error), b, and c
    B = np.array([[1.0, 0.9, 2.0],    # b better, but within one standard error
                  [1.0, 0.5, 2.0],    # b better by more than one standard error
                  [np.inf, 0.5, 2.0],  # a undefined (a view alone makes its lobe)
                  [1.0, 3.0, 2.0]])
    SE = np.full((4, 3), 0.2, np.float32)  # of each candidate's difference from a
    SE[:, 0] = 0.0
    assert list(choose(B, SE, 0, 0, (2, 2)).ravel()) == [0, 1, 0, 0]
    assert list(choose(B, SE, 0, 0, (2, 2), z=3.0).ravel()) == [0, 0, 0, 0]
    assert list(choose(B, None, 0, 0, (2, 2)).ravel()) == [1, 1, 1, 0]  # least, however slight
    # the threshold grows with the number of candidates: 1 for two, more for many
    assert significance_z(2) == pytest.approx(1.0)
    assert 2.3 < significance_z(21) < 2.5 and significance_z(36) > significance_z(21)
    # candidates: each model alone, then the mean of every two
    cands = candidates(3)
    assert cands == [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    assert candidates(3, blend=False) == cands[:3]
    chosen = np.array([[3, 5], [1, 4]])
    choice, partner = resolve(cands, chosen)
    assert choice.tolist() == [[0, 1], [1, 0]] and partner.tolist() == [[1, 2], [1, 2]]
    same = np.tile([0, 1, 2], (4, 1))
    same[1, 1] = 2  # b taken as c at texel 1
    choice, partner = resolve(cands, chosen, same)
    assert choice.tolist() == [[0, 2], [1, 0]] and partner.tolist() == [[1, 2], [1, 2]]


def test_sh_is_judged_by_its_own_projection_not_a_plain_refit(tmp_path):
    """The best stage reruns an SH fit on the sampled cap from its store to get each
    view's exact leave-one-out residual (prior and regularisation held); without the
    store it falls back to a plain least-squares refit, which lets a view at the cap's
    edge determine a coefficient alone and overstates the error."""
    import shutil

    from parammap.stages.best import error_table
    from parammap.stages.fit import fit_sh_map
    from parammap.stores.observation import open_observation_map
    from parammap.stores.paths import Processed

    case, label = patches_case(texels=12, noise=0.01, seed=2)
    write_observation_arrays(tmp_path / "observation.zarr", case.radiance, case.direction,
                             case.valid, 1000.0, 1000.0, tile=6)
    cfg = validate_config({"captures": {"x": "."}})
    fit_sh_map(tmp_path / "observation.zarr", tmp_path / "fit" / "sh-rlsop-16.zarr",
               "rlsop", 4, cfg["fit"]["sh"], "synchronous", 1)
    (tmp_path / "params").mkdir()
    write_param_map(tmp_path / "params" / "sh-rlsop-16.exr",
                    param_map_from_fit(tmp_path / "fit" / "sh-rlsop-16.zarr"))
    write_param_map(tmp_path / "params" / "diffuse.exr",
                    diffuse_map(tmp_path / "observation.zarr"))
    proc = Processed(tmp_path)
    maps = {n: read_param_map(proc.params(n)) for n in ("sh-rlsop-16", "diffuse")}
    obs = open_observation_map(proc.observation)
    exact, se = error_table(proc, maps, obs, default=1)
    assert np.isfinite(exact).all() and se.shape == (144, 2) and (se[:, 1] == 0).all()
    assert np.isfinite(se).all() and (se[:, 0] > 0).all()
    # the stage reads such a map's coefficients from its store a tile at a time (not
    # held whole): the same errors as from the EXR
    m = run_best(tmp_path, tmp_path, cfg, models=["sh-rlsop-16", "diffuse"])
    assert m["loo_error_median"]["sh-rlsop-16"] == pytest.approx(float(np.median(exact[:, 0])))
    shutil.rmtree(tmp_path / "fit")
    plain, none = error_table(proc, maps, obs)
    assert none is None
    # diffuse: the same model either way, judged on views chosen with the other's help
    assert abs(np.median(plain[:, 1]) / np.median(exact[:, 1]) - 1) < 0.1
    fin = np.isfinite(plain[:, 0])
    assert np.median(plain[fin, 0]) > 1.1 * np.median(exact[:, 0])  # 1.18 measured


def test_an_sh_fit_records_the_tone_map_it_fitted_and_a_refit_from_the_store_repeats_it(
        tmp_path):
    """The display-weighted SH fit's gamma is the observation map's display gamma, kept
    in the store: the best stage's rerun (and any reader) gets the stored coefficients
    from it, and not from a fit of the radiance."""
    from parammap.models.sh import fit_sh_tile
    from parammap.stages.fit import fit_sh_map
    from parammap.stores.fit import open_fit
    from parammap.stores.observation import open_observation_map

    case, _ = patches_case(texels=12, noise=0.01, seed=3)
    write_observation_arrays(tmp_path / "observation.zarr", case.radiance, case.direction,
                             case.valid, 1000.0, 1000.0, tile=6)
    obs = open_observation_map(tmp_path / "observation.zarr")
    fits = {}
    for on in (True, False):
        cfg = validate_config({"captures": {"x": "."},
                               "fit": {"sh": {"display_weights": on}}})
        store = tmp_path / f"sh-{on}.zarr"
        fit_sh_map(tmp_path / "observation.zarr", store, "rlsop", 4, cfg["fit"]["sh"],
                   "synchronous", 1)
        fits[on] = open_fit(store)
    g = fits[True]
    assert g.display_gamma == pytest.approx(obs.display_gamma())
    assert fits[False].display_gamma is None
    assert "display_gamma" in g.describe()  # carried into the EXR header
    rows, cols = slice(0, 6), slice(6, 12)
    again = fit_sh_tile(obs.radiance[rows, cols], obs.direction[rows, cols],
                        obs.valid[rows, cols], 4, "rlsop", sampled_cap=True,
                        shrink=g.shrink, robust=g.robust, display_gamma=g.display_gamma,
                        noise=obs.noise[rows, cols] if obs.noise is not None else None)
    stored = g["coeffs"][rows, cols]
    assert np.allclose(again["coeffs"], stored, rtol=1e-4, atol=1e-6)
    plain = fits[False]["coeffs"][rows, cols]
    assert not np.allclose(plain, stored, rtol=1e-2, atol=1e-4)


def test_the_mean_of_two_models_is_judged_exactly_and_taken_where_their_errors_cancel(
        tmp_path):
    """Two maps biased in opposite directions (Kd 30 % high and 30 % low): each alone
    predicts the left-out views badly, their mean is the least-squares diffuse fit.
    A pair's left-out error is exactly that of a map of the mean of the two (linear
    models), the stage takes the pair everywhere, and its render is that mean."""
    from parammap.stages.best import candidates, error_table
    from parammap.stores.observation import open_observation_map
    from parammap.stores.paths import Processed

    case, _ = patches_case(texels=12, noise=0.01, seed=3)
    write_observation_arrays(tmp_path / "observation.zarr", case.radiance, case.direction,
                             case.valid, 1000.0, 1000.0, tile=6)
    (tmp_path / "params").mkdir()
    kd = diffuse_map(tmp_path / "observation.zarr")
    maps = {}
    for name, f in (("high", 1.3), ("low", 0.7), ("mean", 1.0)):
        maps[name] = ParamMap("diffuse", kd.params * f, kd.width_mm, kd.height_mm)
        write_param_map(tmp_path / "params" / f"{name}.exr", maps[name])
    proc = Processed(tmp_path)
    obs = open_observation_map(proc.observation)
    B, _ = error_table(proc, {k: maps[k] for k in ("high", "low")}, obs,
                       cands=candidates(2))
    ref, _ = error_table(proc, {"mean": maps["mean"]}, obs)
    np.testing.assert_allclose(B[:, 2], ref[:, 0], rtol=1e-5)
    assert (B[:, 2] < B[:, :2].min(1)).mean() > 0.9
    cfg = validate_config({"captures": {"x": "."}})
    m = run_best(tmp_path, tmp_path, cfg, models=["high", "low"])
    assert m["default"] == "high+low" and m["chosen_fraction"]["high+low"] > 0.9
    assert m["values_per_texel"] == 3  # the mean of two diffuse maps is one Kd
    best = read_param_map(tmp_path / "params" / "best.exr")
    intr = Intrinsics(np.array([[800.0, 0, 160], [0, 800.0, 120], [0, 0, 1]]), np.zeros(5),
                      (320, 240))
    R, t = look_at(np.array([500.0, 500.0, 900.0]), np.array([500.0, 500.0, 0.0]))
    got, inside = render(best, intr, R, t)
    want, _ = render(maps["mean"], intr, R, t)
    pair = np.rint(best.params[..., 0]) != np.rint(best.params[..., 1])
    assert inside.sum() > 1000 and pair.mean() > 0.9
    # pixels between texels that all took the pair render as the mean map
    close = np.isclose(got[inside], want[inside], rtol=1e-5).all(-1)
    assert close.mean() > 0.8


def test_views_a_fit_leans_on_are_those_of_leverage_above_one_half():
    from parammap.models.selection import influential, loo_diffuse

    rng = np.random.default_rng(4)
    n, N = 2, 6
    L = 1.0 + 0.1 * rng.standard_normal((n, N, 3))
    W = np.ones((n, N), bool)
    w = np.ones((n, N))
    w[0, 0] = 10.0  # leverage 10 / 15 = 0.67: the fit leans on it
    w[1, 0] = 4.0   # leverage 4 / 9 = 0.44: it does not
    kd = (w[..., None] * L).sum(1) / w.sum(1)[:, None]  # the weighted least-squares fit
    e, bad = loo_diffuse(kd, np.zeros((n, N, 3)), L, W, w)
    r = kd[:, None] - L
    got = influential(e, r, W)
    assert not bad.any()
    assert got[0].tolist() == [True] + [False] * 5 and not got[1].any()


def test_basis_materials_left_out_views_refit_the_texels_own_lobe_directions():
    """A basis material shares m and the lobe colours, but each texel's lobe directions
    are its own fit's: held fixed in the leave-one-out they would keep what the left-out
    view taught them. The linearised refit frees them (two angles a lobe) between the
    amplitudes alone and a full MH refit (which also frees m and the colours): with the
    same residuals, a larger design only raises each view's leverage, so PRESS is
    ordered amplitudes <= + directions <= everything."""
    from parammap.models.mh import mh_eval
    from parammap.models.mh.uncertainty import loo_residuals
    from parammap.models.selection import loo_amplitudes, loo_linear, press

    rng = np.random.default_rng(5)
    n, N = 40, 24
    V = rng.normal(size=(n, N, 3))
    V[..., 2] = np.abs(V[..., 2]) + 0.3
    V /= np.linalg.norm(V, axis=-1, keepdims=True)
    P = np.zeros((n, 10))
    P[:, :3] = 0.2
    P[:, 3] = rng.uniform(5, 60, n)
    P[:, 4:7] = rng.uniform(0.5, 1.5, (n, 3))
    d = np.c_[rng.normal(0, 0.3, (n, 2)), np.ones(n)]
    P[:, 7:] = d / np.linalg.norm(d, axis=1, keepdims=True)
    L = mh_eval(P, V) * (1 + 0.05 * rng.standard_normal((n, N, 3)))
    W, w = np.ones((n, N), bool), np.ones((n, N))
    lobe = mh_eval(np.c_[np.zeros((n, 3)), P[:, 3:]], V)[..., None]
    held = loo_linear(np.concatenate([np.broadcast_to(np.eye(3), (n, N, 3, 3)), lobe], -1),
                      mh_eval(P, V) - L, w, W)
    e_held, e_free, e_all = (press(x, w) for x in (held, loo_amplitudes(P, V, L, W, w),
                                                  loo_residuals(P, V, L, W, w)))
    assert np.isfinite(e_free).all()
    assert (e_held < e_free).all() and (e_free <= e_all * (1 + 1e-9)).all()
    assert np.median(e_free / e_held) > 1.05  # two angles among five or six parameters
