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
    """MH radiance of B parameter vectors P (B, 4 + 6K) (conventions.md layout) in
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


LM_CONVERGED, LM_DAMPED, LM_CAPPED = 0, 1, 2


def _normal_texel(x: np.ndarray, V: np.ndarray, L: np.ndarray, Wt: np.ndarray, K: int,
                  A: np.ndarray, g: np.ndarray, Q: np.ndarray, QR: np.ndarray,
                  want: bool, qT: np.ndarray, rT: np.ndarray) -> float:
    """Weighted least-squares cost of one texel in x-space; with ``want`` also the
    Gauss-Newton matrix J^T W J into ``A`` (nx, nx) and J^T W r into ``g`` (nx,).

    Every Jacobian column of channel c is a multiple of one of the 1 + 4K vectors
    q = (1, and per lobe p, m p ln(cos), dp/dtheta, dp/dphi) over the observations (the
    ln m column: a sum over lobes), so the weighted Gram matrix of q (``Q``, (1 + 4K)^2)
    and q^T W r (``QR``, (1 + 4K, 3)) give A and g: no (3N, nx) Jacobian is formed."""
    n = V.shape[0]
    nx = x.shape[0]
    nb = 1 + 4 * K
    m = math.exp(x[MHX_LNM])
    d, dth, dph = _lobe_frames(x, K)
    val = 0.0
    # q and the residuals per observation first (qT (nb, N), rT (3, N): observations
    # contiguous), then their weighted products as dot products over the observations,
    # which vectorise (accumulating into Q per observation does not)
    for i in range(n):
        wt = Wt[i]
        r0, r1, r2 = _observe(x, V, L, i, K, m, d, dth, dph, qT, want)
        val += wt * (r0 * r0 + r1 * r1 + r2 * r2)
        if want:
            qT[0, i] = wt  # the weighted constant column: q_0 w q_b = w q_b
            rT[0, i], rT[1, i], rT[2, i] = r0, r1, r2
    if want:
        for a in range(nb):
            for c in range(3):
                QR[a, c] = _dot(qT[0, :n], rT[c, :n]) if a == 0 else \
                    _dot3(qT[0, :n], qT[a, :n], rT[c, :n])
            for b in range(a, nb):
                if a == 0:
                    Q[a, b] = _sum(qT[0, :n]) if b == 0 else _dot(qT[0, :n], qT[b, :n])
                else:
                    Q[a, b] = _dot3(qT[0, :n], qT[a, :n], qT[b, :n])
    if not want:
        return val
    for a in range(nb):
        for b in range(a):
            Q[a, b] = Q[b, a]
    for i in range(nx):
        g[i] = 0.0
        for j in range(nx):
            A[i, j] = 0.0
    # per channel: rows with one q (Kd_c, Ks_kc, theta_k, phi_k) as (x index, q index,
    # factor), and the ln m row, sum_k Ks_kc q_(2 + 4k)
    nz = 1 + 3 * K
    xi = np.empty(nz, np.int64)
    qi = np.empty(nz, np.int64)
    sc = np.empty(nz)
    u = np.empty(nb)  # the ln m row's combination of q, per channel
    for ch in range(3):
        xi[0], qi[0], sc[0] = ch, 0, 1.0
        for a in range(nb):
            u[a] = 0.0
        for k in range(K):
            b = MH_HEAD + MHX_LOBE * k
            ks = x[b + ch]
            xi[1 + 3 * k], qi[1 + 3 * k], sc[1 + 3 * k] = b + ch, 1 + 4 * k, 1.0
            xi[2 + 3 * k], qi[2 + 3 * k], sc[2 + 3 * k] = b + 3, 3 + 4 * k, ks
            xi[3 + 3 * k], qi[3 + 3 * k], sc[3 + 3 * k] = b + 4, 4 + 4 * k, ks
            u[2 + 4 * k] = ks
        for a in range(nz):
            g[xi[a]] += sc[a] * QR[qi[a], ch]
            for b in range(nz):
                A[xi[a], xi[b]] += sc[a] * sc[b] * Q[qi[a], qi[b]]
            t = 0.0
            for k in range(K):
                t += u[2 + 4 * k] * Q[2 + 4 * k, qi[a]]
            A[MHX_LNM, xi[a]] += sc[a] * t
            A[xi[a], MHX_LNM] += sc[a] * t
        t = 0.0
        gl = 0.0
        for k in range(K):
            gl += u[2 + 4 * k] * QR[2 + 4 * k, ch]
            for l2 in range(K):
                t += u[2 + 4 * k] * u[2 + 4 * l2] * Q[2 + 4 * k, 2 + 4 * l2]
        A[MHX_LNM, MHX_LNM] += t
        g[MHX_LNM] += gl
    return val


def _cholesky(M: np.ndarray, floor: float) -> bool:
    """Cholesky factor of the symmetric M (n, n) in place of its lower triangle; False
    where a pivot is not above ``floor`` (M not positive definite, or nearly singular)."""
    n = M.shape[0]
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s -= M[j, k] * M[j, k]
        if not s > floor:
            return False
        s = math.sqrt(s)
        M[j, j] = s
        for i in range(j + 1, n):
            t = M[i, j]
            for k in range(j):
                t -= M[i, k] * M[j, k]
            M[i, j] = t / s
    return True


def _chol_solve(M: np.ndarray, rhs: np.ndarray, out: np.ndarray) -> bool:
    """Solve the symmetric positive definite system M out = rhs by Cholesky, in place
    of M's lower triangle; False if M is not positive definite."""
    n = M.shape[0]
    if not _cholesky(M, 0.0):
        return False
    for i in range(n):
        t = rhs[i]
        for k in range(i):
            t -= M[i, k] * out[k]
        out[i] = t / M[i, i]
    for i in range(n - 1, -1, -1):
        t = out[i]
        for k in range(i + 1, n):
            t -= M[k, i] * out[k]
        out[i] = t / M[i, i]
    return True


