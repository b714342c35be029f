"""Compiled starting points of the MH fit: per-lobe non-negative least squares over a
profile of shininess values, and a neighbour's parameters rescaled to a texel's data
(numba; numpy fallbacks where it is missing)."""

from __future__ import annotations

import math

import numpy as np

from ...conventions import MH_HEAD, MH_LOBE
from .kernel import _dot, _dot3, _jit
from .solve import _chol_solve


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
