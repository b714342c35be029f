"""Compiled cost and gradient of the MH least-squares objective for one texel.

nlopt calls its objective once per evaluation from Python; at a few hundred
observations a numpy version spends most of its ~40 us in per-call overhead. This
kernel does the same arithmetic in one compiled loop (numba), a few microseconds.
:func:`parammap.models.mh.fit._objective` falls back to numpy where numba is missing.
"""

from __future__ import annotations

import math

import numpy as np

from ...conventions import MH_HEAD, MHX_LNM, MHX_LOBE

try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised only without numba
    njit = None

LOSSES = {"linear": 0, "soft_l1": 1, "huber": 2}


def _cost_grad(x: np.ndarray, V: np.ndarray, L: np.ndarray, Wt: np.ndarray, K: int,
               loss: int, f: float, grad: np.ndarray, want_grad: bool) -> float:
    """Cost of x-space parameters ``x`` (``conventions.mhx_size(K)``) on directions
    V (n, 3) and scaled radiance L (n, 3), each observation weighted by Wt (n,); fills ``grad`` when
    ``want_grad``. Same layout and maths as the numpy objective in
    :mod:`parammap.models.mh.fit`."""
    n = V.shape[0]
    m = math.exp(x[MHX_LNM])
    d = np.empty((K, 3))
    dth = np.empty((K, 3))
    dph = np.empty((K, 3))
    for k in range(K):
        b = MH_HEAD + MHX_LOBE * k
        th = x[b + 3]
        ph = x[b + 4]
        st, ct, sp, cp = math.sin(th), math.cos(th), math.sin(ph), math.cos(ph)
        d[k, 0], d[k, 1], d[k, 2] = st * cp, st * sp, ct
        dth[k, 0], dth[k, 1], dth[k, 2] = ct * cp, ct * sp, -st
        dph[k, 0], dph[k, 1], dph[k, 2] = -st * sp, st * cp, 0.0
    if want_grad:
        for j in range(grad.shape[0]):
            grad[j] = 0.0
    P = np.empty(K)
    LC = np.empty(K)
    C = np.empty(K)
    val = 0.0
    for i in range(n):
        v0, v1, v2 = V[i, 0], V[i, 1], V[i, 2]
        r0, r1, r2 = x[0] - L[i, 0], x[1] - L[i, 1], x[2] - L[i, 2]
        for k in range(K):
            c = v0 * d[k, 0] + v1 * d[k, 1] + v2 * d[k, 2]
            if c > 0.0:
                lc = math.log(c)
                p = math.exp(m * lc)
            else:
                lc, p = 0.0, 0.0
            C[k], P[k], LC[k] = c, p, lc
            b = MH_HEAD + MHX_LOBE * k
            r0 += x[b] * p
            r1 += x[b + 1] * p
            r2 += x[b + 2] * p
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
        e0, e1, e2 = wt * e0, wt * e1, wt * e2
        if want_grad:
            grad[0] += e0
            grad[1] += e1
            grad[2] += e2
            for k in range(K):
                p = P[k]
                if p == 0.0:
                    continue
                b = MH_HEAD + MHX_LOBE * k
                grad[b] += p * e0
                grad[b + 1] += p * e1
                grad[b + 2] += p * e2
                gp = (e0 * x[b] + e1 * x[b + 1] + e2 * x[b + 2]) * p
                grad[MHX_LNM] += gp * LC[k] * m
                gd = gp * m / C[k]
                grad[b + 3] += gd * (v0 * dth[k, 0] + v1 * dth[k, 1] + v2 * dth[k, 2])
                grad[b + 4] += gd * (v0 * dph[k, 0] + v1 * dph[k, 1])
    return val