def _spd_inverse(A: np.ndarray, Ai: np.ndarray) -> bool:
    """Ai = A^-1 for a symmetric positive definite A (n, n) by Cholesky; False (Ai
    undefined) where A is not positive definite or a pivot falls below 1e-12 of A's
    largest diagonal element: there the caller takes the pseudo-inverse."""
    n = A.shape[0]
    M = np.empty((n, n))
    top = 0.0
    for i in range(n):
        top = max(top, A[i, i])
        for j in range(n):
            M[i, j] = A[i, j]
    if not _cholesky(M, 1e-12 * top):
        return False
    # inverse of the factor L (lower), then A^-1 = L^-T L^-1
    Li = np.zeros((n, n))
    for i in range(n):
        Li[i, i] = 1.0 / M[i, i]
        for j in range(i):
            t = 0.0
            for k in range(j, i):
                t -= M[i, k] * Li[k, j]
            Li[i, j] = t / M[i, i]
    for i in range(n):
        for j in range(i + 1):
            t = 0.0
            for k in range(i, n):
                t += Li[k, i] * Li[k, j]
            Ai[i, j] = t
            Ai[j, i] = t
    return True


def _lm_batch(X: np.ndarray, V: np.ndarray, L: np.ndarray, Wt: np.ndarray, K: int,
              lb: np.ndarray, ub: np.ndarray, iters: int, ftol: float,
              state: np.ndarray) -> np.ndarray:
    """Bounded Levenberg-Marquardt for each texel of a batch, in place on ``X``
    (B, nx) x-space starts (scaled radiance L (B, N, 3), weights Wt (B, N), bounds
    lb (nx,) and ub (B, nx)). A variable at a bound whose gradient pushes outward is
    held for the step (active set), so the others keep converging; a texel stops when
    a step lowers its cost by less than ``ftol`` (relative) or the damping saturates.
    Returns why each texel stopped (B,): :data:`LM_CONVERGED`, :data:`LM_DAMPED` (no
    step lowers the cost) or :data:`LM_CAPPED` (``iters`` steps). Writes ``state``
    (B, 1 + 2 nx) at the point reached: the cost, its gradient, and the diagonal of the
    Gauss-Newton matrix J^T W J (for the polish that follows: its first evaluation and
    the scale of its variables)."""
    B, nx = X.shape
    nb = 1 + 4 * K
    Q = np.empty((nb, nb))
    QR = np.empty((nb, 3))
    A = np.empty((nx, nx))
    An = np.empty((nx, nx))
    M = np.empty((nx, nx))
    g = np.empty(nx)
    gn = np.empty(nx)
    rhs = np.empty(nx)
    step = np.empty(nx)
    xn = np.empty(nx)
    fixed = np.empty(nx, np.bool_)
    qT = np.empty((nb, V.shape[1]))  # scratch of _normal_texel
    rT = np.empty((3, V.shape[1]))
    why = np.full(B, 2, np.int64)
    for b in range(B):
        x = X[b]
        for i in range(nx):
            x[i] = min(max(x[i], lb[i]), ub[b, i])
        cost = _normal_texel(x, V[b], L[b], Wt[b], K, A, g, Q, QR, True, qT, rT)
        lam = 1e-3
        it = 0
        while it < iters:
            it += 1
            for i in range(nx):
                fixed[i] = (x[i] <= lb[i] and g[i] > 0.0) or (x[i] >= ub[b, i] and g[i] < 0.0)
            for i in range(nx):
                for j in range(nx):
                    M[i, j] = 0.0 if (fixed[i] or fixed[j]) else A[i, j]
                if fixed[i]:
                    M[i, i] = 1.0
                    rhs[i] = 0.0
                else:
                    M[i, i] = A[i, i] + lam * max(A[i, i], 1e-12)
                    rhs[i] = -g[i]
            if not _chol_solve(M, rhs, step):
                lam *= 10.0
                if lam > 1e10:
                    why[b] = 1
                    break
                continue
            for i in range(nx):
                xn[i] = min(max(x[i] + step[i], lb[i]), ub[b, i])
            # A and g with the cost in one pass: near the optimum most steps are taken
            cn = _normal_texel(xn, V[b], L[b], Wt[b], K, An, gn, Q, QR, True, qT, rT)
            if cn < cost:
                gain = (cost - cn) / max(cost, 1e-300)
                for i in range(nx):
                    x[i] = xn[i]
                    g[i] = gn[i]
                    for j in range(nx):
                        A[i, j] = An[i, j]
                cost = cn
                # a small gain means convergence only for a step near Gauss-Newton's:
                # a heavily damped step gains little anywhere
                if gain < ftol and lam < 1.0:
                    why[b] = 0
                    break
                lam = max(lam * 0.3, 1e-12)
            elif lam < 1.0 and cn - cost <= ftol * cost:
                # a near Gauss-Newton step that changes the cost by less than the
                # tolerance either way: at the optimum (round-off decides the sign)
                why[b] = 0
                break
            else:
                lam *= 10.0
                if lam > 1e10:
                    why[b] = 1
                    break
        state[b, 0] = cost
        for i in range(nx):
            state[b, 1 + i] = 2.0 * g[i]
            state[b, 1 + nx + i] = A[i, i]
    return why


