"""The MH fit of a tile of texels: starts, the optimisers of :mod:`.optim`, lobe selection
(K = auto, the lobe window, negligible lobes), and the tile's outputs."""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.ndimage import uniform_filter

from ...config import default
from ...conventions import (
    MH_M,
    FitArray,
    FitStatus,
    mh_dir,
    mh_dir_z,
    mh_ks,
    mh_lobe,
    mh_lobes,
    mh_sd_size,
    mh_size,
    mhx_size,
)
from ..residuals import mean_percentage_residual
from ..weights import noise_weights, reduced_chi2
from .initial import extend_guess_batch, initial_guess_batch, initial_guess_published
from .kernel import lobe_support, rss_batch
from .kernel import residual_stats as _residual_stats
from .model import (
    M_MIN,
    _lobes_present,
    _sort_lobes_batch,
    bic,
    mh_eval,
    overshoots,
)
from .optim import FitResult, MhFitConfig, fit_texel, polish_batch, refine_batch
from .starts import initial_batch
from .uncertainty import loo_error, parameter_sd

# ---------------------------------------------------------------------------------
# nlopt fit of one texel


# Most lobes ``auto`` may use (``fit.mh.K_max``): a cap on work and storage, not a
# model choice (BIC and the lobe window choose). A highlight whose shape is not a Phong
# lobe (microfacet, Blinn) takes two lobes, so two lights take four (docs: results).
K_MAX_AUTO = default("fit.mh.K_max")


# ---------------------------------------------------------------------------------
# A tile of texels


def mh_outputs(K_max: int) -> dict[str, tuple[tuple[int, ...], str, float]]:
    """Arrays of an MH fit store: name -> (trailing shape, dtype, fill value)."""
    return {
        FitArray.PARAMS: ((mh_size(K_max),), "float32", float("nan")),
        FitArray.RMSE: ((3,), "float32", float("nan")),
        FitArray.MPR: ((3,), "float32", float("nan")),
        FitArray.CHI2: ((), "float32", float("nan")),
        FitArray.SD: ((mh_sd_size(K_max),), "float32", float("nan")),
        FitArray.K_USED: ((), "int8", 0),
        FitArray.EVALS: ((), "int32", 0),
        FitArray.STATUS: ((), "int8", int(FitStatus.NOT_FITTED)),
    }


