"""A microfacet SVBRDF per texel under the capture's lights (model ``svbrdf-ggx``,
issue 48 item 2).

Each texel of the flat surface (normal +z) reflects each light ``j`` (a point at
``p_j``, surface frame, mm; relative RGB intensity ``w_j``) as

    L(v) = sum_j w_j e_j [Kd ((1 - c) + c T(l_j) T(v)) + Ks D(h_j) Vis(l_j, v)],
    e_j = cos(theta_j) (R / r_j)^2

with ``l_j`` the unit vector to the light, ``r_j`` its distance, ``theta_j`` its angle
from the normal, ``R`` = :data:`REFERENCE_MM` (``e_j`` is the irradiance relative to
that of the same light a metre away at normal incidence, so that the ``w_j`` are the
lights' true relative intensities and a moved light dims with its distance as a lamp
does), ``h_j`` the half vector of ``l_j`` and the view ``v``, ``D`` the GGX
(Trowbridge-Reitz) distribution of roughness ``alpha`` and ``Vis`` Smith's
height-correlated visibility ``G2 / (4 n.l n.v)`` (Heitz 2014). ``Kd`` (RGB) is the
diffuse radiance per unit ``e`` of the first light at normal incidence (albedo / pi
times its intensity), ``Ks`` (RGB) the specular amplitude (Fresnel F0 times the
intensity, its rise toward grazing not modelled: the views rarely see a highlight
beyond 60 deg of incidence, where Schlick's factor stays within 10 % of F0 for a
dielectric). ``c`` in [0, 1] is the share of the diffuse light that crosses a
dielectric coating on its way in and out (a plastic, a varnish, a glossy print): ``T``
is the coating's Fresnel transmittance (:func:`coat_transmittance`, index
:data:`COAT_IOR`) relative to normal incidence, which dims that light toward grazing
(to 0.75 at 75 deg); a matte surface (paper, cloth) has ``c`` = 0. Without it a
coated texel's diffuse fall-off is taken up by the lobe, which then comes out wider
and brighter than the surface's (alpha 15-30 % and Ks 25-35 % too high on a rough
plastic). Radiance is in the observation map's units.

A room is not dark: what the walls and the sky send back lights the surface evenly
from every direction. Where the capture states that light (``ambient``, an irradiance
``a`` in the units of ``e w``, RGB; :func:`ambient_irradiance` from the share a lab
measures with the lamps off), each texel adds what a uniform sky of radiance ``a / pi``
gives it:

    Kd ((1 - c) + c Tbar T(v)) a + Ks E(v, alpha) a / pi

with ``E`` GGX's directional albedo (:func:`ggx_albedo`) and ``Tbar`` the coating's
cosine-weighted mean transmittance (:func:`coat_sky_transmittance`). Without it the sky
is taken for the lamps: the albedo comes out too high by its share of the irradiance,
and a map relit under other lamps carries the old sky's share with them.

For a given ``alpha`` the radiance is linear in the matte and coated parts of ``Kd``
and in ``Ks``, so a texel's fit is a one-dimensional search over ``alpha`` (a grid in
log alpha, then a parabola through the best three) with the amplitudes per channel
solved exactly and non-negative at each step (variable projection): no start to
choose and no local minimum in the amplitudes, vectorised over thousands of texels.
``c`` is the coated part's share of ``Kd`` (luminance) at the best ``alpha``, and
``Kd`` and ``Ks`` are solved once more with it.
"""

from __future__ import annotations

import itertools
import math
import warnings
from functools import cache
from typing import Any, NamedTuple

import nlopt
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import median_filter

from ..conventions import LUMINANCE, SV_ALPHA, SV_COAT, SV_KD, SV_KS, SV_SIZE, FitArray, FitStatus
from ..geometry import texel_centres
from .lights import expand_lights
from .residuals import mean_percentage_residual
from .weights import noise_weights, reduced_chi2

__all__ = ["ALPHA_RANGE", "COAT_F", "COAT_IOR", "COAT_WINDOW_F", "MIN_OBS", "OFF_HIGHLIGHT",
           "ALBEDO_NODES", "LightRig", "alpha_grid", "ambient_irradiance", "card_scale",
           "coat_regions", "coat_share", "coat_sky_transmittance", "coat_transmittance",
           "fit_svbrdf_batch", "fit_svbrdf_tile", "fresnel_dielectric", "ggx_albedo",
           "ggx_albedo_table", "ggx_vis", "light_terms",
           "light_weights", "lobe_rejected", "metallic_roughness", "neighbour_priors",
           "pool_svbrdf_tile", "lobe_profiles", "shared_lobe_alpha",
           "refine_lights", "specular_basis", "svbrdf_eval", "svbrdf_outputs"]

#: GGX alpha searched: from a near-mirror (a lobe about 0.3 deg wide) to fully rough.
ALPHA_RANGE = (0.005, 1.0)
GRID_STEPS = 48
REFINE_GRID_STEPS = 24  # half the fit's: the objective needs each texel's best alpha roughly
#: the irradiance's reference distance (1 m): e = 1 a metre from a light, facing it
REFERENCE_MM = 1000.0
MIN_OBS = SV_SIZE + 1  # observations a texel needs (per channel: Kd, Ks, alpha shared)
#: refractive index of a dielectric (a coating, a plastic): F0 = 0.04, glTF's
COAT_IOR = 1.5
#: the F statistic (one parameter) a texel's coat must reach to be kept on its own
#: evidence: chi-square's 99 % point for one degree of freedom
COAT_F = 6.63
#: the F statistic (two parameters) a texel's lobe must reach to be kept: chi-square's
#: 99 % point for two degrees of freedom, over two
LOBE_F = 4.61
#: chi-square's 99 % point for two degrees of freedom: a texel fitted without a lobe
#: keeps none where its own views reject its neighbours' lobe by this much
#: (:func:`lobe_rejected`)
PRIOR_REJECT_CHI2 = 9.21
#: a view is off a texel's highlight where the lobe gives under this share of its
#: diffuse light: the coat's evidence is judged there (a tenth left a rough plastic,
#: whose broad lobe reaches most views, with too few views to show its coat)
OFF_HIGHLIGHT = 0.3
#: the median F over a texel's (2 r + 1)^2 window (r = :data:`POOL_RADIUS`) for the coat
#: to be kept: noise alone gives chi-square's median for one degree of freedom, 0.45, and
#: the 81 texels, at least some 20 of them independent (neighbours share photo pixels),
#: put their median within 0.45 +- 0.24; 1.2 is 3 sds above
COAT_WINDOW_F = 1.2


def fresnel_dielectric(cos_t, ior: float = COAT_IOR) -> np.ndarray:
    """Unpolarised Fresnel reflectance of light arriving from air at ``cos_t`` (any
    shape) to the normal of a smooth dielectric of index ``ior``."""
    c = np.clip(np.asarray(cos_t, float), 1e-6, 1.0)
    ct = np.sqrt(1 - (1 - c * c) / ior ** 2)  # the refracted ray's cosine
    rs = ((c - ior * ct) / (c + ior * ct)) ** 2
    rp = ((ior * c - ct) / (ior * c + ct)) ** 2
    return 0.5 * (rs + rp)


def coat_transmittance(cos_t) -> np.ndarray:
    """The coating's transmittance ``T = (1 - F(cos_t)) / (1 - F0)`` relative to normal
    incidence (1 there, 0.75 at 75 deg, 0 at grazing; any shape)."""
    return (1 - fresnel_dielectric(cos_t)) / (1 - fresnel_dielectric(1.0))


class LightRig(NamedTuple):
    """The lights a relightable map is fitted and drawn under: positions (J, 3) mm
    (surface frame), relative RGB intensities (J, 3), the flat-field's relative
    irradiance the observations were divided by
    (:class:`parammap.models.radiometry.IrradianceGrid`, or None) and the room's ambient
    irradiance (3,) in the units of ``e w`` (or None: a dark room). Its fields are
    :func:`svbrdf_eval`'s light arguments, in order."""

    position_mm: np.ndarray
    intensity: np.ndarray
    irradiance: Any = None
    ambient: np.ndarray | None = None


@cache
def coat_sky_transmittance() -> float:
    """``Tbar = 2 int_0^1 T(mu) mu dmu``: the share of an even sky's light that crosses
    the coating (:func:`coat_transmittance`) on its way in, relative to normal
    incidence."""
    x, w = np.polynomial.legendre.leggauss(64)
    mu = (x + 1) / 2
    return float(np.sum(w * coat_transmittance(mu) * mu))


#: the directional albedo's table (:func:`ggx_albedo_table`): view cosines (linear) by
#: alphas (log); bilinear between its nodes, it is within 0.01 of the integral (the
#: viewer's shader holds the same table)
ALBEDO_NODES = (25, 24)


@cache
def ggx_albedo_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(view cosines (m,), ln alphas (n,), albedo (m, n)): GGX's directional albedo
    ``E(v, alpha) = int D(h) Vis(l, v) cos(theta_l) dw_l`` (Fresnel 1), by Gauss-Legendre
    quadrature over the distribution of the half vector (a thousandth of a Monte Carlo
    integral's figure). Smooth in both, so that :func:`ggx_albedo` interpolates it."""
    x, wx = np.polynomial.legendre.leggauss(64)
    u, wu = (x + 1) / 2, wx / 2  # GGX's half-vector CDF: tan theta = alpha sqrt(u / (1 - u))
    nphi = 32
    phi = (np.arange(nphi) + 0.5) * math.pi / nphi  # the plane of v is a mirror: half turn
    mus, alpha = np.linspace(0.02, 1.0, ALBEDO_NODES[0]), alpha_grid(ALBEDO_NODES[1])
    th = np.arctan(alpha[:, None, None] * np.sqrt(u / (1 - u))[:, None])  # (n, u, 1)
    h = np.stack(np.broadcast_arrays(np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi),
                                     np.cos(th)), -1)  # (n, u, phi, 3)
    a2 = (alpha * alpha)[:, None, None]
    E = np.empty((len(mus), len(alpha)))
    for i, mu in enumerate(mus):
        vh = h[..., 0] * math.sqrt(1 - mu * mu) + h[..., 2] * mu
        n_l = 2 * vh * h[..., 2] - mu
        c = _ggx_cosines(h[..., 2], mu, n_l)
        D = a2 / (math.pi * (c[0] * (a2 - 1) + 1) ** 2)
        # D Vis cos_l over the half vector's density D cos_h, times dw_l / dw_h = 4 v.h
        g = np.where((n_l > 0) & (vh > 0), _ggx_dvis(c, a2) / D * c[2] * 4 * vh / h[..., 2],
                     0.0)
        E[i] = np.einsum("nup,u->n", g, wu) / nphi
    return mus, np.log(alpha), E


def ggx_albedo(n_v, alpha) -> np.ndarray:
    """GGX's directional albedo (Fresnel 1) at view cosines ``n_v`` and roughness
    ``alpha`` (broadcastable), interpolated bilinearly in (cosine, ln alpha) from
    :func:`ggx_albedo_table`: 1 for a mirror, 0.5-0.6 at alpha 1 (energy the single
    scattering loses)."""
    n_v, alpha = np.broadcast_arrays(np.asarray(n_v, float), np.asarray(alpha, float))
    return _albedo_at(_albedo_rows(n_v), alpha)


