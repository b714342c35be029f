"""The per-texel optimisers of the MH fit: Levenberg-Marquardt over a batch of texels
(compiled), the bounded nlopt polish of the stacked texels, and one texel's own nlopt
fit; the fit's options (:class:`MhFitConfig`)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import nlopt
import numpy as np

from ...config import default
from ...conventions import (
    MHX_KD,
    MHX_LNM,
    FitStatus,
    mh_lobes,
    mhx_ks,
    mhx_phi,
    mhx_size,
    mhx_theta,
)
from .kernel import LOSSES, cost_grad, cost_grad_batch, gram
from .model import (
    LN_M_MAX,
    _from_x,
    _params_to_x_batch,
    _sort_lobes,
    _to_x,
    _x_to_params_batch,
    mh_eval,
)
from .solve import LM_CONVERGED, lm_batch

ALGORITHMS = {
    "lbfgs": nlopt.LD_LBFGS,
    "slsqp": nlopt.LD_SLSQP,
    "mma": nlopt.LD_MMA,
    "ccsaq": nlopt.LD_CCSAQ,
    "tnewton": nlopt.LD_TNEWTON_PRECOND_RESTART,
    "var2": nlopt.LD_VAR2,
    "bobyqa": nlopt.LN_BOBYQA,
}


BATCH_EVALS = 25  # evaluations of the stacked-texel polish before the per-texel fallback


# compiled LM: steps per texel at most, and the relative gain below which it stops (the
# nlopt polish's default tolerance, MhFitConfig.ftol_rel, so the polish starts where it
# would stop)
LM_ITERS = 60


LM_FTOL = 1e-7


KS_CAP = 20.0  # Ks <= KS_CAP x the texel's brightest observation (scaled units)


def _bounds(K: int, ks_max: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Bounds in x-space. ``ks_max`` caps the lobe amplitudes: a peak between samples
    may exceed every observation, but not by orders of magnitude; without a cap a
    narrow lobe whose peak no view saw can grow without limit (a spike in renders)."""
    lb, ub, ks = _bounds_template(K)
    ub = ub.copy()
    ub[ks] = ks_max
    return lb.copy(), ub


