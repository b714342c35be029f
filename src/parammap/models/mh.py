"""Multiple Highlight (MH) model: evaluation and the bounded nlopt fit of one texel.

``L_c(v) = Kd_c + sum_k Ks_kc * max(0, d_k . v) ** m`` per RGB channel, K lobes sharing
one shininess m (000 eq. 1, 004 eq. 11.2). Parameter vectors follow conventions.md:
``Kd.R Kd.G Kd.B m`` then per lobe ``Ks.R Ks.G Ks.B d.X d.Y d.Z`` (4 + 6K values).

The optimiser works on ``x = [Kd(3), ln m, (Ks(3), theta, phi) per lobe]``: polar angles
keep each d a unit vector in the upper hemisphere (theta in [0, pi/2]) and ln m keeps m
in [1, 10000], so every constraint is a plain bound, which all of nlopt's local
gradient algorithms honour. Radiances are divided by one per-texel scale before the fit
(conditioning); Kd and Ks are multiplied back, so stored parameters are in the
observation map's radiance units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import nlopt
import numpy as np

from ..conventions import LUMINANCE, FitStatus
from ..errors import InputError
from ._mh_kernel import LOSSES, cost_grad, gram
from .weights import noise_weights, reduced_chi2

__all__ = [
    "ALGORITHMS",
    "FitResult",
    "MhFitConfig",
    "bic",
    "drop_negligible_lobes",
    "fit_mh_map",
    "fit_mh_tile",
    "fit_texel",
    "initial_guess_batch",
    "initial_guess_published",
    "mean_percentage_residual",
    "mh_eval",
    "mh_figures",
    "mh_outputs",
    "n_params",
    "parse_lobes",
    "polish_batch",
    "refine_batch",
    "repair_mh_tile",
    "stains",
]

ALGORITHMS = {
    "lbfgs": nlopt.LD_LBFGS,
    "slsqp": nlopt.LD_SLSQP,
    "mma": nlopt.LD_MMA,
    "ccsaq": nlopt.LD_CCSAQ,
    "tnewton": nlopt.LD_TNEWTON_PRECOND_RESTART,
    "var2": nlopt.LD_VAR2,
    "bobyqa": nlopt.LN_BOBYQA,
}
M_MIN, M_MAX = 1.0, 10000.0
LN_M_MAX = math.log(M_MAX)

# status codes stored per texel
STATUS_NOT_FITTED, STATUS_OK, STATUS_TOO_FEW, STATUS_FAILED = (
    int(FitStatus.NOT_FITTED), int(FitStatus.OK), int(FitStatus.TOO_FEW), int(FitStatus.FAILED))


def n_params(K: int) -> int:
    """Length of the MH parameter vector for K lobes."""
    return 4 + 6 * K


def mh_eval(params: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Evaluate MH parameter vectors.

    Parameters
    ----------
    params : (..., 4 + 6K) conventions.md layout.
    directions : (..., N, 3) unit view directions, surface frame.

    Returns
    -------
    (..., N, 3) radiance.
    """
    params = np.asarray(params, float)
    v = np.asarray(directions, float)
    K = (params.shape[-1] - 4) // 6
    out = np.broadcast_to(params[..., None, 0:3], v.shape).copy()
    m = params[..., 3][..., None]
    for k in range(K):
        ks = params[..., 4 + 6 * k: 7 + 6 * k]
        d = params[..., 7 + 6 * k: 10 + 6 * k]
        c = np.clip(np.einsum("...nc,...c->...n", v, d), 0.0, None)
        out += (c ** m)[..., None] * ks[..., None, :]
    return out


def mean_percentage_residual(measured: np.ndarray, fitted: np.ndarray,
                             valid: np.ndarray | None = None) -> np.ndarray:
    """004's mean percentage residual per channel: mean of ``100 |fit - meas| / meas``
    over valid observations. (..., N, 3) inputs, (..., 3) output."""
    meas = np.asarray(measured, float)
    den = np.maximum(np.abs(meas), 1e-9 * np.nanmax(np.abs(meas), axis=-2, keepdims=True)
                     + 1e-30)
    pct = 100 * np.abs(np.asarray(fitted, float) - meas) / den
    if valid is None:
        return pct.mean(axis=-2)
    w = np.asarray(valid, float)[..., None]
    return (np.where(w > 0, pct, 0)).sum(-2) / np.maximum(w.sum(-2), 1)


def bic(rss: float, n: int, K: int, floor: float = 0.0) -> float:
    """Bayesian information criterion of a K-lobe fit with ``n`` residuals (d has two
    degrees of freedom, so 4 + 5K free parameters). ``floor`` is the smallest mean
    squared residual taken as real: below it (noise-free data) extra lobes only fit
    round-off, which must not count as evidence."""
    k = 3 if K == 0 else 4 + 5 * K  # K = 0: Kd alone (no shininess to fit)
    return n * math.log(max(rss / n, floor, 1e-300)) + k * math.log(n)


# ---------------------------------------------------------------------------------
# Initial guesses