def _albedo_rows(n_v) -> tuple[np.ndarray, np.ndarray]:
    """:func:`ggx_albedo`'s table interpolated at view cosines ``n_v`` (...): (..., n)
    at each of its alpha nodes, and the nodes' ln alpha (n,). Taken once for views
    whose albedo is wanted at many alphas."""
    mu, la, E = ggx_albedo_table()
    x = np.clip((np.asarray(n_v, float) - mu[0]) / (mu[1] - mu[0]), 0, len(mu) - 1.000001)
    i = x.astype(int)
    fx = (x - i)[..., None]
    return E[i] * (1 - fx) + E[i + 1] * fx, la


def _albedo_at(rows: tuple[np.ndarray, np.ndarray], alpha) -> np.ndarray:
    """:func:`ggx_albedo` from :func:`_albedo_rows` at ``alpha`` (broadcastable to the
    rows' leading shape)."""
    Ev, la = rows
    y = np.clip((np.log(np.clip(np.asarray(alpha, float), *ALPHA_RANGE)) - la[0])
                / (la[1] - la[0]), 0, len(la) - 1.000001)
    y = np.broadcast_to(y, Ev.shape[:-1])
    j = y.astype(int)[..., None]
    fy = y - j[..., 0]
    lo = np.take_along_axis(Ev, j, -1)[..., 0]
    hi = np.take_along_axis(Ev, j + 1, -1)[..., 0]
    return lo * (1 - fy) + hi * fy


def ambient_irradiance(share, at_mm: np.ndarray, lights_mm: np.ndarray,
                       weights: np.ndarray) -> np.ndarray:
    """(3,) the ambient irradiance ``a`` (units of ``e w``) from the ``share`` (scalar or
    RGB, in [0, 1)) of a white card's light at ``at_mm`` (3,) that stays when the lamps
    are off: ``a = e w (at) share / (1 - share)``."""
    _, e = light_terms(np.asarray(at_mm, float), lights_mm)
    s = np.broadcast_to(np.asarray(share, float), (3,))
    return (e @ np.asarray(weights, float)) * s / (1 - s)


def alpha_grid(steps: int = GRID_STEPS) -> np.ndarray:
    """(steps,) alphas evenly spaced in log over :data:`ALPHA_RANGE`."""
    return np.geomspace(*ALPHA_RANGE, steps)