_normal_texel = _jit(_normal_texel, _normal_texel)
_cholesky = _jit(_cholesky, _cholesky)
_chol_solve = _jit(_chol_solve, _chol_solve)
_spd_inverse = _jit(_spd_inverse, _spd_inverse)
lm_batch = _jit(_lm_batch)


def _sandwich_batch(X: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                    w: np.ndarray, K: np.ndarray, nlobes: np.ndarray, want_cov: bool,
                    loo: np.ndarray, bad: np.ndarray, var: np.ndarray) -> None:
    """Leave-one-view-out residuals and the HC3 sandwich of many texels (the compiled
    :func:`parammap.models.mh.uncertainty.loo_residuals` and ``parameter_sd``).

    X : (n, nx) x-space parameters (Kd, ln m, per lobe Ks, theta, phi; unscaled);
    V, L : (n, N, 3); W : (n, N) bool; w : (n, N) weights; nlobes : (n,) lobes used
    (the others' columns are not free). Writes ``loo`` (n, N, 3), ``bad`` (n,) (a
    view's leave-one-out block singular) and, with ``want_cov``, the variances of the
    free x-space parameters into ``var`` (n, nx) (NaN elsewhere).

    As in :func:`_normal_texel`, the Jacobian row of channel c puts each of the
    1 + 4K per-observation values q (1, and per free lobe p, m p ln(cos), dp/dtheta,
    dp/dphi) into one column (``col[c, a]``) times a factor of the texel
    (``fac[c, a]``). So J^T W J, each view's 3 x 3 hat block and the sandwich's middle
    term follow from the products q_a q_b (packed, a <= b): no (3N x nx) Jacobian.
    """
    n, N = W.shape
    nx = X.shape[1]
    Kx = (nx - MH_HEAD) // MHX_LOBE
    nbx = 1 + 4 * Kx
    npx = nbx * (nbx + 1) // 2
    qqT = np.zeros((npx, N))  # q_a q_b (a <= b) per view, views contiguous
    F2 = np.zeros((3, N))
    r = np.zeros((N, 3))
    q = np.zeros(nbx)
    col = np.zeros((3, nbx), np.int64)
    fac = np.zeros((3, nbx))
    pa = np.zeros(npx, np.int64)
    pb = np.zeros(npx, np.int64)
    S = np.zeros((6, npx))  # the six distinct hat-block quadratic forms, packed
    G = np.zeros((3, npx))
    h = np.empty((3, 3))
    for t in range(n):
        x = X[t]
        m = math.exp(x[MHX_LNM])
        nl = nlobes[t]
        # lobes are sorted, the first nl present: the free columns are a prefix of x
        # (without a lobe, Kd alone: no shininess to determine)
        nf = MH_HEAD + MHX_LOBE * nl if nl > 0 else 3
        nb = 1 + 4 * nl
        npk = nb * (nb + 1) // 2
        i = 0
        for a in range(nb):
            for b in range(a, nb):
                pa[i], pb[i] = a, b
                i += 1
        for c in range(3):
            col[c, 0], fac[c, 0] = c, 1.0
            for k in range(nl):
                b = MH_HEAD + MHX_LOBE * k
                ks = x[b + c]
                col[c, 1 + 4 * k], fac[c, 1 + 4 * k] = b + c, 1.0
                col[c, 2 + 4 * k], fac[c, 2 + 4 * k] = MHX_LNM, ks
                col[c, 3 + 4 * k], fac[c, 3 + 4 * k] = b + 3, ks
                col[c, 4 + 4 * k], fac[c, 4 + 4 * k] = b + 4, ks
        d, dth, dph = _lobe_frames(x, Kx)
        Qp = np.empty(npk)
        for v in range(N):
            for c in range(3):
                r[v, c] = 0.0
            if not W[t, v]:
                for i in range(npk):
                    qqT[i, v] = 0.0
                continue
            v0, v1, v2 = V[t, v, 0], V[t, v, 1], V[t, v, 2]
            q[0] = 1.0
            for a in range(1, nb):
                q[a] = 0.0
            r0, r1, r2 = x[0] - L[t, v, 0], x[1] - L[t, v, 1], x[2] - L[t, v, 2]
            for k in range(Kx):
                b = MH_HEAD + MHX_LOBE * k
                cs = v0 * d[k, 0] + v1 * d[k, 1] + v2 * d[k, 2]
                if cs <= 0.0:
                    continue
                lc = math.log(cs)
                p = math.exp(m * lc)
                r0 += x[b] * p
                r1 += x[b + 1] * p
                r2 += x[b + 2] * p
                if k < nl:  # a free lobe (the others: only their part of the prediction)
                    dpdc = m * p / cs
                    j = 1 + 4 * k
                    q[j] = p
                    q[j + 1] = p * m * lc
                    q[j + 2] = dpdc * (v0 * dth[k, 0] + v1 * dth[k, 1] + v2 * dth[k, 2])
                    q[j + 3] = dpdc * (v0 * dph[k, 0] + v1 * dph[k, 1])
            r[v, 0], r[v, 1], r[v, 2] = r0, r1, r2
            for i in range(npk):
                qqT[i, v] = q[pa[i]] * q[pb[i]]
        for i in range(npk):
            Qp[i] = _dot(w[t], qqT[i])
        # A = J^T W J over the free columns
        A = np.zeros((nf, nf))
        for c in range(3):
            for i in range(npk):
                a, b = pa[i], pb[i]
                z = fac[c, a] * fac[c, b] * Qp[i]
                A[col[c, a], col[c, b]] += z
                if a != b:
                    A[col[c, b], col[c, a]] += z
        Ai = np.empty((nf, nf))
        if not _spd_inverse(A, Ai):
            Ai = np.linalg.pinv(A)
        # hat block of a view: H[a, c] = w sum_ij q_i q_j fac[a, i] fac[c, j]
        # Ai[col[a, i], col[c, j]], symmetrised over (i, j) for the packed products
        s = 0
        for a in range(3):
            for c in range(a, 3):
                for i in range(npk):
                    ia, ib = pa[i], pb[i]
                    z = fac[a, ia] * fac[c, ib] * Ai[col[a, ia], col[c, ib]]
                    if ia != ib:
                        z += fac[a, ib] * fac[c, ia] * Ai[col[a, ib], col[c, ia]]
                    S[s, i] = z
                s += 1
        bad[t] = False
        for v in range(N):
            if not W[t, v]:
                for c in range(3):
                    loo[t, v, c] = 0.0
                continue
            wv = w[t, v]
            s = 0
            for a in range(3):
                for c in range(a, 3):
                    z = 0.0
                    for i in range(npk):
                        z += S[s, i] * qqT[i, v]
                    hv = (1.0 if a == c else 0.0) - wv * z
                    h[a, c] = hv
                    h[c, a] = hv
                    s += 1
            co00 = h[1, 1] * h[2, 2] - h[1, 2] * h[2, 1]
            co01 = h[0, 2] * h[2, 1] - h[0, 1] * h[2, 2]
            co02 = h[0, 1] * h[1, 2] - h[0, 2] * h[1, 1]
            co10 = h[1, 2] * h[2, 0] - h[1, 0] * h[2, 2]
            co11 = h[0, 0] * h[2, 2] - h[0, 2] * h[2, 0]
            co12 = h[0, 2] * h[1, 0] - h[0, 0] * h[1, 2]
            co20 = h[1, 0] * h[2, 1] - h[1, 1] * h[2, 0]
            co21 = h[0, 1] * h[2, 0] - h[0, 0] * h[2, 1]
            co22 = h[0, 0] * h[1, 1] - h[0, 1] * h[1, 0]
            det = h[0, 0] * co00 + h[0, 1] * co10 + h[0, 2] * co20
            if not abs(det) > 1e-9:
                bad[t] = True
                for c in range(3):
                    loo[t, v, c] = r[v, c]
                continue
            r0, r1, r2 = r[v, 0], r[v, 1], r[v, 2]
            loo[t, v, 0] = (co00 * r0 + co01 * r1 + co02 * r2) / det
            loo[t, v, 1] = (co10 * r0 + co11 * r1 + co12 * r2) / det
            loo[t, v, 2] = (co20 * r0 + co21 * r1 + co22 * r2) / det
        if not want_cov:
            continue
        dof = -nf  # residuals minus free parameters
        for v in range(N):
            if W[t, v]:
                dof += 3
        # B = sum over rows of (w J loo)^T (w J loo); cov = Ai B Ai
        for v in range(N):
            for c in range(3):
                f = w[t, v] * loo[t, v, c]  # 0 where not valid
                F2[c, v] = f * f
        for c in range(3):
            for i in range(npk):
                G[c, i] = _dot(F2[c], qqT[i])
        Bm = np.zeros((nf, nf))
        for c in range(3):
            for i in range(npk):
                a, b = pa[i], pb[i]
                z = fac[c, a] * fac[c, b] * G[c, i]
                Bm[col[c, a], col[c, b]] += z
                if a != b:
                    Bm[col[c, b], col[c, a]] += z
        for i in range(nx):
            var[t, i] = np.nan
        if dof <= 0:
            continue
        for i in range(nf):
            z = 0.0
            for j in range(nf):
                u = 0.0
                for k in range(nf):
                    u += Ai[i, k] * Bm[k, j]
                z += u * Ai[j, i]
            var[t, i] = z