def _angles(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.arccos(np.clip(d[..., 2], -1, 1)), np.arctan2(d[..., 1], d[..., 0])


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


def _search_m(V, L, W, D, iters: int = 3) -> np.ndarray:
    """Shininess per texel minimising the RSS after the linear solve: a coarse grid over
    ln m, then golden-section search in the best bracket (001)."""
    B = V.shape[0]
    lnc = _log_cos(V, D)
    grid = np.linspace(0.0, LN_M_MAX, 8)
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
    (B, 4 + 6K) parameter vectors (conventions.md layout).
    """
    B, N, _ = V.shape
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
    p = np.zeros((B, n_params(K)))
    p[:, 0:3] = coef[:, 0]
    p[:, 3] = m
    for k in range(K):
        p[:, 4 + 6 * k: 7 + 6 * k] = coef[:, k + 1]
        p[:, 7 + 6 * k: 10 + 6 * k] = D[:, k]
    return p


def _params_to_x_batch(P: np.ndarray, s: np.ndarray) -> np.ndarray:
    B = P.shape[0]
    K = (P.shape[1] - 4) // 6
    X = np.empty((B, 4 + 5 * K))
    X[:, 0:3] = P[:, 0:3] / s[:, None]
    X[:, 3] = np.log(np.clip(P[:, 3], M_MIN, M_MAX))
    for k in range(K):
        X[:, 4 + 5 * k: 7 + 5 * k] = P[:, 4 + 6 * k: 7 + 6 * k] / s[:, None]
        X[:, 7 + 5 * k], X[:, 8 + 5 * k] = _angles(P[:, 7 + 6 * k: 10 + 6 * k])
    return X


def _x_to_params_batch(X: np.ndarray, s: np.ndarray) -> np.ndarray:
    B = X.shape[0]
    K = (X.shape[1] - 4) // 5
    P = np.empty((B, n_params(K)))
    P[:, 0:3] = X[:, 0:3] * s[:, None]
    P[:, 3] = np.exp(X[:, 3])
    for k in range(K):
        th, ph = X[:, 7 + 5 * k], X[:, 8 + 5 * k]
        P[:, 4 + 6 * k: 7 + 6 * k] = X[:, 4 + 5 * k: 7 + 5 * k] * s[:, None]
        P[:, 7 + 6 * k: 10 + 6 * k] = np.stack(
            [np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    return P


BATCH_EVALS = 25  # evaluations of the stacked-texel polish before the per-texel fallback
KS_CAP = 20.0  # Ks <= KS_CAP x the texel's brightest observation (scaled units)


def _bounds(K: int, ks_max: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Bounds in x-space. ``ks_max`` caps the lobe amplitudes: a peak between samples
    may exceed every observation, but not by orders of magnitude; without a cap a
    narrow lobe whose peak no view saw can grow without limit (a spike in renders)."""
    nx = 4 + 5 * K
    lb, ub = np.zeros(nx), np.full(nx, np.inf)
    for k in range(K):
        ub[4 + 5 * k: 7 + 5 * k] = ks_max
    ub[3] = LN_M_MAX
    for k in range(K):
        lb[7 + 5 * k], ub[7 + 5 * k] = 0.0, math.pi / 2
        lb[8 + 5 * k], ub[8 + 5 * k] = -3 * math.pi, 3 * math.pi
    return lb, ub


def _normal_equations(X, V, Ls, W, K, LL=None, need_A: bool = True):
    """Cost, Gauss-Newton matrix J^T J (B, nx, nx) and gradient J^T r (B, nx) of the
    weighted least-squares problem in x-space, for a batch of texels.

    The model of each channel is a combination ``a_c . q_n`` of a few per-observation
    vectors q (1 and per lobe p_k), and every Jacobian column a per-channel multiple of
    q or of p's derivatives (ln m, theta, phi). So cost, J^T J and J^T r all follow from
    the small Gram matrix of these vectors: no (N x 3)-sized array is formed.
    ``LL`` (B, 3) = sum of w L^2, constant over iterations.
    """
    B, N, _ = V.shape
    nx = X.shape[1]
    nb = 1 + 4 * K
    m = np.exp(X[:, 3])
    q = np.empty((B, N, nb), V.dtype)  # observation-major: contiguous rows for gram()
    q[:, :, 0] = 1.0
    coef = np.zeros((B, 3, nx, nb))  # Jacobian columns in terms of q
    amod = np.zeros((B, 3, nb))  # model = amod . q
    amod[:, :, 0] = X[:, 0:3]
    for c in range(3):
        coef[:, c, c, 0] = 1.0
    for k in range(K):
        th, ph = X[:, 7 + 5 * k], X[:, 8 + 5 * k]
        st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
        d = np.stack([st * cp, st * sp, ct], -1)
        dth = np.stack([ct * cp, ct * sp, -st], -1)
        dph = np.stack([-st * sp, st * cp, np.zeros_like(st)], -1)
        c_ = np.matmul(np.stack([d, dth, dph], 1), V.transpose(0, 2, 1))  # (B, 3, N)
        cos = c_[:, 0]
        pos = cos > 0
        cc = np.where(pos, cos, 1.0)
        lnc = np.log(cc)
        pk = np.where(pos, np.exp(m[:, None] * lnc), 0.0)
        ks = X[:, 4 + 5 * k: 7 + 5 * k]
        dpdc = pk * m[:, None] / cc
        q[:, :, 1 + 4 * k] = pk
        q[:, :, 2 + 4 * k] = pk * lnc * m[:, None]
        q[:, :, 3 + 4 * k] = dpdc * c_[:, 1]
        q[:, :, 4 + 4 * k] = dpdc * c_[:, 2]
        amod[:, :, 1 + 4 * k] = ks
        for c in range(3):
            coef[:, c, 4 + 5 * k + c, 1 + 4 * k] = 1.0
            coef[:, c, 3, 2 + 4 * k] = ks[:, c]
            coef[:, c, 7 + 5 * k, 3 + 4 * k] = ks[:, c]
            coef[:, c, 8 + 5 * k, 4 + 4 * k] = ks[:, c]
    Q, qL, _ = gram(q, Ls, W)  # (B, nb, nb), (B, 3, nb)
    qL = qL.transpose(0, 2, 1)
    if LL is None:
        LL = (W[..., None] * Ls * Ls).sum(1)
    # R = q_w r = Q a - qL, per channel; cost = a Q a - 2 a qL + LL
    Qa = np.matmul(amod, Q)  # (B, 3, nb)
    R = Qa.transpose(0, 2, 1) - qL  # (B, nb, 3)
    cost = ((Qa * amod).sum(-1) - 2 * (amod * qL.transpose(0, 2, 1)).sum(-1) + LL).sum(-1)
    cf = coef  # (B, 3, nx, nb)
    A = np.matmul(np.matmul(cf, Q[:, None]), cf.transpose(0, 1, 3, 2)).sum(1) if need_A \
        else None
    g = np.matmul(cf, R.transpose(0, 2, 1)[..., None])[..., 0].sum(1)
    return np.maximum(cost, 0.0), A, g


def refine_batch(V: np.ndarray, L: np.ndarray, W: np.ndarray, P0: np.ndarray,
                 iters: int = 8) -> np.ndarray:
    """Projected Levenberg-Marquardt steps on a batch of texels at once (vectorised),
    in the bounded x-space of the nlopt fit. Brings an initial guess close to the
    optimum so the per-texel nlopt fit only polishes. (B, N, 3) inputs, (B, 4 + 6K)."""
    K = (P0.shape[1] - 4) // 6
    s = np.maximum((L * W[..., None]).sum((1, 2)) / np.maximum(3 * W.sum(1), 1), 1e-12)
    Ls = L / s[:, None, None]
    X = _params_to_x_batch(P0, s)
    lb, ub = _bounds(K)
    ub = np.broadcast_to(ub, X.shape).copy()
    ksmax = KS_CAP * np.max(np.where(W[..., None] > 0, Ls, 0), axis=(1, 2))
    for k in range(K):
        ub[:, 4 + 5 * k: 7 + 5 * k] = ksmax[:, None]
    X = np.clip(X, lb, ub)
    lam = np.full(len(X), 1e-3)
    LL = (W[..., None] * Ls * Ls).sum(1)
    cost, A, g = _normal_equations(X, V, Ls, W, K, LL)
    nx = X.shape[1]
    eye = np.eye(nx)
    act = np.arange(len(X))  # texels still improving
    for _ in range(iters):
        dA = np.maximum(np.diagonal(A[act], axis1=1, axis2=2), 1e-12)
        try:
            step = np.linalg.solve(A[act] + (lam[act, None] * dA)[..., None] * eye,
                                   -g[act, :, None])[..., 0]
        except np.linalg.LinAlgError:
            break
        Xn = np.clip(X[act] + step, lb, ub[act])
        cn, An, gn = _normal_equations(Xn, V[act], Ls[act], W[act], K, LL[act])
        better = np.isfinite(cn) & (cn < cost[act])
        gain = np.where(better, (cost[act] - cn) / np.maximum(cost[act], 1e-300), 0.0)
        b = act[better]
        X[b], A[b], g[b], cost[b] = Xn[better], An[better], gn[better], cn[better]
        lam[act] = np.where(better, lam[act] * 0.3, lam[act] * 10)
        act = act[(gain > 1e-8) | (~better & (lam[act] < 1e6))]
        if len(act) == 0:
            break
    return _x_to_params_batch(X, s)


def initial_guess_published(V: np.ndarray, L: np.ndarray, W: np.ndarray, K: int,
                            min_sep_deg: float = 20.0) -> np.ndarray:
    """The published initial guess (000 ch. 5.1): Kd = mean radiance, Ks = 0, d = the
    direction of the brightest sample (further lobes at the next brightest samples at
    least ``min_sep_deg`` away), m = 10. (B, N, 3) inputs, (B, 4 + 6K) output."""
    B = V.shape[0]
    p = np.zeros((B, n_params(K)))
    w = W[..., None]
    p[:, 0:3] = (L * w).sum(1) / np.maximum(w.sum(1), 1)
    p[:, 3] = 10.0
    Y = np.where(W > 0, L.mean(-1), -np.inf)
    cos_sep = math.cos(math.radians(min_sep_deg))
    for k in range(K):
        i = np.argmax(Y, axis=1)
        d = V[np.arange(B), i]
        p[:, 7 + 6 * k: 10 + 6 * k] = d
        Y = np.where(np.einsum("bnc,bc->bn", V, d) > cos_sep, -np.inf, Y)
    return p


def polish_batch(V: np.ndarray, L: np.ndarray, W: np.ndarray, P0: np.ndarray,
                 cfg: MhFitConfig) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, int]:
    """One bounded nlopt run over a whole batch of texels (least squares only).

    The sum of the texels' objectives is separable, so its minimum is every texel's own
    minimum; one nlopt call with the stacked parameters evaluates all texels in a few
    vectorised numpy operations instead of a Python callback per texel. Started next
    to the optimum (:func:`refine_batch`), it needs few evaluations. A texel whose
    projected gradient is not small afterwards is reported as not converged, and
    :func:`fit_mh_tile` fits it alone with :func:`fit_texel`.

    Returns
    -------
    params (B, 4 + 6K), rss (B,) in radiance units, evaluations, converged (B,) bool,
    nlopt result code.
    """
    B = len(P0)
    K = (P0.shape[1] - 4) // 6
    s = np.maximum((L * W[..., None]).sum((1, 2)) / np.maximum(3 * W.sum(1), 1), 1e-12)
    Ls = L / s[:, None, None]
    LL = (W[..., None] * Ls * Ls).sum(1)
    X0 = _params_to_x_batch(P0, s)
    lb1, ub1 = _bounds(K)
    lb = np.broadcast_to(lb1, X0.shape).copy()
    ub = np.broadcast_to(ub1, X0.shape).copy()
    ksmax = KS_CAP * np.max(np.where(W[..., None] > 0, Ls, 0), axis=(1, 2))
    for k in range(K):
        ub[:, 4 + 5 * k: 7 + 5 * k] = ksmax[:, None]
    X0 = np.clip(X0, lb, ub)
    nx = X0.shape[1]
    best = [math.inf, X0.ravel().copy(), None]

    def fn(x: np.ndarray, grad: np.ndarray) -> float:
        X = x.reshape(B, nx)
        cost, _, g = _normal_equations(X, V, Ls, W, K, LL, need_A=False)
        val = float(cost.sum())
        if grad.size > 0:
            grad[:] = (2 * g).ravel()
        if val < best[0]:
            best[0], best[1], best[2] = val, x.copy(), (cost, 2 * g)
        return val

    opt = nlopt.opt(ALGORITHMS.get(cfg.algorithm, nlopt.LD_LBFGS), B * nx)
    opt.set_lower_bounds(lb.ravel())
    opt.set_upper_bounds(ub.ravel())
    opt.set_min_objective(fn)
    opt.set_ftol_rel(cfg.ftol_rel)
    opt.set_xtol_rel(cfg.xtol_rel)
    # few evaluations: texels that need more are better served alone afterwards
    opt.set_maxeval(min(cfg.max_evals, BATCH_EVALS))
    try:
        opt.optimize(X0.ravel())
        code = int(opt.last_optimize_result())
    except Exception:  # noqa: BLE001 - keep the best point (round-off stops)
        code = -4
    X = best[1].reshape(B, nx)
    if best[2] is None:
        fn(X.ravel(), np.empty(B * nx))
    cost, grad = best[2]
    # first-order check per texel: no coordinate can still lower the cost by more
    # than a tiny fraction with a small relative step
    free = ~(((X <= lb) & (grad > 0)) | ((X >= ub) & (grad < 0)))
    pg = np.where(free, grad, 0.0) * np.maximum(np.abs(X), 0.1)
    converged = np.abs(pg).max(1) <= 1e-3 * np.maximum(cost, 1e-12)
    P = np.stack([_sort_lobes(p) for p in _x_to_params_batch(X, s)])
    return P, cost * s * s, int(opt.get_numevals()), converged, code