def light_terms(points: np.ndarray, lights_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors to the lights and their irradiance factors.

    Parameters
    ----------
    points : (..., 3) surface points (mm, z = 0); lights_mm : (J, 3) light positions, or
        (J, 6) positions and the unit normals of Lambertian emitters (an area light's
        points, :func:`parammap.models.lights.expand_lights`; a zero normal: a point
        that shines alike in every direction).

    Returns
    -------
    l : (..., J, 3) unit vectors toward each light; e : (..., J)
    ``cos theta_j (R / r_j)^2`` (0 for a light below the plane), times the emitter's
    cosine toward the point where it has a normal.
    """
    lights = np.asarray(lights_mm, float)
    d = lights[:, :3] - np.asarray(points, float)[..., None, :]
    r = np.maximum(np.linalg.norm(d, axis=-1), 1e-12)
    l = d / r[..., None]
    e = np.where(d[..., 2] > 0, d[..., 2] / r * (REFERENCE_MM / r) ** 2, 0.0)
    if lights.shape[1] == 6:
        n = lights[:, 3:]
        facing = -(l * n).sum(-1)
        e = e * np.where((n * n).sum(-1) > 0, np.clip(facing, 0.0, None), 1.0)
    return l, e


def ggx_vis(n_h: np.ndarray, n_v: np.ndarray, n_l: np.ndarray, alpha) -> np.ndarray:
    """``D(h) Vis(l, v)`` of GGX with Smith's height-correlated masking-shadowing, for
    the cosines of the half vector, view and light with the normal (any broadcastable
    shapes). 0 where the light or the view is below the surface."""
    c = _ggx_cosines(n_h, n_v, n_l)
    return np.where((n_v > 0) & (n_l > 0), _ggx_dvis(c, np.asarray(alpha, float) ** 2), 0.0)


def _ggx_cosines(n_h, n_v, n_l) -> tuple[np.ndarray, ...]:
    """What :func:`ggx_vis` needs of the cosines whatever alpha: the half vector's
    squared, the view's and the light's (clipped to (0, 1]) and their squares."""
    nv, nl = np.clip(n_v, 1e-6, 1), np.clip(n_l, 1e-6, 1)
    return np.clip(n_h, 0, 1) ** 2, nv, nl, nv * nv, nl * nl


def _ggx_dvis(c: tuple[np.ndarray, ...], a2) -> np.ndarray:
    """``D Vis`` from :func:`_ggx_cosines` ``c`` at ``a2`` = alpha squared."""
    ch2, nv, nl, nv2, nl2 = c
    D = a2 / (math.pi * (ch2 * (a2 - 1) + 1) ** 2)
    return D * 0.5 / (nl * np.sqrt(nv2 * (1 - a2) + a2) + nv * np.sqrt(nl2 * (1 - a2) + a2))


def _dvis_seen_loop(ch2, nv, nl, nv2, nl2, e_seen, a2):
    out = np.empty(ch2.shape)
    for b in range(ch2.shape[0]):
        a = a2[b]
        for n in range(ch2.shape[1]):
            for j in range(ch2.shape[2]):
                d = ch2[b, n, j] * (a - 1) + 1
                vis = 0.5 / (nl[b, n, j] * math.sqrt(nv2[b, n, j] * (1 - a) + a)
                             + nv[b, n, j] * math.sqrt(nl2[b, n, j] * (1 - a) + a))
                out[b, n, j] = e_seen[b, n, j] * a / (math.pi * d * d) * vis
    return out


def ggx_dvis_seen(c: tuple[np.ndarray, ...], e_seen: np.ndarray, a2: np.ndarray
                  ) -> np.ndarray:
    """``e_seen D Vis`` (B, N, J): the cosines ``c`` of :func:`_ggx_cosines` and the
    irradiance ``e_seen`` (B, N, J) at each texel's alpha squared ``a2`` (B,). One
    compiled pass (numba; a fit's grid search spends most of its time here), numpy where
    numba is missing."""
    kernel = _compiled(_dvis_seen_loop)
    if kernel is None:
        return e_seen * _ggx_dvis(c, np.asarray(a2, float)[:, None, None])
    return kernel(*c, e_seen, np.ascontiguousarray(a2, float))


@cache
def _compiled(f):
    """``f`` compiled by numba (cached on disk, GIL released), or None where numba is
    missing (the caller's numpy path)."""
    try:
        from numba import njit
    except ImportError:  # pragma: no cover - exercised only without numba
        return None
    return njit(cache=True, nogil=True)(f)


def specular_basis(l: np.ndarray, e: np.ndarray, views: np.ndarray, alpha) -> np.ndarray:
    """Per light, ``e_j D(h_j) Vis(l_j, v)``: l (..., J, 3) and e (..., J) of
    :func:`light_terms`, views (..., N, 3) unit; alpha broadcastable to (..., 1, 1).
    Returns (..., N, J)."""
    v = views[..., :, None, :]
    L = l[..., None, :, :]
    h = v + L
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    return e[..., None, :] * ggx_vis(h[..., 2], v[..., 2], L[..., 2], alpha)


def svbrdf_eval(params: np.ndarray, points: np.ndarray, views: np.ndarray,
                lights_mm: np.ndarray, weights: np.ndarray, irradiance=None,
                ambient: np.ndarray | None = None) -> np.ndarray:
    """Radiance (M, 3) of parameter vectors (M, ``SV_SIZE``) at surface points (M, 3)
    seen from unit directions (M, 3), under lights (J, 3) mm of relative RGB
    intensities ``weights`` (J, 3) and the room's ``ambient`` irradiance (3,) (units of
    ``e w``; None: none); divided by ``irradiance(points)`` where given (the
    flat-field's relative irradiance, :class:`parammap.models.radiometry.IrradianceGrid`:
    the capture's frames were read so). The light arguments are a :class:`LightRig`'s
    fields."""
    p = np.asarray(params, float)
    v = np.asarray(views, float)
    l, e = light_terms(points, lights_mm)  # (M, J, 3), (M, J)
    alpha = np.clip(p[:, SV_ALPHA], *ALPHA_RANGE)[:, None, None]
    s = specular_basis(l, e, v[:, None, :], alpha)[:, 0]  # (M, J)
    w = np.asarray(weights, float)
    c = np.clip(np.nan_to_num(p[:, SV_COAT]), 0, 1)[:, None]
    coated = ((e * coat_transmittance(l[..., 2])) @ w) * coat_transmittance(v[:, 2])[:, None]
    matte, spec = e @ w, s @ w
    if ambient is not None:
        a = np.asarray(ambient, float)
        matte = matte + a
        coated = coated + a * coat_sky_transmittance() * coat_transmittance(v[:, 2])[:, None]
        spec = spec + a / math.pi * ggx_albedo(v[:, 2], alpha[:, 0, 0])[:, None]
    out = p[:, SV_KD] * ((1 - c) * matte + c * coated) + p[:, SV_KS] * spec
    return out if irradiance is None else out / irradiance(points)[:, None]


def _solve_small(G: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Solve many small symmetric positive definite systems G (..., k, k) x = r (..., k)
    by Cholesky, vectorised over the leading axes (numpy's batched solve spends most of
    its time per matrix at k <= 5)."""
    k = G.shape[-1]
    L = np.zeros_like(G)
    for j in range(k):
        d = G[..., j, j] - np.einsum("...i,...i->...", L[..., j, :j], L[..., j, :j])
        L[..., j, j] = np.sqrt(np.maximum(d, 1e-300))
        for i in range(j + 1, k):
            L[..., i, j] = (G[..., i, j] - np.einsum("...m,...m->...", L[..., i, :j],
                                                    L[..., j, :j])) / L[..., j, j]
    z = np.empty_like(r)
    for i in range(k):  # L z = r, then L^T x = z
        z[..., i] = (r[..., i] - np.einsum("...m,...m->...", L[..., i, :i], z[..., :i])) \
            / L[..., i, i]
    x = np.empty_like(r)
    for i in reversed(range(k)):
        x[..., i] = (z[..., i] - np.einsum("...m,...m->...", L[..., i + 1:, i],
                                           x[..., i + 1:])) / L[..., i, i]
    return x


def _nnls_small(G: np.ndarray, r: np.ndarray, yy: np.ndarray) -> tuple[np.ndarray,
                                                                           np.ndarray]:
    """Non-negative least squares of many small problems from their normal equations:
    G (B, P, P), r (B, P), yy (B,) the weighted sum of squares of the data. Where the
    unconstrained solution is non-negative it is the answer; elsewhere every support
    set is solved and the feasible one of least residual kept (exact: the solution is
    the unconstrained one on its support). Returns (B, P) and (B,) RSS."""
    B, P = r.shape
    ridge = 1e-12 * np.maximum(np.trace(G, axis1=1, axis2=2), 1e-300)
    Gr = G + ridge[:, None, None] * np.eye(P)
    best = _solve_small(Gr, r)
    best_rss = yy - np.einsum("bk,bk->b", best, r)  # at the optimum, c.G.c = c.r
    rest = np.flatnonzero(~(best >= 0).all(1))
    if len(rest):
        Gq, rq, yq = Gr[rest], r[rest], yy[rest]
        cb, rb = np.zeros((len(rest), P)), yq.copy()
        for k in range(1, P):  # every support of k bases in one batched solve
            subs = np.array(list(itertools.combinations(range(P), k)))  # (n, k)
            Gs = Gq[:, subs[:, :, None], subs[:, None, :]]  # (b, n, k, k)
            rs = rq[:, subs]  # (b, n, k)
            c = _solve_small(Gs, rs)
            rss = yq[:, None] - np.einsum("bnk,bnk->bn", c, rs)
            rss = np.where((c >= 0).all(-1), rss, np.inf)
            j = np.argmin(rss, 1)
            ok = rss[np.arange(len(rest)), j] < rb
            rb[ok] = rss[ok, j[ok]]
            full = np.zeros((int(ok.sum()), P))
            np.put_along_axis(full, subs[j[ok]], c[ok, j[ok]], axis=1)
            cb[ok] = full
        best[rest], best_rss[rest] = cb, rb
    return best, np.maximum(best_rss, 0.0)


def _diffuse_moments(y: np.ndarray, omega: np.ndarray, D: list[np.ndarray]) -> dict:
    """The sums of :func:`_amplitudes` that do not depend on alpha: the P diffuse bases
    D (each (B, 3), constant over the views, or (B, N, 3)) against themselves and the
    data y (B, N, 3) under the weights omega (B, N)."""
    B = y.shape[0]
    P = len(D)
    sw = omega.sum(1)  # (B,)
    Dw = [d[:, None, :] * sw[:, None, None] if d.ndim == 2 else d * omega[:, :, None]
          for d in D]  # constant ones: their weight summed over the views, (B, 1, 3)
    G = np.empty((B, 3, P, P))
    r = np.empty((B, 3, P))
    oy = np.einsum("bn,bnc->bc", omega, y)
    for p in range(P):
        r[:, :, p] = D[p] * oy if D[p].ndim == 2 else np.einsum("bnc,bnc->bc", Dw[p], y)
        for q in range(p, P):
            if D[p].ndim == 2 and D[q].ndim == 2:
                g = D[p] * D[q] * sw[:, None]
            elif D[p].ndim == 2:
                g = D[p] * np.einsum("bn,bnc->bc", omega, D[q])
            elif D[q].ndim == 2:
                g = D[q] * np.einsum("bn,bnc->bc", omega, D[p])
            else:
                g = np.einsum("bnc,bnc->bc", Dw[p], D[q])
            G[:, :, p, q] = G[:, :, q, p] = g
    # every basis over the views, for the compiled specular sums
    Dn = np.stack([np.broadcast_to(d[:, None, :] if d.ndim == 2 else d, y.shape) for d in D])
    return {"D": D, "Dn": Dn, "G": G, "r": r, "yy": np.einsum("bn,bnc->bc", omega, y * y)}


def _spec_moments_loop(y, omega, S, Dn):
    B, N, Q, C = S.shape
    P = Dn.shape[0]
    rs = np.empty((B, C, Q))
    Gss = np.empty((B, C, Q, Q))
    Gds = np.empty((B, C, P, Q))
    for b in range(B):
        for c in range(C):
            for q in range(Q):
                r = 0.0
                for n in range(N):
                    r += omega[b, n] * S[b, n, q, c] * y[b, n, c]
                rs[b, c, q] = r
                for k in range(q, Q):
                    g = 0.0
                    for n in range(N):
                        g += omega[b, n] * S[b, n, q, c] * S[b, n, k, c]
                    Gss[b, c, q, k] = g
                    Gss[b, c, k, q] = g
                for p in range(P):
                    g = 0.0
                    for n in range(N):
                        g += omega[b, n] * S[b, n, q, c] * Dn[p, b, n, c]
                    Gds[b, c, p, q] = g
    return rs, Gss, Gds


def _spec_moments(y: np.ndarray, omega: np.ndarray, D: list[np.ndarray], S: np.ndarray,
                  Dn: np.ndarray | None = None) -> dict:
    """The sums of :func:`_amplitudes` that involve the Q specular bases S (B, N, Q, 3):
    against the data, themselves and each diffuse basis of D (:func:`_diffuse_moments`;
    ``Dn`` its (P, B, N, 3) stack, for the compiled pass)."""
    kernel = None if Dn is None else _compiled(_spec_moments_loop)
    if kernel is not None:
        rs, Gss, Gds = kernel(y, omega, S, Dn)
        return {"rs": rs, "Gss": Gss, "Gds": Gds}
    B, N, Q, _ = S.shape
    P = len(D)
    Sw = S * omega[:, :, None, None]
    rs = np.empty((B, 3, Q))
    Gss = np.empty((B, 3, Q, Q))
    Gds = np.empty((B, 3, P, Q))
    for q in range(Q):  # Q is the number of lights at most: plain loops
        rs[:, :, q] = np.einsum("bnc,bnc->bc", Sw[:, :, q], y)
        for p in range(P):
            Gds[:, :, p, q] = D[p] * Sw[:, :, q].sum(1) if D[p].ndim == 2 else \
                np.einsum("bnc,bnc->bc", Sw[:, :, q], D[p])
        for k in range(q, Q):
            Gss[:, :, q, k] = Gss[:, :, k, q] = np.einsum("bnc,bnc->bc", Sw[:, :, q], S[:, :, k])
    return {"rs": rs, "Gss": Gss, "Gds": Gds}


def _amplitudes(y: np.ndarray, omega: np.ndarray, dm: dict, S: np.ndarray,
                prior: tuple[np.ndarray, np.ndarray] | None = None,
                sm: dict | None = None, use: list[int] | None = None,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel non-negative diffuse and specular amplitudes of a batch at one alpha.

    y (B, N, 3) radiance, omega (B, N) weights (0: not observed); dm the diffuse bases'
    sums (:func:`_diffuse_moments`); S (B, N, Q, 3) the Q specular bases; prior: a
    Gaussian prior on the first specular amplitude per channel, its mean (B, 3) and its
    precision (B, 3) in units of the weighted residuals (0: none), whose penalty the RSS
    then includes; sm: the specular sums (:func:`_spec_moments`), when already made; use:
    which of dm's diffuse bases the model has (default all, P of them).
    Returns coefficients (B, P + Q, 3) (diffuse first), RSS (B, 3) and the normal
    matrices (B, 3, P + Q, P + Q) (without the prior)."""
    B, N, Q, _ = S.shape
    sm = _spec_moments(y, omega, dm["D"], S, dm.get("Dn")) if sm is None else sm
    use = list(range(len(dm["D"]))) if use is None else use
    P = len(use)
    K = P + Q
    G = np.empty((B, 3, K, K))
    G[:, :, :P, :P] = dm["G"][:, :, use][:, :, :, use]
    G[:, :, :P, P:] = sm["Gds"][:, :, use]
    G[:, :, P:, :P] = np.swapaxes(G[:, :, :P, P:], 2, 3)
    G[:, :, P:, P:] = sm["Gss"]
    r = np.concatenate([dm["r"][:, :, use], sm["rs"]], 2)
    yy = dm["yy"]
    if prior is not None:
        mu, lam = prior
        G = G.copy()
        G[:, :, P, P] += lam
        r = r.copy()
        r[:, :, P] += lam * mu
        yy = yy + lam * mu * mu
    c, rss = _nnls_small(G.reshape(B * 3, K, K), r.reshape(B * 3, K), yy.reshape(B * 3))
    return (np.swapaxes(c.reshape(B, 3, K), 1, 2), rss.reshape(B, 3), G)


def coat_share(kd: np.ndarray) -> np.ndarray:
    """(B,) the coated part's share of the diffuse amplitudes' luminance, from the two
    per channel (B, 2, 3) (matte, coated); 0 where both are 0."""
    lum = kd @ LUMINANCE  # (B, 2)
    tot = lum.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(tot > 0, np.clip(lum[:, 1] / tot, 0, 1), 0.0)


def _diffuse_and_cosines(views: np.ndarray, l: np.ndarray, e: np.ndarray, w: np.ndarray,
                         ambient: np.ndarray | None) -> tuple:
    """What a batch's fit needs whatever alpha: the matte diffuse basis ``e_w`` (B, 3)
    and the coated one (B, N, 3) (each with the room's ``ambient`` light, (3,) or
    None), the GGX term's cosines (:func:`_ggx_cosines`, each (B, N, J)), the lights'
    irradiance where light and view are above the surface (B, N, J) (0 elsewhere), and
    the ambient light as given. ``l``, ``e``: :func:`light_terms` at the texels;
    ``w`` (J, 3) the lights' intensities."""
    e_w = e @ w  # (B, 3)
    t_v = coat_transmittance(np.asarray(views, float)[..., 2])[..., None]  # (B, N, 1)
    coated = ((e * coat_transmittance(l[..., 2])) @ w)[:, None, :] * t_v  # (B, N, 3)
    sky = None
    if ambient is not None:
        sky = np.asarray(ambient, float)
        e_w = e_w + sky
        coated = coated + sky * coat_sky_transmittance() * t_v
    # the half vectors do not depend on alpha: their cosines once for every alpha tried
    v = np.asarray(views, float)[:, :, None, :]
    h = v + l[:, None]
    n_h = h[..., 2] / np.maximum(np.linalg.norm(h, axis=-1), 1e-12)  # (B, N, J)
    n_v = np.broadcast_to(v[..., 2], n_h.shape)
    n_l = np.broadcast_to(l[:, None, :, 2], n_h.shape)
    e_seen = np.where((n_v > 0) & (n_l > 0), e[:, None, :], 0.0)  # (B, N, J)
    return e_w, coated, _ggx_cosines(n_h, n_v, n_l), e_seen, sky


def _lobe_bases(c: tuple[np.ndarray, ...], e_seen: np.ndarray, alpha,
                w: np.ndarray | None, sky: np.ndarray | None,
                rows: tuple[np.ndarray, np.ndarray] | None = None,
                group: np.ndarray | None = None) -> np.ndarray:
    """The specular bases of n texels at their alphas (n,) (or one for all), from the
    cosines ``c`` and ``e_seen`` of :func:`_diffuse_and_cosines`: (n, N, 1, 3) with the
    lights' intensities ``w`` (J, 3) (and the sky's share of the lobe, ``sky`` (3,) or
    None; ``rows``: :func:`_albedo_rows` at the views, when already taken), or one per
    light (n, N, J, 3) with ``w`` None (``group`` (P, J): the lights' shares of the
    P points the cosines are of, :func:`parammap.models.lights.expand_lights`)."""
    a = np.broadcast_to(np.asarray(alpha, float).ravel(), e_seen.shape[:1])
    s = ggx_dvis_seen(c, e_seen, a * a)  # (n, N, P)
    if w is None:
        s = s if group is None else s @ group
        return np.broadcast_to(s[..., None], s.shape + (3,))
    s = s @ w  # (n, N, 3)
    if sky is not None:  # the sky's share of the lobe, an even sky's
        rows = rows or _albedo_rows(c[1][..., 0])
        s = s + _albedo_at(rows, a[:, None])[..., None] * (sky / math.pi)
    return s[:, :, None, :]  # (n, N, 1, 3)


def fit_svbrdf_batch(y: np.ndarray, views: np.ndarray, omega: np.ndarray,
                     points: np.ndarray, lights_mm: np.ndarray, weights: np.ndarray | None,
                     grid: np.ndarray | None = None, sd: bool = True,
                     prior: dict[str, np.ndarray] | None = None,
                     with_coat: bool = True, evidence: bool = False,
                     start: dict[str, np.ndarray] | None = None,
                     coat_choice: np.ndarray | None = None,
                     ambient: np.ndarray | None = None,
                     group: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Fit a batch of texels.

    Parameters
    ----------
    y : (B, N, 3) radiance; views : (B, N, 3) unit directions to the cameras;
    omega : (B, N) observation weights (0 where not observed);
    points : (B, 3) texel centres (mm); lights_mm : (J, 3), or (P, 6) an area light's
        points (:func:`light_terms`);
    weights : (J, 3) relative intensities of the lights, or None: one specular
        amplitude per light and channel is fitted instead of a shared ``Ks`` (the pilot
        fit of :func:`light_weights`); per light, not per point, with ``group``.
    group : (P, J) the lights' shares of the points of ``lights_mm``
        (:func:`parammap.models.lights.expand_lights`), for ``weights`` None; None: each
        point its own light.
    grid : the alphas searched (:func:`alpha_grid`); sd : False: only ``alpha``,
        ``coat``, ``amplitudes`` (B, 1 + Q, 3) and ``rss``.
    with_coat : False: every texel matte (the coat's share 0).
    evidence : return, for :func:`coat_evidence`, each texel's ``coat_f`` (the F statistic
        of its coat), ``alpha`` and ``coat`` (the coated model's), ``alpha_matte`` (the
        matte model's) and, with priors, ``sig2``: the state ``start`` takes.
    start : an ``evidence`` call's result: its alphas and coat shares taken, no search.
    coat_choice : (B,) bool, the texels that keep their coat (the others matte); None:
        those whose own F statistic passes :data:`COAT_F`.
    ambient : (3,) the room's ambient irradiance (:func:`svbrdf_eval`), or None; with
        ``weights`` only (the pilot's per-light amplitudes leave it out).
    prior : Gaussian priors per texel (shared ``Ks`` only): ``u_mean``, ``u_var`` (B,)
        on ln alpha, ``ks_mean``, ``ks_var`` (B, 3) on Ks (:func:`neighbour_priors`);
        the data's residuals are scaled by each channel's residual variance of the
        texel's own fit, so both terms are in units of their own sd. The sds returned
        are the posterior's (data and prior combined).

    Returns
    -------
    dict: ``estimate`` (B, ``SV_SIZE``) (with ``weights`` None, ``Ks`` of the first
    light), ``ks`` (B, J, 3) the specular amplitude per light (``Ks w_j``), ``stdev``
    (B, ``SV_SIZE``) standard deviations (HC3 sandwich, those of alpha and Ks at least
    their change when a view of leverage over :data:`JACKKNIFE_LEVERAGE` is left out;
    with ``prior``, the posterior's; the coat's NaN where the texel is matte),
    ``stdev_ks`` (B, J, 3),
    ``rss`` (B,) the weighted residual sum, ``dof`` (B,) degrees of freedom, ``coat_f``
    (B,) the coat's F statistic (0 where not tested).
    """
    grid = alpha_grid() if grid is None else np.asarray(grid, float)
    y = np.asarray(y, float)
    B, N, _ = y.shape
    l, e = light_terms(points, lights_mm)  # (B, P, 3), (B, P)
    shared = weights is not None
    group = None if shared or group is None else np.asarray(group, float)
    w = np.asarray(weights, float) if shared else \
        np.ones((e.shape[1], 3)) if group is None else group @ np.ones((group.shape[1], 3))
    # the diffuse bases: matte (constant over the views) and coated
    e_w, coated, cos, e_seen, sky = _diffuse_and_cosines(views, l, e, w, ambient if shared
                                                         else None)

    def bases(alpha, sel=slice(None), geo=None):
        """(n, N, 1, 3) or (n, N, J, 3) the specular bases of the texels ``sel`` at their
        alphas (n,); ``geo``: their (cosines, e_seen, albedo rows), when already taken
        out."""
        c, es, rows = geo or (tuple(x[sel] for x in cos), e_seen[sel], None)
        return _lobe_bases(c, es, alpha, w if shared else None, sky, rows, group)

    u = np.log(grid)
    every = np.arange(B)

    def profile(dm, uses, idx, ap=None, pen=None):
        """(n, grid) each texel's least objective at every alpha of the grid, one per
        diffuse model (``uses``: which of dm's bases it has; the specular sums once)."""
        profs = [np.empty((len(idx), len(grid))) for _ in uses]
        # the texels' data and geometry taken out once, not once an alpha
        yi, oi = y[idx], omega[idx]
        c = tuple(x[idx] for x in cos)
        geo = (c, e_seen[idx], _albedo_rows(c[1][..., 0]) if shared and sky is not None
               else None)
        for g, a in enumerate(grid):
            S = bases(np.full(len(idx), a), geo=geo)
            sm = _spec_moments(yi, oi, dm["D"], S, dm.get("Dn"))
            for prof, use in zip(profs, uses, strict=True):
                rss_g = _amplitudes(yi, oi, dm, S, ap, sm, use)[1]
                prof[:, g] = rss_g.sum(1) if pen is None else \
                    (rss_g / sig2[idx]).sum(1) + pen[:, g]
        return profs

    def objective(alpha, dm, sel=slice(None)):
        """At alphas of the texels ``sel``, with their diffuse bases' sums ``dm``."""
        ap = None if amp_prior is None else (amp_prior[0][sel], amp_prior[1][sel])
        c, rss, G = _amplitudes(y[sel], omega[sel], dm, bases(alpha, sel), ap)
        if amp_prior is None:
            return c, rss, G, rss.sum(1)
        pen = (rss / sig2[sel]).sum(1)
        pen += np.where(np.isfinite(prior["u_mean"][sel]),
                        (np.log(alpha) - np.nan_to_num(prior["u_mean"][sel])) ** 2
                        / prior["u_var"][sel], 0.0)
        return c, rss, G, pen

    def best_alpha(prof, cols, idx):
        """Each texel's alpha from its profile (a parabola in log alpha through the best
        grid point and its neighbours) and its amplitudes there."""
        n = len(idx)
        k = np.clip(np.argmin(prof, 1), 1, len(grid) - 2)
        f0, f1, f2 = (prof[np.arange(n), k + d] for d in (-1, 0, 1))
        h = u[1] - u[0]
        curv = (f0 - 2 * f1 + f2) / (h * h)  # second derivative
        slope = (f2 - f0) / (2 * h)
        step = np.where(curv > 0, -slope / np.where(curv > 0, curv, 1), 0.0)
        u_best = u[k] + np.clip(step, -h, h)
        at_edge = np.argmin(prof, 1)
        u_best = np.where((at_edge == 0) | (at_edge == len(grid) - 1), u[at_edge], u_best)
        alpha = np.exp(u_best)
        c, _, _, obj = objective(alpha, _diffuse_moments(y[idx], omega[idx], cols), idx)
        worse = obj > prof.min(1)  # the parabola missed: keep the grid's best
        if worse.any():
            alpha[worse] = grid[np.argmin(prof[worse], 1)]
            c[worse] = objective(alpha[worse], _diffuse_moments(
                y[idx[worse]], omega[idx[worse]], [x[worse] for x in cols]), idx[worse])[0]
        return alpha, c

    def mixed(coat, idx):
        """(n, N, 3) the one diffuse basis of the texels idx at coat shares (n,)."""
        return (1 - coat)[:, None, None] * e_w[idx][:, None, :] \
            + coat[:, None, None] * coated[idx]

    nobs = (omega > 0).sum(1)
    amp_prior = upen = sig2 = None
    if prior is not None:
        if not shared:
            raise ValueError("priors need the lights' intensities (a shared Ks)")
        upen = np.where(np.isfinite(prior["u_mean"])[:, None],
                        (u[None] - np.nan_to_num(prior["u_mean"])[:, None]) ** 2
                        / prior["u_var"][:, None], 0.0)
    cols = [e_w, coated] if with_coat else [e_w]
    # the matte model's profile beside the coated one's where the coat is tested
    both = with_coat and sd and start is None
    if start is None:
        D2 = _diffuse_moments(y, omega, cols)
        uses = [list(range(len(cols))), [0]] if both else [list(range(len(cols)))]
        profs = profile(D2, uses, every)
        if prior is not None:
            # each channel's residual variance of the texel's own best fit
            own = grid[np.argmin(profs[0], 1)]
            rss_own = _amplitudes(y, omega, D2, bases(own))[1]
            scale = np.einsum("bn,bnc->bc", omega, y * y) / np.maximum(nobs, 1)[:, None]
            sig2 = np.maximum(rss_own / np.maximum(nobs - 2, 1)[:, None],
                              1e-8 * scale + 1e-30)  # (B, 3)
    else:
        sig2 = start.get("sig2")
    if prior is not None:
        amp_prior = (np.nan_to_num(prior["ks_mean"]),
                     np.where(np.isfinite(prior["ks_mean"]), sig2 / prior["ks_var"], 0.0))
    if start is None:
        if prior is not None:
            profs = profile(D2, uses, every, amp_prior, upen)
        alpha, c = best_alpha(profs[0], cols, every)
        # the coat's share of the diffuse light
        coat = coat_share(c[:, :2]) if with_coat else np.zeros(B)
        if not sd:
            c, rss, G, _ = objective(alpha, _diffuse_moments(y, omega, [mixed(coat, every)]))
            return {"alpha": alpha, "coat": coat, "amplitudes": c, "rss": rss.sum(1)}
        # the coat is kept where it explains the data better than a matte texel does, by
        # an F test of its one parameter: on a matte texel its fall-off toward grazing
        # trades against a broad lobe's rise (alpha near 1) and fits noise (with priors,
        # their penalties left out)
        alpha_m, f_coat = alpha, np.zeros(B)
        if both:
            alpha_m, _ = best_alpha(profs[1], [e_w], every)
            dif_c = mixed(coat, every)
            fits = []
            for a, dif in ((alpha_m, np.broadcast_to(e_w[:, None, :], y.shape)),
                           (alpha, dif_c)):
                cc = objective(a, _diffuse_moments(y, omega, [dif]))[0]
                spec = np.einsum("bnqc,bqc->bnc", bases(a), cc[:, 1:])
                fits.append((cc[:, None, 0] * dif, spec))
            # judged on the views off the highlights (each model's lobe under
            # OFF_HIGHLIGHT of its diffuse light): there a coat's fall-off toward grazing
            # shows, and a lobe whose shape is not GGX's (a Phong one) does not pass for it
            off = omega > 0
            for d_part, s_part in fits:
                off &= s_part @ LUMINANCE < OFF_HIGHLIGHT * (d_part @ LUMINANCE)
            w_off = np.where(off, omega, 0.0)
            rss_m, rss_c = (np.einsum("bn,bnc->bc", w_off, (y - d_part - s_part) ** 2)
                            for d_part, s_part in fits)
            # per channel, then their mean: a view's noise is shared by its channels
            # (one pixel), so the three channels' gains are one parameter's, not three
            n_off = off.sum(1)
            dof_c = np.maximum(n_off - 2, 1)[:, None]
            f_coat = np.where(n_off >= MIN_OBS, ((rss_m - rss_c) / np.maximum(
                rss_c / dof_c, 1e-300)).mean(1), 0.0)
        if evidence:
            return {"coat_f": f_coat, "alpha": alpha, "coat": coat, "alpha_matte": alpha_m,
                    **({} if sig2 is None else {"sig2": sig2})}
    else:
        alpha, coat, alpha_m = (np.array(start[k], float) for k in
                                ("alpha", "coat", "alpha_matte"))
        f_coat = np.asarray(start["coat_f"], float)
    keep = (f_coat > COAT_F) if coat_choice is None else np.asarray(coat_choice, bool)
    keep = keep & bool(with_coat)
    alpha = np.where(keep, alpha, alpha_m)
    coat = np.where(keep, coat, 0.0)
    # the amplitudes and their sds at the chosen alpha and coat
    dif = mixed(coat, every)
    c, rss, _, _ = objective(alpha, _diffuse_moments(y, omega, [dif]))
    lobe = np.ones(B, bool)
    if prior is None and shared:
        # the lobe is kept where it explains the views better than a texel without one,
        # by an F test of its two parameters (alpha, and its amplitude: one across the
        # channels, as the coat's): on a matte texel a lobe fits the views' noise and,
        # broad, trades against the diffuse term, taking part of the albedo with it
        wd = omega[..., None] * dif
        kd0 = np.maximum(np.einsum("bnc,bnc->bc", wd, y) / np.maximum(
            np.einsum("bnc,bnc->bc", wd, dif), 1e-300), 0.0)
        rss0 = np.einsum("bn,bnc->bc", omega, (y - kd0[:, None, :] * dif) ** 2)
        dof1 = np.maximum(nobs - 3 - keep, 1)[:, None]
        f_lobe = ((rss0 - rss) / 2 / np.maximum(rss / dof1, 1e-300)).mean(1)
        lobe = (f_lobe > LOBE_F) | (nobs < MIN_OBS)
        c[~lobe, 0], c[~lobe, 1:] = kd0[~lobe], 0.0
        rss[~lobe] = rss0[~lobe]
        alpha = np.where(lobe, alpha, ALPHA_RANGE[1])
    # a matte texel's coat is not a parameter of its fit (the F test fixed it)
    d_coat = np.where(keep[:, None, None], coated - e_w[:, None, :], 0.0)
    sd_all, lev = _sandwich_sd(y, omega, dif, d_coat, c, bases, alpha)
    sd_all[:, -2] = np.where(keep, sd_all[:, -2], np.nan)
    sd_all[~lobe, -1] = np.nan
    Q = c.shape[1] - 1
    dof = np.maximum(3 * nobs - (3 * (1 + Q) + 1 + keep), 1)
    sd_c = sd_all[:, :-2].reshape(B, 3, 1 + Q)  # per channel: Kd, amplitudes
    sd_coat, sd_u = sd_all[:, -2], sd_all[:, -1]
    if shared:
        # a lobe one view draws passes through it and leaves it no residual for the
        # sandwich to see (HC3 divides that residual by 1 - h): its sds are at least
        # what leaving that view out changes
        lev = lev.reshape(B, N, 3).mean(-1)
        top = lev.argmax(1)
        idx = np.flatnonzero(lobe & (lev[every, top] > JACKKNIFE_LEVERAGE))
        if idx.size:
            om = omega[idx].copy()
            om[np.arange(idx.size), top[idx]] = 0.0
            r = fit_svbrdf_batch(y[idx], views[idx], om, points[idx], lights_mm, weights,
                                 grid, sd=False, with_coat=with_coat, ambient=ambient,
                                 prior=None if prior is None else
                                 {k: v[idx] for k, v in prior.items()})
            sd_u[idx] = np.fmax(sd_u[idx], np.abs(np.log(r["alpha"] / alpha[idx])))
            sd_c[idx, :, 1] = np.fmax(sd_c[idx, :, 1], np.abs(r["amplitudes"][:, 1] - c[idx, 1]))
    if prior is not None:  # the posterior's: data and prior combined
        with np.errstate(divide="ignore"):
            has = np.isfinite(prior["u_mean"])
            sd_u = np.where(has, 1 / np.sqrt(1 / sd_u ** 2 + 1 / prior["u_var"]), sd_u)
            hk = np.isfinite(prior["ks_mean"])
            sd_c[:, :, 1] = np.where(hk, 1 / np.sqrt(1 / sd_c[:, :, 1] ** 2
                                                     + 1 / prior["ks_var"]), sd_c[:, :, 1])
    params = np.empty((B, SV_SIZE))
    params[:, SV_KD] = c[:, 0]
    params[:, SV_KS] = c[:, 1]
    params[:, SV_ALPHA] = alpha
    params[:, SV_COAT] = coat
    sd = np.empty((B, SV_SIZE))
    sd[:, SV_KD] = sd_c[:, :, 0]
    sd[:, SV_KS] = np.where(lobe[:, None], sd_c[:, :, 1], np.nan)
    sd[:, SV_ALPHA] = alpha * sd_u
    sd[:, SV_COAT] = sd_coat
    ks = (c[:, 1:2] * w[None]) if shared else c[:, 1:]
    return {"estimate": params, "ks": ks, "stdev": sd,
            "stdev_ks": sd_c[:, :, 1:].swapaxes(1, 2), "rss": rss.sum(1), "dof": dof,
            "coat_f": f_coat}


def _sandwich_sd(y, omega, diffuse, d_coat, c, bases, alpha, rel_step: float = 1e-3,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3 (1 + Q) + 2) standard deviations of each channel's amplitudes (Kd, then the
    Q specular ones), of the coat's share and of ln alpha, and (B, 3 N) the
    observations' leverages (view-major, then channel): the sandwich
    ``A^-1 (J^T W diag(r^2) W J) A^-1``, ``A = J^T W J``, robust to noise that grows with
    the radiance (a highlight's views are noisier than the rest), with MacKinnon and
    White's HC3 leverage correction ``r_i / (1 - h_ii)``. ``diffuse`` (B, N, 3) is the
    diffuse basis at the fitted coat share and ``d_coat`` (B, N, 3) its derivative in
    the share."""
    B, N, _ = y.shape
    Q = c.shape[1] - 1
    S = bases(alpha)  # (B, N, Q, 3)
    dS = (bases(alpha * math.exp(rel_step)) - bases(alpha * math.exp(-rel_step))) \
        / (2 * rel_step)
    P = 3 * (1 + Q) + 2
    Jm = np.zeros((B, N, 3, P))
    for ch in range(3):
        Jm[:, :, ch, ch * (1 + Q)] = diffuse[..., ch]
        Jm[:, :, ch, ch * (1 + Q) + 1: (ch + 1) * (1 + Q)] = S[..., ch]
        Jm[:, :, ch, -2] = c[:, None, 0, ch] * d_coat[..., ch]
        Jm[:, :, ch, -1] = np.einsum("bnq,bq->bn", dS[..., ch], c[:, 1:, ch])
    r = y - c[:, None, 0] * diffuse - np.einsum("bnqc,bqc->bnc", S, c[:, 1:])
    Jm = Jm.reshape(B, N * 3, P)
    wv = np.repeat(omega, 3, axis=1)  # (B, 3N)
    rv = r.reshape(B, N * 3)
    A = np.einsum("bkp,bk,bkq->bpq", Jm, wv, Jm)
    ridge = 1e-12 * np.maximum(np.trace(A, axis1=1, axis2=2), 1e-300)[:, None, None]
    Ai = np.linalg.pinv(A + ridge * np.eye(P))
    # HC3: each residual over its leverage's complement, so that a view that alone
    # draws the highlight (leverage near 1) says how little the rest pin it down
    h = np.clip(np.einsum("bkp,bpq,bkq->bk", Jm, Ai, Jm) * wv, 0.0, 0.99)
    M = np.einsum("bkp,bk,bkq->bpq", Jm, wv * wv * (rv / (1 - h)) ** 2, Jm)
    cov = Ai @ M @ Ai
    return np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None)), h


def _profile_objective(y, views, omega, points, lights_mm, grid, group=None) -> float:
    """Sum over texels of each one's least weighted residual (each light its own
    specular amplitude) relative to its weighted sum of squares: scale-free, so that
    a bright texel does not outweigh a dark one."""
    # matte: where the highlights are places the lights, and a coat's freedom on a matte
    # texel (its fall-off against a broad lobe) only blurs that
    r = fit_svbrdf_batch(y, views, omega, points, lights_mm, None, grid=grid, sd=False,
                         with_coat=False, group=group)
    ss = np.einsum("bn,bnc->b", omega, y * y)
    return float(np.sum(r["rss"] / np.maximum(ss, 1e-30)))


def refine_lights(y: np.ndarray, views: np.ndarray, omega: np.ndarray, points: np.ndarray,
                  lights_mm: np.ndarray, reach: float = 0.5, max_evals: int = 200,
                  extents: list | None = None, target_mm: np.ndarray | None = None,
                  also_from: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """The light positions (J, 3) that let the SVBRDF explain a sample of texels best.

    A light found from Phong lobes is biased (a Phong lobe fitted to a microfacet
    highlight leans toward grazing, so its mirror ray falls short of the light); with
    the microfacet model the highlights' positions across the map say where the light
    is. Minimises :func:`_profile_objective` over the positions with nlopt's BOBYQA
    (bounded, derivative-free), each coordinate within ``reach`` times the light's
    distance from the sample's centre of its start.

    Parameters
    ----------
    y, views : (B, N, 3); omega : (B, N); points : (B, 3) mm; lights_mm : (J, 3) start.
    extents : per light None or its shape (:func:`parammap.models.lights.expand_lights`),
        which moves with its centre and faces ``target_mm`` (3,) (the surface's centre)
        unless it states its normal.
    also_from : (J, 3) another start (the lab's measured positions, the found ones where
        none was measured): the refinement starts from whichever explains the sample
        better, within ``reach`` of it.

    Returns
    -------
    (J, 3) positions and a record: ``start`` and ``final`` objective, ``evaluations``
    (and with ``also_from``, ``started_from``: ``given`` or ``also_from``).
    """
    grid = alpha_grid(REFINE_GRID_STEPS)

    def f(x, grad):
        pts, group = expand_lights(x.reshape(-1, 3), extents, target_mm)
        return _profile_objective(y, views, omega, points, pts, grid, group)

    x0 = np.asarray(lights_mm, float).ravel()
    start = f(x0, np.empty(0))
    took = {}
    if also_from is not None:
        x1 = np.asarray(also_from, float).ravel()
        other = f(x1, np.empty(0))
        took = {"started_from": "also_from" if other < start else "given"}
        if other < start:
            x0, start = x1, other
    centre = np.asarray(points, float).mean(0)
    dist = np.repeat(np.linalg.norm(x0.reshape(-1, 3) - centre, axis=1), 3)
    lo, hi = x0 - reach * dist, x0 + reach * dist
    lo[2::3] = np.maximum(lo[2::3], 1e-3 * dist[2::3])  # above the surface

    opt = nlopt.opt(nlopt.LN_BOBYQA, len(x0))
    opt.set_lower_bounds(lo)
    opt.set_upper_bounds(hi)
    opt.set_min_objective(f)
    opt.set_initial_step(0.05 * dist)
    opt.set_xtol_abs(5e-4 * dist)  # a tenth of the 0.5 % a light is placed to at best
    opt.set_maxeval(max_evals)
    try:
        x = opt.optimize(x0)
    except (nlopt.RoundoffLimited, RuntimeError):
        x = x0
    final = f(x, np.empty(0))
    if final > start:
        x, final = x0, start
    return x.reshape(-1, 3), {"start": start, "final": final,
                              "evaluations": int(opt.get_numevals()), **took}


def light_weights(ks: np.ndarray, sd_ks: np.ndarray, min_z: float = 3.0) -> np.ndarray:
    """(J, 3) relative intensities of the lights (the first's 1) from a pilot fit's
    per-light specular amplitudes ``ks`` (B, J, 3) and their sds: per channel, the
    median over the texels where both amplitudes stand ``min_z`` sds above zero of
    ``ks_j / ks_1`` (each texel's Fresnel and albedo cancel in the ratio). 1 where too
    few texels say."""
    ks, sd = np.asarray(ks, float), np.asarray(sd_ks, float)
    J = ks.shape[1]
    w = np.ones((J, 3))
    sig = ks > min_z * np.nan_to_num(sd, nan=np.inf)
    for j in range(1, J):
        for c in range(3):
            on = sig[:, 0, c] & sig[:, j, c]
            if on.sum() >= 16:
                w[j, c] = float(np.median(ks[on, j, c] / ks[on, 0, c]))
    return w


def svbrdf_outputs() -> dict[str, tuple[tuple[int, ...], str, float]]:
    """Arrays of an svbrdf fit store: name -> (trailing shape, dtype, fill value)."""
    return {
        FitArray.PARAMS: ((SV_SIZE,), "float32", float("nan")),
        FitArray.SD: ((SV_SIZE,), "float32", float("nan")),
        FitArray.RMSE: ((3,), "float32", float("nan")),
        FitArray.MPR: ((3,), "float32", float("nan")),
        FitArray.CHI2: ((), "float32", float("nan")),
        FitArray.STATUS: ((), "int8", int(FitStatus.NOT_FITTED)),
    }


def coat_regions(f: np.ndarray, r: int | None = None) -> np.ndarray:
    """(t, u) bool: the texels that keep their coat, those whose (2 r + 1)^2 window's
    median coat F statistic (``f`` (t, u), NaN where not fitted: no evidence; r =
    :data:`POOL_RADIUS`) exceeds :data:`COAT_WINDOW_F`: a coat is a material's, and one
    texel's views rarely tell it from a broad lobe, a window's do. The median keeps a
    material's edge where it is (a matte texel beside a plastic keeps no coat)."""
    r = POOL_RADIUS if r is None else r
    ok = np.isfinite(f)
    med = median_filter(np.where(ok, f, 0.0), size=2 * r + 1, mode="reflect")
    return ok & (med > COAT_WINDOW_F)


def _tile_inputs(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray,
                 noise: np.ndarray | None, origin: tuple[int, int],
                 grid: tuple[int, int, float, float], irradiance) -> tuple[np.ndarray, ...]:
    """A tile's observations as the fits take them, flattened over its texels: texel
    centres (n, 3) mm, radiance with the flat-field's irradiance put back (n, N, 3),
    directions (n, N, 3), valid (n, N), noise (n, N) or None, weights (n, N)
    (:func:`fit_svbrdf_tile`'s arguments)."""
    t, u, N, _ = radiance.shape
    S, T, width, height = grid
    r0, c0 = origin
    pts = texel_centres(S, T, width, height, np.arange(r0, r0 + t),
                        np.arange(c0, c0 + u)).reshape(-1, 3)
    L = np.asarray(radiance, float).reshape(t * u, N, 3)
    if irradiance is not None:
        L = L * irradiance(pts)[:, None, None]
    V = np.asarray(direction, float).reshape(t * u, N, 3)
    W = np.asarray(valid, bool).reshape(t * u, N) & np.isfinite(L).all(-1) \
        & np.isfinite(V).all(-1) & (V[..., 2] > 0)
    NZ = None if noise is None else np.asarray(noise, float).reshape(t * u, N)
    omega = noise_weights(NZ, W)
    L = np.where(W[..., None], L, 0.0)
    V = np.where(W[..., None], V, np.array([0.0, 0.0, 1.0]))
    return pts, L, V, W, NZ, omega


def lobe_rejected(y: np.ndarray, views: np.ndarray, omega: np.ndarray, points: np.ndarray,
                  lights_mm: np.ndarray, weights: np.ndarray, own: np.ndarray,
                  alpha: np.ndarray, ks: np.ndarray,
                  ambient: np.ndarray | None = None) -> np.ndarray:
    """Whether texels fitted without a lobe reject a lobe of the given ``alpha`` (B,)
    and ``Ks`` (B, 3) (their neighbours'): the lobe imposed and Kd refitted raises the
    weighted residual over the lobe-less fit's by more than chi-square's 99 % point for
    the lobe's two parameters (:data:`PRIOR_REJECT_CHI2`, in units of the lobe-less
    fit's residual variance; the mean over the channels, whose noise is one pixel's).
    Where the views never look where the lobe shows, nothing changes and nothing is
    rejected; where they do, a matte texel's flat views reject it.

    Parameters
    ----------
    y : (B, N, 3) radiance; views : (B, N, 3); omega : (B, N) weights (0: not seen);
    points : (B, 3) mm; own : (B, ``SV_SIZE``) the texels' own parameters (their coat
    is kept).

    Returns
    -------
    (B,) bool.
    """
    B, N, _ = y.shape
    flat_p, flat_v = np.repeat(points, N, 0), views.reshape(-1, 3)
    dif = np.array(own, float)
    dif[:, SV_KD], dif[:, SV_KS] = 1.0, 0.0
    lobe = dif.copy()
    lobe[:, SV_KD], lobe[:, SV_KS], lobe[:, SV_ALPHA] = 0.0, ks, alpha
    d, s = (svbrdf_eval(np.repeat(x, N, 0), flat_p, flat_v, lights_mm, weights,
                        ambient=ambient).reshape(B, N, 3) for x in (dif, lobe))
    wd = omega[..., None] * d
    den = np.maximum(np.einsum("bnc,bnc->bc", wd, d), 1e-300)

    def rss(target):
        kd = np.maximum(np.einsum("bnc,bnc->bc", wd, target) / den, 0.0)
        return np.einsum("bn,bnc->bc", omega, (target - kd[:, None] * d) ** 2)

    rss0 = rss(y)
    sig2 = np.maximum(rss0 / np.maximum((omega > 0).sum(1) - 1, 1)[:, None], 1e-300)
    return ((rss(y - s) - rss0) / sig2).mean(1) > PRIOR_REJECT_CHI2


def fit_svbrdf_tile(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray, *,
                    origin: tuple[int, int], grid: tuple[int, int, float, float],
                    lights_mm: np.ndarray, weights: np.ndarray,
                    noise: np.ndarray | None = None, batch: int = 1024,
                    prior: dict[str, np.ndarray] | None = None,
                    irradiance=None, ambient: np.ndarray | None = None,
                    ) -> dict[str, np.ndarray]:
    """Fit every texel of a tile (:func:`fit_svbrdf_batch`).

    Parameters
    ----------
    radiance, direction : (t, u, N, 3); valid : (t, u, N) bool.
    origin : the tile's first row and column in the map; grid : the map's ``(S, T,
        width_mm, height_mm)`` (texel centres, :func:`parammap.geometry.texel_centres`).
    lights_mm : (J, 3); weights : (J, 3) relative intensities (:func:`light_weights`).
    noise : (t, u, N) relative sd per observation (weights, chi-square), or None.
    prior : per texel (t u, ...) priors of :func:`fit_svbrdf_batch`, or None.
    irradiance : the flat-field's relative irradiance the observations were divided by
        (:class:`parammap.models.radiometry.IrradianceGrid`), put back: the lights'
        fall-off is the model's own. None: the observations as they are.
    ambient : (3,) the room's ambient irradiance (:func:`svbrdf_eval`), or None.

    Returns
    -------
    dict of (t, u, ...) arrays as :func:`svbrdf_outputs`.
    """
    t, u, N, _ = radiance.shape
    out = {k: np.full((t, u) + shp, fill, dtype)
           for k, (shp, dtype, fill) in svbrdf_outputs().items()}
    flat = {k: v.reshape((t * u,) + v.shape[2:]) for k, v in out.items()}
    pts, L, V, W, NZ, omega = _tile_inputs(radiance, direction, valid, noise, origin, grid,
                                           irradiance)
    nobs = W.sum(1)
    flat[FitArray.STATUS][nobs < MIN_OBS] = FitStatus.TOO_FEW
    todo = np.flatnonzero(nobs >= MIN_OBS)
    # first each texel's evidence for a coat, then the coat where its neighbours' agree
    states, f = {}, np.full(t * u, np.nan)
    for s0 in range(0, len(todo), batch):
        sel = todo[s0:s0 + batch]
        pr = None if prior is None else {k: v[sel] for k, v in prior.items()}
        try:
            states[s0] = fit_svbrdf_batch(L[sel], V[sel], omega[sel], pts[sel], lights_mm,
                                          weights, prior=pr, evidence=True, ambient=ambient)
        except (np.linalg.LinAlgError, FloatingPointError):
            flat[FitArray.STATUS][sel] = FitStatus.FAILED
            continue
        f[sel] = states[s0]["coat_f"]
    keep = coat_regions(f.reshape(t, u)).ravel()
    for s0, state in states.items():
        sel = todo[s0:s0 + batch]
        pr = None if prior is None else {k: v[sel] for k, v in prior.items()}
        try:
            r = fit_svbrdf_batch(L[sel], V[sel], omega[sel], pts[sel], lights_mm, weights,
                                 prior=pr, start=state, coat_choice=keep[sel],
                                 ambient=ambient)
        except (np.linalg.LinAlgError, FloatingPointError):
            flat[FitArray.STATUS][sel] = FitStatus.FAILED
            continue
        P = r["estimate"]
        fitted = svbrdf_eval(np.repeat(P, N, 0), np.repeat(pts[sel], N, 0),
                             V[sel].reshape(-1, 3), lights_mm, weights,
                             ambient=ambient).reshape(len(sel), N, 3)
        flat[FitArray.PARAMS][sel] = P
        flat[FitArray.SD][sel] = r["stdev"]
        res = np.where(W[sel][..., None], fitted - L[sel], 0.0)
        flat[FitArray.RMSE][sel] = np.sqrt((res ** 2).sum(1) / nobs[sel][:, None])
        flat[FitArray.MPR][sel] = mean_percentage_residual(L[sel], fitted, W[sel])
        if NZ is not None:
            flat[FitArray.CHI2][sel] = reduced_chi2(L[sel], fitted, NZ[sel], W[sel], SV_SIZE)
        flat[FitArray.STATUS][sel] = np.where(np.isfinite(P).all(1), FitStatus.OK,
                                              FitStatus.FAILED)
    return out


# ---------------------------------------------------------------------------------
# Neighbours: a texel whose own views leave alpha or Ks undetermined takes its region's

POOL_RADIUS = 4  # texels: the (2 r + 1)^2 window the neighbours' values come from
POOL_MIN = 5  # determined neighbours needed
WALD_Z = 2.576  # two-sided 99 %: a texel's own value this far from the neighbours' stays
KS_MIN_Z = 3.0  # a determined highlight: Ks (luminance) this many sds above zero
# a view whose own observation sets more than half of its fitted value (leverage, the
# channels' mean; Huber's bound for a point the fit cannot be trusted on) is left out
# once to bound the lobe's sds (fit_svbrdf_batch)
JACKKNIFE_LEVERAGE = 0.5


def _windows(a: np.ndarray, r: int) -> np.ndarray:
    """(T, S, ...) -> (T - 2r, S - 2r, (2r + 1)^2, ...) neighbourhoods."""
    w = sliding_window_view(a, (2 * r + 1, 2 * r + 1), axis=(0, 1))
    w = np.moveaxis(w, (-2, -1), (2, 3))
    return w.reshape(w.shape[:2] + (-1,) + a.shape[2:])


def neighbour_priors(P: np.ndarray, SD: np.ndarray, ok: np.ndarray, r: int = POOL_RADIUS,
                     ) -> dict[str, np.ndarray]:
    """Empirical-Bayes priors on ln alpha and Ks from each texel's neighbours.

    Among the texels of its (2 r + 1)^2 window (itself left out) whose own fit
    determined a highlight (Ks at least ``KS_MIN_Z`` sds above zero, alpha's sd
    known), the median is the prior's mean and its variance the spread between them
    (the robust variance less their own sampling variance) plus the median's own,
    ``pi / 2 s^2 / n``: within a uniform patch the prior is as tight as the patch is
    uniform; across a material's edge it widens.

    Parameters
    ----------
    P, SD : (T, S, SV_SIZE) parameters and sds (NaN where not fitted); ok : (T, S).

    Returns
    -------
    ``u_mean``, ``u_var`` (T - 2r, S - 2r) for ln alpha, ``ks_mean``, ``ks_var``
    (T - 2r, S - 2r, 3), ``n`` the determined neighbours (the windows' centres are
    the texels r from the edges of the arrays given).
    """
    lum = LUMINANCE
    ks, sks = P[..., SV_KS], SD[..., SV_KS]
    det = ok & np.isfinite(SD[..., SV_ALPHA]) & (ks @ lum > KS_MIN_Z * np.sqrt(
        np.nan_to_num(sks, nan=np.inf) ** 2 @ lum ** 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(det, np.log(P[..., SV_ALPHA]), np.nan)
        su = np.where(det, SD[..., SV_ALPHA] / P[..., SV_ALPHA], np.nan)
    ksd = np.where(det[..., None], ks, np.nan)
    sksd = np.where(det[..., None], sks, np.nan)
    centre = (2 * r + 1) ** 2 // 2
    keep = np.ones((2 * r + 1) ** 2, bool)
    keep[centre] = False
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        for name, v, sv in (("u", u, su), ("ks", ksd, sksd)):
            W = _windows(v, r)[:, :, keep]
            SW = _windows(sv, r)[:, :, keep]
            med = np.nanmedian(W, axis=2)
            mad = 1.4826 * np.nanmedian(np.abs(W - med[:, :, None]), axis=2)
            own = np.nanmedian(SW ** 2, axis=2)
            n = np.isfinite(W).sum(2)
            tau2 = np.maximum(mad ** 2 - own, 0.0)
            out[f"{name}_mean"] = med
            out[f"{name}_var"] = tau2 + np.pi / 2 * mad ** 2 / np.maximum(n, 1) + 1e-12
        out["n"] = np.isfinite(_windows(u, r)[:, :, keep]).sum(2)
    return out


def lobe_profiles(y: np.ndarray, views: np.ndarray, omega: np.ndarray, points: np.ndarray,
                  lights_mm: np.ndarray, weights: np.ndarray, own: np.ndarray,
                  grid: np.ndarray, ambient: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each texel's sums for a lobe it shares with other texels, at every alpha of the
    grid, its own diffuse term (at its own coat share) eliminated.

    A ``Ks`` common to texels t then fits them with the weighted residual sum
    ``sum_t c_t - 2 Ks b_t + Ks^2 a_t`` (per channel), least at ``Ks = sum b / sum a``.

    Parameters
    ----------
    y : (B, N, 3) radiance; views : (B, N, 3); omega : (B, N) weights (0: not seen);
    points : (B, 3) mm; own : (B, ``SV_SIZE``) the texels' own fits (their coat share);
    grid : (G,) alphas.

    Returns
    -------
    a, b : (B, G, 3) ``S'S - (D'S)^2 / D'D`` and ``S'y - D'S D'y / D'D``; c : (B, 3)
    ``y'y - (D'y)^2 / D'D`` (D the diffuse basis, S the lobe's at unit Ks).
    """
    l, e = light_terms(points, lights_mm)
    w = np.asarray(weights, float)
    e_w, coated, cos, e_seen, sky = _diffuse_and_cosines(views, l, e, w, ambient)
    coat = np.clip(np.nan_to_num(own[:, SV_COAT]), 0, 1)[:, None, None]
    D = (1 - coat) * e_w[:, None, :] + coat * coated  # (B, N, 3)
    wD = omega[..., None] * D
    DD = np.maximum(np.einsum("bnc,bnc->bc", wD, D), 1e-300)
    Dy = np.einsum("bnc,bnc->bc", wD, y)
    c = np.einsum("bn,bnc->bc", omega, y * y) - Dy ** 2 / DD
    rows = _albedo_rows(cos[1][..., 0]) if sky is not None else None
    a = np.empty((len(y), len(grid), 3))
    b = np.empty_like(a)
    Dn = np.ascontiguousarray(D[None])
    for g, alpha in enumerate(grid):
        sm = _spec_moments(y, omega, [D], _lobe_bases(cos, e_seen, alpha, w, sky, rows), Dn)
        DS = sm["Gds"][:, :, 0, 0]
        a[:, g] = sm["Gss"][:, :, 0, 0] - DS ** 2 / DD
        b[:, g] = sm["rs"][:, :, 0] - DS * Dy / DD
    return a, b, c


def _box_sums(x: np.ndarray, r: int) -> np.ndarray:
    """(T, S, ...) -> the same shape: each texel's sum over its (2 r + 1)^2 window less
    itself (zero outside the array)."""
    pad = np.pad(x, ((r + 1, r), (r + 1, r)) + ((0, 0),) * (x.ndim - 2))
    c = pad.cumsum(0).cumsum(1)
    k = 2 * r + 1
    box = c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]
    return box - x


def shared_lobe_alpha(a: np.ndarray, b: np.ndarray, c: np.ndarray, sig2: np.ndarray,
                      member: np.ndarray, grid: np.ndarray, r: int = POOL_RADIUS,
                      ) -> np.ndarray:
    """ln alpha of the lobe each texel's neighbours share.

    The texels of each (2 r + 1)^2 window (itself left out) are fitted jointly: one
    alpha and one Ks per channel over the window, each texel's own diffuse term
    (:func:`lobe_profiles`' sums, in units of each texel's residual variance
    ``sig2``). A narrow highlight is seen near its peak by few texels and in its tails
    by the rest, whose views determine only about ``Ks alpha^2``: their own alphas
    scatter, and broad ones pass the test of a determined Ks more often, so a median of
    them is biased broad; their joint likelihood is as sharp as the peaks make it.

    Parameters
    ----------
    a, b : (T, S, G, 3); c : (T, S, 3); sig2 : (T, S, 3); member : (T, S) bool, the
    texels that take part; grid : (G,) alphas (even in log).

    Returns
    -------
    (T, S) ln alpha at the joint profile's least (a parabola through the best grid
    point and its neighbours), NaN where the window has no member.
    """
    wt = np.where(member[..., None], 1 / np.maximum(sig2, 1e-300), 0.0)
    A = _box_sums(np.nan_to_num(a) * wt[:, :, None], r)
    B = _box_sums(np.nan_to_num(b) * wt[:, :, None], r)
    C = _box_sums(np.nan_to_num(c) * wt, r)
    with np.errstate(divide="ignore", invalid="ignore"):
        ks = np.maximum(B / A, 0.0)  # (T, S, G, 3)
        prof = (C[:, :, None] - 2 * ks * B + ks * ks * A).sum(-1)  # (T, S, G)
    prof = np.where(np.isfinite(prof), prof, np.inf)
    G = len(grid)
    h = math.log(grid[1] / grid[0])
    j = np.argmin(prof, -1)
    k = np.clip(j, 1, G - 2)
    f0, f1, f2 = (np.take_along_axis(prof, (k + d)[..., None], -1)[..., 0] for d in (-1, 0, 1))
    with np.errstate(invalid="ignore", over="ignore"):
        curv = f0 - 2 * f1 + f2
        step = np.where(curv > 0, -(f2 - f0) / 2 / np.where(curv > 0, curv, 1), 0.0)
    u = np.log(grid)[k] + h * np.clip(np.nan_to_num(step), -1, 1)
    u = np.where((j == 0) | (j == G - 1), np.log(grid)[j], u)
    none = (_box_sums(member.astype(float), r) < 0.5) | ~np.isfinite(f1)
    return np.where(none, np.nan, u)


def _shared_alpha(P: np.ndarray, ok: np.ndarray, halo_obs: tuple, origin: tuple[int, int],
                  grid: tuple[int, int, float, float], lights_mm: np.ndarray,
                  weights: np.ndarray, irradiance, ambient: np.ndarray | None, r: int,
                  ) -> np.ndarray:
    """:func:`shared_lobe_alpha` (T, S) over a tile and its halo: P (T, S, SV_SIZE) and
    ok (T, S) the tile pass's; ``halo_obs`` their radiance, directions, valid and noise
    (or None), whose first texel is ``origin``."""
    rad, dirs, valid, noise = halo_obs
    T, S = P.shape[:2]
    pts, L, V, _, _, omega = _tile_inputs(rad, dirs, valid, noise, origin, grid, irradiance)
    own = np.nan_to_num(P.reshape(T * S, -1))
    alphas = alpha_grid()  # the fit's: half as many steps put alpha 0.1 5 % low
    a, b, c = lobe_profiles(L, V, omega, pts, lights_mm, weights, own, alphas, ambient)
    N = L.shape[1]
    fitted = svbrdf_eval(np.repeat(own, N, 0), np.repeat(pts, N, 0), V.reshape(-1, 3),
                         lights_mm, weights, ambient=ambient).reshape(L.shape)
    # each texel's weight: its own fit's residual variance per channel
    sig2 = np.einsum("bn,bnc->bc", omega, (L - fitted) ** 2) / np.maximum(
        (omega > 0).sum(1) - 3, 1)[:, None]
    # the texels the tile pass gave a lobe: a matte neighbour's flat views would pull
    # the joint fit toward lobes too narrow to show in them
    lobed = ok & (np.nan_to_num(P[..., SV_KS]) @ LUMINANCE > 0)
    return shared_lobe_alpha(a.reshape(T, S, *a.shape[1:]), b.reshape(T, S, *b.shape[1:]),
                             c.reshape(T, S, 3), sig2.reshape(T, S, 3), lobed, alphas, r)


def pool_svbrdf_tile(fields: dict[str, np.ndarray], radiance: np.ndarray,
                     direction: np.ndarray, valid: np.ndarray, offset: tuple[int, int], *,
                     origin: tuple[int, int], grid: tuple[int, int, float, float],
                     lights_mm: np.ndarray, weights: np.ndarray,
                     noise: np.ndarray | None = None, irradiance=None,
                     ambient: np.ndarray | None = None, halo_obs: tuple | None = None,
                     ) -> dict[str, np.ndarray] | None:
    """The repair pass of an svbrdf fit (:func:`parammap.stages.fit.fit_map`): every
    texel of a tile refitted with its neighbours' priors on ln alpha and Ks
    (:func:`neighbour_priors`, from the tile pass's results over the tile and its halo
    ``fields``), unless its own values reject them (a two-sided 99 % Wald test on ln
    alpha, where its lobe's amplitude is determined (``KS_MIN_Z``), or on Ks's
    luminance: a texel at a material's edge, or a scratch, keeps its own). A texel
    that saw its highlight in one view, or in none, takes its region's roughness and
    specular amplitude: the highlight is drawn as smooth as the region.
    With ``halo_obs`` (the observations of the tile and its halo: radiance, direction,
    valid, noise or None) the prior on ln alpha is centred on the joint fit of the
    neighbours that have a lobe (:func:`shared_lobe_alpha`) where that is narrower than
    their own values' median.

    Returns the tile's arrays as :func:`fit_svbrdf_tile` plus ``changed``, or None."""
    r = POOL_RADIUS
    P, SD = fields[FitArray.PARAMS].astype(float), fields[FitArray.SD].astype(float)
    ok = fields[FitArray.STATUS] == FitStatus.OK
    t, u = radiance.shape[:2]
    i0, j0 = offset
    pad = ((r, r), (r, r), (0, 0))
    pri = neighbour_priors(np.pad(P, pad, constant_values=np.nan),
                           np.pad(SD, pad, constant_values=np.nan),
                           np.pad(ok, pad[:2], constant_values=False), r)
    if halo_obs is not None:
        # the median of the determined neighbours' own alphas is biased broad where few
        # of them saw the peak (shared_lobe_alpha): the prior is centred on their joint
        # fit where that is narrower; its width stays their own values' spread
        u_joint = _shared_alpha(P, ok, halo_obs, (origin[0] - i0, origin[1] - j0), grid,
                                lights_mm, weights, irradiance, ambient, r)
        pri["u_mean"] = np.where(np.isfinite(u_joint) & np.isfinite(pri["u_mean"]),
                                 np.minimum(u_joint, pri["u_mean"]), pri["u_mean"])
    pri = {k: v[i0:i0 + t, j0:j0 + u].reshape((t * u,) + v.shape[2:]) for k, v in pri.items()}
    own = P[i0:i0 + t, j0:j0 + u].reshape(t * u, -1)
    sd_own = SD[i0:i0 + t, j0:j0 + u].reshape(t * u, -1)
    lum = LUMINANCE
    with np.errstate(divide="ignore", invalid="ignore"):
        su = sd_own[:, SV_ALPHA] / own[:, SV_ALPHA]
        du = np.abs(np.log(own[:, SV_ALPHA]) - pri["u_mean"])
        rej_u = du > WALD_Z * np.sqrt(su ** 2 + pri["u_var"])
        # only a determined lobe's width can reject the neighbours': a lobe whose
        # amplitude the views leave undetermined (a spike fitted to one bright view)
        # has a narrow ln alpha sd that the Wald test would trust (pbr-mirror: 16
        # texels of a plastic of alpha 0.076 kept alpha 0.008 and Ks 20x theirs)
        rej_u &= own[:, SV_KS] @ lum > KS_MIN_Z * np.sqrt(sd_own[:, SV_KS] ** 2 @ lum ** 2)
        dk = np.abs((own[:, SV_KS] - pri["ks_mean"]) @ lum)
        rej_k = dk > WALD_Z * np.sqrt((sd_own[:, SV_KS] ** 2 + pri["ks_var"]) @ lum ** 2)
    take = ok[i0:i0 + t, j0:j0 + u].ravel() & (pri["n"] >= POOL_MIN) \
        & np.isfinite(pri["u_mean"]) & ~(rej_u & np.isfinite(su)) & ~(rej_k & np.isfinite(dk))
    # a texel fitted without a lobe has no sd to test the neighbours' values by: its own
    # views are asked whether they would have shown that lobe (a matte texel among a
    # few false lobes must not take theirs)
    bare = np.flatnonzero(take & ~(own[:, SV_KS] @ lum > 0))
    if bare.size:
        pts, L, V, _, _, omega = _tile_inputs(radiance, direction, valid, noise, origin,
                                              grid, irradiance)
        take[bare[lobe_rejected(L[bare], V[bare], omega[bare], pts[bare], lights_mm,
                                weights, own[bare], np.exp(pri["u_mean"][bare]),
                                np.nan_to_num(pri["ks_mean"][bare]), ambient)]] = False
    if not take.any():
        return None
    base = {k: fields[k][i0:i0 + t, j0:j0 + u].copy() for k in svbrdf_outputs()}
    out = fit_svbrdf_tile(radiance, direction, valid & take.reshape(t, u, 1), origin=origin,
                          grid=grid, lights_mm=lights_mm, weights=weights, noise=noise,
                          prior={k: v for k, v in pri.items() if k != "n"},
                          irradiance=irradiance, ambient=ambient)
    sel = take.reshape(t, u) & (out[FitArray.STATUS] == FitStatus.OK)
    for k in base:
        base[k][sel] = out[k][sel]
    base[FitArray.CHANGED] = sel.astype(np.int8)
    return base


# ---------------------------------------------------------------------------------
# The metallic-roughness model of glTF 2.0 and MaterialX's standard_surface

DIELECTRIC_F0 = 0.04  # glTF's (and most renderers') reflectance at normal incidence
CHROMA_MAX = 0.1  # a dielectric's highlight is the light's colour: Ks's RGB spread
ALBEDO_CEILING = 0.9  # without a dielectric to scale by, the brightest texel's albedo


#: points per side of the grid over the surface :func:`card_scale` averages over
CARD_GRID = 32


def card_scale(irradiance_scale: float, width_mm: float, height_mm: float,
               lights_mm: np.ndarray, weights: np.ndarray,
               ambient: np.ndarray | None = None) -> float:
    """The scale ``k`` of :func:`metallic_roughness` from a white card of known
    reflectance (:attr:`parammap.models.radiometry.Radiometry.irradiance_scale`).

    The card measured the lights' absolute irradiance on average over the surface; the
    map's lights give ``e w + a`` there in units of ``k`` (:func:`svbrdf_eval`). ``k`` is
    the ratio of the two means (luminance), over a regular grid of points.

    Parameters
    ----------
    irradiance_scale : the card's ``pi L / rho`` where its relative irradiance is 1
        (the frames' radiance units).
    width_mm, height_mm : the surface; lights_mm : (J, 3); weights : (J, 3);
    ambient : (3,) or None, as in :func:`svbrdf_eval`.
    """
    f = (np.arange(CARD_GRID) + 0.5) / CARD_GRID
    X, Y = np.meshgrid(f * width_mm, f * height_mm)
    pts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], -1)
    E = light_terms(pts, lights_mm)[1] @ np.asarray(weights, float)
    if ambient is not None:
        E = E + np.asarray(ambient, float)
    return float(irradiance_scale / np.mean(E @ LUMINANCE))


def metallic_roughness(P: np.ndarray, SD: np.ndarray | None = None,
                       scale: float | None = None,
                       ) -> dict[str, np.ndarray | float | str]:
    """glTF's metallic-roughness parameters of an svbrdf map.

    ``Kd = albedo / pi * k`` and ``Ks = F0 k`` share the scale ``k`` of the first light
    (the irradiance it gives a metre away, in the radiance's units). A white card of
    stated reflectance measures it (``scale``, :func:`card_scale`). Without one, a
    dielectric reflects ``F0 = 0.04`` of the light, uncoloured: over the texels whose Ks
    is determined (3 sds, where ``SD`` is given) and grey (RGB spread under ``CHROMA_MAX`` of its
    mean), ``k`` is the median of ``Ks / 0.04``; where no texel qualifies (every
    highlight coloured: all metal), ``k`` puts the 99th percentile of the diffuse
    albedo at ``ALBEDO_CEILING``. Per texel, the diffuse albedo ``rho = pi Kd / k`` and
    ``F0 = Ks / k`` are glTF's ``baseColor (1 - metallic)`` and ``0.04 (1 - metallic)
    + baseColor metallic``: metallic from their luminances (the root in [0, 1] of that
    quadratic), then baseColor per channel. Roughness is ``sqrt(alpha)``.

    Parameters
    ----------
    P : (..., SV_SIZE); SD : its sds, or None; scale : ``k``, or None (from the map).

    Returns
    -------
    dict: ``base_color`` (..., 3) linear, ``metallic`` (...), ``roughness`` (...), ``scale``
    (k) and ``scale_from`` (``white_card``, ``dielectric`` or ``albedo_ceiling``).
    """
    P = np.nan_to_num(np.asarray(P, float))
    kd, ks, alpha = P[..., SV_KD], P[..., SV_KS], P[..., SV_ALPHA]
    lum_s = ks @ LUMINANCE
    with np.errstate(invalid="ignore", divide="ignore"):
        chroma = (ks.max(-1) - ks.min(-1)) / np.maximum(ks.mean(-1), 1e-30)
        det = lum_s > 0
        if SD is not None:
            det &= lum_s > KS_MIN_Z * np.sqrt(np.nan_to_num(SD[..., SV_KS], nan=np.inf) ** 2
                                              @ LUMINANCE ** 2)
    grey = det & (chroma < CHROMA_MAX)
    if scale is not None:
        k, source = float(scale), "white_card"
    elif grey.sum() >= 16:
        k, source = float(np.median(lum_s[grey])) / DIELECTRIC_F0, "dielectric"
    else:
        top = np.percentile(math.pi * (kd @ LUMINANCE), 99)
        k, source = float(max(top, 1e-30) / ALBEDO_CEILING), "albedo_ceiling"
    rho, f0 = math.pi * kd / k, ks / k
    r, f = rho @ LUMINANCE, f0 @ LUMINANCE
    # 0.04 x^2 - (F0 + rho) x + rho = 0, x = 1 - metallic in [0, 1]
    b = f + r
    disc = np.sqrt(np.maximum(b * b - 4 * DIELECTRIC_F0 * r, 0.0))
    x = np.where(f <= DIELECTRIC_F0, 1.0, np.clip((b - disc) / (2 * DIELECTRIC_F0), 0, 1))
    m = 1 - x
    with np.errstate(invalid="ignore", divide="ignore"):
        base = np.where((x > 0.5)[..., None], rho / np.maximum(x, 1e-12)[..., None],
                        (f0 - DIELECTRIC_F0 * x[..., None]) / np.maximum(m, 1e-12)[..., None])
    return {"base_color": np.clip(base, 0, 1), "metallic": np.clip(m, 0, 1),
            "roughness": np.sqrt(np.clip(alpha, *ALPHA_RANGE)), "scale": k,
            "scale_from": source}
