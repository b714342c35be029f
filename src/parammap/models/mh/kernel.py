"""Compiled cost and gradient of the MH least-squares objective for one texel.

nlopt calls its objective once per evaluation from Python; at a few hundred
observations a numpy version spends most of its ~40 us in per-call overhead. This
kernel does the same arithmetic in one compiled loop (numba), a few microseconds.
:func:`parammap.models.mh.fit._objective` falls back to numpy where numba is missing.
"""

from __future__ import annotations

import math

import numpy as np

from ...conventions import MH_HEAD, MH_LOBE, MHX_LNM, MHX_LOBE

try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised only without numba
    njit = None

LOSSES = {"linear": 0, "soft_l1": 1, "huber": 2}


def _jit(f, fallback=None):
    """``f`` compiled by numba (cached on disk, GIL released), or ``fallback`` where numba
    is missing (None for the entry points: callers then take their numpy paths)."""
    return njit(cache=True, nogil=True)(f) \
        if njit is not None else fallback


def _sum(a: np.ndarray) -> float:
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i]
    return s


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


def _dot3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i] * c[i]
    return s


# sums over the observations, allowed to reassociate (so they vectorise: several times
# faster; the order changes only the last bits): the kernels store per-observation
# values first and form their products with these
if njit is not None:
    _sum, _dot, _dot3 = (njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})(f)
                         for f in (_sum, _dot, _dot3))


