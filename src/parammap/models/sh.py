"""Spherical harmonics (SH) model: basis, hemisphere solid angles and projections.

Basis (conventions.md, 004 eqs. 12.1-12.5): real, orthonormal over the full sphere,
index ``i = l (l + 1) + m``, ``n`` bands give ``n^2`` coefficients per channel::

    y_l^m = sqrt(2) K_l^m cos(m phi) P_l^m(cos theta)      m > 0
    y_l^m = sqrt(2) K_l^m sin(-m phi) P_l^-m(cos theta)    m < 0
    y_l^0 = K_l^0 P_l^0(cos theta)

with the Condon-Shortley phase inside ``P_m^m`` (004 eq. 12.1 rule 2). theta is the
zenith and phi the azimuth of a direction in the surface frame.

The samples cover only the upper hemisphere; ``hemisphere`` selects how (004 ch. 12.3):

- ``zh`` (zero hemisphere): project with the lower hemisphere taken as zero;
- ``mirror``: the samples reflected below the equator (the function is even in z);
- ``lsop``: least-squares optimal projection, ``A c = b`` with A the Gram matrix of the
  basis over the upper hemisphere (004 eq. 12.14);
- ``rlsop``: regularised LSOP, ``(A + lambda D) c = b`` with ``D = diag((l (l + 1))^2)``:
  Tikhonov damping of the surface Laplacian of the reconstruction over the whole sphere.
  The unsampled lower hemisphere is what leaves plain LSOP free to oscillate (the
  ringing 004 saw at 64+ coefficients, its ch. 18 suggests filtering); penalising
  roughness removes that freedom, most for the highest bands, while barely touching
  the low bands that carry the data;
- ``wls``: weighted least squares directly on the samples (solid angles as weights).

Every projection integrates with per-sample solid angles: the spherical Voronoi cells of
the texel's valid directions, mirrored below the equator so that the cells of the
upper points tile exactly the upper hemisphere (any upper direction is nearer to an
upper sample than to that sample's mirror image, so no cell crosses the equator and
cells of samples near the equator end exactly on it: the "half cells").
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.spatial import ConvexHull

from ..config import default
from ..conventions import (
    SH_CAP_AWARE,
    SH_HEMISPHERES,
    FitArray,
    FitStatus,
    sh_degree_order,
    sh_norms,
)
from ..errors import InputError
from .residuals import mean_percentage_residual
from .weights import noise_weights, reduced_chi2

__all__ = [
    "coefficient_sd",
    "fit_sh_tile",
    "guarded_project",
    "hemisphere_gram",
    "project",
    "sh_basis",
    "parse_sh_model",
    "planar_solid_angles",
    "project_cap",
    "sh_eval",
    "sh_outputs",
    "smoother",
    "smoother_loo",
    "solid_angles",
]


def sh_basis(directions: np.ndarray, n: int) -> np.ndarray:
    """Real SH basis values.

    Parameters
    ----------
    directions : (..., 3) unit vectors, surface frame.
    n : number of bands.

    Returns
    -------
    (..., n^2) values, index ``l (l + 1) + m``.
    """
    d = np.asarray(directions, float)
    x = np.clip(d[..., 2], -1.0, 1.0)
    phi = np.arctan2(d[..., 1], d[..., 0])
    s = np.sqrt(np.maximum(1 - x * x, 0.0))
    K = sh_norms(n)
    out = np.empty(d.shape[:-1] + (n * n,))
    pmm = np.ones_like(x)
    for m in range(n):
        if m > 0:
            pmm = -(2 * m - 1) * s * pmm  # (-1)^m (2m - 1)!! (1 - x^2)^(m/2)
        p_prev, p = None, pmm
        cm, sm = (np.cos(m * phi), np.sin(m * phi)) if m else (None, None)
        for l in range(m, n):
            if l == m + 1:
                p_prev, p = p, x * (2 * m + 1) * pmm
            elif l > m + 1:
                p_prev, p = p, ((2 * l - 1) * x * p - (l + m - 1) * p_prev) / (l - m)
            if m == 0:
                out[..., l * (l + 1)] = K[l, 0] * p
            else:
                out[..., l * (l + 1) + m] = math.sqrt(2) * K[l, m] * cm * p
                out[..., l * (l + 1) - m] = math.sqrt(2) * K[l, m] * sm * p
    return out


def sh_eval(coeffs: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Reconstruct radiance: coeffs (..., 3, n^2), directions (..., N, 3) ->
    (..., N, 3) (004 eq. 12.15)."""
    n = int(round(math.sqrt(coeffs.shape[-1])))
    Y = sh_basis(directions, n)
    return np.matmul(Y, np.swapaxes(coeffs, -1, -2))


