"""Repair of MH \"stains\": texels stuck in a poor local minimum beside well-fitted
neighbours of the same material are refit from the neighbours' parameters; so are
texels that missed a lobe their neighbours found (a whole patch can miss a second
highlight, and then its neighbourhood median does not expose it)."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter

from ...conventions import MH_KD, MH_M, FitStatus, mh_dir, mh_dir_z, mh_ks, mh_lobes, mh_size
from ..residuals import mean_percentage_residual
from .fit import MhFitConfig, fit_texel
from .kernel import rescaled_batch
from .model import bic, mh_eval
from .uncertainty import parameter_sd

# A texel whose RMSE exceeds this many times the median of its neighbourhood is refit
# from its neighbours' parameters (the texels of one material share a minimum; a poor
# local minimum shows as a "stain" of high residual among well-fitted neighbours).
REPAIR_FACTOR = 3.0
REPAIR_RADIUS = 4  # neighbourhood (2r + 1)^2 = 9x9 texels
REPAIR_STARTS = 3  # well-fitted neighbours tried as starts, those that explain it best (8
# on the demo: the same held-out error and mean RMSE within 0.3 %, the fit 1.6x slower)
REPAIR_ROUNDS = 32  # a stain wider than the neighbourhood is repaired from its rim inwards


def _neighbourhood_median(e: np.ndarray, radius: int) -> np.ndarray:
    """Median of ``e`` (H, W) over each texel's (2r + 1)^2 window, NaN ignored."""
    from numpy.lib.stride_tricks import sliding_window_view

    pad = np.pad(e, radius, constant_values=np.nan)
    win = sliding_window_view(pad, (2 * radius + 1, 2 * radius + 1))
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(win.reshape(e.shape + (-1,)), -1)


def stains(rmse: np.ndarray, status: np.ndarray, factor: float = REPAIR_FACTOR,
           radius: int = REPAIR_RADIUS) -> np.ndarray:
    """Sizes (texels) of the connected blobs of texels whose RMSE (mean over channels)
    exceeds ``factor`` times the median of their (2 ``radius`` + 1)^2 neighbourhood,
    largest first: ``rmse`` (T, S, 3), ``status`` (T, S)."""
    from scipy.ndimage import label

    e = np.where(status == FitStatus.OK, np.nanmean(rmse, -1), np.nan)
    with np.errstate(invalid="ignore"):
        out = e > factor * _neighbourhood_median(e, radius)
    lab, n = label(out)
    return np.sort(np.bincount(lab.ravel())[1:])[::-1] if n else np.zeros(0, int)


def _rescaled_starts(P: np.ndarray, V: np.ndarray, L: np.ndarray, k: int) -> tuple[
        np.ndarray, np.ndarray]:
    """Neighbours' fits as starts for one texel: each keeps its shininess and lobe
    directions, and takes the Kd and Ks that fit the texel's own data best (linear
    least squares, clipped at zero; texels of one material differ in colour, not in
    lobe shape).

    Parameters
    ----------
    P : (c, 4 + 6K) candidate parameters (K >= k); V, L : (N, 3) the texel's data.

    Returns
    -------
    (c, 4 + 6k) starts and (c,) their residual sums of squares.
    """
    c = len(P)
    if rescaled_batch is not None:
        Q, rss = np.empty((c, mh_size(k))), np.empty(c)
        rescaled_batch(np.ascontiguousarray(P, float), np.ascontiguousarray(V, float),
                       np.ascontiguousarray(L, float), k, Q, rss)
        return Q, rss
    A = np.ones((c, len(V), 1 + k))
    for j in range(k):
        A[..., 1 + j] = np.clip(np.einsum("nc,ic->in", V, P[:, mh_dir(j)]), 0, None) \
            ** P[:, MH_M, None]
    # least squares by the normal equations of all candidates at once (a ridge of
    # 1e-12 of the trace for a lobe that no observation reaches), clipped at zero
    G = np.matmul(A.transpose(0, 2, 1), A)
    G += 1e-12 * np.trace(G, axis1=1, axis2=2)[:, None, None] * np.eye(1 + k)
    x = np.linalg.solve(G, np.matmul(A.transpose(0, 2, 1), L)).clip(min=0)  # (c, 1+k, 3)
    Q = np.array(P[:, : mh_size(k)], float, copy=True)
    Q[:, MH_KD] = x[:, 0]
    for j in range(k):
        Q[:, mh_ks(j)] = x[:, 1 + j]
    rss = ((np.einsum("inj,ijc->inc", A, x) - L) ** 2).sum((1, 2))
    return Q, rss


