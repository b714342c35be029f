"""Initial guesses of the MH fit: linear solves for Kd and Ks, a search over m and
the lobe directions (ours), and the published guess of 004 ch. 11.2."""

from __future__ import annotations

import math

import numpy as np

from ...conventions import MH_KD, MH_M, mh_dir, mh_ks, mh_lobes, mh_size
from .kernel import gram
from .model import LN_M_MAX, mh_eval
from .starts import initial_batch


def _nnls_batch(A: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Non-negative weighted least squares for many small problems at once.

    A : (B, N, P) design shared by the three channels, y : (B, N, 3), w : (B, N)
    weights. Active set by repeatedly pinning the most negative coefficient to zero
    (exact for P <= 2, close otherwise). Works on the normal equations only.
    Returns coefficients (B, P, 3) and RSS (B,).
    """
    B, N, P = A.shape
    G, rhs, yy = gram(A, y, w)  # rhs (B, 3, P)
    active = np.ones((B, 3, P), bool)
    eye = np.eye(P)
    ridge = 1e-12 * np.trace(G, axis1=1, axis2=2)[:, None, None, None] * eye
    for _ in range(P + 1):
        mask = active[..., :, None] & active[..., None, :]
        Gm = G[:, None] * mask + eye * (~active)[..., None] + ridge
        x = np.linalg.solve(Gm, (rhs * active)[..., None])[..., 0]  # (B, 3, P)
        neg = x < -1e-15
        if not neg.any():
            break
        worst = np.argmin(np.where(neg, x, 0), axis=2)
        bi, ci = np.nonzero(neg.any(axis=2))
        active[bi, ci, worst[bi, ci]] = False
    x = np.clip(x, 0, None) * active
    rss = yy - 2 * (x * rhs).sum((1, 2)) + (np.matmul(x, G) * x).sum((1, 2))
    return np.moveaxis(x, 1, 2), np.maximum(rss, 0.0)


def _log_cos(V: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(B, N, K) ln max(0, d_k . v), -inf where the lobe does not reach."""
    c = np.matmul(V, D.transpose(0, 2, 1))
    with np.errstate(divide="ignore"):
        return np.where(c > 0, np.log(np.maximum(c, 1e-300)), -np.inf)


def _solve_linear_lc(lnc, L, W, m):
    B, N, _ = lnc.shape
    m = m.astype(lnc.dtype)
    A = np.concatenate([np.ones((B, N, 1), lnc.dtype), np.exp(lnc * m[:, None, None])], axis=2)
    return _nnls_batch(A, L, W)


def _solve_linear(V, L, W, D, m):
    return _solve_linear_lc(_log_cos(V, D), L, W, m)


def _lobe_terms(V: np.ndarray, D: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(B, N, K) = max(0, d_k . v) ** m for directions D (B, K, 3) and m (B,)."""
    return np.exp(_log_cos(V, D) * m[:, None, None])


M_GRID = 8  # points of the grid over ln m in [0, ln M_MAX]
M_GOLDEN = 3  # golden-section steps in the best grid bracket


def _search_m(V, L, W, D, iters: int = M_GOLDEN) -> np.ndarray:
    """Shininess per texel minimising the RSS after the linear solve: a coarse grid over
    ln m, then golden-section search in the best bracket (001)."""
    B = V.shape[0]
    lnc = _log_cos(V, D)
    grid = np.linspace(0.0, LN_M_MAX, M_GRID)
    rss = np.stack([_solve_linear_lc(lnc, L, W, np.full(B, math.exp(u)))[1] for u in grid], 1)
    k = np.argmin(rss, axis=1)
    lo = grid[np.maximum(k - 1, 0)]
    hi = grid[np.minimum(k + 1, len(grid) - 1)]
    g = (math.sqrt(5) - 1) / 2

    def f(u):
        return _solve_linear_lc(lnc, L, W, np.exp(u))[1]

    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iters):
        left = fc < fd  # the minimum lies in [a, d]
        a, b = np.where(left, a, c), np.where(left, d, b)
        c_new = np.where(left, b - g * (b - a), d)
        d_new = np.where(left, c, a + g * (b - a))
        fe = f(np.where(left, c_new, d_new))
        fc, fd = np.where(left, fe, fd), np.where(left, fc, fe)
        c, d = c_new, d_new
    return np.exp((a + b) / 2)


def initial_guess_batch(
    V: np.ndarray, L: np.ndarray, W: np.ndarray, K: int, min_sep_deg: float = 10.0
) -> np.ndarray:
    """The better initial guess (in the spirit of 001), for a batch of texels.

    Each lobe is placed at the direction of the largest remaining residual (at least
    ``min_sep_deg`` from earlier lobes), then Kd and all Ks are solved by non-negative
    linear least squares for fixed directions and m, and m is searched (grid, then
    golden section on ln m). :func:`fit_mh_tile` then runs a few vectorised
    Levenberg-Marquardt steps over the whole tile (:func:`refine_batch`), so nlopt
    starts next to the optimum.

    Parameters
    ----------
    V : (B, N, 3) directions, L : (B, N, 3) radiance, W : (B, N) 0/1 validity.

    Returns
    -------
    (B, 4 + 6K) parameter vectors (docs/reference/conventions.md layout).
    """
    B, N, _ = V.shape
    if initial_batch is not None:
        out = np.zeros((B, mh_size(K)))
        initial_batch(np.ascontiguousarray(V, float), np.ascontiguousarray(L, float),
                      np.ascontiguousarray(W, float), K, math.cos(math.radians(min_sep_deg)),
                      LN_M_MAX, M_GRID, M_GOLDEN, out)
        return out
    D = np.zeros((B, 0, 3))
    Y = L.mean(-1)
    resid = np.where(W > 0, Y, -np.inf)
    cos_sep = math.cos(math.radians(min_sep_deg))
    m = np.full(B, 10.0)
    for _ in range(K):
        if D.shape[1]:
            near = (np.matmul(V, D.transpose(0, 2, 1)) > cos_sep).any(-1)
            resid = np.where(near, -np.inf, resid)
        i = np.argmax(resid, axis=1)
        D = np.concatenate([D, V[np.arange(B), i][:, None, :]], axis=1)
        m = _search_m(V, L, W, D)
        coef, _ = _solve_linear(V, L, W, D, m)
        model = np.matmul(np.concatenate(
            [np.ones((B, N, 1), V.dtype), _lobe_terms(V, D, m.astype(V.dtype))], 2), coef)
        resid = np.where(W > 0, (L - model).mean(-1), -np.inf)
    coef, _ = _solve_linear(V, L, W, D, m)
    p = np.zeros((B, mh_size(K)))
    p[:, MH_KD] = coef[:, 0]
    p[:, MH_M] = m
    for k in range(K):
        p[:, mh_ks(k)] = coef[:, k + 1]
        p[:, mh_dir(k)] = D[:, k]
    return p



def initial_guess_published(V: np.ndarray, L: np.ndarray, W: np.ndarray, K: int,
                            min_sep_deg: float = 20.0) -> np.ndarray:
    """The published initial guess (000 ch. 5.1): Kd = mean radiance, Ks = 0, d = the
    direction of the brightest sample (further lobes at the next brightest samples at
    least ``min_sep_deg`` away), m = 10. (B, N, 3) inputs, (B, 4 + 6K) output."""
    B = V.shape[0]
    p = np.zeros((B, mh_size(K)))
    w = W[..., None]
    p[:, MH_KD] = (L * w).sum(1) / np.maximum(w.sum(1), 1)
    p[:, MH_M] = 10.0
    Y = np.where(W > 0, L.mean(-1), -np.inf)
    cos_sep = math.cos(math.radians(min_sep_deg))
    for k in range(K):
        i = np.argmax(Y, axis=1)
        d = V[np.arange(B), i]
        p[:, mh_dir(k)] = d
        Y = np.where(np.einsum("bnc,bc->bn", V, d) > cos_sep, -np.inf, Y)
    return p




def extend_guess_batch(V: np.ndarray, L: np.ndarray, W: np.ndarray, P: np.ndarray,
                       min_sep_deg: float = 10.0) -> np.ndarray:
    """A start with one lobe more than the fits ``P`` (B, 4 + 6K): their lobes and m
    kept, the new lobe at the direction of the largest remaining residual (at least
    ``min_sep_deg`` from theirs), Kd and every Ks solved again by non-negative least
    squares. (B, N, 3) V, L; W (B, N) weights. Returns (B, 4 + 6(K + 1))."""
    B, N, _ = V.shape
    K = mh_lobes(P.shape[1])
    D = np.stack([P[:, mh_dir(k)] for k in range(K)], 1) if K else np.zeros((B, 0, 3))
    resid = np.where(W > 0, (L - mh_eval(P, V)).mean(-1), -np.inf)
    if K:
        near = (np.matmul(V, D.transpose(0, 2, 1)) > math.cos(math.radians(min_sep_deg))).any(-1)
        resid = np.where(near, -np.inf, resid)
    i = np.argmax(resid, axis=1)
    D = np.concatenate([D, V[np.arange(B), i][:, None, :]], axis=1)
    m = P[:, MH_M] if K else np.full(B, 10.0)
    coef, _ = _solve_linear(V, L, W, D, m)
    p = np.zeros((B, mh_size(K + 1)))
    p[:, MH_KD] = coef[:, 0]
    p[:, MH_M] = m
    for k in range(K + 1):
        p[:, mh_ks(k)] = coef[:, k + 1]
        p[:, mh_dir(k)] = D[:, k]
    return p
