"""Leave-one-view-out prediction error (PRESS) of fitted maps of any model, per texel,
so that different models can be compared on how well they predict views they did not
see (the best-model stage). Every function returns the weighted PRESS
``sum_v w_v |e_v|^2`` of the texels, with ``e_v`` the residual of view v once the
(linearised) fit is refitted without it, ``(I - H_vv)^-1 r_v`` (H the hat matrix, H_vv
its 3 x 3 block of the view's channels): the same criterion as the MH fitter's lobe
choice (:func:`parammap.models.mh.uncertainty.loo_error`, used here for MH maps), inf
where a view alone determines a parameter.

Inputs: V, L (n, N, 3) directions and radiance, W (n, N) valid, w (n, N) weights (0
where invalid).
"""

from __future__ import annotations

import numpy as np

from ..conventions import MH_KD, mh_ks, mh_lobes
from .mh.model import mh_eval
from .sh import sh_basis

__all__ = ["press_amplitudes", "press_diffuse", "press_linear", "press_sh"]


def press_linear(J: np.ndarray, r: np.ndarray, w: np.ndarray, W: np.ndarray) -> np.ndarray:
    """PRESS (n,) of a model linear in its parameters, with design J (n, N, 3, q) and
    residuals r (n, N, 3) of its least-squares fit (weights w (n, N))."""
    n, N, _, q = J.shape
    sw = np.sqrt(np.where(W, w, 0.0))[..., None, None]
    Jw = J * sw
    A = np.einsum("nvcq,nvcp->nqp", Jw, Jw) + 1e-12 * np.eye(q)
    with np.errstate(invalid="ignore", divide="ignore"):
        Ai = np.linalg.pinv(A)
        H = np.einsum("nviq,nqp,nvjp->nvij", Jw, Ai, Jw, optimize=True)
        IH = np.eye(3) - H
        det = np.linalg.det(IH)
        bad = ~(np.abs(det) > 1e-9) & W
        IH = np.where(bad[..., None, None], np.eye(3), IH)
        e = (r * sw[..., 0])[..., None]
        loo = np.linalg.solve(IH, e)[..., 0]
    out = (np.where(W[..., None], loo, 0.0) ** 2).sum((1, 2))
    return np.where(bad.any(1), np.inf, out)


def press_diffuse(kd: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                  w: np.ndarray) -> np.ndarray:
    """PRESS of view-independent radiance ``kd`` (n, 3) (the weighted mean)."""
    J = np.broadcast_to(np.eye(3), L.shape[:2] + (3, 3))
    return press_linear(J, np.where(W[..., None], kd[:, None] - L, 0.0), w, W)


def press_amplitudes(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                     w: np.ndarray) -> np.ndarray:
    """PRESS of MH maps whose lobe shapes (m, directions, colours) are not the texel's
    own but shared (the basis materials): only Kd and each lobe's amplitude are
    refitted without the view."""
    P = np.asarray(P, float)
    K = mh_lobes(P.shape[1])
    cols = [np.broadcast_to(np.eye(3), L.shape[:2] + (3, 3))]
    for k in range(K):
        one = P.copy()
        one[:, MH_KD] = 0.0
        for j in range(K):
            if j != k:
                one[:, mh_ks(j)] = 0.0
        cols.append(mh_eval(one, V)[..., None])  # the lobe, its colour included
    J = np.concatenate(cols, -1)
    return press_linear(J, np.where(W[..., None], mh_eval(P, V) - L, 0.0), w, W)


def press_sh(C: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
             w: np.ndarray) -> np.ndarray:
    """PRESS of SH maps, coefficients C (n, 3 nc) (channel-major, conventions.md),
    refitting without the view only the coefficients the texel uses (non-zero; the
    bands its views resolve). The channels share one design, so the hat matrix is the
    same scalar per view for the three."""
    C = np.nan_to_num(np.asarray(C, float))
    n = len(C)
    nc = C.shape[1] // 3
    Cc = C.reshape(n, 3, nc)
    Y = sh_basis(V, int(round(np.sqrt(nc))))  # (n, N, nc)
    use = (Cc != 0).any(1)  # (n, nc)
    Yu = Y * use[:, None, :]
    pred = np.einsum("nvk,nck->nvc", Y, Cc)
    r = np.where(W[..., None], pred - L, 0.0)
    ww = np.where(W, w, 0.0)
    A = np.einsum("nv,nvk,nvl->nkl", ww, Yu, Yu) + np.eye(nc) * (~use)[:, :, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        h = ww * np.einsum("nvk,nkl,nvl->nv", Yu, np.linalg.pinv(A), Yu)
        bad = (h > 1 - 1e-9) & W
        loo = r / np.where(bad, 1.0, 1 - h)[..., None]
    out = (ww[..., None] * loo ** 2).sum((1, 2))
    return np.where(bad.any(1), np.inf, out)