# ---------------------------------------------------------------------------------
# nlopt fit of one texel


@dataclass(frozen=True)
class MhFitConfig:
    """Options of the per-texel fit (config section ``fit.mh``)."""

    algorithm: str = "lbfgs"
    init: str = "better"  # better | published
    loss: str = "linear"  # linear | soft_l1 | huber
    f_scale: float = 0.05  # robust loss scale, relative to the texel's radiance scale
    max_evals: int = 400
    ftol_rel: float = 1e-10
    xtol_rel: float = 1e-8
    bic_margin: float = 10.0  # auto-K adds a lobe only if BIC drops by more
    bic_floor: float = 1e-3  # residuals below this fraction of the radiance are noise
    polish: str = "texel"  # texel (one nlopt run per texel) | batch (stacked texels first)


@dataclass
class FitResult:
    params: np.ndarray  # (4 + 6K,)
    rss: float
    evals: int
    status: int
    nlopt_code: int


def _to_x(p: np.ndarray, s: float) -> np.ndarray:
    K = (len(p) - 4) // 6
    x = np.empty(4 + 5 * K)
    x[0:3] = p[0:3] / s
    x[3] = math.log(min(max(p[3], M_MIN), M_MAX))
    for k in range(K):
        x[4 + 5 * k: 7 + 5 * k] = p[4 + 6 * k: 7 + 6 * k] / s
        th, ph = _angles(p[7 + 6 * k: 10 + 6 * k])
        x[7 + 5 * k], x[8 + 5 * k] = th, ph
    return x


