"""Per-texel standard deviations of fitted MH parameters.

From a converged fit: the Jacobian J of the residuals with respect to the free
parameters (x space: Kd, ln m, and per lobe Ks and two angles; analytic,
:func:`jacobian_x`) and the covariance A^-1 B A^-1 with A = J^T W J and
B = J^T W diag(r*^2) W J, r* the leave-one-view-out residuals (the leverage-corrected
"sandwich" HC3 of linearised least squares): a capture's noise grows with the radiance,
and the few views near a highlight pull the fit to themselves, so both the textbook
s^2 A^-1 and the plain sandwich (HC0) understate the lobe's uncertainty (Ks up to 6x on
the test material). Checked against the spread of fits over noise realisations of one
material (three noise seeds): Kd and the lobe direction within about 25 %, m and Ks
(set by the few views near the highlight) overstated by at most 1.8x.
Reported in the parameters' own units (:func:`parammap.conventions.mh_sd_channels`):
Kd, m and Ks directly, the lobe direction as an angle in degrees. Lobes a texel does
not use (Ks = 0) get NaN.
"""

from __future__ import annotations

import numpy as np

from ...conventions import (
    MH_HEAD,
    MH_KD,
    MH_M,
    MH_SD_LOBE,
    MHX_KD,
    MHX_LNM,
    mh_dir,
    mh_ks,
    mh_lobes,
    mh_sd_dir,
    mh_sd_size,
    mhx_ks,
    mhx_phi,
    mhx_size,
    mhx_theta,
)
from .model import M_MAX, M_MIN, _lobes_present, _params_to_x_batch, mh_eval
from .solve import sandwich_batch

__all__ = ["jacobian_x", "loo_error", "loo_residuals", "parameter_sd"]