cost_grad = njit(cache=True, nogil=True)(_cost_grad) if njit is not None else None


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
                  want: bool) -> float:
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
    if want:
        for a in range(nb):
            for c in range(3):
                QR[a, c] = 0.0
            for b in range(nb):
                Q[a, b] = 0.0
    q = np.empty(nb)
    q[0] = 1.0
    val = 0.0
    for i in range(n):
        wt = Wt[i]
        if wt == 0.0:
            continue
        v0, v1, v2 = V[i, 0], V[i, 1], V[i, 2]
        r0, r1, r2 = x[0] - L[i, 0], x[1] - L[i, 1], x[2] - L[i, 2]
        for k in range(K):
            c = v0 * d[k, 0] + v1 * d[k, 1] + v2 * d[k, 2]
            j = 1 + 4 * k
            if c > 0.0:
                lc = math.log(c)
                p = math.exp(m * lc)
                dpdc = p * m / c
                q[j] = p
                q[j + 1] = p * lc * m
                q[j + 2] = dpdc * (v0 * dth[k, 0] + v1 * dth[k, 1] + v2 * dth[k, 2])
                q[j + 3] = dpdc * (v0 * dph[k, 0] + v1 * dph[k, 1])
                b = MH_HEAD + MHX_LOBE * k
                r0 += x[b] * p
                r1 += x[b + 1] * p
                r2 += x[b + 2] * p
            else:
                q[j] = 0.0
                q[j + 1] = 0.0
                q[j + 2] = 0.0
                q[j + 3] = 0.0
        val += wt * (r0 * r0 + r1 * r1 + r2 * r2)
        if want:
            for a in range(nb):
                wq = wt * q[a]
                if wq == 0.0:
                    continue
                QR[a, 0] += wq * r0
                QR[a, 1] += wq * r1
                QR[a, 2] += wq * r2
                for b in range(a, nb):
                    Q[a, b] += wq * q[b]
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


def _chol_solve(M: np.ndarray, rhs: np.ndarray, out: np.ndarray) -> bool:
    """Solve the symmetric positive definite system M out = rhs by Cholesky, in place
    of M's lower triangle; False if M is not positive definite."""
    n = M.shape[0]
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s -= M[j, k] * M[j, k]
        if not s > 0.0:
            return False
        s = math.sqrt(s)
        M[j, j] = s
        for i in range(j + 1, n):
            t = M[i, j]
            for k in range(j):
                t -= M[i, k] * M[j, k]
            M[i, j] = t / s
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


def _lm_batch(X: np.ndarray, V: np.ndarray, L: np.ndarray, Wt: np.ndarray, K: int,
              lb: np.ndarray, ub: np.ndarray, iters: int, ftol: float) -> np.ndarray:
    """Bounded Levenberg-Marquardt for each texel of a batch, in place on ``X``
    (B, nx) x-space starts (scaled radiance L (B, N, 3), weights Wt (B, N), bounds
    lb (nx,) and ub (B, nx)). A variable at a bound whose gradient pushes outward is
    held for the step (active set), so the others keep converging; a texel stops when
    a step lowers its cost by less than ``ftol`` (relative) or the damping saturates.
    Returns why each texel stopped (B,): :data:`LM_CONVERGED`, :data:`LM_DAMPED` (no
    step lowers the cost) or :data:`LM_CAPPED` (``iters`` steps)."""
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
    why = np.full(B, 2, np.int64)
    for b in range(B):
        x = X[b]
        for i in range(nx):
            x[i] = min(max(x[i], lb[i]), ub[b, i])
        cost = _normal_texel(x, V[b], L[b], Wt[b], K, A, g, Q, QR, True)
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
            cn = _normal_texel(xn, V[b], L[b], Wt[b], K, An, gn, Q, QR, True)
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
            else:
                lam *= 10.0
                if lam > 1e10:
                    why[b] = 1
                    break
    return why


if njit is not None:
    _normal_texel = njit(cache=True, nogil=True)(_normal_texel)
    _chol_solve = njit(cache=True, nogil=True)(_chol_solve)
    lm_batch = njit(cache=True, nogil=True)(_lm_batch)
else:  # pragma: no cover - exercised only without numba
    lm_batch = None