sandwich_batch = _jit(_sandwich_batch)


def _nnls_texel(A: np.ndarray, Y: np.ndarray, w: np.ndarray, P: int, x: np.ndarray) -> float:
    """Non-negative weighted least squares of one texel, the three channels sharing the
    design ``A`` (N, P) (the compiled counterpart of ``initial._nnls_batch``: active set
    by pinning the most negative coefficient, on the normal equations). Writes x (P, 3);
    returns the RSS."""
    N = A.shape[0]
    G = np.zeros((P, P))
    R = np.zeros((P, 3))
    yy = 0.0
    for n in range(N):
        wn = w[n]
        if wn == 0.0:
            continue
        for c in range(3):
            yy += wn * Y[n, c] * Y[n, c]
        for a in range(P):
            wa = wn * A[n, a]
            for c in range(3):
                R[a, c] += wa * Y[n, c]
            for b in range(a, P):
                G[a, b] += wa * A[n, b]
    return _nnls_solve(G, R, yy, P, x)


def _nnls_solve(G: np.ndarray, R: np.ndarray, yy: float, P: int, x: np.ndarray) -> float:
    """:func:`_nnls_texel` from its normal equations: G (P, P) (upper triangle),
    R (P, 3), yy the weighted sum of squares of the targets. Writes x (P, 3); returns
    the RSS."""
    tr = 0.0
    for a in range(P):
        tr += G[a, a]
        for b in range(a):
            G[a, b] = G[b, a]
    M = np.empty((P, P))
    rhs = np.empty(P)
    sol = np.empty(P)
    active = np.empty(P, np.bool_)
    rss = 0.0
    for c in range(3):
        for a in range(P):
            active[a] = True
        for _ in range(P + 1):
            for a in range(P):
                for b in range(P):
                    M[a, b] = G[a, b] if (active[a] and active[b]) else 0.0
                M[a, a] = (G[a, a] if active[a] else 1.0) + 1e-12 * tr
                rhs[a] = R[a, c] if active[a] else 0.0
            if not _chol_solve(M, rhs, sol):
                for a in range(P):
                    sol[a] = 0.0
                break
            worst, wv = -1, -1e-15
            for a in range(P):
                if sol[a] < wv:
                    worst, wv = a, sol[a]
            if worst < 0:
                break
            active[worst] = False
        for a in range(P):
            x[a, c] = max(sol[a], 0.0) if active[a] else 0.0
        # rss of this channel from the normal equations
        s = 0.0
        for a in range(P):
            s -= 2.0 * x[a, c] * R[a, c]
            for b in range(P):
                s += x[a, c] * G[a, b] * x[b, c]
        rss += s
    return max(rss + yy, 0.0)


