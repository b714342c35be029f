"""Repair of MH \"stains\": texels stuck in a poor local minimum beside well-fitted
neighbours of the same material are refit from the neighbours' parameters."""

from __future__ import annotations

import numpy as np

from ...conventions import FitStatus, mh_dir_z, mh_lobes, mh_size
from ..residuals import mean_percentage_residual
from .fit import MhFitConfig, fit_texel
from .model import bic, mh_eval
from .uncertainty import parameter_sd

# A texel whose RMSE exceeds this many times the median of its neighbourhood is refit
# from its neighbours' parameters (the texels of one material share a minimum; a poor
# local minimum shows as a "stain" of high residual among well-fitted neighbours).
REPAIR_FACTOR = 3.0
REPAIR_RADIUS = 4  # neighbourhood (2r + 1)^2 = 9x9 texels
REPAIR_STARTS = 8  # nearest well-fitted neighbours tried as starts


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


def repair_mh_tile(fields: dict[str, np.ndarray], radiance: np.ndarray,
                   direction: np.ndarray, valid: np.ndarray, offset: tuple[int, int], *,
                   K: int | str, cfg: MhFitConfig | None = None,
                   factor: float = REPAIR_FACTOR, radius: int = REPAIR_RADIUS,
                   starts: int = REPAIR_STARTS) -> dict[str, np.ndarray] | None:
    """Refit the texels of a tile that stand out from their neighbourhood.

    A texel whose RMSE (mean over channels) exceeds ``factor`` times the median over its
    (2 ``radius`` + 1)^2 neighbourhood is refit with nlopt from the parameters of up to
    ``starts`` nearest neighbours that do not stand out; the best fit replaces the texel's
    only if it is better (lower RSS, or for ``auto`` a BIC lower by ``cfg.bic_margin``),
    so a texel whose own data are good is never changed.

    Parameters
    ----------
    fields : the fit store's arrays over the tile and its halo (params, rmse, mpr,
        k_used, evals, status).
    radiance, direction, valid : the tile's observations.
    offset : (row, col) of the tile in the halo arrays.

    Returns
    -------
    None when nothing stands out; else the tile's arrays and ``changed`` (t, u) int8.
    """
    cfg = cfg or MhFitConfig()
    params, status, kused = fields["params"], fields["status"], fields["k_used"]
    e = np.where(status == FitStatus.OK, np.nanmean(fields["rmse"], -1), np.nan)
    med = _neighbourhood_median(e, radius)
    with np.errstate(invalid="ignore"):
        outlier = e > factor * med
        good = (status == FitStatus.OK) & ~outlier
    oy, ox = offset
    t, u = valid.shape[:2]
    sl = (slice(oy, oy + t), slice(ox, ox + u))
    bad = np.argwhere(outlier[sl])
    if len(bad) == 0:
        return None
    out = {k: np.array(fields[k][sl]) for k in ("params", "rmse", "mpr", "sd", "k_used",
                                                "evals", "status") if k in fields}
    out["changed"] = np.zeros((t, u), np.int8)
    gy, gx = np.nonzero(good)
    Kmax = mh_lobes(params.shape[-1])
    for i, j in bad:
        w = valid[i, j] & np.isfinite(radiance[i, j]).all(-1) & np.isfinite(direction[i, j]).all(-1)
        V, L = direction[i, j][w].astype(float), radiance[i, j][w].astype(float)
        n = len(V)
        if n < 4:
            continue
        floor = (cfg.bic_floor * float(np.mean(np.abs(L)))) ** 2
        k0 = int(kused[i + oy, j + ox]) if K == "auto" else int(K)
        rss0 = float(np.sum(fields["rmse"][i + oy, j + ox] ** 2) * n)
        crit0 = bic(rss0, L.size, k0, floor) if K == "auto" else rss0
        d2 = (gy - (i + oy)) ** 2 + (gx - (j + ox)) ** 2
        near = np.argsort(d2, kind="stable")[:starts]
        best = None
        for q in near:
            a, b = gy[q], gx[q]
            k = int(kused[a, b]) if K == "auto" else int(K)
            if k < 1:
                continue
            r = fit_texel(V, L, params[a, b, :mh_size(k)].astype(float), cfg)
            out["evals"][i, j] += r.evals
            if r.status != FitStatus.OK:
                continue
            crit = bic(r.rss, L.size, k, floor) if K == "auto" else r.rss
            if best is None or crit < best[0]:
                best = (crit, r, k)
        margin = cfg.bic_margin if K == "auto" else 0.0
        if best is None or not best[0] < crit0 - margin:
            continue
        _, r, k = best
        p = np.zeros(mh_size(Kmax))
        p[: mh_size(k)] = r.params
        for extra in range(k, Kmax):
            p[mh_dir_z(extra)] = 1.0
        fitted = mh_eval(p, V)
        out["params"][i, j] = p
        out["k_used"][i, j] = k
        out["status"][i, j] = FitStatus.OK
        out["rmse"][i, j] = np.sqrt(((fitted - L) ** 2).mean(0))
        out["mpr"][i, j] = mean_percentage_residual(L, fitted)
        if "sd" in out:
            out["sd"][i, j] = parameter_sd(p[None], V[None], L[None],
                                           np.ones((1, len(V)), bool))[0]
        out["changed"][i, j] = 1
    return out


