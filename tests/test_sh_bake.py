"""SH baked from an MH fit (``sh-mh-<n^2>``, parammap.models.sh.bake)."""

from __future__ import annotations

import numpy as np
import pytest

from parammap.conventions import MH_KD, MH_M, FitArray, FitStatus, mh_dir, mh_ks
from parammap.models.display import tone_gamma
from parammap.models.mh.model import mh_eval
from parammap.models.sh.bake import bake_mh, bake_tile, baked_cap
from parammap.models.sh.basis import sh_eval
from parammap.models.sh.cap import cap_radius, hemisphere_grid
from parammap.synth.sampling import icosahedron


def _mh(kd, ks, m, d) -> np.ndarray:
    p = np.zeros(10)
    p[MH_KD], p[MH_M], p[mh_ks(0)] = kd, m, ks
    p[mh_dir(0)] = np.asarray(d, float) / np.linalg.norm(d)
    return p


def _views(max_zenith: float, level: int = 2) -> np.ndarray:
    return icosahedron(level, max_zenith)


def _shown_error(p, c, dirs, gamma):
    """Mean absolute difference of the values shown at ``dirs`` (M, 3), 0-1."""
    truth = mh_eval(p[None], dirs[None])[0]
    baked = sh_eval(c[None], dirs[None])[0]
    return float(np.mean(np.abs(np.exp(-gamma * np.maximum(baked, 0))
                                - np.exp(-gamma * truth))))


def test_a_diffuse_texel_bakes_to_its_colour_alone():
    v = _views(60)
    p = _mh((0.2, 0.5, 0.7), (0, 0, 0), 10, (0, 0, 1))
    c, rmse = bake_mh(p[None], v[None], np.ones((1, len(v)), bool), 4, gamma=3.0)
    got = sh_eval(c, v[None])[0]
    np.testing.assert_allclose(got, np.broadcast_to((0.2, 0.5, 0.7), got.shape), atol=1e-6)
    assert rmse[0] < 1e-6


def test_the_bands_do_not_cancel_each_other_in_large_coefficients():
    """Over a cap the bands could cancel each other in coefficients of hundreds, which
    a half-float EXR cannot hold: a lobe's baked coefficients stay of the order of its
    own values."""
    v = _views(60)
    p = _mh((0.3, 0.2, 0.1), (0.6, 0.6, 0.6), 40, (0.3, -0.2, 0.93))
    c, _ = bake_mh(p[None], v[None], np.ones((1, len(v)), bool), 8, gamma=2.0)
    g, _ = hemisphere_grid(4.0)
    peak = mh_eval(p[None], g[None])[0].max()
    assert np.abs(c).max() < 5 * peak


@pytest.mark.parametrize("m", [20.0, 80.0])
def test_a_lobe_between_the_views_is_drawn_and_more_bands_draw_it_closer(m):
    """Between sparse views the baked SH follows the MH lobe: the lobe's peak, which no
    view sees, and the whole cap are shown more closely with more bands, and always
    more closely than by the texel's mean level (a diffuse texture)."""
    v = _views(65, level=1)  # ~ 20 views 20 deg apart
    d = np.array([0.3, -0.2, 0.93])
    p = _mh((0.1, 0.1, 0.1), (0.6, 0.6, 0.6), m, d)
    g, _ = hemisphere_grid(2.0)
    inside = (g @ v.T).max(1) >= np.cos(cap_radius(v))
    gamma = tone_gamma(mh_eval(p[None], g[inside][None])[0])
    errs = {}
    for n in (4, 6, 8):
        c, _ = bake_mh(p[None], v[None], np.ones((1, len(v)), bool), n, gamma)
        errs[n] = (_shown_error(p, c[0], g[inside], gamma),
                   _shown_error(p, c[0], (d / np.linalg.norm(d))[None], gamma))
    assert errs[8][0] < errs[4][0] and errs[8][1] < errs[4][1], errs
    if m <= 20:  # a lobe 8 bands resolve (half width 15 deg): 4 levels of 255 at most
        assert errs[8][0] < 0.015, errs
    # never worse than the texel's mean level over the cap (a diffuse texture)
    mean = mh_eval(p[None], g[inside][None])[0].mean(0)
    flat = np.zeros((3, 64))
    flat[:, 0] = mean / sh_eval(np.eye(64)[None, :1].repeat(3, 1), g[:1][None])[0, 0]
    assert errs[8][0] < _shown_error(p, flat, g[inside], gamma)


