"""Leave-one-view-out predictions of fitted maps of any model, per texel, so that
different models can be compared on how well they predict views they did not see (the
best-model stage). ``e_v``, the residual of view v once the (linearised) fit is
refitted without it, is ``(I - H_vv)^-1 r_v`` (H the hat matrix, H_vv its 3 x 3 block of
the view's channels): the MH fitter's lobe choice uses the same
(:func:`parammap.models.mh.uncertainty.loo_residuals`, used here for MH maps).

The ``loo_*`` functions return the (n, N, 3) residuals (prediction minus observation,
0 where not valid) and (n,) bool where a view alone determines a parameter (its
left-out prediction is undefined). :func:`press` sums them as squares in radiance,
:func:`display_error` measures them as the held-out comparison measures renders: in
8-bit levels after the report's tone map.

Inputs: V, L (n, N, 3) directions and radiance, W (n, N) valid, w (n, N) weights (0
where invalid).
"""

from __future__ import annotations

import numpy as np

from ..conventions import (
    MH_KD,
    SV_ALPHA,
    SV_COAT,
    SV_KD,
    SV_KS,
    SV_SIZE,
    mh_ks,
    mh_lobes,
    mhx_phi,
    mhx_theta,
)
from .mh.model import mh_eval
from .mh.uncertainty import jacobian_x
from .sh.basis import sh_basis, sh_eval
from .svbrdf import (
    LightRig,
    coat_sky_transmittance,
    coat_transmittance,
    ggx_albedo,
    light_terms,
    specular_basis,
    svbrdf_eval,
)

__all__ = ["INFLUENCE", "display_error", "influential", "loo_amplitudes", "loo_diffuse",
           "loo_linear", "loo_sh", "loo_svbrdf", "predict", "press", "press_linear",
           "view_errors"]

#: a view whose left-out residual exceeds its in-sample residual this many times
#: (leverage above one half for a linear smoother, ``e = r / (1 - h)``) carries more of
#: its own fitted value than all the other views together
INFLUENCE = 2.0

Loo = tuple[np.ndarray, np.ndarray]


def loo_linear(J: np.ndarray, r: np.ndarray, w: np.ndarray, W: np.ndarray) -> Loo:
    """Leave-one-view-out residuals of a model linear in its parameters, with design J
    (n, N, 3, q) and residuals r (n, N, 3) of its least-squares fit (weights w)."""
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
        loo = np.linalg.solve(IH, r[..., None])[..., 0]
    return np.where(W[..., None], loo, 0.0), bad.any(1)


def press(loo: Loo, w: np.ndarray) -> np.ndarray:
    """(n,) weighted PRESS ``sum_v w_v |e_v|^2`` of leave-one-out residuals (inf where a
    view alone determines a parameter)."""
    e, bad = loo
    return np.where(bad, np.inf, (w[..., None] * e ** 2).sum((1, 2)))


def press_linear(J: np.ndarray, r: np.ndarray, w: np.ndarray, W: np.ndarray) -> np.ndarray:
    """PRESS (n,) of a linear model (:func:`loo_linear`)."""
    return press(loo_linear(J, r, w, W), np.where(W, w, 0.0))


def view_errors(loo: Loo, L: np.ndarray, W: np.ndarray, gamma: float | None) -> np.ndarray:
    """(n, N) error of each valid view's leave-one-out prediction (NaN where not
    valid; inf on texels where a view alone determines a parameter): with ``gamma``,
    the mean 8-bit difference over the channels after the tone map ``1 - exp(-gamma
    L)`` of the held-out comparison; without, the squared radiance error (PRESS's
    terms).

    Radiance errors weigh as a viewer sees them with ``gamma``: the tone map compresses
    a highlight's error by ``exp(-gamma L)`` (to 1/20 at the 99th percentile), so the sum
    of squared radiance is ruled by the few views on a highlight, and the mid-tones where
    renders are looked at are not."""
    e, bad = loo
    if gamma is None:
        d = (e ** 2).sum(-1)
    else:
        def tone(x):
            return 255.0 * (1.0 - np.exp(-gamma * np.maximum(x, 0.0)))

        with np.errstate(invalid="ignore"):
            d = np.abs(tone(L + e) - tone(L)).mean(-1)
    d = np.where(W, d, np.nan)
    return np.where(bad[:, None] | ~np.isfinite(np.where(W, d, 0.0)).all(1)[:, None],
                    np.inf, d)


