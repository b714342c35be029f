"""Where the lights are, from the highlights' lobes (issue 48 item 1).

A Phong-like lobe points along the mirror direction of the light that makes it: the
reflection ``l = (-d.x, -d.y, d.z)`` of lobe direction ``d`` about the surface normal
``+z`` is the direction from the texel to the light. Every texel whose views determine
its lobe casts a ray from its centre along ``l``; the rays of one light meet at it. A
light's position is the point nearest to its rays in the least-squares sense, each ray
weighted by its precision (the lobe direction's sd times the distance to the light),
with Tukey biweights so that lobes of another light or poorly determined ones do not
pull it; several lights share the rays out by which light each ray passes closest to
(normalised by its sd), refitted until the shares settle.

Lengths in the surface frame's mm, angles in radians unless named ``_deg``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

__all__ = ["AREA_MAX_SIDE", "AREA_SHAPES", "AREA_STEP_DEG", "LightFit", "area_light_points",
           "expand_lights", "fit_light", "fit_lights", "mirror_to_light"]

TUKEY_C = 4.685  # biweight cut-off, robust sd units (95 % efficiency at the normal)
MIN_RAYS = 8  # fewer rays than this determine no light


def mirror_to_light(d: np.ndarray) -> np.ndarray:
    """The direction toward the light (n, 3) of lobe directions ``d`` (n, 3): their
    mirror image about the surface normal +z."""
    d = np.asarray(d, float)
    return np.stack([-d[..., 0], -d[..., 1], d[..., 2]], -1)


@dataclass
class LightFit:
    """One light found from lobe rays: ``position_mm`` (3,), its covariance (3, 3),
    ``inliers`` (n,) bool over the rays given, the rays' normalised miss distances
    ``z`` (n,) and the robust scale of those (1 where the lobes' sds are right)."""

    position_mm: np.ndarray
    cov_mm2: np.ndarray
    inliers: np.ndarray
    z: np.ndarray
    scale: float

    @property
    def sd_mm(self) -> np.ndarray:
        """(3,) standard deviation of the position along x, y, z."""
        return np.sqrt(np.clip(np.diag(self.cov_mm2), 0, None))


def _nearest_point(p: np.ndarray, u: np.ndarray, w: np.ndarray) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """The point minimising sum w |(I - u u^T)(x - p)|^2 and its information matrix."""
    P = np.eye(3)[None] - u[:, :, None] * u[:, None, :]  # (n, 3, 3) projectors
    A = np.einsum("n,nij->ij", w, P)
    b = np.einsum("n,nij,nj->i", w, P, p)
    return np.linalg.lstsq(A, b, rcond=None)[0], A


def _miss(x: np.ndarray, p: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (n,) from x to each ray, and how far along each ray x lies (n,)."""
    r = x[None] - p
    s = r @ u.T if u.ndim == 1 else np.einsum("ni,ni->n", r, u)
    perp = r - s[:, None] * u
    return np.linalg.norm(perp, axis=1), s


def _ransac_start(p: np.ndarray, u: np.ndarray, sd: np.ndarray, rng: np.random.Generator,
                  tries: int = 300) -> np.ndarray | None:
    """The candidate point most rays pass within ``TUKEY_C`` of their sd: candidates are
    the closest approaches of random pairs of rays (both in front of their texels)."""
    n = len(p)
    best, best_x = -1, None
    for _ in range(tries):
        i, j = rng.choice(n, 2, replace=False)
        w0 = u[i] @ u[j]
        r = p[j] - p[i]
        den = 1 - w0 * w0
        if den < 1e-8:
            continue
        si = (r @ u[i] - w0 * (r @ u[j])) / den
        sj = (w0 * (r @ u[i]) - r @ u[j]) / den
        if si <= 0 or sj <= 0:
            continue
        x = 0.5 * (p[i] + si * u[i] + p[j] + sj * u[j])
        score = int(np.sum(_z(x, p, u, sd) < TUKEY_C))
        if score > best:
            best, best_x = score, x
    return best_x


def fit_light(origins: np.ndarray, dirs: np.ndarray, sd_rad: np.ndarray,
              x0: np.ndarray | None = None, rounds: int = 30, seed: int = 0,
              ) -> LightFit | None:
    """The point the rays ``origins + s dirs`` (n, 3 each, s > 0) meet at.

    Starts from ``x0`` or from the point most rays pass near (pairs of rays, RANSAC),
    then iterates weighted least squares: each ray's miss distance in units of its sd
    at that distance (``s * sd``), Tukey biweights on the misses over their robust
    scale.

    Parameters
    ----------
    origins : (n, 3) texel centres, mm.
    dirs : (n, 3) unit directions toward the light.
    sd_rad : (n,) angular sd of each direction (radians, > 0).

    Returns
    -------
    :class:`LightFit`, or None where fewer than ``MIN_RAYS`` rays are given or they
    leave the point undetermined (all parallel).
    """
    p, u = np.asarray(origins, float), np.asarray(dirs, float)
    sd = np.maximum(np.asarray(sd_rad, float), 1e-6)
    if len(p) < MIN_RAYS:
        return None
    x = x0 if x0 is not None else _ransac_start(p, u, sd, np.random.default_rng(seed))
    if x is None:
        return None
    scale, A = 1.0, None
    for _ in range(rounds):
        d, s = _miss(x, p, u)
        along = np.maximum(s, 1e-9)
        z = np.where(s > 0, d / (along * sd), np.inf)
        near = z < TUKEY_C * scale
        if near.sum() < MIN_RAYS:
            return None
        # a 2-d normal miss: |z| is Rayleigh, median 1.1774 sd
        scale = max(float(np.median(z[near])) / 1.1774, 1e-9)
        t = z / (TUKEY_C * scale)
        w = np.where(t < 1, (1 - t**2) ** 2, 0.0) / (along * sd) ** 2
        x_new, A = _nearest_point(p, u, w)
        if np.linalg.cond(A) > 1e12:
            return None
        done = np.linalg.norm(x_new - x) < 1e-7 * max(np.linalg.norm(x), 1.0)
        x = x_new
        if done:
            break
    x, cov = _angular_refine(x, p, u, sd, w * (np.maximum(_miss(x, p, u)[1], 1e-9)) ** 2)
    z = _z(x, p, u, sd)
    return LightFit(x, cov * scale**2, z < TUKEY_C * scale, z, scale)


def _angular_refine(x: np.ndarray, p: np.ndarray, u: np.ndarray, sd: np.ndarray,
                    w_ang: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximum likelihood for noise in the lobes' directions: ``x`` minimising the sum
    of ``w_ang`` times the squared difference between each ray's direction and the
    direction from its texel to ``x`` (Gauss-Newton from the point-to-ray solution,
    whose misses weigh the rays near the texels too little: it sits short of the
    light by a share that grows with the directions' sd squared). Returns ``x`` and
    the covariance at unit scale."""
    keep = w_ang > 0
    pk, uk, wk = p[keep], u[keep], np.sqrt(w_ang[keep])[:, None]

    def res(y: np.ndarray) -> np.ndarray:
        v = y[None] - pk
        return ((v / np.linalg.norm(v, axis=1, keepdims=True) - uk) * wk).ravel()

    sol = least_squares(res, x, method="lm", x_scale="jac")
    J = sol.jac
    return sol.x, np.linalg.pinv(J.T @ J)


def fit_lights(origins: np.ndarray, dirs: np.ndarray, sd_rad: np.ndarray, n_lights: int,
               rounds: int = 10) -> list[LightFit]:
    """Up to ``n_lights`` lights from one set of rays (:func:`fit_light`): the first on
    every ray, each next on the rays the lights before reject; then each ray goes to
    the light it misses least (in its own sd) and every light is refitted on its rays,
    until the shares settle. Lights whose rays leave them undetermined are dropped.

    Returns
    -------
    list of :class:`LightFit` (``inliers`` over all rays given), brightest first in the
    sense of most rays.
    """
    p, u = np.asarray(origins, float), np.asarray(dirs, float)
    sd = np.asarray(sd_rad, float)
    left = np.ones(len(p), bool)
    fits: list[LightFit] = []
    for _ in range(n_lights):
        f = fit_light(p[left], u[left], sd[left])
        if f is None:
            break
        inl = np.zeros(len(p), bool)
        inl[np.flatnonzero(left)[f.inliers]] = True
        fits.append(f)
        left &= ~inl
    if len(fits) < 2:
        return [_full(f, p, u, sd) for f in fits]
    share = None
    for _ in range(rounds):
        z = np.stack([_z(f.position_mm, p, u, sd) for f in fits])
        new = np.argmin(z, 0)
        if share is not None and np.array_equal(new, share):
            break
        share = new
        refit = [fit_light(p[share == k], u[share == k], sd[share == k])
                 for k in range(len(fits))]
        fits = [f for f in refit if f is not None]
        if len(fits) < 2:
            break
    fits = [_full(f, p, u, sd) for f in fits]
    return sorted(fits, key=lambda f: -int(f.inliers.sum()))


def _z(x: np.ndarray, p: np.ndarray, u: np.ndarray, sd: np.ndarray) -> np.ndarray:
    d, s = _miss(x, p, u)
    return np.where(s > 0, d / (np.maximum(s, 1e-9) * np.maximum(sd, 1e-6)), np.inf)


def _full(f: LightFit, p: np.ndarray, u: np.ndarray, sd: np.ndarray) -> LightFit:
    """``f`` with its misses and inliers over every ray."""
    z = _z(f.position_mm, p, u, sd)
    return LightFit(f.position_mm, f.cov_mm2, z < TUKEY_C * f.scale, z, f.scale)


# --- area lights: each as quadrature points the point-light models sum over -----------

#: an area light's quadrature points are at most this far apart as seen from the surface's
#: centre: under the reflected half-maximum width of a GGX lobe (2.6 alpha rad) from alpha
#: 0.013 up, so that such lobes draw the light's whole shape, not its points
AREA_STEP_DEG = 2.0
#: points across one side of a light at most (36 a light: the svbrdf fit's cost grows with
#: them); a light wider than 12 deg is drawn coarser than AREA_STEP_DEG
AREA_MAX_SIDE = 6
AREA_SHAPES = ("rect", "disc")


def _light_frame(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The light's (width, height) axes: height along the surface's y projected onto the
    light's plane (x where the normal lies near y), width across it."""
    up = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    v = up - normal * (up @ normal)
    v /= np.linalg.norm(v)
    return np.cross(v, normal), v


def area_light_points(centre_mm: np.ndarray, shape: str, size_mm, normal=None,
                      target_mm=None) -> tuple[np.ndarray, np.ndarray]:
    """Equal-area quadrature points of one area light, a Lambertian emitter.

    Parameters
    ----------
    centre_mm : (3,) the light's centre (surface frame, mm).
    shape : ``rect`` (``size_mm`` width and height, the height along the surface's y as
        seen in the light's plane) or ``disc`` (``size_mm[0]`` the diameter).
    normal : (3,) the direction the light faces; default toward ``target_mm`` (the
        surface's centre, (3,); default the origin).

    Returns
    -------
    (Q, 6) each point's position (mm) and the light's unit normal, and (Q,) each point's
    share of the light (sum 1). Seen from ``target_mm`` the points are at most
    :data:`AREA_STEP_DEG` apart (up to :data:`AREA_MAX_SIDE` a side).
    """
    c = np.asarray(centre_mm, float)
    tgt = np.zeros(3) if target_mm is None else np.asarray(target_mm, float)
    n = tgt - c if normal is None else np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    u, v = _light_frame(n)
    step = np.radians(AREA_STEP_DEG) * float(np.linalg.norm(tgt - c))

    def side(length: float) -> int:
        return int(np.clip(np.ceil(length / step), 1, AREA_MAX_SIDE))

    if shape == "rect":
        w, h = float(size_mm[0]), float(size_mm[-1])
        a = ((np.arange(side(w)) + 0.5) / side(w) - 0.5) * w
        b = ((np.arange(side(h)) + 0.5) / side(h) - 0.5) * h
        A, B = np.meshgrid(a, b, indexing="ij")
        off = A.reshape(-1, 1) * u + B.reshape(-1, 1) * v
        share = np.full(len(off), 1.0 / len(off))
    elif shape == "disc":  # a sunflower (Vogel) spiral: equal areas, even spacing
        radius = float(size_mm[0]) / 2
        # a hexagonal packing spaced `step` takes 2 / sqrt(3) points a step^2; the
        # spiral's spacing is a little less even
        q = int(np.clip(np.ceil(4 / 3 * np.pi * radius * radius / (step * step)), 1,
                        AREA_MAX_SIDE * AREA_MAX_SIDE))
        k = np.arange(q)
        r = radius * np.sqrt((k + 0.5) / q) if q > 1 else np.zeros(1)
        t = k * np.pi * (3 - np.sqrt(5))
        off = r[:, None] * (np.cos(t)[:, None] * u + np.sin(t)[:, None] * v)
        share = np.full(q, 1.0 / q)
    else:
        raise ValueError(f"unknown light shape {shape!r}; one of {AREA_SHAPES}")
    return np.c_[c + off, np.broadcast_to(n, off.shape)], share


def expand_lights(centres_mm: np.ndarray, extents: list | None, target_mm=None,
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The point lights the models sum over for lights (J, 3) of which some have an
    extent (``extents[j]``: None, a point light, or a dict with ``shape``, ``size_mm``
    and maybe ``normal``, :func:`area_light_points`).

    Returns
    -------
    (P, 3) positions where every light is a point, else (P, 6) positions and emitter
    normals (zero for a point light, which shines alike in every direction); and (P, J)
    each point's share of each light (the lights' intensities ``w`` (J, 3) become the
    points' as ``group @ w``).
    """
    c = np.asarray(centres_mm, float).reshape(-1, 3)
    ext = list(extents or []) + [None] * (len(c) - len(extents or []))
    if not any(ext):
        return c, np.eye(len(c))
    pts, owner, share = [], [], []
    for j, (cj, e) in enumerate(zip(c, ext, strict=True)):
        if e:
            p, s = area_light_points(cj, e["shape"], e["size_mm"], e.get("normal"), target_mm)
        else:
            p, s = np.r_[cj, 0.0, 0.0, 0.0][None], np.ones(1)
        pts.append(p)
        owner.append(np.full(len(p), j))
        share.append(s)
    owner, share = np.concatenate(owner), np.concatenate(share)
    group = np.zeros((len(owner), len(c)))
    group[np.arange(len(owner)), owner] = share
    return np.vstack(pts), group