def _design(V: np.ndarray, D: np.ndarray, nd: int, lnm: float, A: np.ndarray) -> None:
    """A[:, 0] = 1, A[:, 1 + k] = max(0, d_k . v)^m for the first ``nd`` lobes."""
    m = math.exp(lnm)
    for n in range(V.shape[0]):
        A[n, 0] = 1.0
        for k in range(nd):
            c = V[n, 0] * D[k, 0] + V[n, 1] * D[k, 1] + V[n, 2] * D[k, 2]
            A[n, 1 + k] = math.exp(m * math.log(c)) if c > 0.0 else 0.0


def _log_cos(V: np.ndarray, D: np.ndarray, k: int, LC: np.ndarray) -> None:
    """LC[k, n] = ln(d_k . v_n), -inf where the lobe faces away: the part of the design
    that does not change while m is searched."""
    for n in range(V.shape[0]):
        c = V[n, 0] * D[k, 0] + V[n, 1] * D[k, 1] + V[n, 2] * D[k, 2]
        LC[k, n] = math.log(c) if c > 0.0 else -np.inf


def _profile_nnls(LC: np.ndarray, nd: int, lnm: float, WY: np.ndarray, w: np.ndarray,
                  G0: float, R0: np.ndarray, yy: float, AT: np.ndarray, x: np.ndarray) -> float:
    """The design AT[1 + k] = exp(m LC[k]) (:func:`_log_cos`; 0 below exp(-700), which
    the exponential rounds to anyway) of the first ``nd`` lobes (AT (1 + K, N),
    observations contiguous), then
    :func:`_nnls_texel` (the constant column implied) from the weights w (N,) and the
    weighted targets WY (3, N), with the parts of the normal equations that do not
    depend on m given (``G0`` = sum w, ``R0`` (3,) = sum w Y, ``yy`` = sum w Y^2): the
    search over m evaluates this many times."""
    P = nd + 1
    N = AT.shape[1]
    G = np.zeros((P, P))
    R = np.zeros((P, 3))
    G[0, 0] = G0
    for c in range(3):
        R[0, c] = R0[c]
    m = math.exp(lnm)
    for k in range(nd):
        for n in range(N):
            e = m * LC[k, n]
            AT[1 + k, n] = math.exp(e) if e > -700.0 else 0.0
    # dot products over the observations (they vectorise)
    for k in range(nd):
        G[0, 1 + k] = _dot(w, AT[1 + k])
        for c in range(3):
            R[1 + k, c] = _dot(WY[c], AT[1 + k])
        for j in range(k, nd):
            G[1 + k, 1 + j] = _dot3(w, AT[1 + k], AT[1 + j])
    return _nnls_solve(G, R, yy, P, x)