def _lobe_frames(x: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each lobe's unit direction and its derivatives by theta and phi, (K, 3) each,
    from the x-space angles."""
    d = np.empty((K, 3))
    dth = np.empty((K, 3))
    dph = np.empty((K, 3))
    for k in range(K):
        b = MH_HEAD + MHX_LOBE * k
        st, ct = math.sin(x[b + 3]), math.cos(x[b + 3])
        sp, cp = math.sin(x[b + 4]), math.cos(x[b + 4])
        d[k, 0], d[k, 1], d[k, 2] = st * cp, st * sp, ct
        dth[k, 0], dth[k, 1], dth[k, 2] = ct * cp, ct * sp, -st
        dph[k, 0], dph[k, 1], dph[k, 2] = -st * sp, st * cp, 0.0
    return d, dth, dph


_lobe_frames = _jit(_lobe_frames, _lobe_frames)


def _observe(x: np.ndarray, V: np.ndarray, L: np.ndarray, i: int, K: int, m: float,
             d: np.ndarray, dth: np.ndarray, dph: np.ndarray, qT: np.ndarray,
             want: bool) -> tuple[float, float, float]:
    """Residual (model minus radiance) of observation i (V, L (n, 3)) per channel, for
    x-space parameters x with shininess m and lobe frames d, dth, dph
    (:func:`_lobe_frames`); with ``want`` also its per-lobe values into column i of
    qT (rows 1 + 4k ... 4 + 4k: p, m p ln(cos), dp/dtheta, dp/dphi)."""
    v0, v1, v2 = V[i, 0], V[i, 1], V[i, 2]
    r0, r1, r2 = x[0] - L[i, 0], x[1] - L[i, 1], x[2] - L[i, 2]
    for k in range(K):
        c = v0 * d[k, 0] + v1 * d[k, 1] + v2 * d[k, 2]
        j = 1 + 4 * k
        if c > 0.0:
            lc = math.log(c)
            p = math.exp(m * lc)
            b = MH_HEAD + MHX_LOBE * k
            r0 += x[b] * p
            r1 += x[b + 1] * p
            r2 += x[b + 2] * p
            if want:
                dpdc = p * m / c
                qT[j, i] = p
                qT[j + 1, i] = p * lc * m
                qT[j + 2, i] = dpdc * (v0 * dth[k, 0] + v1 * dth[k, 1] + v2 * dth[k, 2])
                qT[j + 3, i] = dpdc * (v0 * dph[k, 0] + v1 * dph[k, 1])
        elif want:
            qT[j, i] = 0.0
            qT[j + 1, i] = 0.0
            qT[j + 2, i] = 0.0
            qT[j + 3, i] = 0.0
    return r0, r1, r2


_observe = _jit(_observe, _observe)


def _cost_grad(x: np.ndarray, V: np.ndarray, L: np.ndarray, Wt: np.ndarray, K: int,
               loss: int, f: float, grad: np.ndarray, want_grad: bool) -> float:
    """Cost of x-space parameters ``x`` (``conventions.mhx_size(K)``) on directions
    V (n, 3) and scaled radiance L (n, 3), each observation weighted by Wt (n,); fills
    ``grad`` when ``want_grad``. Same layout and maths as the numpy objective in
    :mod:`parammap.models.mh.fit`.

    As in :func:`_normal_texel`, the per-observation values (the loss derivative per
    channel, and per lobe p, m p ln(cos), dp/dtheta, dp/dphi) are stored first and the
    gradient formed from dot products over the observations."""
    n = V.shape[0]
    nb = 1 + 4 * K
    m = math.exp(x[MHX_LNM])
    d, dth, dph = _lobe_frames(x, K)
    qT = np.empty((nb, n)) if want_grad else np.empty((0, 0))
    eT = np.empty((3, n)) if want_grad else np.empty((0, 0))
    val = 0.0
    for i in range(n):
        r0, r1, r2 = _observe(x, V, L, i, K, m, d, dth, dph, qT, want_grad)
        wt = Wt[i]
        if loss == 0:
            val += wt * (r0 * r0 + r1 * r1 + r2 * r2)
            e0, e1, e2 = 2.0 * r0, 2.0 * r1, 2.0 * r2
        elif loss == 1:
            q0 = math.sqrt(1.0 + (r0 / f) ** 2)
            q1 = math.sqrt(1.0 + (r1 / f) ** 2)
            q2 = math.sqrt(1.0 + (r2 / f) ** 2)
            val += wt * 2.0 * f * f * (q0 - 1.0 + q1 - 1.0 + q2 - 1.0)
            e0, e1, e2 = 2.0 * r0 / q0, 2.0 * r1 / q1, 2.0 * r2 / q2
        else:
            a0, a1, a2 = abs(r0), abs(r1), abs(r2)
            val += wt * (r0 * r0 if a0 <= f else 2.0 * f * a0 - f * f)
            val += wt * (r1 * r1 if a1 <= f else 2.0 * f * a1 - f * f)
            val += wt * (r2 * r2 if a2 <= f else 2.0 * f * a2 - f * f)
            e0 = 2.0 * r0 if a0 <= f else 2.0 * f * math.copysign(1.0, r0)
            e1 = 2.0 * r1 if a1 <= f else 2.0 * f * math.copysign(1.0, r1)
            e2 = 2.0 * r2 if a2 <= f else 2.0 * f * math.copysign(1.0, r2)
        if want_grad:
            eT[0, i], eT[1, i], eT[2, i] = wt * e0, wt * e1, wt * e2
    if not want_grad:
        return val
    for j in range(grad.shape[0]):
        grad[j] = 0.0
    for c in range(3):
        grad[c] = _sum(eT[c])
        for k in range(K):
            b = MH_HEAD + MHX_LOBE * k
            ks = x[b + c]
            for a in range(4):
                t = _dot(qT[1 + 4 * k + a], eT[c])
                if a == 0:
                    grad[b + c] = t
                elif a == 1:
                    grad[MHX_LNM] += ks * t
                else:
                    grad[b + 1 + a] += ks * t
    return val


cost_grad = _jit(_cost_grad)


def _eval_batch(P: np.ndarray, V: np.ndarray, out: np.ndarray) -> None:
    """MH radiance of B parameter vectors P (B, 4 + 6K) (docs/reference/conventions.md layout) in
    their directions V (B, N, 3), into ``out`` (B, N, 3): the compiled
    :func:`parammap.models.mh.model.mh_eval` for a batch of texels."""
    B, N = V.shape[0], V.shape[1]
    K = (P.shape[1] - MH_HEAD) // MH_LOBE
    for t in range(B):
        m = P[t, 3]
        nk = 0  # lobes up to the last with some Ks (the others add 0)
        for k in range(K):
            b = MH_HEAD + MH_LOBE * k
            if P[t, b] != 0.0 or P[t, b + 1] != 0.0 or P[t, b + 2] != 0.0:
                nk = k + 1
        for n in range(N):
            r0, r1, r2 = P[t, 0], P[t, 1], P[t, 2]
            for k in range(nk):
                b = MH_HEAD + MH_LOBE * k
                c = V[t, n, 0] * P[t, b + 3] + V[t, n, 1] * P[t, b + 4] \
                    + V[t, n, 2] * P[t, b + 5]
                if c > 0.0:
                    p = math.exp(m * math.log(c))
                    r0 += P[t, b] * p
                    r1 += P[t, b + 1] * p
                    r2 += P[t, b + 2] * p
            out[t, n, 0], out[t, n, 1], out[t, n, 2] = r0, r1, r2


eval_batch = _jit(_eval_batch)


def _residual_stats(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                    rmse: np.ndarray, mpr: np.ndarray) -> None:
    """Per texel and channel, the RMSE and 004's mean percentage residual
    (:func:`parammap.models.residuals.mean_percentage_residual`) of MH parameters
    P (B, 4 + 6K) on the valid (W (B, N) bool) observations V, L (B, N, 3); into
    ``rmse`` and ``mpr`` (B, 3)."""
    B, N = W.shape
    f = np.empty((N, 3))
    for t in range(B):
        _eval_batch(P[t:t + 1], V[t:t + 1], f.reshape((1, N, 3)))
        n = 0
        top = np.zeros(3)
        for v in range(N):
            if W[t, v]:
                n += 1
                for c in range(3):
                    top[c] = max(top[c], abs(L[t, v, c]))
        for c in range(3):
            se, pe = 0.0, 0.0
            floor = 1e-9 * top[c] + 1e-30
            for v in range(N):
                if W[t, v]:
                    r = f[v, c] - L[t, v, c]
                    se += r * r
                    pe += 100.0 * abs(r) / max(abs(L[t, v, c]), floor)
            rmse[t, c] = math.sqrt(se / max(n, 1))
            mpr[t, c] = pe / max(n, 1)


def _rss_batch(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
               rss: np.ndarray) -> None:
    """Residual sum of squares over the valid observations (W (B, N) bool) of MH
    parameters P (B, 4 + 6K) on V, L (B, N, 3), into ``rss`` (B,)."""
    B, N = W.shape
    f = np.empty((N, 3))
    for t in range(B):
        _eval_batch(P[t:t + 1], V[t:t + 1], f.reshape((1, N, 3)))
        s = 0.0
        for v in range(N):
            if W[t, v]:
                for c in range(3):
                    r = f[v, c] - L[t, v, c]
                    s += r * r
        rss[t] = s


def _lobe_support(P: np.ndarray, V: np.ndarray, W: np.ndarray, k: int, thr: np.ndarray,
                  count: np.ndarray) -> None:
    """Per texel, how many valid observations (W (B, N) bool) see lobe k of P
    (B, 4 + 6K) above ``thr`` (B,): max over channels of Ks (d . v)^m, into
    ``count`` (B,)."""
    B, N = W.shape
    b = MH_HEAD + MH_LOBE * k
    for t in range(B):
        m = P[t, 3]
        top = max(P[t, b], P[t, b + 1], P[t, b + 2])
        n = 0
        if top > 0.0 and thr[t] < top:
            # (d . v)^m > thr / top  <=>  d . v > (thr / top)^(1/m)
            cmin = math.exp(math.log(thr[t] / top) / m) if thr[t] > 0.0 else 0.0
            for v in range(N):
                if W[t, v]:
                    c = V[t, v, 0] * P[t, b + 3] + V[t, v, 1] * P[t, b + 4] \
                        + V[t, v, 2] * P[t, b + 5]
                    if c > cmin:
                        n += 1
        count[t] = n


_eval_batch = _jit(_eval_batch, _eval_batch)
rss_batch = _jit(_rss_batch)
lobe_support = _jit(_lobe_support)
residual_stats = _jit(_residual_stats)


def _cost_grad_batch(X: np.ndarray, V: np.ndarray, L: np.ndarray, Wt: np.ndarray, K: int,
                     loss: int, f: float, grad: np.ndarray, want_grad: bool,
                     cost: np.ndarray) -> float:
    """:func:`_cost_grad` of every texel of a batch: X (B, nx), V and L (B, N, 3),
    Wt (B, N); each texel's cost into ``cost`` (B,) and, with ``want_grad``, its
    gradient into ``grad`` (B, nx). Returns the sum (the objective of the stacked
    polish, whose minimum is every texel's own)."""
    total = 0.0
    g = np.empty(X.shape[1])
    for b in range(X.shape[0]):
        c = _cost_grad(X[b], V[b], L[b], Wt[b], K, loss, f, g, want_grad)
        cost[b] = c
        total += c
        if want_grad:
            for i in range(X.shape[1]):
                grad[b, i] = g[i]
    return total


_cost_grad = _jit(_cost_grad, _cost_grad)
cost_grad_batch = _jit(_cost_grad_batch)


def _gram_numpy(A: np.ndarray, Y: np.ndarray, w: np.ndarray):
    Aw = A * w[..., None]
    # matmul, not einsum: an order of magnitude faster for these batched products
    G = np.matmul(Aw.transpose(0, 2, 1), A)
    R = np.matmul(Y.transpose(0, 2, 1), Aw)
    yy = (w[..., None] * Y * Y).sum((1, 2))
    return G, R, yy


def _gram_loop(A: np.ndarray, Y: np.ndarray, w: np.ndarray):
    B, N, P = A.shape
    C = Y.shape[2]
    G = np.zeros((B, P, P), A.dtype)
    R = np.zeros((B, C, P), A.dtype)
    yy = np.zeros(B, A.dtype)
    At = np.empty((P, N), A.dtype)  # one texel's weighted design, column-major
    Yt = np.empty((C, N), A.dtype)
    for b in range(B):
        for n in range(N):
            wn = w[b, n]
            for p in range(P):
                At[p, n] = A[b, n, p] * wn
            for c in range(C):
                Yt[c, n] = Y[b, n, c]
        for p in range(P):
            for q in range(p, P):
                s = 0.0
                for n in range(N):
                    s += At[p, n] * A[b, n, q]
                G[b, p, q] = s
                G[b, q, p] = s
            for c in range(C):
                s = 0.0
                for n in range(N):
                    s += At[p, n] * Yt[c, n]
                R[b, c, p] = s
        s = 0.0
        for c in range(C):
            for n in range(N):
                s += w[b, n] * Yt[c, n] * Yt[c, n]
        yy[b] = s
    return G, R, yy


# fastmath: lets the sums vectorise (reassociation only changes the last bits)
_gram_compiled = njit(cache=True, nogil=True, fastmath=True)(_gram_loop) \
    if njit is not None else None
GRAM_LOOP_MAX_P = 4  # above this, numpy's batched matmul is the faster one


def gram(A: np.ndarray, Y: np.ndarray, w: np.ndarray):
    """Weighted Gram products of many small least-squares problems.

    A : (B, N, P) design, Y : (B, N, C) targets, w : (B, N) weights.
    Returns G = A^T W A (B, P, P), R = Y^T W A (B, C, P) and yy = sum w Y^2 (B,).
    Compiled for P <= ``GRAM_LOOP_MAX_P`` where numba is present (numpy's batched
    matmul is slow for a P of a few, and faster beyond).
    """
    if _gram_compiled is None or A.shape[2] > GRAM_LOOP_MAX_P:
        return _gram_numpy(A, Y, w)
    return _gram_compiled(A, Y, w.astype(A.dtype, copy=False))



