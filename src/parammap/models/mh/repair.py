"""Repair of MH \"stains\": texels stuck in a poor local minimum beside well-fitted
neighbours of the same material are refit from the neighbours' parameters; so are
texels that missed a lobe their neighbours found (a whole patch can miss a second
highlight, and then its neighbourhood median does not expose it). Texels whose own
views leave the shininess undetermined take their neighbours'."""

from __future__ import annotations

import math
import warnings

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import label, maximum_filter
from scipy.stats import chi2

from ...conventions import (
    MH_KD,
    MH_M,
    FitArray,
    FitStatus,
    mh_dir,
    mh_dir_z,
    mh_ks,
    mh_lobes,
    mh_sd_dir,
    mh_size,
    mhx_size,
)
from ..residuals import mean_percentage_residual
from ..weights import noise_weights, reduced_chi2
from .model import bic, mh_eval, separate_lobes
from .optim import MhFitConfig, fit_texel, refine_batch
from .starts import rescaled_batch
from .uncertainty import loo_error, parameter_sd

# A texel whose RMSE exceeds this many times the median of its neighbourhood is refit
# from its neighbours' parameters (the texels of one material share a minimum; a poor
# local minimum shows as a "stain" of high residual among well-fitted neighbours).
REPAIR_FACTOR = 3.0
REPAIR_RADIUS = 4  # neighbourhood (2r + 1)^2 = 9x9 texels
REPAIR_STARTS = 3  # well-fitted neighbours tried as starts, those that explain it best (8
# on the demo: the same held-out error and mean RMSE within 0.3 %, the fit 1.6x slower)
REPAIR_ROUNDS = 32  # a stain wider than the neighbourhood is repaired from its rim inwards
# LM steps that rank a texel's starts (the best is then converged and polished): on
# the demo the same repaired RMSE as 60 steps to three digits, the repair 1.25x faster
RANK_ITERS = 20
# Shininess pooled from the neighbours (:func:`_pool_shininess`): a refit with m held
# at the pooled value is taken while its likelihood ratio against the texel's own fit
# stays below chi-square(1 dof) at 99 %, or where it predicts the texel's views left
# out at least as well; pulls below POOL_MIN_SHIFT in ln m (5 % in m) are not refitted;
# a window needs POOL_MIN_NEIGHBOURS texels with a lobe to say anything; no texel's sd
# of ln m counts below POOL_SD_FLOOR (a weight, not infinity).
POOL_LR = float(chi2.ppf(0.99, 1))
POOL_MIN_SHIFT = 0.05
POOL_MIN_NEIGHBOURS = 5
POOL_SD_FLOOR = 1e-3


