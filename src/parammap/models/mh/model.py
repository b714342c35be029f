"""The MH model itself: evaluation, metrics, the fitters' x space and lobe order.

``L_c(v) = Kd_c + sum_k Ks_kc * max(0, d_k . v) ** m`` per RGB channel, K lobes sharing
one shininess m (000 eq. 1, 004 eq. 11.2); the parameter layout is
:mod:`parammap.conventions` (``mh_*``).
"""

from __future__ import annotations

import math

import numpy as np

from ...conventions import (
    MH_KD,
    MH_M,
    MHX_KD,
    MHX_LNM,
    mh_dir,
    mh_ks,
    mh_lobes,
    mh_size,
    mhx_ks,
    mhx_lobes,
    mhx_phi,
    mhx_size,
    mhx_theta,
)
from ...errors import InputError
from ..weights import reduced_chi2
from .kernel import eval_batch

M_MIN, M_MAX = 1.0, 10000.0
LN_M_MAX = math.log(M_MAX)
# A lobe draws a highlight of its own when its peak is farther from every other lobe of
# the texel than this many half widths at half maximum (their half-maximum regions
# apart). Lobes nearer together draw one highlight that is not a Phong lobe, and no one
# of their directions is the light's.
LOBE_SEPARATION = 2.0


def mh_eval(params: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Evaluate MH parameter vectors.

    Parameters
    ----------
    params : (..., 4 + 6K) docs/reference/conventions.md layout.
    directions : (..., N, 3) unit view directions, surface frame.

    Returns
    -------
    (..., N, 3) radiance.
    """
    params = np.asarray(params, float)
    v = np.asarray(directions, float)
    if eval_batch is not None and params.ndim == 2 and v.ndim == 3 \
            and len(params) == len(v) and v.shape[2] == 3:
        out = np.empty(v.shape)
        eval_batch(np.ascontiguousarray(params), np.ascontiguousarray(v), out)
        return out
    K = mh_lobes(params.shape[-1])
    out = np.broadcast_to(params[..., None, MH_KD], v.shape).copy()
    m = params[..., MH_M][..., None]
    for k in range(K):
        ks = params[..., mh_ks(k)]
        d = params[..., mh_dir(k)]
        c = np.clip(np.einsum("...nc,...c->...n", v, d), 0.0, None)
        out += (c ** m)[..., None] * ks[..., None, :]
    return out


def bic(rss: float, n: int, K: int, floor: float = 0.0) -> float:
    """Bayesian information criterion of a K-lobe fit with ``n`` residuals (d has two
    degrees of freedom, so 4 + 5K free parameters). ``floor`` is the smallest mean
    squared residual taken as real: below it (noise-free data) extra lobes only fit
    round-off, which must not count as evidence."""
    k = 3 if K == 0 else mhx_size(K)  # K = 0: Kd alone (no shininess to fit)
    return n * math.log(max(rss / n, floor, 1e-300)) + k * math.log(n)



def _angles(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.arccos(np.clip(d[..., 2], -1, 1)), np.arctan2(d[..., 1], d[..., 0])



def _params_to_x_batch(P: np.ndarray, s: np.ndarray) -> np.ndarray:
    B = P.shape[0]
    K = mh_lobes(P.shape[1])
    X = np.empty((B, mhx_size(K)))
    X[:, MHX_KD] = P[:, MH_KD] / s[:, None]
    X[:, MHX_LNM] = np.log(np.clip(P[:, MH_M], M_MIN, M_MAX))
    for k in range(K):
        X[:, mhx_ks(k)] = P[:, mh_ks(k)] / s[:, None]
        X[:, mhx_theta(k)], X[:, mhx_phi(k)] = _angles(P[:, mh_dir(k)])
    return X


def _x_to_params_batch(X: np.ndarray, s: np.ndarray) -> np.ndarray:
    B = X.shape[0]
    K = mhx_lobes(X.shape[1])
    P = np.empty((B, mh_size(K)))
    P[:, MH_KD] = X[:, MHX_KD] * s[:, None]
    P[:, MH_M] = np.exp(X[:, MHX_LNM])
    for k in range(K):
        th, ph = X[:, mhx_theta(k)], X[:, mhx_phi(k)]
        P[:, mh_ks(k)] = X[:, mhx_ks(k)] * s[:, None]
        P[:, mh_dir(k)] = np.stack(
            [np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    return P



def _to_x(p: np.ndarray, s: float) -> np.ndarray:
    K = mh_lobes(len(p))
    x = np.empty(mhx_size(K))
    x[MHX_KD] = p[MH_KD] / s
    x[MHX_LNM] = math.log(min(max(p[MH_M], M_MIN), M_MAX))
    for k in range(K):
        x[mhx_ks(k)] = p[mh_ks(k)] / s
        # scalar math: this runs once per texel fit, where numpy's per-call cost dominates
        dx, dy, dz = (float(c) for c in p[mh_dir(k)])
        n = math.sqrt(dx * dx + dy * dy + dz * dz)
        x[mhx_theta(k)] = math.acos(min(max(dz / n, -1.0), 1.0))
        x[mhx_phi(k)] = math.atan2(dy, dx)
    return x


def _from_x(x: np.ndarray, s: float) -> np.ndarray:
    K = (len(x) - 4) // 5
    p = np.empty(mh_size(K))
    p[MH_KD] = x[MHX_KD] * s
    p[MH_M] = math.exp(x[MHX_LNM])
    for k in range(K):
        p[mh_ks(k)] = x[mhx_ks(k)] * s
        th, ph = x[mhx_theta(k)], x[mhx_phi(k)]
        p[mh_dir(k)] = (math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph),
                                    math.cos(th))
    return p



def _sort_lobes(p: np.ndarray) -> np.ndarray:
    K = mh_lobes(len(p))
    if K < 2:
        return p
    lobes = p[4:].reshape(K, 6)
    order = np.argsort(-lobes[:, :3].sum(1), kind="stable")
    out = p.copy()
    out[4:] = lobes[order].ravel()
    return out



def _lobes_present(P: np.ndarray) -> np.ndarray:
    """(n,) number of lobes with a non-zero Ks in parameter rows P (n, 4 + 6K)."""
    K = mh_lobes(P.shape[1])
    return sum((P[:, mh_ks(k)].sum(1) > 0).astype(int) for k in range(K))


def _sort_lobes_batch(P: np.ndarray) -> np.ndarray:
    return np.array([_sort_lobes(p) for p in P]) if len(P) else P


def parse_lobes(K: str | int) -> int | str:
    """``"auto"`` or a positive lobe count from a model name part."""
    if str(K) == "auto":
        return "auto"
    try:
        k = int(K)
    except ValueError:
        k = 0
    if k < 1:
        raise InputError(f"MH lobes must be a positive integer or auto (got {K!r})")
    return k


def separate_lobes(params: np.ndarray, kused: np.ndarray) -> np.ndarray:
    """(H, W, Kmax) bool: lobe k of each texel draws a highlight of its own, its direction
    more than :data:`LOBE_SEPARATION` half widths at half maximum (``acos(2^(-1/m))``
    for the texel's shininess m) from each other lobe the texel uses."""
    Kmax = mh_lobes(params.shape[-1])
    m = np.maximum(np.nan_to_num(params[..., MH_M].astype(float)), 1.0)
    hwhm = np.arccos(np.power(0.5, 1.0 / m))
    d = np.stack([np.nan_to_num(params[..., mh_dir(k)].astype(float)) for k in range(Kmax)], -2)
    cos = np.clip(np.einsum("...kc,...lc->...kl", d, d), -1.0, 1.0)
    near = np.arccos(cos) <= LOBE_SEPARATION * hwhm[..., None, None]
    used = np.arange(Kmax) < kused[..., None]
    near &= used[..., None, :] & ~np.eye(Kmax, dtype=bool)
    return used & ~near.any(-1)


def _peak(P: np.ndarray) -> np.ndarray:
    """(n,) the largest luminance (sum over channels) MH parameters P (n, 4 + 6K) draw at
    their lobes' peaks above the horizon (lobes of one width peak there, or between
    peaks no higher than the largest); 0 where none."""
    K = mh_lobes(P.shape[-1])
    if K == 0:
        return np.zeros(len(P))
    d = np.stack([P[:, mh_dir(k)] for k in range(K)], 1)
    ks = np.stack([P[:, mh_ks(k)].sum(-1) for k in range(K)], 1)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    up = (d[..., 2] > 0) & (ks > 0) & (norm[..., 0] > 0)
    d = np.where(up[..., None], d / np.where(norm > 0, norm, 1.0), [0.0, 0.0, 1.0])
    return np.where(up, mh_eval(P, d).sum(-1), 0.0).max(1)


def overshoots(alts: list[np.ndarray], V: np.ndarray, L: np.ndarray, W: np.ndarray,
               noise: np.ndarray | None) -> np.ndarray:
    """(len(alts) - 1, n): whether each fit with more lobes than the first (``alts``:
    (n, 4 + 6K) padded parameters, fewest lobes first, NaN where that fit failed) leaves
    more than the noise unexplained and draws a highlight brighter than anything the
    texel's views (V (n, N, 3), L (n, N, 3), W (n, N) bool; ``noise`` (n, N) their
    relative sd) saw and than the fewest lobes draw, by more than three of its own RMS
    residuals (luminance).

    Such a peak lies between the views, and no view tells its height. Where the lobes
    explain the views to their noise (reduced chi-square within three of its sd of 1),
    the highlight is a Phong lobe's and its height follows from the lobes' shape, as a
    real highlight between views does (two lights, a sharp lobe). Where they do not (a
    microfacet highlight, peak and tail, drawn as several Phong lobes), the lobes
    describe a shape that is not theirs: a lobe whose flank alone the views see takes
    the texel's one shininess, fitted to another lobe, and lobes side by side can sum
    to a spike. Neither the residuals nor a left-out view sees it; it differs from
    texel to texel, and a render draws it as salt-and-pepper speckle. Fewer lobes
    through the same views extrapolate the highlight by their shape alone. With the
    noise unknown, nothing is judged.
    """
    out = np.zeros((len(alts) - 1, len(V)), bool)
    if noise is None:
        return out
    y = np.where(W, L.sum(-1), -np.inf)
    ref = np.maximum(y.max(1), _peak(np.nan_to_num(alts[0])))
    n = np.maximum(W.sum(1), 1)
    for i, P in enumerate(alts[1:]):
        Q = np.nan_to_num(P)
        fitted = mh_eval(Q, V)
        r = np.where(W, fitted.sum(-1) - np.where(W, L.sum(-1), 0.0), 0.0)
        rmse = np.sqrt((r * r).sum(1) / n)
        k = (np.stack([Q[:, mh_ks(j)].sum(-1) for j in range(mh_lobes(Q.shape[-1]))], 1)
             > 0).sum(1)
        free = mhx_size(k)
        dof = np.maximum(3 * W.sum(1) - free, 1)
        with np.errstate(divide="ignore", invalid="ignore"):  # a failed fit's zeros
            misfit = reduced_chi2(L, fitted, noise, W, free) > 1.0 + 3.0 * np.sqrt(2.0 / dof)
        out[i] = np.isfinite(P).all(1) & misfit & (_peak(Q) > ref + 3.0 * rmse)
    return out