def _initial_batch(V: np.ndarray, L: np.ndarray, W: np.ndarray, K: int, cos_sep: float,
                   ln_m_max: float, grid: int, golden: int, out: np.ndarray) -> None:
    """The better initial guess of many texels (compiled counterpart of
    ``initial.initial_guess_batch``, same steps): each lobe at the direction of the
    largest remaining residual, m by a grid over ln m then golden-section search, Kd
    and Ks by non-negative least squares. Writes ``out`` (B, 4 + 6K) parameters."""
    B, N = W.shape
    D = np.zeros((K, 3))
    AT = np.empty((1 + K, N))
    WY = np.empty((3, N))
    LC = np.empty((K, N))
    x = np.empty((1 + K, 3))
    resid = np.empty(N)
    R0 = np.empty(3)
    gr = (math.sqrt(5.0) - 1.0) / 2.0
    for t in range(B):
        Vt, Lt, wt = V[t], L[t], W[t]
        G0, yy = 0.0, 0.0
        for c in range(3):
            R0[c] = 0.0
        for n in range(N):
            wn = wt[n]
            G0 += wn
            for c in range(3):
                WY[c, n] = wn * Lt[n, c]
                R0[c] += wn * Lt[n, c]
                yy += wn * Lt[n, c] * Lt[n, c]
        for n in range(N):
            resid[n] = (Lt[n, 0] + Lt[n, 1] + Lt[n, 2]) / 3.0 if wt[n] > 0 else -np.inf
        lnm = math.log(10.0)
        for k in range(K):
            if k > 0:
                for n in range(N):
                    for j in range(k):
                        if Vt[n, 0] * D[j, 0] + Vt[n, 1] * D[j, 1] + Vt[n, 2] * D[j, 2] > cos_sep:
                            resid[n] = -np.inf
            best_n = 0
            for n in range(N):
                if resid[n] > resid[best_n]:
                    best_n = n
            for c in range(3):
                D[k, c] = Vt[best_n, c]
            _log_cos(Vt, D, k, LC)
            # ln m: the best of a grid, then golden-section search in its bracket
            bi, bf = 0, np.inf
            for i in range(grid):
                u = ln_m_max * i / (grid - 1)
                f = _profile_nnls(LC, k + 1, u, WY, wt, G0, R0, yy, AT, x)
                if f < bf:
                    bi, bf = i, f
            a = ln_m_max * max(bi - 1, 0) / (grid - 1)
            b = ln_m_max * min(bi + 1, grid - 1) / (grid - 1)
            c1, d1 = b - gr * (b - a), a + gr * (b - a)
            fc = _profile_nnls(LC, k + 1, c1, WY, wt, G0, R0, yy, AT, x)
            fd = _profile_nnls(LC, k + 1, d1, WY, wt, G0, R0, yy, AT, x)
            for _ in range(golden):
                if fc < fd:
                    b, d1, fd = d1, c1, fc
                    c1 = b - gr * (b - a)
                    fc = _profile_nnls(LC, k + 1, c1, WY, wt, G0, R0, yy, AT, x)
                else:
                    a, c1, fc = c1, d1, fd
                    d1 = a + gr * (b - a)
                    fd = _profile_nnls(LC, k + 1, d1, WY, wt, G0, R0, yy, AT, x)
            lnm = (a + b) / 2.0
            _profile_nnls(LC, k + 1, lnm, WY, wt, G0, R0, yy, AT, x)
            for n in range(N):
                if wt[n] > 0:
                    s = 0.0
                    for c in range(3):
                        mod = x[0, c]
                        for j in range(k + 1):
                            mod += AT[1 + j, n] * x[1 + j, c]
                        s += Lt[n, c] - mod
                    resid[n] = s / 3.0
                else:
                    resid[n] = -np.inf
        for c in range(3):
            out[t, c] = x[0, c]
        out[t, 3] = math.exp(lnm)
        for k in range(K):
            b0 = MH_HEAD + MH_LOBE * k
            for c in range(3):
                out[t, b0 + c] = x[1 + k, c]
                out[t, b0 + 3 + c] = D[k, c]