def fit_mh_tile(
    radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray, K: int | str,
    cfg: MhFitConfig = MhFitConfig(), K_max: int = K_MAX_AUTO, noise: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Fit every texel of a tile.

    Parameters
    ----------
    radiance, direction : (t, u, N, 3); valid : (t, u, N) bool.
    noise : (t, u, N) relative sd per observation: observations are weighted by
        :func:`parammap.models.weights.noise_weights` (LM, nlopt and the K = 0 start),
        and ``chi2`` is reported.
    K : lobes, or ``"auto"`` (add lobes up to ``K_max`` while BIC improves by more than
        ``cfg.bic_margin``).

    Returns
    -------
    dict of arrays shaped (t, u, ...) as :func:`mh_outputs` (params padded to K_max
    lobes with Ks = 0, d = +z). A texel with too few observations or a failed
    optimisation is flagged in ``status`` and never stops the tile.
    """
    t, u, N, _ = radiance.shape
    Kmax = K_max if K == "auto" else int(K)
    out = {k: np.full((t, u) + shp, fill, dtype) for k, (shp, dtype, fill) in
           mh_outputs(Kmax).items()}
    V = direction.reshape(t * u, N, 3).astype(float)
    L = radiance.reshape(t * u, N, 3).astype(float)
    # a NaN or infinity in any component makes the sum non-finite
    W = valid.reshape(t * u, N) & np.isfinite(L.sum(-1) + V.sum(-1))
    L[~W] = 0.0  # L and V are copies (astype)
    V[~W] = [0.0, 0.0, 1.0]
    NZ = None if noise is None else noise.reshape(t * u, N)
    NW = noise_weights(NZ, W)
    nobs = W.sum(1)
    # the fits _select_lobes chooses among: every K of ``auto`` (0 .. K_max), or K and
    # K - 1 lobes for a fixed K >= 2
    select = cfg.lobe_window > 0 and (K == "auto" or Kmax >= 2)
    Ks = range(1, Kmax + 1) if K == "auto" else ([Kmax - 1, Kmax] if select else [Kmax])
    alts = {k: np.full((t * u, mh_size(Kmax)), np.nan) for k in Ks} if select else {}
    todo = np.flatnonzero(nobs >= 4)  # 004: at least four observations
    few = np.flatnonzero(nobs < 4)
    flat = {k: v.reshape((t * u,) + v.shape[2:]) for k, v in out.items()}
    flat[FitArray.STATUS][few] = FitStatus.TOO_FEW
    if len(todo) == 0:
        return out
    init = initial_guess_batch if cfg.init == "better" else initial_guess_published
    Wf = NW[todo]
    # the numpy initial guesses in float32 (twice as fast; LM and nlopt then work in
    # float64); the compiled one works in float64 anyway
    dt = np.float64 if initial_batch is not None else np.float32
    V32, L32, W32 = (a.astype(dt, copy=False) for a in (V[todo], L[todo], Wf))

    def starts(k: int, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Initial guesses (and LM steps) with k lobes for the texels todo[sel], whether
        the LM converged there, and its state (:func:`refine_batch`)."""
        p0 = init(V32[sel], L32[sel], W32[sel], k).astype(float)
        return refine_batch(V[todo[sel]], L[todo[sel]], Wf[sel], p0, state=True) \
            if cfg.init == "better" else (p0, np.zeros(len(sel), bool), None)

    # LM-converged texels get their nlopt polish stacked: one bounded run over all of
    # them (their objectives are separable), the few it leaves unconverged alone after
    stacked = cfg.polish == "batch" and cfg.loss == "linear" and cfg.algorithm != "bobyqa"
    nres = 3 * nobs[todo]
    # L is 0 where not valid
    floor = (cfg.bic_floor * np.abs(L[todo]).sum((1, 2)) / nres) ** 2

    def texel_data(j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = W[todo[j]]
        return V[todo[j]][w], L[todo[j]][w], NW[todo[j]][w]

    # per texel: best fit so far (result, lobes), its BIC, evaluations, and whether BIC
    # stopped adding lobes (``auto``)
    best, best_bic = [None] * len(todo), np.full(len(todo), math.inf)
    evals = np.zeros(len(todo), int)
    stopped = np.zeros(len(todo), bool)
    if K == "auto":
        # K = 0 first: a lobe must pay for itself against a diffuse texel
        wt0 = Wf[..., None]
        kd = (wt0 * L[todo]).sum(1) / Wf.sum(1)[:, None]
        rss0 = (wt0 * np.where(W[todo][..., None], L[todo] - kd[:, None], 0.0) ** 2).sum((1, 2))
        for j in range(len(todo)):
            best[j] = (FitResult(np.r_[kd[j], M_MIN], float(rss0[j]), 0, FitStatus.OK, 0), 0)
            best_bic[j] = bic(float(rss0[j]), int(nres[j]), 0, float(floor[j]))
    for k in Ks:
        # one number of lobes for every texel still adding lobes: the starts of texels
        # that BIC already stopped are never computed
        run = np.flatnonzero(~stopped)
        if len(run) == 0:
            break
        start = np.full((len(todo), mh_size(k)), np.nan)
        conv = np.zeros(len(todo), bool)  # the batch LM converged: no LM in fit_texel
        lm_state = np.full((len(todo), 1 + 2 * mhx_size(k)), np.nan)
        # a texel whose best fit so far has k - 1 lobes starts from that fit with one
        # lobe more (the lobes it found stay where they are); the others from the
        # initial guess. On the demo: held-out mh-2 9.07 -> 7.63, mh-auto 7.34 -> 7.18
        grow = np.array([j for j in run if k >= 2 and cfg.init == "better"
                         and best[j] is not None and best[j][1] == k - 1
                         and best[j][0].status == FitStatus.OK], int)
        fresh = np.setdiff1d(run, grow)
        for sel, (P0, c0, st) in (
                (fresh, starts(k, fresh) if len(fresh) else (None,) * 3),
                (grow, refine_batch(V[todo[grow]], L[todo[grow]], Wf[grow], extend_guess_batch(
                    V[todo[grow]], L[todo[grow]], Wf[grow],
                    np.stack([best[j][0].params for j in grow])), state=True)
                 if len(grow) else (None,) * 3)):
            if P0 is not None:
                start[sel], conv[sel] = P0, c0
                if st is not None:
                    lm_state[sel] = st
        done = {}
        sel = run[conv[run]] if stacked else run[:0]
        if len(sel):
            st = lm_state[sel]
            P, rss, ev, ok, code = polish_batch(V[todo[sel]], L[todo[sel]], Wf[sel],
                                                start[sel], cfg,
                                                st if np.isfinite(st).all() else None)
            ok &= np.isfinite(P).all(1) & np.isfinite(rss)
            for i, j in enumerate(sel):
                if ok[i]:
                    done[j] = FitResult(P[i], float(rss[i]), ev, FitStatus.OK, code)
                elif np.isfinite(P[i]).all():
                    start[j] = P[i]  # LM converged, the stacked run left it: nlopt alone
        for j in run:
            b = todo[j]
            r = done.get(j)
            if r is None:
                v, y, wt = texel_data(j)
                try:
                    r = fit_texel(v, y, start[j], cfg, w=wt, lm=not conv[j])
                except Exception:  # noqa: BLE001 - a failed texel is flagged, never fatal
                    r = FitResult(np.full(mh_size(k), np.nan), math.inf, 0, FitStatus.FAILED,
                                  -1)
            evals[j] += r.evals
            if select and r.status == FitStatus.OK:
                alts[k][b] = _padded(r.params, k, Kmax)
            crit = bic(r.rss, int(nres[j]), k, float(floor[j])) \
                if r.status == FitStatus.OK else math.inf
            if best[j] is None or (K != "auto" and r.status == FitStatus.OK) or \
                    crit < best_bic[j] - cfg.bic_margin:
                best[j], best_bic[j] = (r, k), crit
            elif K == "auto":
                stopped[j] = True
    for j, b in enumerate(todo):
        r, k = best[j]
        flat[FitArray.PARAMS][b] = _padded(r.params, k, Kmax)
        flat[FitArray.K_USED][b] = k
        flat[FitArray.EVALS][b] = evals[j]
        flat[FitArray.STATUS][b] = r.status
    # residual diagnostics for the whole tile at once
    ok = todo[flat[FitArray.STATUS][todo] == FitStatus.OK]
    if select and len(ok):
        _select_lobes(flat, alts, ok, (t, u), V, L, W, NW, cfg.lobe_window, NZ)
    if len(ok):
        P = flat[FitArray.PARAMS][ok].astype(float)
        before = _lobes_present(P)
        P = drop_negligible_lobes(P, V[ok], L[ok], W[ok])
        after = _lobes_present(P)
        for j in np.flatnonzero(after < before):
            # the lobes left were fitted beside the one now gone: refit them alone
            b, k = ok[j], int(after[j])
            flat[FitArray.K_USED][b] = k
            w = W[b]
            v, y, wt = V[b][w], L[b][w], NW[b][w]
            if k == 0:
                P[j, :3] = (wt[:, None] * y).sum(0) / wt.sum()
                continue
            p0 = P[j, : mh_size(k)]
            rss0 = float(np.sum(wt[:, None] * (mh_eval(p0, v) - y) ** 2))
            try:
                r = fit_texel(v, y, p0.copy(), cfg, w=wt)
            except Exception:  # noqa: BLE001 - keep the unrefitted lobes
                continue
            if r.status == FitStatus.OK and r.rss < rss0:
                P[j, : mh_size(k)] = r.params
        flat[FitArray.PARAMS][ok] = P
        P = flat[FitArray.PARAMS][ok].astype(float)
        flat[FitArray.RMSE][ok], flat[FitArray.MPR][ok] = residual_stats(P, V[ok], L[ok], W[ok])
        flat[FitArray.SD][ok] = parameter_sd(flat[FitArray.PARAMS][ok].astype(float), V[ok],
                                             L[ok], W[ok],
                                      NW[ok])
        if NZ is not None:
            # free parameters: Kd, m, and per lobe Ks and a direction (two angles)
            flat[FitArray.CHI2][ok] = reduced_chi2(L[ok], mh_eval(P, V[ok]), NZ[ok], W[ok],
                                            mhx_size(flat[FitArray.K_USED][ok].astype(int)))
    return out


def residual_stats(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) RMSE and (n, 3) mean percentage residual (004) per channel of MH
    parameters P (n, 4 + 6K) on the valid observations (W (n, N) bool) of V, L
    (n, N, 3)."""
    if _residual_stats is not None:
        rmse, mpr = np.empty((len(P), 3)), np.empty((len(P), 3))
        _residual_stats(np.ascontiguousarray(P, float), np.ascontiguousarray(V, float),
                        np.ascontiguousarray(L, float), np.ascontiguousarray(W, bool),
                        rmse, mpr)
        return rmse, mpr
    fitted = mh_eval(P, V)
    w = W[..., None]
    n = np.maximum(w.sum(1), 1)
    return (np.sqrt((np.where(w, fitted - L, 0) ** 2).sum(1) / n),
            mean_percentage_residual(L, fitted, W))


def _padded(params: np.ndarray, k: int, K: int) -> np.ndarray:
    """A k-lobe parameter vector padded to K lobes (unused lobes: Ks = 0, d = +z)."""
    p = np.zeros(mh_size(K))
    p[: mh_size(k)] = params[: mh_size(k)]
    for extra in range(k, K):
        p[mh_dir_z(extra)] = 1.0
    return p


def _select_lobes(flat: dict, alts: dict[int, np.ndarray], ok: np.ndarray,
                  shape: tuple[int, int], V: np.ndarray, L: np.ndarray, W: np.ndarray,
                  NW: np.ndarray, window: int, noise: np.ndarray | None = None) -> None:
    """Choose each texel's number of lobes by how well the fit predicts left-out views.

    A lobe that lowers the residual of the views it was fitted to can still predict
    worse between them: with sparse views and a lobe shape unlike the model's (a
    microfacet tail), a second lobe narrows the highlight onto the observed views, and
    BIC (``auto``), which counts parameters but not where the views lie, keeps it (or
    drops a lobe seen in few views that does predict them). The leave-one-view-out
    error (:func:`~.uncertainty.loo_error`) of each alternative fit (``alts``: lobes ->
    (n, 4 + 6K) padded parameters, NaN where that fit failed) is summed over ``window``
    x ``window`` texels of the tile (neighbours share their material; one texel's error
    is noisy), and each texel takes the number of lobes with the lowest sum (the fewer
    lobes on a tie). A fit with more lobes whose peak no view measures, where the lobes
    do not explain the views to their ``noise`` ((n, N) relative sd), is not available
    (:func:`~.model.overshoots`: leave-one-out cannot see such a spike). Changes
    ``flat`` in place.
    """
    ks = sorted(alts)
    # whether a texel has a lobe at all stays BIC's choice (and drop_negligible_lobes'):
    # a lobe that one view alone saw has no leave-one-out support, yet may be real
    ok = ok[np.isin(flat[FitArray.K_USED][ok], ks)]
    if len(ok) == 0:
        return
    errs = np.full((len(ks), len(ok)), np.inf)
    for i, k in enumerate(ks):
        has = np.isfinite(alts[k][ok]).all(1)
        sel = ok[has]
        if len(sel):
            errs[i, has] = loo_error(alts[k][sel], V[sel], L[sel], W[sel], NW[sel])
    finite = np.isfinite(errs)
    if not finite.any():
        return
    # a view that alone determines a lobe (singular leave-one-out) is, once left out,
    # predicted as by the fit without that lobe: the error of one lobe fewer (a tie,
    # which goes to fewer lobes, so the neighbours decide); a failed fit, or the fewest
    # lobes: the worst prediction of the tile
    worst = errs[finite].max()
    for i in range(len(ks)):
        prev = errs[i - 1] if i else np.full(len(ok), worst)
        errs[i] = np.where(np.isfinite(errs[i]), errs[i], prev)
    errs = np.where(np.isfinite(errs), errs, worst)
    pooled = []
    for e in errs:
        g = np.zeros(shape[0] * shape[1])
        g[ok] = e
        pooled.append(uniform_filter(g.reshape(shape), window, mode="nearest").ravel()[ok])
    pooled = np.array(pooled)
    # a texel keeps its fit unless another is available and predicts better
    cur = np.searchsorted(ks, flat[FitArray.K_USED][ok])
    avail = np.array([np.isfinite(alts[k][ok]).all(1) for k in ks])
    avail[1:] &= ~overshoots([alts[k][ok] for k in ks], V[ok], L[ok], W[ok],
                             None if noise is None else noise[ok])
    pooled = np.where(avail, pooled, np.inf)
    choice = np.argmin(pooled, 0)  # argmin takes the first: fewer lobes on a tie
    change = (choice != cur) & (pooled[choice, np.arange(len(ok))]
                                < pooled[cur, np.arange(len(ok))])
    for i, k in enumerate(ks):
        b = ok[change & (choice == i)]
        flat[FitArray.PARAMS][b] = alts[k][b]
        flat[FitArray.K_USED][b] = k


# Observations that must see a lobe above twice the texel's noise for it to count as
# measured: three views x three channels are the fewest residuals that locate a peak
# (direction, width) and its colour. Five (the lobe's parameter count) also removed
# real, sharp lobes that 17 views of 004 ch. 13.2 still recover.
MIN_SUPPORT = 3
# A lobe's peak farther than this many view spacings from every view lies in a gap of
# the sampling: a set of views with nearest-neighbour spacing s leaves few points more
# than s from all of them, and rings or spirals of views (the demo's) up to about 2 s
# (95 % of the demo's second lobes that no view saw at half maximum are nearer).
GAP_SPACINGS = 2.0


def view_spacing(V: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n,) angular spacing (radians) of each texel's valid views: the median angle
    from a view to its nearest other view (pi where fewer than two). V (n, N, 3),
    W (n, N)."""
    G = np.matmul(V, V.transpose(0, 2, 1))
    G = np.where(W[:, :, None] & W[:, None, :], G, -1.0)
    N = V.shape[1]
    G[:, np.arange(N), np.arange(N)] = -1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # texels with fewer than 2 views
        c = np.nanmedian(np.where(W, G.max(2), np.nan), 1)
    return np.where(W.sum(1) >= 2, np.arccos(np.clip(np.nan_to_num(c, nan=-1.0), -1, 1)),
                    np.pi)


def _peak_observed(P: np.ndarray, V: np.ndarray, W: np.ndarray, k: int,
                   spacing: np.ndarray) -> np.ndarray:
    """(n,) bool: some view looked at lobe k's peak. The valid view nearest to its
    direction is within the lobe's half-maximum cone (``(d . v)^m >= 1/2``) or within
    :data:`GAP_SPACINGS` times the texel's ``spacing`` (:func:`view_spacing`): the
    peak lies among the sampled directions, not in a gap between them or beyond them.
    P (n, 4 + 6K), V (n, N, 3), W (n, N)."""
    c = np.where(W, np.einsum("nvj,nj->nv", V, P[:, mh_dir(k)]), -1.0).max(1)
    near = np.arccos(np.clip(c, -1, 1))
    half = np.arccos(0.5 ** (1.0 / np.maximum(P[:, MH_M], 1.0)))
    return near <= np.maximum(half, GAP_SPACINGS * spacing)


def drop_negligible_lobes(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                          floor: float = 1e-3) -> np.ndarray:
    """Write lobes the data do not support as absent, instead of noise.

    Two lobes that split one highlight between them are merged into one (Ks summed,
    direction weighted by strength); then a lobe is written as absent (Ks = 0, d = +z;
    m = 1 when no lobe is left) when the texel's data do not pay for it, or when fewer
    than :data:`MIN_SUPPORT` observations see it above twice the noise.
    Both use the criterion of ``auto`` (BIC): a change is made where ``n ln(RSS'/RSS)``
    stays below ``5 ln n`` (the five parameters a lobe costs), with the mean squared
    residual floored at ``(floor x mean radiance)^2`` as in :func:`bic`.

    Parameters
    ----------
    P : (n, 4 + 6K) fitted parameters; V, L : (n, N, 3) directions and radiance;
    W : (n, N) valid.
    """
    P = np.array(P, float, copy=True)
    K = mh_lobes(P.shape[1])
    if K == 0:
        return P
    w = W.astype(bool)[..., None]
    nres = 3 * np.maximum(W.sum(1), 1)
    fl = (floor * np.einsum("nvc,nv->n", np.abs(L), w[..., 0]) / nres) ** 2

    def rss(Q, rows):
        if rss_batch is not None:
            r2 = np.empty(len(Q))
            rss_batch(np.ascontiguousarray(Q), np.ascontiguousarray(V[rows], float),
                      np.ascontiguousarray(L[rows], float), np.ascontiguousarray(w[rows, :, 0]),
                      r2)
        else:
            r2 = (np.where(w[rows], mh_eval(Q, V[rows]) - L[rows], 0.0) ** 2).sum((1, 2))
        return np.maximum(r2, fl[rows] * nres[rows])

    pen = 5 * np.log(nres)
    # each texel's RSS kept current; a change is judged only where it can apply
    rssP = rss(P, slice(None))

    def take(Q, rows, also=None):
        """Take Q at the rows where BIC says the change costs nothing (or ``also``)."""
        if len(rows) == 0:
            return
        rq = rss(Q[rows], rows)
        ok = nres[rows] * np.log(rq / rssP[rows]) < pen[rows]
        if also is not None:
            ok |= also
        P[rows[ok]] = Q[rows[ok]]
        rssP[rows[ok]] = rq[ok]

    for k in range(K):
        for j in range(k + 1, K):
            a, b = mh_lobe(k), mh_lobe(j)
            wa = P[:, a][:, :3].sum(1, keepdims=True)
            wb = P[:, b][:, :3].sum(1, keepdims=True)
            d = P[:, a][:, 3:] * wa + P[:, b][:, 3:] * wb
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
            Q = P.copy()
            Q[:, a] = np.c_[P[:, a][:, :3] + P[:, b][:, :3], d]
            Q[:, b] = [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
            take(Q, np.flatnonzero((wa[:, 0] > 0) & (wb[:, 0] > 0)))
    for k in range(K):
        Q = P.copy()
        Q[:, mh_lobe(k)] = [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        rows = np.flatnonzero(P[:, mh_ks(k)].sum(1) > 0)
        # seen above twice the noise in fewer than MIN_SUPPORT observations, a lobe is
        # not determined by the data (a noise spike, a highlight that fell between
        # views) and would only sparkle in other views
        noise = np.sqrt(rssP[rows] / nres[rows])
        if lobe_support is not None:
            support = np.empty(len(rows), np.int64)
            lobe_support(np.ascontiguousarray(P[rows]), np.ascontiguousarray(V[rows], float),
                         np.ascontiguousarray(w[rows, :, 0]), k, 2 * noise, support)
        else:
            c = np.clip(np.einsum("nvj,nj->nv", V[rows], P[rows][:, mh_dir(k)]), 0, None) \
                ** P[rows, MH_M, None] * P[rows][:, mh_ks(k)].max(1, keepdims=True)
            support = (W[rows] & (c > 2 * noise[:, None])).sum(1)
        take(Q, rows, support < MIN_SUPPORT)
    # a lobe beside another whose peak lies where no view looked is placed by its tail
    # alone: with a lobe shape unlike the model's, the fit puts one in a gap between the
    # views (pbr-tiny's rough conductor: a second lobe about 40 deg from the first, as
    # strong, its nearest view 2-5 view spacings away), and a render there shows a
    # highlight the surface lacks. A texel keeps one such lobe, its strongest, if none
    # of its lobes was seen.
    on = np.stack([P[:, mh_ks(k)].sum(1) > 0 for k in range(K)], 1)
    rows = np.flatnonzero(on.sum(1) > 1)
    if len(rows):
        sp = view_spacing(V[rows], W[rows])
        gone = ~np.stack([_peak_observed(P[rows], V[rows], W[rows], k, sp)
                          for k in range(K)], 1) & on[rows]
        strength = np.stack([P[rows][:, mh_ks(k)].sum(1) for k in range(K)], 1)
        lone = ~(on[rows] & ~gone).any(1)
        first = np.argmax(np.where(on[rows], strength, -np.inf), 1)
        gone[lone, first[lone]] = False
        for k in range(K):
            P[rows[gone[:, k]], mh_lobe(k)] = [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    none = _lobes_present(P) == 0
    P[none, MH_M] = M_MIN
    return _sort_lobes_batch(P)


