"""Compiled batched solvers of the MH fit: damped Gauss-Newton (Levenberg-Marquardt)
steps over many texels at once, and the sandwich covariance of the fitted parameters
(numba; numpy fallbacks where it is missing)."""

from __future__ import annotations

import math

import numpy as np

from ...conventions import MH_HEAD, MHX_LNM, MHX_LOBE
from .kernel import _dot, _dot3, _jit, _lobe_frames, _observe, _sum

LM_CONVERGED, LM_DAMPED, LM_CAPPED = 0, 1, 2  # why a texel's LM stopped


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
