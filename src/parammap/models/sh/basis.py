"""SH basis, evaluation, the hemisphere's solid angles per sample (spherical Voronoi
cells) and the published projections (004 ch. 12)."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ...conventions import (
    SH_HEMISPHERES,
    sh_degree_order,
    sh_norms,
)
from ...errors import InputError


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
