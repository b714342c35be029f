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