def _from_x(x: np.ndarray, s: float) -> np.ndarray:
    K = (len(x) - 4) // 5
    p = np.empty(n_params(K))
    p[0:3] = x[0:3] * s
    p[3] = math.exp(x[3])
    for k in range(K):
        p[4 + 6 * k: 7 + 6 * k] = x[4 + 5 * k: 7 + 5 * k] * s
        th, ph = x[7 + 5 * k], x[8 + 5 * k]
        p[7 + 6 * k: 10 + 6 * k] = (math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph),
                                    math.cos(th))
    return p


def _objective(V: np.ndarray, L: np.ndarray, K: int, loss: str, f: float,
               compiled: bool | None = None, w: np.ndarray | None = None):
    """nlopt objective with analytic gradient, on scaled radiance L (n, 3), each
    observation's loss weighted by ``w`` (n,; default 1).

    The compiled kernel (:mod:`._mh_kernel`) by default; the numpy version (all lobes
    at once, few numpy calls) where numba is missing or ``compiled=False``. Both keep
    the best point evaluated in ``fn.best``.
    """
    best = [math.inf, None]
    wv = np.ones(len(V)) if w is None else np.ascontiguousarray(w, dtype=float)
    if compiled is None:
        compiled = cost_grad is not None
    if compiled:
        Vc = np.ascontiguousarray(V, dtype=float)
        Lc = np.ascontiguousarray(L, dtype=float)
        code = LOSSES[loss]
        fl = float(f)
        nograd = np.empty(4 + 5 * K)

        def fn_c(x: np.ndarray, grad: np.ndarray) -> float:
            want = grad.size > 0
            val = cost_grad(x, Vc, Lc, wv, K, code, fl, grad if want else nograd, want)
            if val < best[0]:
                best[0], best[1] = val, x.copy()
            return val

        fn_c.best = best
        return fn_c

    idx_ks = np.array([4 + 5 * k + c for k in range(K) for c in range(3)])
    idx_th = np.array([7 + 5 * k for k in range(K)])
    idx_ph = idx_th + 1

    def fn(x: np.ndarray, grad: np.ndarray) -> float:
        m = math.exp(x[3])
        th, ph = x[idx_th], x[idx_ph]
        st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
        C = V @ np.stack([st * cp, st * sp, ct], 1).T  # (n, K)
        pos = C > 0
        Cs = np.where(pos, C, 1.0)
        lc = np.log(Cs)
        P = np.where(pos, np.exp(m * lc), 0.0)
        KS = x[idx_ks].reshape(K, 3)
        r = P @ KS + x[0:3] - L
        if loss == "linear":
            val = float(np.vdot(wv[:, None] * r, r))
            dr = 2 * r
        elif loss == "soft_l1":
            sq = np.sqrt(1 + (r / f) ** 2)
            val = float(np.sum(wv[:, None] * 2 * f * f * (sq - 1)))
            dr = 2 * r / sq
        else:  # huber
            a = np.abs(r)
            val = float(np.sum(wv[:, None] * np.where(a <= f, r * r, 2 * f * a - f * f)))
            dr = np.where(a <= f, 2 * r, 2 * f * np.sign(r))
        dr = wv[:, None] * dr
        if grad.size > 0:
            G = dr @ KS.T  # (n, K): sum over channels of dr * Ks
            grad[0:3] = dr.sum(0)
            grad[idx_ks] = (P.T @ dr).ravel()
            GP = G * P
            grad[3] = float(np.vdot(GP, lc)) * m
            Gd = GP * (m / Cs)
            grad[idx_th] = np.einsum("nk,nk->k", V @ np.stack([ct * cp, ct * sp, -st], 1).T, Gd)
            grad[idx_ph] = np.einsum("nk,nk->k", V @ np.stack([-st * sp, st * cp, 0 * st], 1).T,
                                     Gd)
        if val < best[0]:
            best[0], best[1] = val, x.copy()
        return val

    fn.best = best
    return fn