@lru_cache(maxsize=16)
def hemisphere_gram(n: int) -> np.ndarray:
    """(n^2, n^2) Gram matrix ``A_ij = int_H y_i y_j`` over the upper hemisphere.

    Exact quadrature: Gauss-Legendre in cos(theta) on [0, 1] (the products are
    polynomials there once the azimuthal integral has selected equal |m|) times the
    trapezoid rule in phi, exact for trigonometric polynomials of degree < 4n.
    """
    xg, wg = np.polynomial.legendre.leggauss(2 * n + 4)
    x = 0.5 * (xg + 1)
    w = 0.5 * wg
    nphi = 4 * n + 4
    phi = 2 * np.pi * np.arange(nphi) / nphi
    X, PHI = np.meshgrid(x, phi, indexing="ij")
    s = np.sqrt(1 - X * X)
    d = np.stack([s * np.cos(PHI), s * np.sin(PHI), X], -1).reshape(-1, 3)
    Y = sh_basis(d, n)
    wt = (w[:, None] * np.full(nphi, 2 * np.pi / nphi)[None]).ravel()
    A = (Y * wt[:, None]).T @ Y
    A = 0.5 * (A + A.T)
    A.setflags(write=False)
    return A


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _normalised(v):
    n = np.sqrt(_dot(v, v))
    return (v[0] / n, v[1] / n, v[2] / n)


def _signed_area(a, b, c):
    """Signed solid angle of spherical triangles (Van Oosterom & Strackee); vectors as
    (x, y, z) tuples of arrays (component arrays: much faster than np.cross here)."""
    num = _dot(a, _cross(b, c))
    den = 1 + _dot(a, b) + _dot(b, c) + _dot(c, a)
    return 2 * np.arctan2(num, den)


def _triangulation(ref: np.ndarray) -> np.ndarray:
    """Outward-oriented triangles of the convex hull of ref and its mirror image that
    touch the upper hemisphere (the others only bound lower cells)."""
    N = len(ref)
    pts = np.concatenate([ref, ref * [1, 1, -1]])
    tri = ConvexHull(pts).simplices
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return tri[(tri < N).any(axis=1)]