_nnls_solve = _jit(_nnls_solve, _nnls_solve)
_nnls_texel = _jit(_nnls_texel, _nnls_texel)
_profile_nnls = _jit(_profile_nnls, _profile_nnls)
_design = _jit(_design, _design)
_log_cos = _jit(_log_cos, _log_cos)
initial_batch = _jit(_initial_batch)


def _rescaled_batch(P: np.ndarray, owner: np.ndarray, V: np.ndarray, L: np.ndarray,
                    W: np.ndarray, k: int, Q: np.ndarray, rss: np.ndarray) -> None:
    """Compiled ``repair._rescaled_starts``: each candidate's shininess and first ``k``
    lobe directions kept, Kd and Ks by weighted least squares on the data of texel
    ``owner[i]`` (V, L (T, N, 3), weights W (T, N); a ridge of 1e-12 of the trace),
    clipped at zero. P (c, 4 + 6K) in, Q (c, 4 + 6k) and the weighted rss (c,) out."""
    c, N = P.shape[0], V.shape[1]
    nb = 1 + k
    A = np.empty((N, nb))
    D = np.empty((max(k, 1), 3))
    G = np.empty((nb, nb))
    M = np.empty((nb, nb))
    R = np.empty((nb, 3))
    rhs = np.empty(nb)
    sol = np.empty(nb)
    x = np.empty((nb, 3))
    for i in range(c):
        o = owner[i]
        Vt, Lt, wt = V[o], L[o], W[o]
        for j in range(k):
            for a in range(3):
                D[j, a] = P[i, MH_HEAD + MH_LOBE * j + 3 + a]
        _design(Vt, D, k, math.log(P[i, 3]), A)
        for a in range(nb):
            for ch in range(3):
                R[a, ch] = 0.0
            for b in range(nb):
                G[a, b] = 0.0
        for n in range(N):
            w = wt[n]
            if w == 0.0:
                continue
            for a in range(nb):
                wa = w * A[n, a]
                for ch in range(3):
                    R[a, ch] += wa * Lt[n, ch]
                for b in range(nb):
                    G[a, b] += wa * A[n, b]
        tr = 0.0
        for a in range(nb):
            tr += G[a, a]
        for ch in range(3):
            for a in range(nb):
                for b in range(nb):
                    M[a, b] = G[a, b]
                M[a, a] += 1e-12 * tr
                rhs[a] = R[a, ch]
            if not _chol_solve(M, rhs, sol):
                for a in range(nb):
                    sol[a] = 0.0
            for a in range(nb):
                x[a, ch] = max(sol[a], 0.0)
        s = 0.0
        for n in range(N):
            if wt[n] == 0.0:
                continue
            for ch in range(3):
                f = -Lt[n, ch]
                for a in range(nb):
                    f += A[n, a] * x[a, ch]
                s += wt[n] * f * f
        rss[i] = s
        for a in range(Q.shape[1]):
            Q[i, a] = P[i, a]
        for ch in range(3):
            Q[i, ch] = x[0, ch]
            for j in range(k):
                Q[i, MH_HEAD + MH_LOBE * j + ch] = x[1 + j, ch]


rescaled_batch = _jit(_rescaled_batch)