def fit_texel(V: np.ndarray, L: np.ndarray, p0: np.ndarray,
              cfg: MhFitConfig = MhFitConfig(), w: np.ndarray | None = None) -> FitResult:
    """Bounded nlopt fit of one texel from initial parameters ``p0`` (4 + 6K).

    Parameters
    ----------
    V : (n, 3) unit view directions of the valid observations.
    L : (n, 3) their radiance.
    w : (n,) observation weights (:mod:`.weights`; default 1); the RSS is weighted.

    Returns
    -------
    FitResult with parameters in conventions.md layout (lobes sorted by strength) and
    the residual sum of squares in radiance units squared.
    """
    K = (len(p0) - 4) // 6
    s = float(max(np.mean(L), 1e-12))
    Ls = L / s
    x0 = _to_x(p0, s)
    nx = len(x0)
    lb, ub = _bounds(K, KS_CAP * float(np.max(Ls)))
    x0 = np.clip(x0, lb, ub)
    opt = nlopt.opt(ALGORITHMS[cfg.algorithm], nx)
    opt.set_lower_bounds(lb)
    opt.set_upper_bounds(ub)
    fn = _objective(V, Ls, K, cfg.loss, cfg.f_scale, w=w)
    opt.set_min_objective(fn)
    opt.set_ftol_rel(cfg.ftol_rel)
    opt.set_xtol_rel(cfg.xtol_rel)
    opt.set_maxeval(cfg.max_evals)
    status = STATUS_OK
    try:
        x = opt.optimize(x0)
        code = int(opt.last_optimize_result())
    except Exception:  # noqa: BLE001 - nlopt's errors do not share one base class
        # Keep the best point reached: round-off and "generic failure" stops happen
        # mostly at an already converged start.
        x = fn.best[1] if fn.best[1] is not None else x0
        code = -4
    if fn.best[1] is not None:
        x = fn.best[1]  # the best point evaluated (what nlopt returns, or better)
    p = _sort_lobes(_from_x(x, s))
    if cfg.loss == "linear" and fn.best[1] is not None:
        rss = fn.best[0] * s * s  # the objective is the RSS of the scaled radiance
    else:
        rss = float(np.sum((1.0 if w is None else w[:, None]) * (mh_eval(p, V) - L) ** 2))
    if not np.all(np.isfinite(p)) or not math.isfinite(rss):
        status = STATUS_FAILED
    return FitResult(p, rss, int(opt.get_numevals()), status, code)


def _sort_lobes(p: np.ndarray) -> np.ndarray:
    K = (len(p) - 4) // 6
    if K < 2:
        return p
    lobes = p[4:].reshape(K, 6)
    order = np.argsort(-lobes[:, 0:3].sum(1), kind="stable")
    out = p.copy()
    out[4:] = lobes[order].ravel()
    return out


