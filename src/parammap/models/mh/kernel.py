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
    return njit(cache=True, nogil=True)(f) if njit is not None else fallback


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


def _cost_grad(x: np.ndarray, V: np.ndarray, L: np.ndarray, Wt: np.ndarray, K: int,
               loss: int, f: float, grad: np.ndarray, want_grad: bool) -> float:
    """Cost of x-space parameters ``x`` (``conventions.mhx_size(K)``) on directions
    V (n, 3) and scaled radiance L (n, 3), each observation weighted by Wt (n,); fills ``grad`` when
    ``want_grad``. Same layout and maths as the numpy objective in
    :mod:`parammap.models.mh.fit`."""
    n = V.shape[0]
    m = math.exp(x[MHX_LNM])
    d, dth, dph = _lobe_frames(x, K)
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


cost_grad = _jit(_cost_grad)


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
    d, dth, dph = _lobe_frames(x, K)
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
            # the cost alone first: A and g only for a step that is taken
            cn = _normal_texel(xn, V[b], L[b], Wt[b], K, An, gn, Q, QR, False)
            if cn < cost:
                cn = _normal_texel(xn, V[b], L[b], Wt[b], K, An, gn, Q, QR, True)
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
    return why


_normal_texel = _jit(_normal_texel, _normal_texel)
_chol_solve = _jit(_chol_solve, _chol_solve)
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
    """
    n, N = W.shape
    nx = X.shape[1]
    Kx = (nx - MH_HEAD) // MHX_LOBE
    # the Jacobian of the free columns only: a texel with fewer lobes than the layout
    # holds has a smaller system (the products below grow with its square)
    J = np.zeros((N, 3, nx))
    r = np.zeros((N, 3))
    M = np.empty((3, nx))
    for t in range(n):
        x = X[t]
        m = math.exp(x[MHX_LNM])
        nl = nlobes[t]
        # lobes are sorted, the first nl present: the free columns are a prefix of x
        # (without a lobe, Kd alone: no shininess to determine)
        nf = MH_HEAD + MHX_LOBE * nl if nl > 0 else 3
        d, dth, dph = _lobe_frames(x, Kx)
        A = np.zeros((nf, nf))
        for v in range(N):
            for c in range(3):
                r[v, c] = 0.0
                for i in range(nf):
                    J[v, c, i] = 0.0
            if not W[t, v]:
                continue
            v0, v1, v2 = V[t, v, 0], V[t, v, 1], V[t, v, 2]
            for c in range(3):
                r[v, c] = x[c] - L[t, v, c]
                J[v, c, c] = 1.0
            for k in range(Kx):
                b = MH_HEAD + MHX_LOBE * k
                cs = v0 * d[k, 0] + v1 * d[k, 1] + v2 * d[k, 2]
                if cs <= 0.0:
                    continue
                if k >= nl:  # not free: only its (zero) part of the prediction
                    p = math.exp(m * math.log(cs))
                    for c in range(3):
                        r[v, c] += x[b + c] * p
                    continue
                lc = math.log(cs)
                p = math.exp(m * lc)
                dpdc = m * p / cs
                a_th = dpdc * (v0 * dth[k, 0] + v1 * dth[k, 1] + v2 * dth[k, 2])
                a_ph = dpdc * (v0 * dph[k, 0] + v1 * dph[k, 1])
                for c in range(3):
                    ks = x[b + c]
                    r[v, c] += ks * p
                    J[v, c, MHX_LNM] += ks * p * m * lc
                    J[v, c, b + c] = p
                    J[v, c, b + 3] = ks * a_th
                    J[v, c, b + 4] = ks * a_ph
            wv = w[t, v]
            for c in range(3):
                for i in range(nf):
                    a = wv * J[v, c, i]
                    if a == 0.0:
                        continue
                    for j in range(nf):
                        A[i, j] += a * J[v, c, j]
        Ai = np.linalg.pinv(A)
        bad[t] = False
        for v in range(N):
            if not W[t, v]:
                for c in range(3):
                    loo[t, v, c] = 0.0
                continue
            sw = math.sqrt(w[t, v])
            # the view's 3 x 3 block of the hat matrix, H = Jw Ai Jw^T
            for c in range(3):
                for j in range(nf):
                    s = 0.0
                    for i in range(nf):
                        s += J[v, c, i] * Ai[i, j]
                    M[c, j] = s * sw
            h = np.empty((3, 3))
            for a in range(3):
                for c in range(3):
                    s = 0.0
                    for j in range(nf):
                        s += M[a, j] * J[v, c, j]
                    h[a, c] = (1.0 if a == c else 0.0) - s * sw
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
        Bm = np.zeros((nf, nf))
        for v in range(N):
            if not W[t, v]:
                continue
            for c in range(3):
                f = w[t, v] * loo[t, v, c]
                for i in range(nf):
                    a = f * J[v, c, i]
                    if a == 0.0:
                        continue
                    for j in range(nf):
                        Bm[i, j] += a * f * J[v, c, j]
        T = Ai @ Bm
        for i in range(nx):
            var[t, i] = np.nan
        if dof <= 0:
            continue
        for i in range(nf):
            s = 0.0
            for j in range(nf):
                s += T[i, j] * Ai[j, i]
            var[t, i] = s


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


def _design_log(LC: np.ndarray, nd: int, lnm: float, A: np.ndarray) -> None:
    """:func:`_design` from the logarithms of :func:`_log_cos`: A[:, 1 + k] = exp(m LC[k])
    (0 below exp(-700), which the exponential would round to anyway)."""
    m = math.exp(lnm)
    for n in range(A.shape[0]):
        A[n, 0] = 1.0
        for k in range(nd):
            e = m * LC[k, n]
            A[n, 1 + k] = math.exp(e) if e > -700.0 else 0.0


def _initial_batch(V: np.ndarray, L: np.ndarray, W: np.ndarray, K: int, cos_sep: float,
                   ln_m_max: float, grid: int, golden: int, out: np.ndarray) -> None:
    """The better initial guess of many texels (compiled counterpart of
    ``initial.initial_guess_batch``, same steps): each lobe at the direction of the
    largest remaining residual, m by a grid over ln m then golden-section search, Kd
    and Ks by non-negative least squares. Writes ``out`` (B, 4 + 6K) parameters."""
    B, N = W.shape
    D = np.zeros((K, 3))
    A = np.empty((N, 1 + K))
    LC = np.empty((K, N))
    x = np.empty((1 + K, 3))
    resid = np.empty(N)
    gr = (math.sqrt(5.0) - 1.0) / 2.0
    for t in range(B):
        Vt, Lt, wt = V[t], L[t], W[t]
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
                _design_log(LC, k + 1, u, A)
                f = _nnls_texel(A, Lt, wt, k + 2, x)
                if f < bf:
                    bi, bf = i, f
            a = ln_m_max * max(bi - 1, 0) / (grid - 1)
            b = ln_m_max * min(bi + 1, grid - 1) / (grid - 1)
            c1, d1 = b - gr * (b - a), a + gr * (b - a)
            _design_log(LC, k + 1, c1, A)
            fc = _nnls_texel(A, Lt, wt, k + 2, x)
            _design_log(LC, k + 1, d1, A)
            fd = _nnls_texel(A, Lt, wt, k + 2, x)
            for _ in range(golden):
                if fc < fd:
                    b, d1, fd = d1, c1, fc
                    c1 = b - gr * (b - a)
                    _design_log(LC, k + 1, c1, A)
                    fc = _nnls_texel(A, Lt, wt, k + 2, x)
                else:
                    a, c1, fc = c1, d1, fd
                    d1 = a + gr * (b - a)
                    _design_log(LC, k + 1, d1, A)
                    fd = _nnls_texel(A, Lt, wt, k + 2, x)
            lnm = (a + b) / 2.0
            _design_log(LC, k + 1, lnm, A)
            _nnls_texel(A, Lt, wt, k + 2, x)
            for n in range(N):
                if wt[n] > 0:
                    s = 0.0
                    for c in range(3):
                        mod = x[0, c]
                        for j in range(k + 1):
                            mod += A[n, 1 + j] * x[1 + j, c]
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


_nnls_texel = _jit(_nnls_texel, _nnls_texel)
_design = _jit(_design, _design)
_log_cos = _jit(_log_cos, _log_cos)
_design_log = _jit(_design_log, _design_log)
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