def solid_angles(directions: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """Solid angle of each direction's spherical Voronoi cell within the upper
    hemisphere.

    Parameters
    ----------
    directions : (..., N, 3) unit vectors with z > 0; a batch of texels shares one
        triangulation (the Delaunay triangulation of ``reference``, default the batch
        mean), while each texel's own directions give its cell areas, so per-texel
        areas cost one convex hull per batch. Directions of nearby texels differ by
        small smooth shifts, which keep the triangulation valid.

    Returns
    -------
    (..., N) solid angles in steradians, summing to 2 pi per texel.
    """
    d = np.asarray(directions, float)
    batch = d.shape[:-2]
    N = d.shape[-2]
    d = d.reshape((-1, N, 3))
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    d[..., 2] = np.maximum(d[..., 2], 1e-6)
    ref = d.mean(0) if reference is None else np.asarray(reference, float)
    ref = ref / np.linalg.norm(ref, axis=-1, keepdims=True)
    tri = _triangulation(ref)
    B = d.shape[0]
    pts = np.concatenate([d, d * [1, 1, -1]], axis=1)  # (B, 2N, 3)
    comp = [np.ascontiguousarray(pts[..., k]) for k in range(3)]
    a, b, c = (tuple(x[:, tri[:, k]] for x in comp) for k in range(3))  # (B, F) each
    u = _normalised(_cross(tuple(bb - aa for aa, bb in zip(a, b, strict=True)),
                           tuple(cc - aa for aa, cc in zip(a, c, strict=True))))

    def mid(p, q):
        return _normalised(tuple(pp + qq for pp, qq in zip(p, q, strict=True)))

    mab, mbc, mca = mid(a, b), mid(b, c), mid(c, a)
    offs = (np.arange(B) * 2 * N)[:, None]
    area = np.zeros(B * 2 * N)
    for v, m1, m2, k in ((a, mab, mca, 0), (b, mbc, mab, 1), (c, mca, mbc, 2)):
        contrib = _signed_area(v, m1, u) + _signed_area(v, u, m2)
        area += np.bincount((offs + tri[:, k]).ravel(), contrib.ravel(), minlength=B * 2 * N)
    return area.reshape(B, 2 * N)[:, :N].reshape(batch + (N,))


def planar_solid_angles(directions: np.ndarray, grid: int = 512) -> np.ndarray:
    """004's quadrature weights (ch. 12.2): the area of each direction's Voronoi cell in
    the projection onto the surface plane (inside the unit disc), divided by its
    cos(theta). Kept to reproduce the published projections' artefacts; the cells are
    measured on a ``grid`` x ``grid`` raster of the disc (nearest projected direction).

    Parameters
    ----------
    directions : (..., N, 3) unit vectors with z > 0.

    Returns
    -------
    (..., N) weights in steradians (approximately; they sum to about 2 pi only where
    the views reach the equator).
    """
    from scipy.spatial import cKDTree

    d = np.asarray(directions, float)
    batch, N = d.shape[:-2], d.shape[-2]
    d = d.reshape((-1, N, 3))
    t = (np.arange(grid) + 0.5) / grid * 2 - 1
    X, Y = np.meshgrid(t, t)
    disc = X ** 2 + Y ** 2 <= 1
    pts = np.stack([X[disc], Y[disc]], 1)
    cell = (2.0 / grid) ** 2
    out = np.empty(d.shape[:2])
    for b in range(len(d)):
        _, idx = cKDTree(d[b, :, :2]).query(pts)
        area = np.bincount(idx, minlength=N) * cell
        out[b] = area / np.maximum(d[b, :, 2], 1e-3)
    return out.reshape(batch + (N,))


def project(
    radiance: np.ndarray, directions: np.ndarray, weights: np.ndarray, n: int,
    hemisphere: str = "lsop", reg: float = 1e-4, basis: np.ndarray | None = None,
) -> np.ndarray:
    """SH coefficients of a batch of texels.

    Parameters
    ----------
    radiance : (B, N, 3); directions : (B, N, 3) upper-hemisphere unit vectors;
    weights : (B, N) solid angles (0 for invalid samples).
    n : bands; hemisphere : ``zh``, ``mirror``, ``lsop``, ``rlsop`` or ``wls``.
    reg : lambda of ``rlsop`` (relative to A, whose diagonal is ~0.5).
    basis : ``sh_basis(directions, n)`` when already computed.

    Returns
    -------
    (B, 3, n^2) coefficients, channel blocks in R, G, B order.
    """
    if hemisphere not in SH_HEMISPHERES:
        raise InputError(f"unknown hemisphere handling {hemisphere!r} "
                         f"(one of {', '.join(SH_HEMISPHERES)})")
    Y = sh_basis(directions, n) if basis is None else basis  # (B, N, n2)
    Yw = Y * weights[..., None]
    b = np.matmul(radiance.transpose(0, 2, 1), Yw)  # (B, 3, n2): int_H f y_i
    if hemisphere == "zh":
        return b
    if hemisphere == "mirror":
        l_, m_ = sh_degree_order(n)
        even = ((l_ + m_) % 2 == 0).astype(float)  # y_i(x, y, -z) = (-1)^(l+m) y_i
        return 2 * b * even
    if hemisphere == "wls":
        G = np.matmul(Yw.transpose(0, 2, 1), Y)
        G += 1e-10 * np.trace(G, axis1=1, axis2=2)[:, None, None] * np.eye(n * n)
        return np.linalg.solve(G[:, None], b[..., None])[..., 0]
    A = hemisphere_gram(n)
    if hemisphere == "rlsop":
        l_, _ = sh_degree_order(n)
        A = A + reg * np.diag((l_ * (l_ + 1.0)) ** 2)
    return np.linalg.solve(A, b.reshape(-1, n * n).T).T.reshape(b.shape)


# ---------------------------------------------------------------------------------
# The sampled cap: what a texel's views actually covered

LOW_BANDS = 1  # band 0: the prior fills unsampled directions with the texel's mean level
GRID_STEP_DEG = 2.0  # midpoint quadrature step of the hemisphere grid


@lru_cache(maxsize=4)
def hemisphere_grid(step_deg: float = GRID_STEP_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint quadrature of the upper hemisphere: (G, 3) directions and (G,) solid
    angles (sum 2 pi), uniform in zenith and azimuth so that the pole is resolved as
    finely as the equator."""
    nt = int(round(90 / step_deg))
    npk = int(round(360 / step_deg))
    th = (np.arange(nt) + 0.5) * (np.pi / 2 / nt)
    ph = (np.arange(npk) + 0.5) * (2 * np.pi / npk)
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1)
    w = np.sin(TH) * (np.pi / 2 / nt) * (2 * np.pi / npk)
    w *= 2 * np.pi / w.sum()
    d, w = d.reshape(-1, 3), w.ravel()
    d.setflags(write=False)
    w.setflags(write=False)
    return d, w


@lru_cache(maxsize=8)
def _grid_basis(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The basis at :func:`hemisphere_grid`'s directions (G, n^2) and the mask (n^2,)
    of the bands above :data:`LOW_BANDS`, computed once per n (every validity pattern
    of a map needs them)."""
    Yg = sh_basis(hemisphere_grid()[0], n)
    l_, _ = sh_degree_order(n)
    high = l_ >= LOW_BANDS
    Yg.setflags(write=False)
    high.setflags(write=False)
    return Yg, high


def cap_radius(directions: np.ndarray, expected_views: float = 3.0) -> float:
    """Radius (radians) of a hole among view directions (N, 3) that counts as
    unsampled: the disc that would hold ``expected_views`` views at the capture's mean
    density over the zenith range it covers (a Poisson count of 3 is absent by chance
    in 5 % of such discs, so only real gaps and the region beyond the last views
    qualify; the median nearest-neighbour spacing, tried first, flagged most of the
    hemisphere of an irregular capture)."""
    d = np.asarray(directions, float)
    covered = 2 * np.pi * (1 - np.clip(d[:, 2], 0, 1).min())
    return float(np.sqrt(expected_views * covered / (np.pi * len(d))))


class SampledCap:
    """The part of the upper hemisphere a texel's views cover, for one batch of texels
    sharing a reference set of directions.

    A grid direction is *sampled* when a view direction lies within ``rho`` of it
    (:func:`cap_radius`); farther from every view, nothing was looked at. Attributes:

    - ``rho`` : radius (radians);
    - ``fraction`` : (N,) part of each sample's Voronoi cell inside the cap, so that
      cells next to an unsampled region stay bounded (a sample at 72 deg no longer
      stands for the whole ring out to the equator);
    - ``prior`` : (n^2, n^2) ``int_U h_i h_j`` over the unsampled directions U, with h
      the basis above the low bands (band 0 zeroed): its quadratic form is the energy
      of a reconstruction's variation where no view looked, which the projections
      below penalise so that U is filled by the texel's mean level, not by an
      extrapolated lobe (a linear band-1 extrapolation, tried too, overshoots at
      grazing angles);
    - ``basis_u``, ``zenith_u`` : (|U|, n^2) basis values at the unsampled grid
      directions and their zenith angles (the guard).
    """

    def __init__(self, reference: np.ndarray, n: int, rho: float | None = None):
        ref = np.asarray(reference, float)
        ref = ref / np.linalg.norm(ref, axis=-1, keepdims=True)
        self.rho = cap_radius(ref) if rho is None else float(rho)
        g, w = hemisphere_grid()
        c = g @ ref.T  # (G, N)
        near = c.argmax(1)
        inside = c[np.arange(len(g)), near] >= math.cos(self.rho)
        N = len(ref)
        cell = np.bincount(near, w, minlength=N)
        kept = np.bincount(near[inside], w[inside], minlength=N)
        self.fraction = np.where(cell > 0, kept / np.maximum(cell, 1e-300), 1.0)
        Yg, high = _grid_basis(n)
        H = Yg[~inside] * high
        self.prior = (H * w[~inside, None]).T @ H
        self.basis_u = Yg[~inside]
        self.zenith_u = np.arccos(g[~inside, 2])
        self.unsampled_sr = float(w[~inside].sum())


def roughness(n: int) -> np.ndarray:
    """(n^2, n^2) diagonal ``(l (l + 1))^2 / (L (L + 1))^2``: the squared surface
    Laplacian of a reconstruction over the sphere, scaled so that the top band is 1."""
    l_, _ = sh_degree_order(n)
    top = max((n - 1) * n, 1)
    return np.diag((l_ * (l_ + 1.0) / top) ** 2)


def _loo_score(Y, y, omega, M, rhs):
    """Coefficients and the weighted leave-one-out error of a linear projection
    ``c = M^-1 Y^T diag(omega) y`` (exact for linear smoothers: r_i / (1 - H_ii))."""
    c = np.linalg.solve(M, rhs)  # (B, n2, 3)
    Z = np.linalg.solve(M, np.swapaxes(Y, 1, 2))  # (B, n2, N)
    h = omega * np.einsum("bik,bki->bi", Y, Z)
    r = (y - Y @ c) / np.maximum(1 - h, 1e-3)[..., None]
    return c, np.sum(omega[..., None] * r * r, axis=(1, 2))


def project_cap(
    radiance: np.ndarray, directions: np.ndarray, weights: np.ndarray, n: int,
    hemisphere: str, cap: SampledCap, reg: float | str | np.ndarray = "auto",
    basis: np.ndarray | None = None, prior_scale: np.ndarray | None = None,
    system: bool = False,
) -> tuple[np.ndarray, ...]:
    """Projections that know which directions were observed (lsop, rlsop, wls).

    Least squares over the sampled cap, ``(A + P + lambda D) c = b``, with b
    ``sum_i w_i f_i y(d_i)`` (cell weights cut at the cap), P the prior of
    :class:`SampledCap` (variation held to zero where no view looked) and D
    :func:`roughness`:

    - ``lsop`` and ``wls``: A the Gram matrix of the samples, ``sum_i w_i y(d_i)
      y(d_i)^T``, lambda 0. On the cap, LSOP's exact Gram matrix (004 eq. 12.14) is
      replaced by this one, consistent with b: with the exact one, b is only a
      quadrature of the data and renders of sharp highlights suffered (measured on the
      physically based capture: LSOP-16 lost to a diffuse texture on one held-out view).
      The two names differ only with ``sampled_cap: false``;
    - ``rlsop``: as ``lsop`` with lambda ``reg`` (relative to the mean diagonal of
      ``A + P``; a number, or (B,) per texel) or, with ``auto``, per texel the value
      of a grid (0 included) with the least leave-one-out error (exact for least
      squares), so the regularised fit is never worse than the plain one on the
      texel's own cross-validation. (Pooling the choice over a batch, tried first,
      let the many matte texels of a batch smooth away a conductor's highlight.)

    Parameters
    ----------
    radiance, directions : (B, N, 3); weights : (B, N) Voronoi solid angles;
    cap : the batch's :class:`SampledCap`; basis : ``sh_basis(directions, n)``.
    prior_scale : (B,) factor on the prior per texel (the guard's escalation).

    system : also return the (B, n^2, n^2) matrix M of the normal equations solved,
        ``c = M^-1 Y^T diag(omega) y`` (for the coefficients' covariance).

    Returns
    -------
    (B, 3, n^2) coefficients and (B,) the relative lambda used (and M).
    """
    Y = sh_basis(directions, n) if basis is None else basis
    omega = weights * cap.fraction
    rhs = np.swapaxes(Y, 1, 2) @ (omega[..., None] * radiance)  # (B, n2, 3)
    A = np.swapaxes(Y, 1, 2) @ (omega[..., None] * Y)
    ps = np.ones(len(Y)) if prior_scale is None else np.asarray(prior_scale, float)
    A = A + ps[:, None, None] * cap.prior
    scale = np.trace(A, axis1=1, axis2=2)[:, None, None] / (n * n)
    A = A + 1e-9 * scale * np.eye(n * n)
    D = roughness(n)
    B = len(Y)
    if hemisphere != "rlsop" or not isinstance(reg, str):
        lam = np.broadcast_to(np.asarray(0.0 if hemisphere != "rlsop" else reg, float),
                              (B,)).copy()
        M = A + (lam[:, None, None] * scale) * D
        c = np.linalg.solve(M, rhs)
        return (np.swapaxes(c, 1, 2), lam) + ((M,) if system else ())
    if reg != "auto":
        raise InputError(f"regularisation must be a number or 'auto' (got {reg!r})")
    best_score = np.full(B, np.inf)
    best_c = np.empty((B, n * n, 3))
    lam = np.zeros(B)
    for g in [0.0] + [10.0 ** k for k in range(-5, 1)]:
        c, score = _loo_score(Y, radiance, omega, A + g * scale * D, rhs)
        better = score < best_score
        best_score[better], best_c[better], lam[better] = score[better], c[better], g
    out = (np.swapaxes(best_c, 1, 2), lam)
    return out + ((A + (lam[:, None, None] * scale) * D,) if system else ())


def resolvable_bands(directions: np.ndarray, n: int) -> int:
    """The most bands (at most ``n``, at least 2) that view directions (N, 3) resolve.

    With ``N`` views over the solid angle ``Omega`` their zenith range covers, the
    mean spacing is ``Delta = sqrt(Omega / N)``; degree ``L`` varies over half a
    wavelength ``pi / L``, and irregular sampling (spirals, jitter, holes) needs about
    two samples there, so ``L <= pi / (2 Delta)``. Beyond it, a fit is free between the
    views: with 30 views to 75 degrees, 36 coefficients dimmed a conductor's
    highlight seen from between two views to a third of its radiance; the 25 this rule
    gives followed it (held-out error 12.5 against 34 and a diffuse texture's 19).
    """
    d = np.asarray(directions, float)
    covered = 2 * np.pi * (1 - np.clip(d[:, 2], 0, 1).min())
    delta = math.sqrt(covered / len(d))
    return int(max(2, min(n, math.floor(math.pi / (2 * delta)) + 1)))


PRIOR_FLOOR = 1e-3  # weakest prior (relative), also the pilot fit's


def prior_strength(radiance: np.ndarray, Y: np.ndarray, omega: np.ndarray,
                   pilot: np.ndarray) -> np.ndarray:
    """(B,) weight of the unsampled-region prior per texel: the pilot fit's residual
    variance over the variance of the texel's observations (both weighted by solid
    angle), i.e. ``sigma^2 / tau^2`` of a Gaussian prior whose spread in the holes is
    the spread the texel shows where it was seen, against data whose noise is what the
    model could not explain. Texels whose own data are good get a weak prior (their fit
    is not biased); noisy ones lean on it. Clipped to [``PRIOR_FLOOR``, 1]."""
    w = omega[..., None] / omega.sum(1)[:, None, None]
    fit = Y @ np.swapaxes(pilot, 1, 2)
    res = (w * (radiance - fit) ** 2).sum((1, 2))
    mean = (w * radiance).sum(1, keepdims=True)
    spread = (w * (radiance - mean) ** 2).sum((1, 2))
    return np.clip(res / np.maximum(spread, 1e-30), PRIOR_FLOOR, 1.0)


GUARD_STEPS = 4  # escalations of the prior, x10 each
GUARD_TOLERANCE = 0.1  # of the texel's observed range


def guarded_project(
    radiance: np.ndarray, directions: np.ndarray, weights: np.ndarray, n: int,
    hemisphere: str, reg: float | str = "auto", basis: np.ndarray | None = None,
    system: bool = False,
) -> tuple:
    """:func:`project_cap` with the batch's :class:`SampledCap`, and a guard: a texel
    whose reconstruction at any unsampled direction leaves the range of its own
    observations (widened by ``GUARD_TOLERANCE`` of that range; checked up to one view
    spacing beyond the largest zenith observed) is refitted with the
    prior ten times stronger, up to ``GUARD_STEPS`` times, so that directions no view
    looked at are filled by the low bands rather than by an extrapolated lobe.

    Only the bands the views resolve are fitted (:func:`resolvable_bands`); the
    coefficients above them are zero.

    Returns
    -------
    (B, 3, n^2) coefficients, (B,) the relative lambda, (B,) int8 escalations per texel
    (``GUARD_STEPS + 1``: still outside after the last one), and the bands fitted; with
    ``system``, also the final normal-equation matrices (B, k^2, k^2) of the k fitted
    bands (:func:`project_cap`) and the (B, N) observation weights they were built
    with (``weights`` times the cap's cell fractions): together the linear smoother
    ``c = M^-1 Y^T diag(omega) y`` of :func:`smoother`.
    """
    ref = directions.mean(0)
    full = n
    n = resolvable_bands(ref, n)
    Y = sh_basis(directions, n) if basis is None else basis[..., : n * n]
    cap = SampledCap(ref, n)
    mu = prior_strength(radiance, Y, weights * cap.fraction,
                        project_cap(radiance, directions, weights, n, hemisphere, cap, 0.0,
                                    Y, prior_scale=np.full(len(Y), PRIOR_FLOOR))[0])
    c, lam, M = project_cap(radiance, directions, weights, n, hemisphere, cap, reg, Y,
                            prior_scale=mu, system=True)
    esc = np.zeros(len(c), np.int8)
    # renders look from within the zenith range the views covered, not beyond it
    reach = np.arccos(np.clip(directions[..., 2].min(), -1, 1)) + cap.rho
    Yu = cap.basis_u[cap.zenith_u <= reach]
    omega = weights * cap.fraction
    if not len(Yu):
        return (_pad_bands(c, full), lam, esc, n) + ((M, omega) if system else ())
    lo, hi = radiance.min(1), radiance.max(1)  # (B, 3)
    tol = GUARD_TOLERANCE * (hi - lo) + 1e-12
    for step in range(GUARD_STEPS + 1):
        f = Yu[None] @ np.swapaxes(c, 1, 2)  # (B, U, 3)
        bad = ((f < (lo - tol)[:, None]) | (f > (hi + tol)[:, None])).any((1, 2))
        if not bad.any():
            break
        if step == GUARD_STEPS:
            esc[bad] = GUARD_STEPS + 1  # still outside: reported, not hidden
            break
        esc[bad] += 1
        sel = np.flatnonzero(bad)
        c[sel], _, M[sel] = project_cap(radiance[sel], directions[sel], weights[sel], n,
                                        hemisphere, cap, lam[sel], Y[sel],
                                        prior_scale=mu[sel] * 10.0 ** esc[sel], system=True)
    return (_pad_bands(c, full), lam, esc, n) + ((M, omega) if system else ())


def smoother(M: np.ndarray, Y: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """(B, k^2, N) the linear map ``S = M^-1 Y^T diag(omega)`` from a texel's
    observations to its coefficients (M (B, k^2, k^2), Y (B, N, k^2), omega (B, N))."""
    return np.linalg.solve(M, np.swapaxes(Y, 1, 2) * omega[:, None, :])


def smoother_loo(S: np.ndarray, Y: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(B, N, 3) leave-one-view-out residuals ``r_i / (1 - h_ii)`` of a linear smoother S
    (:func:`smoother`), r (B, N, 3) the residuals of its fit, h the diagonal of the hat
    matrix ``Y S``: exact for a linear smoother with its prior and regularisation held
    fixed. Inf where a view alone determines the fit (h ~ 1)."""
    h = np.einsum("bnk,bkn->bn", Y, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((h > 1 - 1e-9)[..., None], np.inf, r / (1 - h)[..., None])


def coefficient_sd(S: np.ndarray, Y: np.ndarray, r: np.ndarray, n: int,
                   sigma: np.ndarray | None = None) -> np.ndarray:
    """Standard deviations of projected coefficients ``c = M^-1 Y^T diag(omega) y``.

    A linear smoother ``S = M^-1 Y^T diag(omega)`` propagates the observations'
    covariance: channel c's is ``S diag(s_c^2) S^T``. With the capture's noise model
    (``sigma``, the sd of each observation the HDR merge recorded) that is the spread
    over noise realisations. Without it, ``s = r`` (the sandwich, heteroscedasticity-
    robust as the MH uncertainties) scaled by ``N / (N - tr H)`` for the degrees of
    freedom the fit used (H = Y S); the residuals then also carry what the bands cannot
    represent (a sharp highlight), so the sd says how far the fit can be trusted
    rather than how it would vary with the noise.

    Parameters
    ----------
    S : (B, k^2, N) the smoother (:func:`smoother`); Y : (B, N, k^2) basis at the views;
    r : (B, N, 3) residuals; n : bands of the output;
    sigma : (B, N, 3) noise sd of each observation (radiance units), or None.

    Returns
    -------
    (B, 3, n^2): NaN for the bands above k (not fitted: zero by construction).
    """
    if sigma is not None:
        var = np.einsum("bkn,bnc->bck", S * S, sigma * sigma)
    else:
        N = Y.shape[1]
        edf = np.einsum("bnk,bkn->b", Y, S)
        scale = N / np.maximum(N - edf, 1.0)
        var = np.einsum("bkn,bnc->bck", S * S, r * r) * scale[:, None, None]
    return _pad_bands(np.sqrt(var), n, fill=np.nan)


def _pad_bands(c: np.ndarray, n: int, fill: float = 0.0) -> np.ndarray:
    """(B, 3, k^2) coefficients -> (B, 3, n^2), the bands above k ``fill`` (zero)."""
    out = np.full(c.shape[:2] + (n * n,), fill)
    out[..., : c.shape[-1]] = c
    return out


# ---------------------------------------------------------------------------------
# Tiles and maps


def sh_outputs(n: int) -> dict[str, tuple[tuple[int, ...], str, float]]:
    """Arrays of an SH fit store: name -> (trailing shape, dtype, fill value)."""
    return {
        FitArray.COEFFS: ((3 * n * n,), "float32", float("nan")),
        FitArray.SD: ((3 * n * n,), "float32", float("nan")),
        FitArray.RMSE: ((3,), "float32", float("nan")),
        FitArray.MPR: ((3,), "float32", float("nan")),
        FitArray.CHI2: ((), "float32", float("nan")),
        FitArray.REG: ((), "float32", float("nan")),
        FitArray.GUARD: ((), "int8", 0),
        FitArray.BANDS: ((), "int8", n),
        FitArray.STATUS: ((), "int8", int(FitStatus.NOT_FITTED)),
    }


def fit_sh_tile(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray, n: int,
                hemisphere: str, reg: float | str = "auto", batch: int = 256,
                min_obs: int | None = None, sampled_cap: bool = default("fit.sh.sampled_cap"),
                noise: np.ndarray | None = None, areas: str = "spherical",
                loo: bool = False) -> dict[str, np.ndarray]:
    """Project every texel of a tile, batched (texels sharing one validity pattern
    share one triangulation and one :class:`SampledCap`). (t, u, N, 3) inputs; outputs
    as :func:`sh_outputs`. ``sampled_cap`` (default) fits lsop, rlsop and wls with
    :func:`project_cap` and its guard; ``False`` gives the published projections of
    :func:`project` (Voronoi cells out to the equator, fixed ``reg``). ``noise`` (t, u,
    N) relative sd per observation: cell weights are multiplied by the noise weights
    of :func:`parammap.models.weights.noise_weights`, and ``chi2`` is reported.
    ``areas``: ``spherical`` Voronoi cells (default) or 004's ``planar`` cells divided
    by cos(theta) (:func:`planar_solid_angles`), for reproducing its artefacts.
    ``loo``: also ``loo`` (t, u, N, 3), each valid view's leave-one-out residual
    (prediction minus observation, :func:`smoother_loo`; inf where the view alone
    determines the fit), for the projections on the sampled cap (NaN otherwise)."""
    t, u, N, _ = radiance.shape
    outputs = sh_outputs(n) | ({FitArray.LOO: ((N, 3), "float64", float("nan"))} if loo else {})
    out = {k: np.full((t, u) + shp, fill, dtype) for k, (shp, dtype, fill) in
           outputs.items()}
    flat = {k: v.reshape((t * u,) + v.shape[2:]) for k, v in out.items()}
    L = radiance.reshape(t * u, N, 3).astype(float)
    V = direction.reshape(t * u, N, 3).astype(float)
    W = valid.reshape(t * u, N) & np.isfinite(L).all(-1) & np.isfinite(V).all(-1) \
        & (V[..., 2] > 0)
    NW = noise_weights(None if noise is None else noise.reshape(t * u, N), W)
    NZ = None if noise is None else noise.reshape(t * u, N)
    min_obs = min_obs or 4
    nobs = W.sum(1)
    flat[FitArray.STATUS][nobs < min_obs] = FitStatus.TOO_FEW
    todo = np.flatnonzero(nobs >= min_obs)
    # group texels by validity pattern: one triangulation per pattern and batch
    keys = {}
    for b in todo:
        keys.setdefault(W[b].tobytes(), []).append(b)
    for idx in keys.values():
        idx = np.array(idx)
        w = W[idx[0]]
        for s0 in range(0, len(idx), batch):
            sel = idx[s0:s0 + batch]
            v, y = V[sel][:, w], L[sel][:, w]
            try:
                omega = (planar_solid_angles(v) if areas == "planar" else solid_angles(v)) \
                    * NW[sel][:, w]
                Y = sh_basis(v, n)
                if sampled_cap and hemisphere in SH_CAP_AWARE:
                    c, lam, esc, bands, M, om = guarded_project(y, v, omega, n, hemisphere,
                                                                reg, Y, system=True)
                    flat[FitArray.REG][sel], flat[FitArray.GUARD][sel] = lam, esc
                    flat[FitArray.BANDS][sel] = bands
                    sigma = None if NZ is None else NZ[sel][:, w][..., None] * np.abs(y)
                    Yk = Y[..., : bands * bands]
                    Sm = smoother(M, Yk, om)
                    r = y - np.matmul(Y, c.transpose(0, 2, 1))
                    flat[FitArray.SD][sel] = coefficient_sd(Sm, Yk, r, n, sigma).reshape(len(sel),
                                                                                         -1)
                    if loo:
                        flat[FitArray.LOO][sel[:, None], np.flatnonzero(w)[None]] = \
                            smoother_loo(Sm, Yk, -r)  # prediction - observation
                else:
                    c = project(y, v, omega, n, hemisphere,
                                1e-4 if reg == "auto" else float(reg), basis=Y)
            except Exception:  # noqa: BLE001 - a failed batch is flagged, never fatal
                flat[FitArray.STATUS][sel] = FitStatus.FAILED
                continue
            fitted = np.matmul(Y, c.transpose(0, 2, 1))
            flat[FitArray.COEFFS][sel] = c.reshape(len(sel), -1)
            flat[FitArray.RMSE][sel] = np.sqrt(np.mean((fitted - y) ** 2, axis=1))
            flat[FitArray.MPR][sel] = mean_percentage_residual(y, fitted)
            if NZ is not None:
                flat[FitArray.CHI2][sel] = reduced_chi2(y, fitted, NZ[sel][:, w],
                                                 np.ones(y.shape[:2], bool), 3 * n * n)
            flat[FitArray.STATUS][sel] = np.where(np.isfinite(c).all((1, 2)), FitStatus.OK,
                                           FitStatus.FAILED)
    return out


def parse_sh_model(name: str) -> tuple[str, int]:
    """``sh-<hemisphere>-<coefficients>`` -> (hemisphere, bands)."""
    parts = name.split("-")
    if len(parts) != 3 or parts[0] != "sh" or parts[1] not in SH_HEMISPHERES:
        raise InputError(f"SH model name must be sh-<{'|'.join(SH_HEMISPHERES)}>-<n^2> "
                         f"(got {name!r})")
    try:
        nc = int(parts[2])
    except ValueError:
        nc = -1
    n = int(round(math.sqrt(max(nc, 0))))
    if nc < 1 or n * n != nc:
        raise InputError(f"{name}: the coefficient count must be a square (1, 4, 9, 16...)")
    return parts[1], n