# ---------------------------------------------------------------------------------
# A tile of texels


def mh_outputs(K_max: int) -> dict[str, tuple[tuple[int, ...], str, float]]:
    """Arrays of an MH fit store: name -> (trailing shape, dtype, fill value)."""
    return {
        "params": ((n_params(K_max),), "float32", float("nan")),
        "rmse": ((3,), "float32", float("nan")),
        "mpr": ((3,), "float32", float("nan")),
        "chi2": ((), "float32", float("nan")),
        "k_used": ((), "int8", 0),
        "evals": ((), "int32", 0),
        "status": ((), "int8", STATUS_NOT_FITTED),
    }


def fit_mh_tile(
    radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray, K: int | str,
    cfg: MhFitConfig = MhFitConfig(), K_max: int = 3, noise: np.ndarray | None = None,
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
    W = (valid.reshape(t * u, N) & np.isfinite(L).all(-1) & np.isfinite(V).all(-1))
    L = np.where(W[..., None], L, 0.0)
    V = np.where(W[..., None], V, [0.0, 0.0, 1.0])
    NZ = None if noise is None else noise.reshape(t * u, N)
    NW = noise_weights(NZ, W)
    nobs = W.sum(1)
    Ks = range(1, Kmax + 1) if K == "auto" else [Kmax]
    todo = np.flatnonzero(nobs >= 4)  # 004: at least four observations
    few = np.flatnonzero(nobs < 4)
    flat = {k: v.reshape((t * u,) + v.shape[2:]) for k, v in out.items()}
    flat["status"][few] = STATUS_TOO_FEW
    if len(todo) == 0:
        return out
    init = initial_guess_batch if cfg.init == "better" else initial_guess_published
    Wf = NW[todo]
    # the initial guesses in float32 (twice as fast; LM and nlopt then work in float64)
    V32, L32, W32 = V[todo].astype(np.float32), L[todo].astype(np.float32), Wf.astype(np.float32)
    inits = {k: init(V32, L32, W32, k).astype(float) for k in Ks}
    if cfg.init == "better":
        inits = {k: refine_batch(V[todo], L[todo], Wf, p0) for k, p0 in inits.items()}
    polished = {}
    if cfg.polish == "batch" and cfg.loss == "linear" and cfg.algorithm != "bobyqa":
        for k in Ks:
            P, rss, ev, conv, code = polish_batch(V[todo], L[todo], Wf, inits[k], cfg)
            polished[k] = (P, rss, ev, conv & np.isfinite(P).all(1) & np.isfinite(rss), code)
    for j, b in enumerate(todo):
        w = W[b]
        v, y, wt = V[b][w], L[b][w], NW[b][w]
        best, best_bic, evals = None, math.inf, 0
        if K == "auto":
            # K = 0 first: a lobe must pay for itself against a diffuse texel
            kd = (wt[:, None] * y).sum(0) / wt.sum()
            p0 = np.r_[kd, M_MIN]
            floor = (cfg.bic_floor * float(np.mean(np.abs(y)))) ** 2
            rss0 = float(np.sum(wt[:, None] * (y - kd) ** 2))
            best, best_bic = (FitResult(p0, rss0, 0, STATUS_OK, 0), 0), bic(rss0, y.size, 0,
                                                                            floor)
        for k in Ks:
            if k in polished and polished[k][3][j]:
                P, rss, ev, _, code = polished[k]
                r = FitResult(P[j], float(rss[j]), ev, STATUS_OK, code)
            else:
                start = polished[k][0][j] if k in polished else inits[k][j]
                try:
                    r = fit_texel(v, y, start, cfg, w=wt)
                except Exception:  # noqa: BLE001 - a failed texel is flagged, never fatal
                    r = FitResult(np.full(n_params(k), np.nan), math.inf, 0, STATUS_FAILED,
                                  -1)
            evals += r.evals
            floor = (cfg.bic_floor * float(np.mean(np.abs(y)))) ** 2
            crit = bic(r.rss, y.size, k, floor) if r.status == STATUS_OK else math.inf
            if best is None or (K != "auto" and r.status == STATUS_OK) or \
                    crit < best_bic - cfg.bic_margin:
                best, best_bic = (r, k), crit
            elif K == "auto":
                break
        r, k = best
        p = np.zeros(n_params(Kmax))
        p[: n_params(k)] = r.params
        for extra in range(k, Kmax):
            p[9 + 6 * extra] = 1.0  # unused lobe: Ks = 0, d = +z
        flat["params"][b] = p
        flat["k_used"][b] = k
        flat["evals"][b] = evals
        flat["status"][b] = r.status
    # residual diagnostics for the whole tile at once
    ok = todo[flat["status"][todo] == STATUS_OK]
    if len(ok):
        P = flat["params"][ok].astype(float)
        before = _lobes_present(P)
        P = drop_negligible_lobes(P, V[ok], L[ok], W[ok])
        after = _lobes_present(P)
        for j in np.flatnonzero(after < before):
            # the lobes left were fitted beside the one now gone: refit them alone
            b, k = ok[j], int(after[j])
            flat["k_used"][b] = k
            w = W[b]
            v, y, wt = V[b][w], L[b][w], NW[b][w]
            if k == 0:
                P[j, :3] = (wt[:, None] * y).sum(0) / wt.sum()
                continue
            p0 = P[j, : n_params(k)]
            rss0 = float(np.sum(wt[:, None] * (mh_eval(p0, v) - y) ** 2))
            try:
                r = fit_texel(v, y, p0.copy(), cfg, w=wt)
            except Exception:  # noqa: BLE001 - keep the unrefitted lobes
                continue
            if r.status == STATUS_OK and r.rss < rss0:
                P[j, : n_params(k)] = r.params
        flat["params"][ok] = P
        fitted = mh_eval(flat["params"][ok].astype(float), V[ok])
        w = W[ok][..., None]
        n = np.maximum(w.sum(1), 1)
        flat["rmse"][ok] = np.sqrt((np.where(w, fitted - L[ok], 0) ** 2).sum(1) / n)
        flat["mpr"][ok] = mean_percentage_residual(L[ok], fitted, W[ok])
        if NZ is not None:
            # free parameters: Kd, m, and per lobe Ks and a direction (two angles)
            flat["chi2"][ok] = reduced_chi2(L[ok], fitted, NZ[ok], W[ok],
                                            4 + 5 * flat["k_used"][ok].astype(int))
    return out


# A texel whose RMSE exceeds this many times the median of its neighbourhood is refit
# from its neighbours' parameters (the texels of one material share a minimum; a poor
# local minimum shows as a "stain" of high residual among well-fitted neighbours).
REPAIR_FACTOR = 3.0
REPAIR_RADIUS = 4  # neighbourhood (2r + 1)^2 = 9x9 texels
REPAIR_STARTS = 8  # nearest well-fitted neighbours tried as starts
# Observations that must see a lobe above twice the texel's noise for it to count as
# measured: three views x three channels are the fewest residuals that locate a peak
# (direction, width) and its colour. Five (the lobe's parameter count) also removed
# real, sharp lobes that 17 views of 004 ch. 13.2 still recover.
MIN_SUPPORT = 3


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

    e = np.where(status == STATUS_OK, np.nanmean(rmse, -1), np.nan)
    with np.errstate(invalid="ignore"):
        out = e > factor * _neighbourhood_median(e, radius)
    lab, n = label(out)
    return np.sort(np.bincount(lab.ravel())[1:])[::-1] if n else np.zeros(0, int)


def repair_mh_tile(fields: dict[str, np.ndarray], radiance: np.ndarray,
                   direction: np.ndarray, valid: np.ndarray, offset: tuple[int, int], *,
                   K: int | str, cfg: MhFitConfig = MhFitConfig(),
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
    params, status, kused = fields["params"], fields["status"], fields["k_used"]
    e = np.where(status == STATUS_OK, np.nanmean(fields["rmse"], -1), np.nan)
    med = _neighbourhood_median(e, radius)
    with np.errstate(invalid="ignore"):
        outlier = e > factor * med
        good = (status == STATUS_OK) & ~outlier
    oy, ox = offset
    t, u = valid.shape[:2]
    sl = (slice(oy, oy + t), slice(ox, ox + u))
    bad = np.argwhere(outlier[sl])
    if len(bad) == 0:
        return None
    out = {k: np.array(fields[k][sl]) for k in ("params", "rmse", "mpr", "k_used", "evals",
                                                "status")}
    out["changed"] = np.zeros((t, u), np.int8)
    gy, gx = np.nonzero(good)
    Kmax = (params.shape[-1] - 4) // 6
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
            r = fit_texel(V, L, params[a, b, :n_params(k)].astype(float), cfg)
            out["evals"][i, j] += r.evals
            if r.status != STATUS_OK:
                continue
            crit = bic(r.rss, L.size, k, floor) if K == "auto" else r.rss
            if best is None or crit < best[0]:
                best = (crit, r, k)
        margin = cfg.bic_margin if K == "auto" else 0.0
        if best is None or not best[0] < crit0 - margin:
            continue
        _, r, k = best
        p = np.zeros(n_params(Kmax))
        p[: n_params(k)] = r.params
        for extra in range(k, Kmax):
            p[9 + 6 * extra] = 1.0
        fitted = mh_eval(p, V)
        out["params"][i, j] = p
        out["k_used"][i, j] = k
        out["status"][i, j] = STATUS_OK
        out["rmse"][i, j] = np.sqrt(((fitted - L) ** 2).mean(0))
        out["mpr"][i, j] = mean_percentage_residual(L, fitted)
        out["changed"][i, j] = 1
    return out


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
    K = (P.shape[1] - 4) // 6
    if K == 0:
        return P
    w = W.astype(bool)[..., None]
    nres = 3 * np.maximum(W.sum(1), 1)
    fl = (floor * np.abs(np.where(w, L, 0)).sum((1, 2)) / nres) ** 2

    def rss(Q):
        r = np.where(w, mh_eval(Q, V) - L, 0.0)
        return np.maximum((r ** 2).sum((1, 2)), fl * nres)

    pen = 5 * np.log(nres)

    def better(Q, base):
        return nres * np.log(rss(Q) / base) < pen

    for k in range(K):
        for j in range(k + 1, K):
            a, b = slice(4 + 6 * k, 10 + 6 * k), slice(4 + 6 * j, 10 + 6 * j)
            wa = P[:, a][:, :3].sum(1, keepdims=True)
            wb = P[:, b][:, :3].sum(1, keepdims=True)
            d = P[:, a][:, 3:] * wa + P[:, b][:, 3:] * wb
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
            Q = P.copy()
            Q[:, a] = np.c_[P[:, a][:, :3] + P[:, b][:, :3], d]
            Q[:, b] = [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
            ok = (wa[:, 0] > 0) & (wb[:, 0] > 0) & better(Q, rss(P))
            P[ok] = Q[ok]
    for k in range(K):
        Q = P.copy()
        Q[:, 4 + 6 * k: 10 + 6 * k] = [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        # seen above twice the noise in fewer than MIN_SUPPORT observations, a lobe is
        # not determined by the data (a noise spike, a highlight that fell between
        # views) and would only sparkle in other views
        noise = np.sqrt(rss(P) / nres)
        c = np.clip(np.einsum("nvj,nj->nv", V, P[:, 7 + 6 * k: 10 + 6 * k]), 0, None) \
            ** P[:, 3:4] * P[:, 4 + 6 * k: 7 + 6 * k].max(1, keepdims=True)
        support = (W & (c > 2 * noise[:, None])).sum(1)
        ok = (P[:, 4 + 6 * k: 7 + 6 * k].sum(1) > 0) & (better(Q, rss(P))
                                                       | (support < MIN_SUPPORT))
        P[ok] = Q[ok]
    none = P[:, 4::6].sum(1) + P[:, 5::6].sum(1) + P[:, 6::6].sum(1) == 0
    P[none, 3] = M_MIN
    return _sort_lobes_batch(P)


def _lobes_present(P: np.ndarray) -> np.ndarray:
    """(n,) number of lobes with a non-zero Ks in parameter rows P (n, 4 + 6K)."""
    K = (P.shape[1] - 4) // 6
    return sum((P[:, 4 + 6 * k: 7 + 6 * k].sum(1) > 0).astype(int) for k in range(K))


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


def fit_mh_map(obs_path: str | Path, out_path: str | Path, K: int | str, cfg: dict,
               scheduler: str = "processes", workers: int = 2, log=print) -> dict:
    """Fit the MH model with K lobes (or ``auto``) to every texel of an observation map
    into ``fit/mh-<K>.zarr``; returns the figures for ``metrics/fit-mh-<K>.json``."""
    from functools import partial

    from ..fitting import fit_map, fit_summary, open_fit

    K = parse_lobes(K)
    fcfg = MhFitConfig(**{k: cfg[k] for k in MhFitConfig.__dataclass_fields__ if k in cfg})
    if fcfg.algorithm not in ALGORITHMS:
        raise InputError(f"fit.mh.algorithm: unknown {fcfg.algorithm!r} "
                         f"(one of {', '.join(ALGORITHMS)})")
    K_max = cfg.get("K_max", 3) if K == "auto" else K
    repair = partial(repair_mh_tile, K=K, cfg=fcfg) if cfg.get("repair", True) else None
    res = fit_map(obs_path, out_path, partial(fit_mh_tile, K=K, cfg=fcfg, K_max=K_max),
                  mh_outputs(K_max),
                  {"model": "mh", "model_version": 1, "lobes": str(K), "K_max": K_max,
                   "layout": "Kd.R Kd.G Kd.B m (lobeK.Ks.R lobeK.Ks.G lobeK.Ks.B lobeK.d.X "
                             "lobeK.d.Y lobeK.d.Z)*K",
                   "fit": {k: getattr(fcfg, k) for k in MhFitConfig.__dataclass_fields__},
                   "repair": {"factor": REPAIR_FACTOR, "radius": REPAIR_RADIUS,
                              "starts": REPAIR_STARTS} if repair else None},
                  scheduler, workers, log, repair_fn=repair, halo=REPAIR_RADIUS)
    g = open_fit(out_path)
    ok = g["status"][:] == STATUS_OK
    kused = g["k_used"][:][ok]
    return fit_summary(
        out_path, res, f"mh-{K}", scheduler=scheduler, workers=workers,
        lobes_used={str(k): int((kused == k).sum()) for k in np.unique(kused)},
        repaired_texels=int(res.get("repaired", 0)),
        largest_stain_texels=int(next(iter(stains(g["rmse"][:], g["status"][:])), 0)),
        mean_evals=float(g["evals"][:][ok].mean()) if ok.any() else None)


def mh_figures(fit_path: str | Path, obs_path: str | Path, out_dir: str | Path, name: str,
               texels: list[tuple[int, int]] | None = None) -> list[Path]:
    """Parameter maps, residual maps and lobe plots (measured vs fitted with percentage
    residuals, like 004 fig. 11.6) of an MH fit store."""
    from ..fitting import open_fit
    from ..observation import open_observation_map
    from ..report import fit_figures, plot_maps

    g = open_fit(fit_path)
    obs = open_observation_map(obs_path)
    out_dir = Path(out_dir)
    p = g["params"][:].astype(float)
    K = (p.shape[-1] - 4) // 6
    maps = {"Kd (luminance)": p[..., 0:3] @ LUMINANCE,
            "log10 m": np.log10(np.clip(p[..., 3], 1, None))}
    for k in range(K):
        maps[f"lobe {k + 1} Ks (luminance)"] = p[..., 4 + 6 * k: 7 + 6 * k] @ LUMINANCE
        maps[f"lobe {k + 1} zenith (deg)"] = np.degrees(np.arccos(np.clip(p[..., 9 + 6 * k],
                                                                          -1, 1)))
    if g.attrs.get("lobes") == "auto":
        maps["lobes used"] = g["k_used"][:].astype(float)
    paths = [plot_maps(maps, out_dir / f"{name}_params.png", f"{name}: parameter maps")]
    return paths + fit_figures(g, obs, out_dir, name, lambda r, c, d: mh_eval(p[r, c], d),
                               texels)
