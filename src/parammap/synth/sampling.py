"""View-direction sampling schemes over the upper hemisphere (004 ch. 8).

Every function returns unit vectors, shape (N, 3), in the surface frame with z > 0,
restricted to zenith <= ``max_zenith_deg``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["SCHEMES", "icosahedron", "latlong", "sample_directions", "spiral", "stratified"]


def _cap(d: np.ndarray, max_zenith_deg: float) -> np.ndarray:
    keep = d[:, 2] > max(np.cos(np.radians(max_zenith_deg)), 1e-9)
    return d[keep]


def icosahedron(level: int = 2, max_zenith_deg: float = 90.0) -> np.ndarray:
    """Vertices of a subdivided icosahedron in the upper hemisphere (004 ch. 8.1.2).

    The standard orientation (an edge along each axis) gives 17, 73 and 305 directions
    strictly above the equator for levels 1, 2 and 3, as in 004 ch. 13.2.
    """
    p = (1 + 5**0.5) / 2
    verts = [np.array(v, float) for v in (
        (-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p),
        (0, -1, -p), (0, 1, -p), (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1))]
    verts = [v / np.linalg.norm(v) for v in verts]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(level):
        cache: dict[tuple[int, int], int] = {}

        def mid(i: int, j: int, cache: dict = cache) -> int:
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = verts[i] + verts[j]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return _cap(np.array(verts), max_zenith_deg)


def latlong(
    n_zenith: int = 6, n_azimuth_max: int = 32, max_zenith_deg: float = 90.0
) -> np.ndarray:
    """Rings of fixed zenith, azimuth count proportional to sin(zenith), plus the
    normal direction (004 ch. 8.1.3)."""
    zen = np.radians(max_zenith_deg) * np.arange(1, n_zenith + 1) / n_zenith
    dirs = [np.array([[0.0, 0.0, 1.0]])]
    for z in zen:
        n = max(4, int(round(n_azimuth_max * np.sin(z))))
        phi = 2 * np.pi * (np.arange(n) + 0.5 * (len(dirs) % 2)) / n
        dirs.append(np.stack([np.sin(z) * np.cos(phi), np.sin(z) * np.sin(phi),
                              np.full(n, np.cos(z))], axis=1))
    return _cap(np.concatenate(dirs), max_zenith_deg + 1e-6)


def spiral(n: int = 100, turns: float = 6.0, max_zenith_deg: float = 90.0) -> np.ndarray:
    """A spiral from the horizon up to the normal (004 ch. 8.1.1); zenith steps in
    cos so the pole is not oversampled."""
    k = np.arange(n)
    cz = np.cos(np.radians(max_zenith_deg)) + (1 - np.cos(np.radians(max_zenith_deg))) * (
        (k + 0.5) / n)
    zen = np.arccos(cz)
    phi = 2 * np.pi * turns * k / n
    return np.stack([np.sin(zen) * np.cos(phi), np.sin(zen) * np.sin(phi), cz], axis=1)


def stratified(n_side: int = 9, max_zenith_deg: float = 90.0, seed: int = 0) -> np.ndarray:
    """Stratified random directions: one uniform sample in each of n_side^2 cells of
    the unit square mapped to equal-area cells of the cap (004 ch. 8.2, [Gre03])."""
    rng = np.random.default_rng(seed)
    a, b = np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij")
    u = (a.ravel() + rng.random(a.size)) / n_side
    v = (b.ravel() + rng.random(a.size)) / n_side
    cmin = np.cos(np.radians(max_zenith_deg))
    cz = 1 - u * (1 - cmin)
    sz = np.sqrt(1 - cz**2)
    phi = 2 * np.pi * v
    return np.stack([sz * np.cos(phi), sz * np.sin(phi), cz], axis=1)


SCHEMES = {"icosahedron": icosahedron, "latlong": latlong, "spiral": spiral,
           "stratified": stratified}


def sample_directions(scheme: str, max_zenith_deg: float = 90.0, **kwargs) -> np.ndarray:
    """Directions of a named scheme; ``kwargs`` go to the scheme's function."""
    try:
        fn = SCHEMES[scheme]
    except KeyError:
        raise InputError(f"unknown sampling scheme {scheme!r}; one of {sorted(SCHEMES)}") from None
    return fn(max_zenith_deg=max_zenith_deg, **kwargs)