@functools.lru_cache(maxsize=8)
def _bounds_template(K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_bounds` without the Ks cap, and the Ks columns (built once per K: it
    runs once per texel fit)."""
    nx = mhx_size(K)
    lb, ub = np.zeros(nx), np.full(nx, np.inf)
    ub[MHX_LNM] = LN_M_MAX
    for k in range(K):
        lb[mhx_theta(k)], ub[mhx_theta(k)] = 0.0, math.pi / 2
        lb[mhx_phi(k)], ub[mhx_phi(k)] = -3 * math.pi, 3 * math.pi
    ks = np.array([i for k in range(K) for i in range(mhx_ks(k).start, mhx_ks(k).stop)],
                  np.int64)
    return lb, ub, ks


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
    m = np.exp(X[:, MHX_LNM])
    q = np.empty((B, N, nb), V.dtype)  # observation-major: contiguous rows for gram()
    q[:, :, 0] = 1.0
    coef = np.zeros((B, 3, nx, nb))  # Jacobian columns in terms of q
    amod = np.zeros((B, 3, nb))  # model = amod . q
    amod[:, :, 0] = X[:, MHX_KD]
    for c in range(3):
        coef[:, c, c, 0] = 1.0
    for k in range(K):
        th, ph = X[:, mhx_theta(k)], X[:, mhx_phi(k)]
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
        ks = X[:, mhx_ks(k)]
        dpdc = pk * m[:, None] / cc
        q[:, :, 1 + 4 * k] = pk
        q[:, :, 2 + 4 * k] = pk * lnc * m[:, None]
        q[:, :, 3 + 4 * k] = dpdc * c_[:, 1]
        q[:, :, 4 + 4 * k] = dpdc * c_[:, 2]
        amod[:, :, 1 + 4 * k] = ks
        for c in range(3):
            coef[:, c, mhx_ks(k).start + c, 1 + 4 * k] = 1.0
            coef[:, c, MHX_LNM, 2 + 4 * k] = ks[:, c]
            coef[:, c, mhx_theta(k), 3 + 4 * k] = ks[:, c]
            coef[:, c, mhx_phi(k), 4 + 4 * k] = ks[:, c]
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


def _scaled_problem(L: np.ndarray, W: np.ndarray, P0: np.ndarray):
    """The bounded x-space problem of a batch of texels (L (B, N, 3), weights W (B, N),
    parameters P0 (B, 4 + 6K)): each texel's radiance scale s (B,) (its mean weighted
    radiance), the scaled radiance, the start in x space clipped to the bounds, and the
    bounds lb (nx,), ub (B, nx) (Ks capped at KS_CAP x the brightest scaled
    observation)."""
    K = mh_lobes(P0.shape[1])
    s = np.maximum(np.einsum("nvc,nv->n", L, W) / np.maximum(3 * W.sum(1), 1), 1e-12)
    Ls = L / s[:, None, None]
    X = _params_to_x_batch(P0, s)
    lb, ub1 = _bounds(K)
    ub = np.broadcast_to(ub1, X.shape).copy()
    ksmax = KS_CAP * np.where(W[..., None] > 0, Ls, 0).max((1, 2))
    for k in range(K):
        ub[:, mhx_ks(k)] = ksmax[:, None]
    return s, Ls, np.clip(X, lb, ub), lb, ub


def refine_batch(V: np.ndarray, L: np.ndarray, W: np.ndarray, P0: np.ndarray,
                 iters: int | None = None, why: bool = False, state: bool = False,
                 ) -> np.ndarray | tuple:
    """Projected Levenberg-Marquardt steps on a batch of texels at once (vectorised),
    in the bounded x-space of the nlopt fit. Brings an initial guess close to the
    optimum so the per-texel nlopt fit only polishes. (B, N, 3) inputs, (B, 4 + 6K).
    With ``why``, also (B,) bool: the compiled LM converged there (the polish needs no
    LM steps of its own); with ``state`` as well, the (B, 1 + 2 nx) cost, gradient and
    Gauss-Newton diagonal at the result (:func:`polish_batch`'s ``state``; None
    without the compiled LM)."""
    K = mh_lobes(P0.shape[1])
    s, Ls, X, lb, ub = _scaled_problem(L, W, P0)
    if lm_batch is not None:
        st = np.empty((len(X), 1 + 2 * X.shape[1]))
        stop = lm_batch(X, np.ascontiguousarray(V, float), np.ascontiguousarray(Ls, float),
                        np.ascontiguousarray(W, float), K, lb, ub, iters or LM_ITERS, LM_FTOL,
                        st)
        P = _x_to_params_batch(X, s)
        if state:
            return P, stop == LM_CONVERGED, st
        return (P, stop == LM_CONVERGED) if why else P
    iters = iters or 8
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
    P = _x_to_params_batch(X, s)
    if state:
        return P, np.zeros(len(P), bool), None
    return (P, np.zeros(len(P), bool)) if why else P


def polish_batch(V: np.ndarray, L: np.ndarray, W: np.ndarray, P0: np.ndarray,
                 cfg: MhFitConfig, state: np.ndarray | None = None,
                 ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, int]:
    """One bounded nlopt run over a whole batch of texels (least squares only).

    The sum of the texels' objectives is separable, so its minimum is every texel's own
    minimum; one nlopt call with the stacked parameters evaluates all texels in a few
    vectorised numpy operations instead of a Python callback per texel. Started next
    to the optimum (:func:`refine_batch`), it needs few evaluations. A texel whose
    projected gradient is not small afterwards is reported as not converged, and
    :func:`fit_mh_tile` fits it alone with :func:`fit_texel`.

    ``state`` (B, 1 + 2 nx), from :func:`refine_batch` when P0 is its result: the cost
    and gradient there serve nlopt's first evaluation, and each variable is scaled by
    the square root of its Gauss-Newton diagonal (L-BFGS starts from a unit Hessian:
    scaled, its first step is about right; one evaluation fewer on 004's scenes).

    Returns
    -------
    params (B, 4 + 6K), rss (B,) in radiance units, evaluations, converged (B,) bool,
    nlopt result code.
    """
    B = len(P0)
    K = mh_lobes(P0.shape[1])
    s, Ls, X0, lb, ub = _scaled_problem(L, W, P0)
    lb = np.broadcast_to(lb, X0.shape)
    nx = X0.shape[1]
    D = np.ones_like(X0) if state is None else \
        np.sqrt(np.maximum(state[:, 1 + nx:], 1e-300))
    D = np.where(np.isfinite(D) & (D > 0), D, 1.0)
    first = None if state is None else (X0 * D).ravel()
    best = [math.inf, X0.ravel().copy(), None]
    if cost_grad_batch is not None:
        Vc, Lc, Wc = (np.ascontiguousarray(a, float) for a in (V, Ls, W))

        def objective(X):
            cost, g = np.empty(B), np.empty((B, nx))
            cost_grad_batch(X, Vc, Lc, Wc, K, 0, 1.0, g, True, cost)
            return cost, g
    else:
        LL = (W[..., None] * Ls * Ls).sum(1)

        def objective(X):
            cost, _, g = _normal_equations(X, V, Ls, W, K, LL, need_A=False)
            return np.maximum(cost, 0.0), 2 * g

    def fn(y: np.ndarray, grad: np.ndarray) -> float:
        X = y.reshape(B, nx) / D
        if first is not None and np.array_equal(y, first):
            cost, g = state[:, 0], state[:, 1:1 + nx]  # the LM's last evaluation
        else:
            cost, g = objective(X)
        val = float(cost.sum())
        if grad.size > 0:
            grad[:] = (g / D).ravel()
        if val < best[0]:
            best[0], best[1], best[2] = val, X.ravel().copy(), (cost, g)
        return val

    opt = nlopt.opt(ALGORITHMS.get(cfg.algorithm, nlopt.LD_LBFGS), B * nx)
    opt.set_lower_bounds((lb * D).ravel())
    opt.set_upper_bounds((ub * D).ravel())
    opt.set_min_objective(fn)
    opt.set_ftol_rel(cfg.ftol_rel)
    opt.set_xtol_rel(cfg.xtol_rel)
    # few evaluations: texels that need more are better served alone afterwards
    opt.set_maxeval(min(cfg.max_evals, BATCH_EVALS))
    try:
        opt.optimize((X0 * D).ravel())
        code = int(opt.last_optimize_result())
    except Exception:  # noqa: BLE001 - keep the best point (round-off stops)
        code = -4
    X = best[1].reshape(B, nx)
    if best[2] is None:
        fn((X * D).ravel(), np.empty(B * nx))
    cost, grad = best[2]
    # first-order check per texel: no coordinate can still lower the cost by more
    # than a tiny fraction with a small relative step
    free = ~(((X <= lb) & (grad > 0)) | ((X >= ub) & (grad < 0)))
    pg = np.where(free, grad, 0.0) * np.maximum(np.abs(X), 0.1)
    converged = np.abs(pg).max(1) <= 1e-3 * np.maximum(cost, 1e-12)
    P = np.stack([_sort_lobes(p) for p in _x_to_params_batch(X, s)])
    return P, cost * s * s, int(opt.get_numevals()), converged, code


@dataclass(frozen=True)
class MhFitConfig:
    """Options of the per-texel fit (config section ``fit.mh``)."""

    algorithm: str = default("fit.mh.algorithm")
    init: str = default("fit.mh.init")  # better | published
    loss: str = default("fit.mh.loss")  # linear | soft_l1 | huber
    # robust loss scale, relative to the texel's radiance scale
    f_scale: float = default("fit.mh.f_scale")
    max_evals: int = default("fit.mh.max_evals")
    # stop when a step lowers the cost by less than 1e-7 of itself: for a texel of n
    # residuals near reduced chi-square 1, a change of ~1e-7 n in chi-square, far below
    # the 1 that moves a parameter by one standard deviation (1e-10 spent 3x the
    # evaluations crawling along flat valleys, for residuals lower by 0.4 %)
    ftol_rel: float = 1e-7
    xtol_rel: float = 1e-6
    # auto-K adds a lobe only if BIC drops by more
    bic_margin: float = default("fit.mh.bic_margin")
    # residuals below this fraction of the radiance are noise
    bic_floor: float = default("fit.mh.bic_floor")
    # batch (LM-converged texels stacked in one run) | texel (each alone)
    polish: str = default("fit.mh.polish")
    # K fixed >= 2: keep the K-th lobe where it predicts left-out views better than K - 1
    # lobes, judged over this many texels across (0: always K lobes)
    lobe_window: int = default("fit.mh.lobe_window")


@dataclass
class FitResult:
    params: np.ndarray  # (4 + 6K,)
    rss: float
    evals: int
    status: int
    nlopt_code: int


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
        nograd = np.empty(mhx_size(K))

        def fn_c(x: np.ndarray, grad: np.ndarray) -> float:
            want = grad.size > 0
            val = cost_grad(x, Vc, Lc, wv, K, code, fl, grad if want else nograd, want)
            if val < best[0]:
                best[0], best[1] = val, x.copy()
            return val

        fn_c.best = best
        return fn_c

    idx_ks = np.array([mhx_ks(k).start + c for k in range(K) for c in range(3)])
    idx_th = np.array([mhx_theta(k) for k in range(K)])
    idx_ph = idx_th + 1

    def fn(x: np.ndarray, grad: np.ndarray) -> float:
        m = math.exp(x[MHX_LNM])
        th, ph = x[idx_th], x[idx_ph]
        st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
        C = V @ np.stack([st * cp, st * sp, ct], 1).T  # (n, K)
        pos = C > 0
        Cs = np.where(pos, C, 1.0)
        lc = np.log(Cs)
        P = np.where(pos, np.exp(m * lc), 0.0)
        KS = x[idx_ks].reshape(K, 3)
        r = P @ KS + x[MHX_KD] - L
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
            grad[MHX_KD] = dr.sum(0)
            grad[idx_ks] = (P.T @ dr).ravel()
            GP = G * P
            grad[MHX_LNM] = float(np.vdot(GP, lc)) * m
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
              cfg: MhFitConfig = MhFitConfig(), w: np.ndarray | None = None,
              polish: bool = True, lm: bool = True, fixed_m: bool = False) -> FitResult:
    """Bounded nlopt fit of one texel from initial parameters ``p0`` (4 + 6K), after
    compiled Levenberg-Marquardt steps (where numba is present; ``polish=False``: those
    steps only, to rank several starts before polishing the best; ``lm=False``: none,
    for a start the batch LM already converged).

    Parameters
    ----------
    V : (n, 3) unit view directions of the valid observations.
    L : (n, 3) their radiance.
    w : (n,) observation weights (:mod:`.weights`; default 1); the RSS is weighted.
    fixed_m : keep the shininess of ``p0`` (its bounds closed on it).

    Returns
    -------
    FitResult with parameters in docs/reference/conventions.md layout (lobes sorted by strength) and
    the residual sum of squares in radiance units squared.
    """
    K = mh_lobes(len(p0))
    s = max(float(L.mean()), 1e-12)
    Ls = L / s
    x0 = _to_x(p0, s)
    nx = len(x0)
    lb, ub = _bounds(K, KS_CAP * float(Ls.max()))
    x0 = np.clip(x0, lb, ub)
    if fixed_m:
        lb[MHX_LNM] = ub[MHX_LNM] = x0[MHX_LNM]
    if lm and lm_batch is not None and cfg.loss == "linear" and K > 0:
        # compiled LM steps first (cheap, and quadratic near the optimum): nlopt polishes
        X = x0[None].copy()
        lm_batch(X, np.ascontiguousarray(V, float)[None], np.ascontiguousarray(Ls, float)[None],
                 (np.ones(len(V)) if w is None else np.asarray(w, float))[None], K, lb,
                 ub[None], LM_ITERS, LM_FTOL, np.empty((1, 1 + 2 * nx)))
        x0 = X[0]
    if not polish:
        p = _sort_lobes(_from_x(x0, s))
        rss = float(np.sum((1.0 if w is None else w[:, None]) * (mh_eval(p, V) - L) ** 2))
        ok = np.all(np.isfinite(p)) and math.isfinite(rss)
        return FitResult(p, rss, 0, FitStatus.OK if ok else FitStatus.FAILED, 0)
    opt = nlopt.opt(ALGORITHMS[cfg.algorithm], nx)
    opt.set_lower_bounds(lb)
    opt.set_upper_bounds(ub)
    fn = _objective(V, Ls, K, cfg.loss, cfg.f_scale, w=w)
    opt.set_min_objective(fn)
    opt.set_ftol_rel(cfg.ftol_rel)
    opt.set_xtol_rel(cfg.xtol_rel)
    opt.set_maxeval(cfg.max_evals)
    status = FitStatus.OK
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
        status = FitStatus.FAILED
    return FitResult(p, rss, int(opt.get_numevals()), status, code)