def _neighbourhood_median(e: np.ndarray, radius: int, strip_elements: int = 1 << 22,
                          ) -> np.ndarray:
    """Median of ``e`` (H, W) over each texel's (2r + 1)^2 window, NaN ignored (NaN
    where the whole window is). Computed in strips of rows whose windows hold about
    ``strip_elements`` values: the whole map's windows at once took 2 KB a texel (8 GB
    for a 2048^2 map, in the fit's driver)."""
    H, W = e.shape
    w = 2 * radius + 1
    pad = np.pad(np.asarray(e, float), radius, constant_values=np.nan)
    out = np.empty((H, W))
    step = max(1, strip_elements // max(1, W * w * w))
    for r0 in range(0, H, step):
        r1 = min(H, r0 + step)
        win = sliding_window_view(pad[r0:r1 + 2 * radius], (w, w)).reshape(r1 - r0, W, -1)
        s = np.sort(win, -1)  # NaN sort last
        n = np.sum(~np.isnan(s), -1)
        lo = np.take_along_axis(s, np.maximum(n - 1, 0)[..., None] // 2, -1)[..., 0]
        hi = np.take_along_axis(s, (n // 2)[..., None], -1)[..., 0]
        out[r0:r1] = np.where(n > 0, 0.5 * (lo + hi), np.nan)
    return out


def stains(rmse: np.ndarray, status: np.ndarray, factor: float = REPAIR_FACTOR,
           radius: int = REPAIR_RADIUS) -> np.ndarray:
    """Sizes (texels) of the connected blobs of texels whose RMSE (mean over channels)
    exceeds ``factor`` times the median of their (2 ``radius`` + 1)^2 neighbourhood,
    largest first: ``rmse`` (T, S, 3), ``status`` (T, S)."""
    e = np.where(status == FitStatus.OK, np.nanmean(rmse, -1), np.nan)
    with np.errstate(invalid="ignore"):
        out = e > factor * _neighbourhood_median(e, radius)
    lab, n = label(out)
    return np.sort(np.bincount(lab.ravel())[1:])[::-1] if n else np.zeros(0, int)


def _window(at: np.ndarray, radius: int, shape: tuple[int, int], nearest_first: bool = False,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (2 ``radius`` + 1)^2 window around each of the points ``at`` (m, 2): rows and
    columns (m, w) clipped into ``shape``, and (m, w) whether each lies inside it. In
    raster order, or with ``nearest_first`` stably sorted by Chebyshev distance."""
    oy, ox = np.mgrid[-radius:radius + 1, -radius:radius + 1].reshape(2, -1)
    if nearest_first:
        order = np.argsort(np.maximum(np.abs(oy), np.abs(ox)), kind="stable")
        oy, ox = oy[order], ox[order]
    Y, X = at[:, :1] + oy, at[:, 1:] + ox
    inside = (Y >= 0) & (Y < shape[0]) & (X >= 0) & (X < shape[1])
    return Y.clip(0, shape[0] - 1), X.clip(0, shape[1] - 1), inside


def _bic(rss: np.ndarray, n: np.ndarray, k: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """:func:`bic` of many fits at once."""
    free = np.where(k == 0, 3, mhx_size(np.asarray(k)))
    return n * np.log(np.maximum(np.maximum(rss / n, floor), 1e-300)) + free * np.log(n)


def _rescaled_starts(P: np.ndarray, V: np.ndarray, L: np.ndarray, k: int,
                     owner: np.ndarray | None = None, W: np.ndarray | None = None,
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Neighbours' fits as starts for a texel: each keeps its shininess and lobe
    directions, and takes the Kd and Ks that fit the texel's own data best (linear
    least squares, clipped at zero; texels of one material differ in colour, not in
    lobe shape).

    Parameters
    ----------
    P : (c, 4 + 6K) candidate parameters (K >= k).
    V, L : (N, 3) the texel's data; or with ``owner`` (c,) the data of many texels,
        (T, N, 3), candidate i belonging to texel ``owner[i]``.
    W : (T, N) observation weights (0: not observed); default 1.

    Returns
    -------
    (c, 4 + 6k) starts and (c,) their (weighted) residual sums of squares.
    """
    c = len(P)
    if owner is None:
        V, L, owner = V[None], L[None], np.zeros(c, np.int64)
    W = np.ones(V.shape[:2]) if W is None else W
    if rescaled_batch is not None:
        Q, rss = np.empty((c, mh_size(k))), np.empty(c)
        rescaled_batch(np.ascontiguousarray(P, float), np.ascontiguousarray(owner, np.int64),
                       np.ascontiguousarray(V, float), np.ascontiguousarray(L, float),
                       np.ascontiguousarray(W, float), k, Q, rss)
        return Q, rss
    Vo, Lo, wo = V[owner], L[owner], W[owner][..., None]
    A = np.ones(Vo.shape[:2] + (1 + k,))
    for j in range(k):
        A[..., 1 + j] = np.clip(np.einsum("inc,ic->in", Vo, P[:, mh_dir(j)]), 0, None) \
            ** P[:, MH_M, None]
    # least squares by the normal equations of all candidates at once (a ridge of
    # 1e-12 of the trace for a lobe that no observation reaches), clipped at zero
    G = np.matmul(A.transpose(0, 2, 1), wo * A)
    G += 1e-12 * np.trace(G, axis1=1, axis2=2)[:, None, None] * np.eye(1 + k)
    x = np.linalg.solve(G, np.matmul(A.transpose(0, 2, 1), wo * Lo)).clip(min=0)
    Q = np.array(P[:, : mh_size(k)], float, copy=True)
    Q[:, MH_KD] = x[:, 0]
    for j in range(k):
        Q[:, mh_ks(j)] = x[:, 1 + j]
    rss = (wo * (np.einsum("inj,ijc->inc", A, x) - Lo) ** 2).sum((1, 2))
    return Q, rss


def _tile_data(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray,
               noise: np.ndarray | None = None,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tile's observations as (t u, N, 3) directions and radiance, and (t u, N)
    weights: the tile pass's (:func:`~parammap.models.weights.noise_weights` of
    ``noise`` (t, u, N), or 1), 0 where not valid (direction +z, radiance 0)."""
    t, u, N = valid.shape
    W = (valid & np.isfinite(radiance).all(-1) & np.isfinite(direction).all(-1)) \
        .reshape(t * u, N)
    V = np.where(W[..., None], direction.reshape(t * u, N, 3), [0.0, 0.0, 1.0])
    L = np.where(W[..., None], radiance.reshape(t * u, N, 3), 0.0)
    w = noise_weights(None if noise is None else noise.reshape(t * u, N), W)
    return V.astype(float), L.astype(float), np.where(W, w, 0.0).astype(float)


def repair_mh_tile(fields: dict[str, np.ndarray], radiance: np.ndarray,
                   direction: np.ndarray, valid: np.ndarray, offset: tuple[int, int], *,
                   K: int | str, cfg: MhFitConfig | None = None,
                   noise: np.ndarray | None = None,
                   factor: float = REPAIR_FACTOR, radius: int = REPAIR_RADIUS,
                   starts: int = REPAIR_STARTS, pool: bool = True, lobes: bool = True,
                   ) -> dict[str, np.ndarray] | None:
    """Refit the texels of a tile that stand out from their neighbourhood.

    A texel whose RMSE (mean over channels) exceeds ``factor`` times the median over its
    (2 ``radius`` + 1)^2 neighbourhood, or ``factor`` times what the lobes of a
    neighbour with more lobes give it (:func:`_missed_lobes`), is refit with nlopt from
    the parameters of the ``starts`` neighbours in that window that do not stand out
    and explain its data best once their colours are refit (:func:`_rescaled_starts`:
    the nearest texels may be of another material; for ``auto``, by BIC over every
    count of lobes together); the best fit replaces the texel's
    only if it is better (lower RSS, or for ``auto`` a BIC lower by ``cfg.bic_margin``),
    so a texel whose own data are good is never changed.

    Then, with ``pool``, texels whose own views leave m undetermined take their
    neighbours' (:func:`_pool_shininess`), and with ``lobes`` as well, their lobes'
    directions and Ks (:func:`_pool_lobes`).

    Texels repaired in one round serve as starts in the next, up to
    :data:`REPAIR_ROUNDS` rounds: a stain larger than the neighbourhood raises the
    median that should expose it and has no good texel near its core. A texel that
    still stands out is tried again whenever a neighbour changed, repaired before or
    not (the core of a stain, reached first from poor starts, was left stuck: on the
    demo a 10-texel blob of one lobe where its patch has two).

    Parameters
    ----------
    fields : the fit store's arrays over the tile and its halo (params, rmse, mpr,
        k_used, evals, status).
    radiance, direction, valid : the tile's observations.
    offset : (row, col) of the tile in the halo arrays.
    noise : (t, u, N) relative sd per observation: the refits weight the observations
        as the tile pass did (:func:`~parammap.models.weights.noise_weights`; RSS and
        BIC weighted alike), and ``chi2`` of a repaired texel is recomputed.

    Returns
    -------
    dict or None
        None when nothing stands out; else the tile's arrays and ``changed`` (t, u) int8.
    """
    cfg = cfg or MhFitConfig()
    oy, ox = offset
    t, u = valid.shape[:2]
    sl = (slice(oy, oy + t), slice(ox, ox + u))
    # working copies over the halo: a texel repaired in one round is a start for the
    # next (a large stain is repaired from its rim inwards, and its shrinking lowers
    # the neighbourhood medians that hid its core)
    params = np.array(fields[FitArray.PARAMS], copy=True)
    status = np.array(fields[FitArray.STATUS], copy=True)
    kused = np.array(fields[FitArray.K_USED], copy=True)
    rmse = np.array(fields[FitArray.RMSE], copy=True)
    out = {k: np.array(fields[k][sl])
           for k in (FitArray.PARAMS, FitArray.RMSE, FitArray.MPR, FitArray.CHI2, FitArray.SD,
                     FitArray.K_USED, FitArray.EVALS, FitArray.STATUS) if k in fields}
    out[FitArray.CHANGED] = np.zeros((t, u), np.int8)
    tried = np.zeros((t, u), bool)
    data = _tile_data(radiance, direction, valid, noise)
    NZ = None if noise is None else noise.reshape(t * u, -1)

    def take(i: int, j: int, p: np.ndarray, k: int) -> None:
        """Write a refit of the tile's texel (i, j) into the tile and the halo copies."""
        w = data[2][i * u + j] > 0
        V, L = data[0][i * u + j][w], data[1][i * u + j][w]
        fitted = mh_eval(p, V)
        out[FitArray.PARAMS][i, j] = params[i + oy, j + ox] = p
        out[FitArray.K_USED][i, j] = kused[i + oy, j + ox] = k
        out[FitArray.STATUS][i, j] = status[i + oy, j + ox] = FitStatus.OK
        out[FitArray.RMSE][i, j] = rmse[i + oy, j + ox] = np.sqrt(((fitted - L) ** 2).mean(0))
        out[FitArray.MPR][i, j] = mean_percentage_residual(L, fitted)
        if FitArray.CHI2 in out:
            out[FitArray.CHI2][i, j] = reduced_chi2(
                L[None], fitted[None], None if NZ is None else NZ[i * u + j][w][None],
                np.ones((1, len(L)), bool), mhx_size(k))[0]
        out[FitArray.CHANGED][i, j] = 1

    fresh = None  # texels changed in the last round: their neighbours are tried again
    for _ in range(REPAIR_ROUNDS):
        e = np.where(status == FitStatus.OK, np.nanmean(rmse, -1), np.nan)
        med = _neighbourhood_median(e, radius)
        with np.errstate(invalid="ignore"):
            outlier = e > factor * med
            good = (status == FitStatus.OK) & ~outlier
        # a texel (repaired or not) is tried again once a neighbour changed: a stain
        # repaired from its rim inwards reaches its core with poor starts first, and a
        # refit is taken only where it does better, so retrying never makes it worse
        todo = outlier[sl]
        if fresh is not None:
            near_fresh = maximum_filter(fresh, 2 * radius + 1, mode="constant")[sl]
            todo &= near_fresh | ~tried
        todo |= _missed_lobes(params, kused, rmse, good, data, offset,
                              ~todo & (~tried if fresh is None else near_fresh | ~tried),
                              factor=factor, radius=radius, starts=starts)
        bad = np.argwhere(todo)
        if len(bad) == 0:
            break
        tried[todo] = True
        fresh = np.zeros(e.shape, bool)
        refits = _refit_from_neighbours(data, bad, offset, u, params, kused, rmse, good,
                                        K=K, cfg=cfg, radius=radius, starts=starts)
        for (i, j), r in zip(bad, refits, strict=True):
            if r is None:
                continue
            p, k, evals = r
            out[FitArray.EVALS][i, j] += evals
            if p is None:
                continue
            take(i, j, p, k)
            fresh[i + oy, j + ox] = True
        if not fresh.any():
            break
    if FitArray.SD in out and out[FitArray.CHANGED].any():
        _update_sd(out, data, u, out[FitArray.CHANGED] > 0)
    if pool and FitArray.SD in out and FitArray.SD in fields:
        sd = np.array(fields[FitArray.SD], copy=True)
        sd[sl] = out[FitArray.SD]
        pooled = _pool_shininess(params, sd, kused, status, data, offset, (t, u), take,
                                 out, cfg=cfg, radius=radius)
        if pooled.any():
            _update_sd(out, data, u, pooled)
        if lobes:
            sd[sl] = out[FitArray.SD]
            tied = _pool_lobes(params, sd, kused, status, offset, (t, u), take,
                               radius=radius)
            if tied.any():
                _update_sd(out, data, u, tied)
    return out if out[FitArray.CHANGED].any() or tried.any() else None


def _update_sd(out: dict[str, np.ndarray], data: tuple[np.ndarray, np.ndarray, np.ndarray],
               width: int, which: np.ndarray) -> None:
    """The parameter uncertainties of the tile's texels ``which`` (t, u), all at once."""
    ci, cj = np.nonzero(which)
    b = ci * width + cj
    out[FitArray.SD][ci, cj] = parameter_sd(out[FitArray.PARAMS][ci, cj].astype(float), data[0][b],
                                     data[1][b], data[2][b] > 0, data[2][b])


def shininess_prior(lnm: np.ndarray, s: np.ndarray, use: np.ndarray, at: np.ndarray,
                    radius: int = REPAIR_RADIUS,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What each point's neighbours say of its ln m: a random-effects mean (DerSimonian
    and Laird 1986) over its (2 ``radius`` + 1)^2 window, itself left out.

    Each neighbour's ln m counts with weight 1 / (s^2 + tau^2): s its own sd (from its
    fit's Jacobian), tau^2 the spread between neighbours beyond their own noise, by the
    moments of the fixed-effect fit, after leaving out the neighbours far from the
    median (another material beside the patch). A window that
    straddles two materials evenly has a large tau^2, so its mean says little; one
    within a uniform patch says as much as its well-determined texels together.

    Parameters
    ----------
    lnm, s : (H, W) ln m and its sd (inf where undetermined); use : (H, W) bool, the
    texels that count (a lobe fitted); at : (n, 2) points (row, col).

    Returns
    -------
    (n,) prior mean, (n,) its variance for the point (tau^2 plus the mean's own), (n,)
    neighbours counted.
    """
    Y, X, inside = _window(at, radius, lnm.shape)
    ok = inside & use[Y, X] & np.isfinite(s[Y, X]) \
        & ~((Y == at[:, :1]) & (X == at[:, 1:]))
    x = np.where(ok, lnm[Y, X], 0.0)
    v = np.where(ok, np.maximum(s[Y, X], POOL_SD_FLOOR) ** 2, 1.0)
    # the material most of the window's texels belong to: neighbours far from their
    # median (beyond 3 sd of their own noise and of the window's robust spread) are
    # another material's and left out (a precision-weighted median would follow one
    # texel of exact data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a window with no neighbour
        centre = np.nanmedian(np.where(ok, x, np.nan), 1)
        dev = np.abs(x - centre[:, None])
        spread = 1.4826 * np.nanmedian(np.where(ok, dev, np.nan), 1)
    ok &= dev <= 3.0 * np.sqrt(v + np.nan_to_num(spread)[:, None] ** 2)
    w = np.where(ok, 1.0 / v, 0.0)
    k = ok.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sw = w.sum(1)
        fixed = (w * x).sum(1) / sw
        Q = (w * (x - fixed[:, None]) ** 2).sum(1)
        tau2 = np.maximum((Q - (k - 1)) / (sw - (w * w).sum(1) / sw), 0.0)
        ws = np.where(ok, 1.0 / (v + tau2[:, None]), 0.0)
        mean = (ws * x).sum(1) / ws.sum(1)
        var = tau2 + 1.0 / ws.sum(1)
    return mean, var, k


def _pool_shininess(params: np.ndarray, sd: np.ndarray, kused: np.ndarray,
                    status: np.ndarray, data: tuple[np.ndarray, np.ndarray, np.ndarray],
                    offset: tuple[int, int], shape: tuple[int, int], take, out: dict,
                    *, cfg: MhFitConfig, radius: int) -> np.ndarray:
    """Shininess its own views leave undetermined, taken from the neighbours.

    Where a lobe is narrower than the spacing of the views, one or two views see it and
    a texel's m is not determined by its own data (sd of ln m of 1 to 100 in the demo's
    m = 150 and 900 patches) and scatters around the patch's. Each texel's ln m is
    combined with what its neighbours say (:func:`shininess_prior`), each weighted by
    its precision: a texel whose own data determine m keeps it, an undetermined one
    takes the neighbours'. Where that moves m by more than :data:`POOL_MIN_SHIFT`, the
    texel is refit with m held there (where the move is also more than twice the sd of
    what the neighbours say), and the refit is taken only where its own data
    do not reject it: its likelihood ratio of one parameter fixed below
    :data:`POOL_LR` (99 %), or its leave-one-view-out error (PRESS) no larger than the
    texel's own fit's. The second is needed where a Phong lobe is fitted to a
    microfacet highlight: the few views near it carry the misfit, so the texel's own
    data always "prefer" their own m by the likelihood ratio, while the neighbours' m
    predicts each of its views left out as well or better (the texel's own fit must
    not rest on a view that alone determines it, whose PRESS is infinite). A prior
    that would bias a texel whose data are good is never applied.
    Returns (t, u) bool: the texels changed (``take(i, j, params, lobes)`` applied).
    """
    oy, ox = offset
    t, u = shape
    Vt, Lt, Wt = data
    m = params[..., MH_M].astype(float)
    Kmax = mh_lobes(params.shape[-1])
    ks = sum(np.nan_to_num(params[..., mh_ks(k)].astype(float)).sum(-1) for k in range(Kmax))
    use = (status == FitStatus.OK) & (kused >= 1) & (ks > 0) & np.isfinite(m) & (m > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        lnm = np.where(use, np.log(np.where(use, m, 1.0)), 0.0)
        s = np.where(use, sd[..., MH_M] / np.where(use, m, 1.0), np.inf)
    s = np.where(np.isfinite(s) & (s > 0), s, np.inf)
    changed = np.zeros((t, u), bool)
    ci, cj = np.nonzero(use[oy:oy + t, ox:ox + u])
    if len(ci) == 0:
        return changed
    at = np.stack([ci + oy, cj + ox], 1)
    mean, var, k = shininess_prior(lnm, s, use, at, radius)
    own, si = lnm[at[:, 0], at[:, 1]], s[at[:, 0], at[:, 1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        prec = np.where(np.isfinite(si), 1.0 / np.maximum(si, POOL_SD_FLOOR) ** 2, 0.0)
        post = (prec * own + mean / var) / (prec + 1.0 / var)
    # a move is made where it is larger than POOL_MIN_SHIFT and than twice the prior's
    # own sd: neighbours that disagree among themselves (a window across two materials)
    # say too little to move a texel by
    shift = np.abs(post - own)
    go = (k >= POOL_MIN_NEIGHBOURS) & np.isfinite(post) & (shift > POOL_MIN_SHIFT) \
        & (shift > 2.0 * np.sqrt(var))
    for n in np.flatnonzero(go):
        i, j = int(ci[n]), int(cj[n])
        b = i * u + j
        w = Wt[b] > 0
        V, L, wt = Vt[b][w], Lt[b][w], Wt[b][w]
        lobes = int(kused[i + oy, j + ox])
        p0 = np.array(params[i + oy, j + ox, : mh_size(lobes)], float)
        rss0 = float(np.sum(wt[:, None] * (mh_eval(p0, V) - L) ** 2))
        p0[MH_M] = math.exp(post[n])
        try:
            r = fit_texel(V, L, p0, cfg, w=wt, fixed_m=True)
        except Exception:  # noqa: BLE001 - the texel keeps its own fit
            continue
        out[FitArray.EVALS][i, j] += r.evals
        if r.status != FitStatus.OK:
            continue
        p = np.zeros(mh_size(Kmax))
        p[: mh_size(lobes)] = r.params
        for extra in range(lobes, Kmax):
            p[mh_dir_z(extra)] = 1.0
        lr = 3 * len(V) * math.log(max(r.rss, 1e-300) / max(rss0, 1e-300))
        if not (lr < POOL_LR or _predicts_better(params[i + oy, j + ox], p, V, L, wt)):
            continue
        take(i, j, p, lobes)
        changed[i, j] = True
    return changed


def _predicts_better(own: np.ndarray, pooled: np.ndarray, V: np.ndarray, L: np.ndarray,
                     wt: np.ndarray) -> bool:
    """Whether a texel's refit with m held at the neighbours' predicts each of its views
    left out (PRESS) at least as well as its own fit does, where neither view alone
    determines a parameter of its own fit."""
    one = np.ones((1, len(V)), bool)
    e_own, e_new = (loo_error(np.asarray(q, float)[None], V[None], L[None], one, wt[None],
                              fixed_m=f)[0] for q, f in ((own, False), (pooled, True)))
    return bool(np.isfinite(e_own) and e_new <= e_own)


def _pool_lobes(params: np.ndarray, sd: np.ndarray, kused: np.ndarray,
                status: np.ndarray, offset: tuple[int, int], shape: tuple[int, int], take,
                *, radius: int) -> np.ndarray:
    """Lobe directions its own views leave undetermined, taken from the neighbours.

    Where a highlight is narrower than the view spacing, a texel sees it in a few
    views and its lobe's direction scatters around its neighbours' (a render draws the
    highlight as salt and pepper). Under a light, the lobe direction is a smooth
    function of position whatever the material, so each of its components is combined
    with what the neighbours' same lobe says (:func:`shininess_prior`: a
    random-effects mean over the window), each weighted by its precision (the fit's own
    ``d_deg`` sd). The combined direction is taken where the texel's own data do not
    reject the neighbours' (their angle within the 99 % Wald bound of the two
    uncertainties, chi-square with 2 dof) and it moves the lobe by more than twice the
    neighbours' own sd and enough to change the lobe's value at its half width by
    :data:`POOL_MIN_SHIFT`; Kd, Ks and m stay the texel's. Only lobes that draw a
    highlight of their own (:func:`separate_lobes`). Returns (t, u) bool: the texels
    changed.

    Ks was pooled alike and not kept: without m moving with it (the two trade off
    where one view sees the highlight) the renders of pbr-tiny got worse.
    """
    oy, ox = offset
    t, u = shape
    Kmax = mh_lobes(params.shape[-1])
    changed = np.zeros((t, u), bool)
    ok = status == FitStatus.OK
    post = np.array(params[oy:oy + t, ox:ox + u], float)
    moved = np.zeros((t, u, Kmax), bool)
    wald = math.sqrt(float(chi2.ppf(0.99, 2)))
    # lobe k of a texel is compared with lobe k of the neighbours with as many lobes
    # (lobes are ordered by strength; with another count, the order means another lobe)
    counts = [(k, K) for K in range(1, Kmax + 1) for k in range(K)
              if mh_sd_dir(k) < sd.shape[-1]]
    alone = separate_lobes(params, kused)
    for k, K in counts:
        ks = np.nan_to_num(params[..., mh_ks(k)].astype(float)).sum(-1)
        d = params[..., mh_dir(k)].astype(float)
        s_d = np.radians(sd[..., mh_sd_dir(k)].astype(float))
        use = ok & (kused == K) & alone[..., k] & (ks > 0) & np.isfinite(d).all(-1) \
            & np.isfinite(s_d) & (s_d > 0)
        ci, cj = np.nonzero(use[oy:oy + t, ox:ox + u])
        if len(ci) == 0:
            continue
        at = np.stack([ci + oy, cj + ox], 1)
        s = np.where(use, s_d, np.inf)
        own, si = d[at[:, 0], at[:, 1]], s[at[:, 0], at[:, 1]]
        mean, var, n = zip(*(shininess_prior(d[..., a], s, use, at, radius) for a in range(3)),
                           strict=True)
        mean, var, n = np.stack(mean, 1), np.max(var, 0), np.min(n, 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            prec = 1.0 / np.maximum(si, POOL_SD_FLOOR) ** 2
            new = (prec[:, None] * own + mean / var[:, None]) / (prec + 1.0 / var)[:, None]
            new /= np.linalg.norm(new, axis=1, keepdims=True)
            mean_u = mean / np.linalg.norm(mean, axis=1, keepdims=True)
        # the neighbours' direction is taken where the texel's own data do not reject it
        # (angle within the 99 % Wald bound of both uncertainties) and it moves the lobe
        # by more than twice the neighbours' own sd and enough to change the lobe's
        # value at its half width (1 / sqrt(m) from its peak) by POOL_MIN_SHIFT
        apart = np.arccos(np.clip((own * mean_u).sum(1), -1, 1))
        moves = np.arccos(np.clip((own * new).sum(1), -1, 1))
        m = params[at[:, 0], at[:, 1], MH_M].astype(float)
        go = (n >= POOL_MIN_NEIGHBOURS) & np.isfinite(new).all(1) \
            & (apart < wald * np.sqrt(si * si + var)) & (moves > 2.0 * np.sqrt(var)) \
            & (moves * np.sqrt(np.maximum(m, 1.0)) > POOL_MIN_SHIFT)
        post[ci[go], cj[go], mh_dir(k)] = new[go]
        moved[ci[go], cj[go], k] = True
    for i, j in np.argwhere(moved.any(-1)):
        p = np.array(params[i + oy, j + ox], float)
        lobes = int(kused[i + oy, j + ox])
        p[: mh_size(lobes)] = post[i, j, : mh_size(lobes)]
        take(int(i), int(j), p, lobes)
        changed[i, j] = True
    return changed


def _missed_lobes(params: np.ndarray, kused: np.ndarray, rmse: np.ndarray,
                  good: np.ndarray, data: tuple[np.ndarray, np.ndarray, np.ndarray],
                  offset: tuple[int, int], check: np.ndarray, *,
                  factor: float, radius: int, starts: int) -> np.ndarray:
    """(t, u) texels of the tile (among ``check``) that missed a lobe their neighbours
    found: a well-fitted neighbour in the window with more lobes explains the texel's
    data, its shininess and directions kept and only Kd and Ks refit
    (:func:`_rescaled_starts`), with an RMSE ``factor`` times lower than the texel's own
    fit. Such a region (a second highlight that the K-lobe start missed over a whole
    patch) is a stain that the neighbourhood median does not expose, being itself
    poor there. Up to ``starts`` of the nearest such neighbours are tried. ``data``:
    the tile's observations (:func:`_tile_data`)."""
    oy, ox = offset
    t, u = check.shape
    out = np.zeros(check.shape, bool)
    H, Wd = good.shape
    # more lobes than the texel somewhere in its window: the only texels to look at
    more = maximum_filter(np.where(good, kused, -1), 2 * radius + 1, mode="constant",
                          cval=-1)
    cand = check & (more[oy:oy + t, ox:ox + u] > kused[oy:oy + t, ox:ox + u])
    nobs = (data[2] > 0).sum(1)
    ci, cj = np.nonzero(cand)
    at = np.stack([ci + oy, cj + ox], 1)
    with np.errstate(invalid="ignore"):
        own_at = np.nansum(rmse[at[:, 0], at[:, 1]], -1) \
            / np.isfinite(rmse[at[:, 0], at[:, 1]]).sum(-1)
    keep = (own_at > 0) & (nobs[ci * u + cj] >= 4)
    at, rows = at[keep], (ci * u + cj)[keep]
    # up to ``starts`` of the nearest well-fitted neighbours with more lobes
    Y, X, inside = _window(at, radius, good.shape, nearest_first=True)
    use = inside & good[Y, X] & (kused[Y, X] > kused[at[:, 0], at[:, 1]][:, None])
    use &= np.cumsum(use, 1) <= starts
    e, o = np.nonzero(use)
    ny, nx = Y[e, o], X[e, o]
    best = np.full(t * u, np.inf)
    for k in np.unique(kused[ny, nx]):
        m = kused[ny, nx] == k
        _, rss = _rescaled_starts(params[ny[m], nx[m]].astype(float), data[0], data[1],
                                  int(k), owner=rows[e[m]], W=data[2])
        np.minimum.at(best, rows[e[m]], rss)
    own = np.nanmean(rmse[oy:oy + t, ox:ox + u], -1).ravel()
    with np.errstate(invalid="ignore", divide="ignore"):
        hit = np.isfinite(best) & (factor * np.sqrt(best / (3 * np.maximum(nobs, 1))) < own)
    out.ravel()[:] = hit
    return out


def _refit_from_neighbours(data: tuple[np.ndarray, np.ndarray, np.ndarray],
                           bad: np.ndarray, offset: tuple[int, int], width: int,
                           params: np.ndarray,
                           kused: np.ndarray, rmse: np.ndarray, good: np.ndarray,
                           *, K: int | str, cfg: MhFitConfig, radius: int,
                           starts: int) -> list:
    """The refits of one round of :func:`repair_mh_tile`, for the tile's texels ``bad``
    (b, 2) of a tile ``width`` texels across (``data``: :func:`_tile_data`): per texel
    ``None`` when it has too few observations, else (params or None
    when no start did better, lobes, evaluations). The ``starts`` best rescaled starts
    of every texel are converged by the compiled LM in one batch per count of lobes,
    and each texel's best is polished by nlopt."""
    Vt, Lt, Wt = data
    oy, ox = offset
    Kmax = mh_lobes(params.shape[-1])
    res: list = [None] * len(bad)
    rows = bad[:, 0] * width + bad[:, 1]
    n = (Wt[rows] > 0).sum(1)
    ents = np.flatnonzero(n >= 4)
    for e in ents:
        res[e] = (None, 0, 0)
    rows, n = rows[ents], n[ents]
    at = bad[ents] + (oy, ox)
    size = 3 * n
    floor = (cfg.bic_floor * np.abs(Lt[rows] * (Wt[rows, :, None] > 0)).sum((1, 2))
             / np.maximum(size, 1)) ** 2
    k0 = kused[at[:, 0], at[:, 1]].astype(int) if K == "auto" else np.full(len(at), int(K))
    # the current fit's RSS weighted as every refit's (the tile pass's weights)
    r0 = mh_eval(params[at[:, 0], at[:, 1]].astype(float), Vt[rows]) - Lt[rows]
    rss0 = (Wt[rows][..., None] * r0 ** 2).sum((1, 2))
    crit0 = _bic(rss0, size, k0, floor) if K == "auto" else rss0
    # every well-fitted texel of the window, its shininess and lobes kept and its
    # colours refit (one batch per count of lobes); each texel keeps its ``starts`` best
    Y, X, inside = _window(at, radius, good.shape)
    ks = kused[Y, X].astype(int) if K == "auto" else np.full(Y.shape, int(K))
    e, o = np.nonzero(inside & good[Y, X] & (ks >= 1))
    ny, nx, nk = Y[e, o], X[e, o], ks[e, o]
    cand_e, cand_k, cand_crit, cand_q = [], [], [], []
    for k in np.unique(nk):
        m = nk == k
        Q, score = _rescaled_starts(params[ny[m], nx[m]].astype(float), Vt, Lt, int(k),
                                    owner=rows[e[m]], W=Wt)
        cand_e.append(e[m])
        cand_k.append(np.full(int(m.sum()), int(k)))
        cand_crit.append(_bic(score, size[e[m]], k, floor[e[m]]) if K == "auto" else score)
        cand_q += list(Q)
    runs: dict[int, tuple[list, list]] = {}  # lobes -> (entries of bad, starts)
    if cand_q:
        ce, ck, cc = (np.concatenate(x) for x in (cand_e, cand_k, cand_crit))
        order = np.lexsort((np.arange(len(ce)), cc, ce))
        first = np.r_[0, np.flatnonzero(np.diff(ce[order])) + 1]
        rank = np.arange(len(order)) - np.repeat(first, np.diff(np.r_[first, len(order)]))
        for c in order[rank < starts]:
            who, P0 = runs.setdefault(int(ck[c]), ([], []))
            who.append(int(ents[ce[c]]))
            P0.append(cand_q[c])
    info = {int(ents[i]): (int(rows[i]), int(size[i]), float(floor[i]), float(crit0[i]))
            for i in range(len(ents))}
    # every start converged by the compiled LM steps in one batch per count of lobes
    best: dict[int, tuple[float, np.ndarray, int, bool]] = {}
    for k, (who, P0) in runs.items():
        rows = np.array([info[e][0] for e in who])
        P, conv = refine_batch(Vt[rows], Lt[rows], Wt[rows], np.array(P0), why=True,
                               iters=RANK_ITERS)
        rss = (Wt[rows][..., None] * (mh_eval(P, Vt[rows]) - Lt[rows]) ** 2).sum((1, 2))
        for e, p, x, c in zip(who, P, rss, conv, strict=True):
            _, size, floor, _ = info[e]
            if not (np.all(np.isfinite(p)) and np.isfinite(x)):
                continue
            crit = bic(float(x), size, k, floor) if K == "auto" else float(x)
            if e not in best or crit < best[e][0]:
                best[e] = (crit, p, k, bool(c))
    margin = cfg.bic_margin if K == "auto" else 0.0
    for e, (_, p0, k, conv) in best.items():
        b, size, floor, crit0 = info[e]
        w = Wt[b] > 0
        r = fit_texel(Vt[b][w], Lt[b][w], p0, cfg, w=Wt[b][w], lm=not conv)
        if r.status != FitStatus.OK:
            res[e] = (None, 0, r.evals)
            continue
        crit = bic(r.rss, size, k, floor) if K == "auto" else r.rss
        if not crit < crit0 - margin:
            res[e] = (None, 0, r.evals)
            continue
        p = np.zeros(mh_size(Kmax))
        p[: mh_size(k)] = r.params
        for extra in range(k, Kmax):
            p[mh_dir_z(extra)] = 1.0
        res[e] = (p, k, r.evals)
    return res