def display_error(loo: Loo, L: np.ndarray, W: np.ndarray, w: np.ndarray,
                  gamma: float) -> np.ndarray:
    """(n,) mean 8-bit difference, after the tone map of the held-out comparison,
    between each view's observation and its leave-one-out prediction (weighted mean of
    :func:`view_errors` over the valid views; inf where a view alone determines a
    parameter)."""
    d = view_errors(loo, L, W, gamma)
    ww = np.where(W, w, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (ww * np.where(W, d, 0.0)).sum(1) / ww.sum(1)
    return np.where(np.isfinite(out), out, np.inf)


def loo_diffuse(kd: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                w: np.ndarray) -> Loo:
    """Leave-one-out residuals of view-independent radiance ``kd`` (n, 3) (the
    weighted mean)."""
    J = np.broadcast_to(np.eye(3), L.shape[:2] + (3, 3))
    return loo_linear(J, np.where(W[..., None], kd[:, None] - L, 0.0), w, W)


def loo_amplitudes(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                   w: np.ndarray) -> Loo:
    """Leave-one-out residuals of MH maps whose shininess and lobe colours are not the
    texel's own but shared (the basis materials): Kd, each lobe's amplitude and its
    direction (linearised, two angles) are refitted without the view. The directions
    are the texel's own fit's (the source MH map's): held fixed they would keep what the
    left-out view taught them, and a lobe that one view placed would predict that view
    as if it had been seen (on the demo this made the materials' blend with mh-auto the
    map's default, 0.7 % worse on the held-out photos than mh-auto alone)."""
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
    Jx = jacobian_x(P, V)
    for k in range(K):
        cols.append(Jx[..., [mhx_theta(k), mhx_phi(k)]])
    J = np.concatenate(cols, -1)
    return loo_linear(J, np.where(W[..., None], mh_eval(P, V) - L, 0.0), w, W)


def loo_sh(C: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
           w: np.ndarray) -> Loo:
    """Leave-one-out residuals of SH maps, coefficients C (n, 3 nc) (channel-major,
    docs/reference/conventions.md), refitting without the view by plain least squares only the
    coefficients the texel uses (non-zero). For projections with a prior or
    regularisation this overstates the error of views at the edge of the sampled cap
    (their exact smoother: :func:`parammap.models.sh.fit_sh_tile` with ``loo``)."""
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
    return np.where(W[..., None], loo, 0.0), bad.any(1)


def predict(model: str, P: np.ndarray, V: np.ndarray, points: np.ndarray | None = None,
            lights: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(n, N, 3) radiance of parameter rows P (n, p) of ``model`` (``mh``, ``sh``,
    ``svbrdf``, ``diffuse``; docs/reference/conventions.md layouts) seen from directions
    V (n, N, 3); an svbrdf map at its texels' centres ``points`` (n, 3) under its
    ``lights``."""
    P = np.nan_to_num(np.asarray(P, float))
    if model == "diffuse":
        return np.broadcast_to(P[:, None, MH_KD], V.shape)
    if model == "sh":
        return sh_eval(P.reshape(len(P), 3, -1), V)
    if model == "svbrdf":
        n, N, _ = V.shape
        return svbrdf_eval(np.repeat(P, N, 0), np.repeat(points, N, 0), V.reshape(-1, 3),
                           *lights).reshape(n, N, 3)
    return mh_eval(P, V)


def loo_svbrdf(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray, w: np.ndarray,
               points: np.ndarray, lights: tuple, rel_step: float = 1e-3) -> Loo:
    """Leave-one-out residuals of an svbrdf map (:mod:`parammap.models.svbrdf`): Kd, Ks,
    ln alpha and the coat's share (where its region kept one) refitted without the view,
    linearised at the fit.
    ``lights`` as :attr:`parammap.stores.params.ParamMap.lights`: with a flat-field's
    irradiance its radiance is divided by it, as the observations were."""
    P = np.nan_to_num(np.asarray(P, float))
    n, N, _ = V.shape
    rig = LightRig(*lights)
    pos, wl, sky = rig.position_mm, rig.intensity, rig.ambient
    k = np.ones(n) if rig.irradiance is None else 1.0 / rig.irradiance(points)
    l, e = light_terms(points, pos)
    alpha = np.clip(P[:, SV_ALPHA], 1e-6, None)
    coat = np.clip(P[:, SV_COAT], 0, 1)[:, None, None]
    t_v = coat_transmittance(V[..., 2])[..., None]  # (n, N, 1)

    def spec(a):
        s = specular_basis(l, e, V, a.reshape(-1, 1, 1)) @ wl  # (n, N, 3)
        if sky is not None:
            s = s + ggx_albedo(V[..., 2], a[:, None])[..., None] * (sky / np.pi)
        return s

    S = spec(alpha)
    dS = (spec(alpha * np.exp(rel_step)) - spec(alpha * np.exp(-rel_step))) / (2 * rel_step)
    matte = (e @ wl)[:, None]  # (n, 1, 3)
    coated = ((e * coat_transmittance(l[..., 2])) @ wl)[:, None] * t_v  # (n, N, 3)
    if sky is not None:
        matte = matte + sky
        coated = coated + sky * coat_sky_transmittance() * t_v
    diffuse = (1 - coat) * matte + coat * coated
    J = np.zeros((n, N, 3, SV_SIZE))
    eye = np.eye(3)
    J[..., SV_KD] = diffuse[..., None] * eye
    J[..., SV_KS] = S[..., None] * eye
    J[..., SV_ALPHA] = dS * P[:, None, SV_KS]
    # a matte texel's coat was fixed at 0 by its region (not a parameter of its fit)
    J[..., SV_COAT] = np.where(coat > 0, (coated - matte) * P[:, None, SV_KD], 0.0)
    J *= k[:, None, None, None]
    pred = diffuse * P[:, None, SV_KD] + S * P[:, None, SV_KS]
    r = np.where(W[..., None], k[:, None, None] * pred - L, 0.0)
    return loo_linear(J, r, w, W)


def influential(e: np.ndarray, r: np.ndarray, W: np.ndarray,
                factor: float = INFLUENCE) -> np.ndarray:
    """(n, N) bool: valid views whose leave-one-out residual e (n, N, 3) exceeds
    ``factor`` times the in-sample residual r (n, N, 3) of the fit.

    Leaving out such a view measures what the fit loses without it (a lobe that only
    this view saw is gone), not how the fit with it predicts a new direction; a model
    that resolves texel detail loses most there, so judged on those views it loses to
    a smoother one whose new-view predictions are worse (on the analytic demo, 0.2 % of
    the views with left-out errors above 80 levels ranked the basis materials ahead of
    mh-auto, which predicts 200 random directions 3 % better)."""
    with np.errstate(invalid="ignore"):
        return W & (np.linalg.norm(e, axis=-1) > factor * np.linalg.norm(r, axis=-1))