def test_the_cap_is_where_the_views_are():
    v = _views(40)
    g, _ = hemisphere_grid(4.0)
    inside = baked_cap(v[None], np.ones((1, len(v)), bool), g)[0]
    z = np.degrees(np.arccos(g[:, 2]))
    assert inside[z < 35].all() and not inside[z > 60].any()
    # a texel that saw nothing has no cap
    assert not baked_cap(v[None], np.zeros((1, len(v)), bool), g).any()


def test_bake_tile_flags_texels_whose_mh_fit_failed_or_saw_nothing():
    v = _views(50)
    N = len(v)
    rad = np.ones((2, 2, N, 3)) * 0.3
    dirs = np.broadcast_to(v, (2, 2, N, 3)).copy()
    valid = np.ones((2, 2, N), bool)
    valid[1, 1] = False
    P = np.broadcast_to(_mh((0.3, 0.3, 0.3), (0, 0, 0), 10, (0, 0, 1)), (2, 2, 10)).copy()
    ok = np.ones((2, 2), bool)
    ok[0, 1] = False
    out = bake_tile(rad, dirs, valid, P, ok, 3, gamma=2.0)
    st = out[FitArray.STATUS]
    assert st[0, 0] == st[1, 0] == FitStatus.OK
    assert st[0, 1] == FitStatus.FAILED and st[1, 1] == FitStatus.TOO_FEW
    np.testing.assert_allclose(out[FitArray.RMSE][0, 0], 0, atol=1e-6)
    assert np.isnan(out[FitArray.COEFFS][0, 1]).all()


def test_the_stage_bakes_an_mh_fit_which_best_leaves_out(tiny_work, capsys):
    """``fit-sh --model sh-mh-16`` bakes the MH fit ``fit.sh.source`` names into an SH
    map that renders like it at the texels' own views; a missing source is named; the
    best stage leaves the baked map out (its errors are its source's)."""
    from parammap.cli import main
    from parammap.stores.fit import open_fit
    from parammap.stores.observation import open_observation_map
    from parammap.stores.params import read_param_map

    cap, _, out = tiny_work
    o = str(out)
    assert main(["fit-sh", "--out", o, "--model", "sh-mh-16",
                 "--set", "fit.sh.source=mh-1"]) == 2
    assert "mh-1" in capsys.readouterr().err
    assert main(["fit-mh", "--out", o, "--lobes", "1"]) == 0
    assert main(["fit-sh", "--out", o, "--model", "sh-mh-16",
                 "--set", "fit.sh.source=mh-1"]) == 0
    g = open_fit(out / "fit" / "sh-mh-16.zarr")
    assert g.hemisphere == "mh" and g.attrs["source"] == "mh-1"
    assert FitArray.SD not in g
    ok = g[FitArray.STATUS][:] == FitStatus.OK
    src_ok = open_fit(out / "fit" / "mh-1.zarr")[FitArray.STATUS][:] == FitStatus.OK
    assert ok.sum() == src_ok.sum() > 0
    models = ["--model", "mh-1", "--model", "sh-mh-16", "--model", "diffuse"]
    assert main(["export", "--out", o, *models]) == 0
    pm = read_param_map(out / "params" / "sh-mh-16.exr")
    assert pm.hemisphere == "mh" and pm.sd is None
    # at the texels' own views, the values shown of the bake are its source's
    obs = open_observation_map(out / "observation.zarr")
    V, W = obs.direction[:][ok], obs.valid[:][ok]
    src = read_param_map(out / "params" / "mh-1.exr").params[ok]
    shown = {}
    for name, p in (("mh", mh_eval(src, V)), ("sh", sh_eval(
            pm.params[ok].reshape(-1, 3, 16).astype(float), V))):
        shown[name] = np.exp(-g.display_gamma * np.maximum(p, 0))[W]
    flat = np.exp(-g.display_gamma * src[:, None, MH_KD].repeat(V.shape[1], 1))[W]
    assert np.median(np.abs(shown["sh"] - shown["mh"])) < 0.01  # 2.5 levels of 255
    assert np.mean(np.abs(shown["sh"] - shown["mh"])) < np.mean(np.abs(flat - shown["mh"]))
    assert main(["best", "--out", o, *models]) == 0
    best = read_param_map(out / "params" / "best.exr")
    assert best.attrs["candidates"].split() == ["mh-1", "diffuse"]