def repair_mh_tile(fields: dict[str, np.ndarray], radiance: np.ndarray,
                   direction: np.ndarray, valid: np.ndarray, offset: tuple[int, int], *,
                   K: int | str, cfg: MhFitConfig | None = None,
                   factor: float = REPAIR_FACTOR, radius: int = REPAIR_RADIUS,
                   starts: int = REPAIR_STARTS) -> dict[str, np.ndarray] | None:
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

    Parameters
    ----------
    fields : the fit store's arrays over the tile and its halo (params, rmse, mpr,
        k_used, evals, status).
    radiance, direction, valid : the tile's observations.
    offset : (row, col) of the tile in the halo arrays.

    Texels repaired in one round serve as starts in the next, up to
    :data:`REPAIR_ROUNDS` rounds: a stain larger than the neighbourhood raises the
    median that should expose it and has no good texel near its core.

    Returns
    -------
    None when nothing stands out; else the tile's arrays and ``changed`` (t, u) int8.
    """
    cfg = cfg or MhFitConfig()
    oy, ox = offset
    t, u = valid.shape[:2]
    sl = (slice(oy, oy + t), slice(ox, ox + u))
    # working copies over the halo: a texel repaired in one round is a start for the
    # next (a large stain is repaired from its rim inwards, and its shrinking lowers
    # the neighbourhood medians that hid its core)
    params = np.array(fields["params"], copy=True)
    status = np.array(fields["status"], copy=True)
    kused = np.array(fields["k_used"], copy=True)
    rmse = np.array(fields["rmse"], copy=True)
    out = {k: np.array(fields[k][sl]) for k in ("params", "rmse", "mpr", "sd", "k_used",
                                                "evals", "status") if k in fields}
    out["changed"] = np.zeros((t, u), np.int8)
    tried = np.zeros((t, u), bool)
    fresh = None  # texels changed in the last round: their neighbours are tried again
    for _ in range(REPAIR_ROUNDS):
        e = np.where(status == FitStatus.OK, np.nanmean(rmse, -1), np.nan)
        med = _neighbourhood_median(e, radius)
        with np.errstate(invalid="ignore"):
            outlier = e > factor * med
            good = (status == FitStatus.OK) & ~outlier
        todo = outlier[sl] & ~out["changed"].astype(bool)
        if fresh is not None:
            near_fresh = maximum_filter(fresh, 2 * radius + 1, mode="constant")[sl]
            todo &= near_fresh | ~tried
        todo |= _missed_lobes(params, kused, rmse, good, radiance, direction, valid,
                              offset, ~out["changed"].astype(bool) & ~todo
                              & (~tried if fresh is None else near_fresh | ~tried),
                              factor=factor, radius=radius, starts=starts)
        bad = np.argwhere(todo)
        if len(bad) == 0:
            break
        tried[todo] = True
        fresh = np.zeros(e.shape, bool)
        gy, gx = np.nonzero(good)
        for i, j in bad:
            r = _refit_from_neighbours(
                radiance[i, j], direction[i, j], valid[i, j], (i + oy, j + ox), params,
                kused, rmse, gy, gx, K=K, cfg=cfg, radius=radius, starts=starts)
            if r is None:
                continue
            p, k, evals, V, L = r
            out["evals"][i, j] += evals
            if p is None:
                continue
            fitted = mh_eval(p, V)
            out["params"][i, j] = params[i + oy, j + ox] = p
            out["k_used"][i, j] = kused[i + oy, j + ox] = k
            out["status"][i, j] = status[i + oy, j + ox] = FitStatus.OK
            out["rmse"][i, j] = rmse[i + oy, j + ox] = np.sqrt(((fitted - L) ** 2).mean(0))
            out["mpr"][i, j] = mean_percentage_residual(L, fitted)
            out["changed"][i, j] = 1
            fresh[i + oy, j + ox] = True
        if not fresh.any():
            break
    if "sd" in out and out["changed"].any():
        # the uncertainties of every repaired texel at once (nothing above reads them)
        ci, cj = np.nonzero(out["changed"])
        W = valid[ci, cj] & np.isfinite(radiance[ci, cj]).all(-1) \
            & np.isfinite(direction[ci, cj]).all(-1)
        V = np.where(W[..., None], direction[ci, cj], [0.0, 0.0, 1.0]).astype(float)
        L = np.where(W[..., None], radiance[ci, cj], 0.0).astype(float)
        out["sd"][ci, cj] = parameter_sd(out["params"][ci, cj].astype(float), V, L, W)
    return out if out["changed"].any() or tried.any() else None


def _missed_lobes(params: np.ndarray, kused: np.ndarray, rmse: np.ndarray,
                  good: np.ndarray, radiance: np.ndarray, direction: np.ndarray,
                  valid: np.ndarray, offset: tuple[int, int], check: np.ndarray, *,
                  factor: float, radius: int, starts: int) -> np.ndarray:
    """(t, u) texels of the tile (among ``check``) that missed a lobe their neighbours
    found: a well-fitted neighbour in the window with more lobes explains the texel's
    data, its shininess and directions kept and only Kd and Ks refit
    (:func:`_rescaled_starts`), with an RMSE ``factor`` times lower than the texel's own
    fit. Such a region (a second highlight that the K-lobe start missed over a whole
    patch) is a stain that the neighbourhood median does not expose, being itself
    poor there. Up to ``starts`` of the nearest such neighbours are tried."""
    oy, ox = offset
    out = np.zeros(check.shape, bool)
    H, Wd = good.shape
    # more lobes than the texel somewhere in its window: the only texels to look at
    more = maximum_filter(np.where(good, kused, -1), 2 * radius + 1, mode="constant",
                          cval=-1)
    cand = check & (more[oy:oy + check.shape[0], ox:ox + check.shape[1]]
                    > kused[oy:oy + check.shape[0], ox:ox + check.shape[1]])
    for i, j in np.argwhere(cand):
        at = (i + oy, j + ox)
        own = float(np.nanmean(rmse[at]))
        if not own > 0:
            continue
        r0, c0 = max(at[0] - radius, 0), max(at[1] - radius, 0)
        win = (slice(r0, min(at[0] + radius + 1, H)), slice(c0, min(at[1] + radius + 1, Wd)))
        ny, nx = np.nonzero(good[win] & (kused[win] > kused[at]))
        d = np.maximum(np.abs(ny + r0 - at[0]), np.abs(nx + c0 - at[1]))
        order = np.argsort(d, kind="stable")[:starts]
        ny, nx = ny[order] + r0, nx[order] + c0
        w = valid[i, j] & np.isfinite(radiance[i, j]).all(-1) \
            & np.isfinite(direction[i, j]).all(-1)
        if w.sum() < 4:
            continue
        V, L = direction[i, j][w].astype(float), radiance[i, j][w].astype(float)
        ks = kused[ny, nx].astype(int)
        best = min(float(_rescaled_starts(params[ny[ks == k], nx[ks == k]].astype(float),
                                          V, L, int(k))[1].min())
                   for k in np.unique(ks))
        out[i, j] = factor * np.sqrt(best / L.size) < own
    return out


def _refit_from_neighbours(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray,
                           at: tuple[int, int], params: np.ndarray, kused: np.ndarray,
                           rmse: np.ndarray, gy: np.ndarray, gx: np.ndarray, *,
                           K: int | str, cfg: MhFitConfig, radius: int, starts: int):
    """One texel of :func:`repair_mh_tile`: ``None`` when it has too few observations,
    else (params or None when no start did better, lobes, evaluations, V, L)."""
    w = valid & np.isfinite(radiance).all(-1) & np.isfinite(direction).all(-1)
    V, L = direction[w].astype(float), radiance[w].astype(float)
    n = len(V)
    if n < 4:
        return None
    Kmax = mh_lobes(params.shape[-1])
    floor = (cfg.bic_floor * float(np.mean(np.abs(L)))) ** 2
    k0 = int(kused[at]) if K == "auto" else int(K)
    rss0 = float(np.sum(rmse[at] ** 2) * n)
    crit0 = bic(rss0, L.size, k0, floor) if K == "auto" else rss0
    near = np.flatnonzero((np.abs(gy - at[0]) <= radius) & (np.abs(gx - at[1]) <= radius))
    ks = kused[gy[near], gx[near]].astype(int) if K == "auto" else np.full(len(near), int(K))
    best, evals = None, 0
    cands = []  # (rescaled criterion, lobes, start): the best ``starts`` of every count
    for k in np.unique(ks[ks >= 1]):
        sel = near[ks == k]
        Q, score = _rescaled_starts(params[gy[sel], gx[sel]].astype(float), V, L, int(k))
        crit = [bic(float(x), L.size, int(k), floor) if K == "auto" else float(x)
                for x in score]
        cands += [(crit[q], int(k), Q[q]) for q in range(len(Q))]
    cands.sort(key=lambda c: c[0])
    # every start converged by the compiled LM steps, the best of them polished by nlopt
    for _, k, q in cands[:starts]:
        r = fit_texel(V, L, q, cfg, polish=False)
        if r.status != FitStatus.OK:
            continue
        crit = bic(r.rss, L.size, k, floor) if K == "auto" else r.rss
        if best is None or crit < best[0]:
            best = (crit, r, k)
    if best is not None:
        _, r, k = best
        r = fit_texel(V, L, r.params, cfg)
        evals += r.evals
        best = None if r.status != FitStatus.OK else (
            bic(r.rss, L.size, k, floor) if K == "auto" else r.rss, r, k)
    margin = cfg.bic_margin if K == "auto" else 0.0
    if best is None or not best[0] < crit0 - margin:
        return None, 0, evals, V, L
    _, r, k = best
    p = np.zeros(mh_size(Kmax))
    p[: mh_size(k)] = r.params
    for extra in range(k, Kmax):
        p[mh_dir_z(extra)] = 1.0
    return p, k, evals, V, L