def jacobian_x(P: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Jacobian of :func:`mh_eval` in x space (Kd, ln m, per lobe Ks, theta, phi),
    analytic.

    Parameters
    ----------
    P : (n, 4 + 6K) parameters (unit lobe directions); V : (n, N, 3) view directions.

    Returns
    -------
    (n, N, 3, 4 + 5K): d radiance (channel) / d x. Kd and Ks enter linearly; a lobe
    ``Ks c^m`` with ``c = max(d . v, 0)`` gives ``Ks c^m m ln c`` for ln m and
    ``Ks m c^(m - 1) (dd/dtheta . v)`` for an angle (0 where c = 0).
    """
    P = np.asarray(P, float)
    V = np.asarray(V, float)
    n, N = V.shape[:2]
    K = mh_lobes(P.shape[1])
    J = np.zeros((n, N, 3, mhx_size(K)))
    rgb = np.arange(3)
    J[:, :, rgb, rgb + MHX_KD.start] = 1.0
    m = np.clip(P[:, MH_M], M_MIN, M_MAX)[:, None]
    for k in range(K):
        ks = P[:, mh_ks(k)][:, None, :]  # (n, 1, 3)
        d = P[:, mh_dir(k)]
        th = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
        ph = np.arctan2(d[:, 1], d[:, 0])
        c = np.clip(np.einsum("nvc,nc->nv", V, d), 0.0, None)
        pos = c > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            cm = np.where(pos, c ** m, 0.0)
            dcm = np.where(pos, m * cm / np.where(pos, c, 1.0), 0.0)  # m c^(m - 1)
            J[..., MHX_LNM] += (cm * m * np.log(np.where(pos, c, 1.0)))[..., None] * ks
        J[:, :, rgb, rgb + mhx_ks(k).start] = cm[..., None]
        st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
        dth = np.stack([ct * cp, ct * sp, -st], -1)
        dph = np.stack([-st * sp, st * cp, np.zeros_like(st)], -1)
        for col, dd in ((mhx_theta(k), dth), (mhx_phi(k), dph)):
            J[..., col] = (dcm * np.einsum("nvc,nc->nv", V, dd))[..., None] * ks
    return J


def _linearised(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                weights: np.ndarray | None):
    """The fit linearised at ``P``: Jacobian J (n, 3N, nx) of the model in x space
    (zero at invalid observations), J weighted, residuals r (n, N, 3), weights w (n, N),
    free (n, nx) parameters the texel uses, A = J^T W J (identity on the others) and the
    mask of free pairs."""
    n = P.shape[0]
    nx = mhx_size(mh_lobes(P.shape[1]))
    w = (np.ones(W.shape) if weights is None else np.asarray(weights, float)) * W
    base = mh_eval(P, V)
    r = np.where(W[..., None], base - L, 0.0)
    J = np.where(W[..., None, None], jacobian_x(P, V), 0.0)
    present = _lobes_present(P)
    free = np.ones((n, nx), bool)
    for k in range(mh_lobes(P.shape[1])):
        gone = present <= k  # lobes are sorted: the first ``present`` are used
        cols = [*range(mhx_ks(k).start, mhx_ks(k).stop), mhx_theta(k), mhx_phi(k)]
        free[np.ix_(gone, cols)] = False
    free[present == 0, MHX_LNM] = False  # no lobe: no shininess to determine
    J = J.reshape(n, -1, nx)
    JW = J * w.repeat(3, axis=1)[..., None]
    mask = free[:, :, None] & free[:, None, :]
    # batched matmul: an order of magnitude faster than einsum for these small products
    A = np.where(mask, np.matmul(JW.transpose(0, 2, 1), J), 0.0) \
        + np.eye(nx) * (~free)[:, :, None]
    return J, JW, r, w, free, A, mask


def loo_residuals(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                  weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-view-out residuals of fitted MH parameters, per texel and view.

    The linearised fit's leave-one-out residual of view v is ``(I - H_vv)^-1 r_v``, H the
    (weighted) hat matrix and H_vv its 3 x 3 block of the view's channels: a view that
    alone determines a lobe (H_vv near I) predicts itself badly once left out.

    Parameters
    ----------
    P : (n, 4 + 6K) fitted parameters; V, L : (n, N, 3); W : (n, N) bool;
    weights : (n, N) the fit's observation weights (default 1).

    Returns
    -------
    (n, N, 3) prediction minus observation of each view once left out (0 where not
    valid), and (n,) bool: some view's leave-one-out system is singular (that view
    alone determines a parameter).
    """
    P = np.asarray(P, float)
    if sandwich_batch is not None:
        loo, bad, _ = _compiled(P, V, L, W, weights, False)
        return loo, bad
    J, _, r, w, free, A, _ = _linearised(P, V, L, W, weights)
    return _loo(J, r, w, free, A, W)


def _compiled(P, V, L, W, weights, want_cov: bool):
    """:func:`loo_residuals` and the sandwich's variances in x space, by the compiled
    kernel (:func:`.kernel.sandwich_batch`): (n, N, 3), (n,) bool, (n, nx)."""
    n, N = W.shape
    X = _params_to_x_batch(P, np.ones(n))
    w = (np.ones(W.shape) if weights is None else np.asarray(weights, float)) * W
    loo = np.zeros((n, N, 3))
    bad = np.zeros(n, bool)
    var = np.full(X.shape, np.nan)
    sandwich_batch(np.ascontiguousarray(X), np.ascontiguousarray(V, float),
                   np.ascontiguousarray(L, float), np.ascontiguousarray(W, bool),
                   np.ascontiguousarray(w, float), mh_lobes(P.shape[1]),
                   _lobes_present(P).astype(np.int64), want_cov, loo, bad, var)
    return loo, bad, var


def _loo(J, r, w, free, A, W, Ai=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`loo_residuals` from the pieces of :func:`_linearised` (``Ai``: the
    pseudo-inverse of A, where already known)."""
    n, N = W.shape
    nx = J.shape[-1]
    sw = np.sqrt(w).repeat(3, axis=1)[..., None]
    Jw = np.where(free[:, None, :], J * sw, 0.0)  # (n, 3N, nx)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if Ai is None:
            Ai = np.linalg.pinv(A)
        # each view's 3 x 3 block of the hat matrix, by batched matmuls (einsum's
        # contraction is several times slower for these small shapes)
        M = np.matmul(Jw, Ai).reshape(n, N, 3, nx)
        H = np.matmul(M, Jw.reshape(n, N, 3, nx).transpose(0, 1, 3, 2))
        IH = np.eye(3) - H
        # 3 x 3 inverses by cofactors, vectorised (LAPACK's per-matrix calls dominate at
        # this size); a view whose block is (nearly) singular is predicted only by itself
        a, b, c = IH[..., 0, 0], IH[..., 0, 1], IH[..., 0, 2]
        d, e, f = IH[..., 1, 0], IH[..., 1, 1], IH[..., 1, 2]
        g, h, i = IH[..., 2, 0], IH[..., 2, 1], IH[..., 2, 2]
        co = np.stack([e * i - f * h, c * h - b * i, b * f - c * e,
                       f * g - d * i, a * i - c * g, c * d - a * f,
                       d * h - e * g, b * g - a * h, a * e - b * d], -1)
        det = a * co[..., 0] + b * co[..., 3] + c * co[..., 6]
        bad = ~(np.abs(det) > 1e-9) & W
        inv = co.reshape(n, N, 3, 3) / np.where(bad, 1.0, det)[..., None, None]
        # H acts on the weighted residuals; a view of weight 0 has H_vv = 0
        loo = np.where(bad[..., None], r, np.matmul(inv, r[..., None])[..., 0])
    return np.where(W[..., None], loo, 0.0), bad.any(1)


def loo_error(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
              weights: np.ndarray | None = None, fixed_m: bool = False) -> np.ndarray:
    """Leave-one-view-out prediction error of fitted MH parameters, per texel: the sum
    of the squared (weighted) leave-one-out residuals of :func:`loo_residuals`, PRESS,
    which estimates how the texel's fit does in directions no view of it saw, at the
    cost of one Jacobian. ``fixed_m``: of a fit with m held (not a free parameter).

    Returns
    -------
    (n,) weighted PRESS (inf where a view's leave-one-out system is singular).
    """
    if fixed_m:
        J, _, r, w, free, A, _ = _linearised(np.asarray(P, float), V, L, W, weights)
        free[:, MHX_LNM] = False
        A[:, MHX_LNM, :] = A[:, :, MHX_LNM] = 0.0
        A[:, MHX_LNM, MHX_LNM] = 1.0
        loo, bad = _loo(J, r, w, free, A, W)
    else:
        loo, bad = loo_residuals(P, V, L, W, weights)
    w = (np.ones(W.shape) if weights is None else np.asarray(weights, float)) * W
    return np.where(bad, np.inf, (w[..., None] * loo ** 2).sum((1, 2)))


def parameter_sd(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                 weights: np.ndarray | None = None) -> np.ndarray:
    """Standard deviations of fitted MH parameters.

    Parameters
    ----------
    P : (n, 4 + 6K) fitted parameters (docs/reference/conventions.md layout).
    V, L : (n, N, 3) directions and radiance; W : (n, N) bool validity.
    weights : (n, N) the fit's observation weights (default 1).

    Returns
    -------
    (n, 4 + 4K) float64: sd of Kd.RGB, m, then per lobe Ks.RGB and the direction (deg);
    NaN where a lobe is absent or the problem is not determined.
    """
    P = np.asarray(P, float)
    n = P.shape[0]
    K = mh_lobes(P.shape[1])
    X = _params_to_x_batch(P, np.ones(n))
    if sandwich_batch is not None:
        var = _compiled(P, V, L, W, weights, True)[2]
    else:
        J, JW, r, w, free, A, mask = _linearised(P, V, L, W, weights)
        # the sandwich A^-1 B A^-1 with B from the leave-one-view-out residuals (HC3):
        # the noise of a capture grows with the radiance, and the few views near a
        # highlight pull the fit to themselves, so their own residuals understate it
        with np.errstate(invalid="ignore", divide="ignore"):
            Ai = np.linalg.pinv(A)
        loo, _ = _loo(J, r, w, free, A, W, Ai)
        Jr = JW * loo.reshape(n, -1)[..., None]
        Bm = np.where(mask, np.matmul(Jr.transpose(0, 2, 1), Jr), 0.0)
        dof = 3 * W.sum(1) - free.sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cov = Ai @ Bm @ Ai
            var = np.where(free, np.diagonal(cov, axis1=1, axis2=2), np.nan)
        var = np.where(dof[:, None] > 0, var, np.nan)
    sd_x = np.sqrt(np.clip(var, 0, None))
    out = np.full((n, mh_sd_size(K)), np.nan)
    out[:, MH_KD] = sd_x[:, MHX_KD]
    out[:, MH_M] = P[:, MH_M] * sd_x[:, MHX_LNM]  # d m = m d(ln m)
    for k in range(K):
        b = MH_HEAD + MH_SD_LOBE * k
        out[:, b:b + 3] = sd_x[:, mhx_ks(k)]  # Ks.RGB, then the direction
        th = X[:, mhx_theta(k)]
        ang = np.sqrt(sd_x[:, mhx_theta(k)] ** 2 + (np.sin(th) * sd_x[:, mhx_phi(k)]) ** 2)
        out[:, mh_sd_dir(k)] = np.degrees(ang)
    return out

