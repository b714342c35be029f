"""Render a parameter map as a calibrated camera saw it.

Each pixel's ray (lens distortion undone, OpenCV model) is intersected with the surface
plane z = 0; the model is evaluated in the pixel's own view direction (from the plane
point to the camera centre) and interpolated bilinearly between texel centres (the
radiance for MH, the parameters for the linear SH and diffuse models; see
:func:`evaluate_bilinear`). Output is linear HDR radiance in the units of the
observation map, aligned with the photo of that camera by construction (no manual
alignment, unlike 004 ch. 16).
"""

from __future__ import annotations

import numpy as np

from .conventions import MH_KD, mh_dir, mh_lobes
from .errors import InputError
from .geometry import (
    Intrinsics,
    camera_centre,
    pixel_to_plane,
    plane_to_texel,
    project_points,
    sample_image,
    unit,
)
from .models.display import tone_map
from .models.mh import mh_eval
from .models.sh.basis import sh_eval
from .models.svbrdf import svbrdf_eval
from .stores.params import ParamMap, best_shares

__all__ = ["bilinear_corners", "evaluate", "evaluate_bilinear", "lookup_bilinear", "render",
           "reproject_frame", "surface_points", "tone_map"]


#: pixels a render evaluates at once (its memory, not the photo's)
RENDER_CHUNK = 1 << 18


def bilinear_corners(shape: tuple[int, int], row: np.ndarray, col: np.ndarray,
                     ) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """The four texels around continuous texel coordinates (texel centres at integer +
    0.5, as :func:`parammap.geometry.plane_to_texel` returns), clamped at the edges, and
    their bilinear weights: ``[(rows, cols) x 4]``, ``[(M,) weights x 4]``."""
    T, S = shape
    r = np.clip(np.asarray(row) - 0.5, 0, T - 1)
    c = np.clip(np.asarray(col) - 0.5, 0, S - 1)
    r0 = np.minimum(np.floor(r).astype(int), max(T - 2, 0))
    c0 = np.minimum(np.floor(c).astype(int), max(S - 2, 0))
    r1, c1 = np.minimum(r0 + 1, T - 1), np.minimum(c0 + 1, S - 1)
    fr, fc = r - r0, c - c0
    return ([(r0, c0), (r0, c1), (r1, c0), (r1, c1)],
            [(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc])


def lookup_bilinear(params: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a (T, S, P) map at continuous texel coordinates (see
    :func:`bilinear_corners`). (M,) coordinates -> (M, P)."""
    idx, wts = bilinear_corners(params.shape[:2], row, col)
    return sum(w[:, None] * params[r, c] for (r, c), w in zip(idx, wts, strict=True))


def evaluate_bilinear(model: str, params: np.ndarray, row: np.ndarray, col: np.ndarray,
                      directions: np.ndarray, points: np.ndarray | None = None,
                      lights: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Radiance (M, 3) between texel centres, seen from directions (M, 3).

    SH and diffuse maps are linear in their parameters, so their parameters are
    interpolated. An MH model is not: neighbouring texels may order their lobes
    differently, or have one lobe fewer (Ks = 0, d = +z), and interpolating a lobe
    direction with another texel's unrelated lobe, or shininess across a highlight,
    makes a lobe neither texel has (held-out errors of two-lobe maps doubled on a
    physically based capture). MH is evaluated at the four texels and the radiance
    interpolated; the viewer does the same.
    """
    if model != "mh":
        return evaluate(model, lookup_bilinear(params, row, col), directions, points, lights)
    idx, wts = bilinear_corners(params.shape[:2], row, col)
    return sum(w[:, None] * evaluate(model, params[r, c], directions)
               for (r, c), w in zip(idx, wts, strict=True))


def evaluate(model: str, params: np.ndarray, directions: np.ndarray,
             points: np.ndarray | None = None,
             lights: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Radiance (M, 3) of per-point parameter vectors (M, P) seen from directions (M, 3).
    An svbrdf map also needs the surface points (M, 3) mm and its lights (positions and
    relative intensities, :attr:`parammap.stores.params.ParamMap.lights`)."""
    if model == "diffuse":
        return params[:, MH_KD].astype(float)
    if model == "mh":

        p = params.astype(float).copy()
        K = mh_lobes(p.shape[1])
        for k in range(K):  # interpolated lobe directions are renormalised
            d = p[:, mh_dir(k)]
            p[:, mh_dir(k)] = d / np.maximum(np.linalg.norm(d, axis=1,
                                                                        keepdims=True), 1e-12)
        return mh_eval(p, directions[:, None, :])[:, 0]
    if model == "sh":

        nc = params.shape[1] // 3
        return sh_eval(params.astype(float).reshape(-1, 3, nc), directions[:, None, :])[:, 0]
    if model == "svbrdf":
        if points is None or lights is None:
            raise InputError("an svbrdf map is evaluated at surface points under its lights")
        return svbrdf_eval(params, points, directions, *lights)
    raise InputError(f"unknown model {model!r}")


def surface_points(
    intr: Intrinsics, R: np.ndarray, t: np.ndarray, width_mm: float, height_mm: float,
    size: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Plane points of every pixel centre and the mask of pixels inside the region.

    Returns
    -------
    points : (H, W, 3) surface-frame points (mm); inside : (H, W) bool.
    """
    W, H = size or intr.image_size
    P = np.empty((H, W, 3))
    hit = np.empty((H, W), bool)
    step = max(1, RENDER_CHUNK // W)  # rows at once: the undistortion's temporaries
    for r0 in range(0, H, step):
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(r0, min(r0 + step, H),
                                                                dtype=float))
        P[r0:r0 + step], hit[r0:r0 + step] = pixel_to_plane(np.stack([u, v], -1), intr.K,
                                                            intr.dist, R, t)
    inside = hit & (P[..., 0] >= 0) & (P[..., 0] <= width_mm) & (P[..., 1] >= 0) \
        & (P[..., 1] <= height_mm)
    return P, inside


def render(pm: ParamMap, intr: Intrinsics, R: np.ndarray, t: np.ndarray,
           size: tuple[int, int] | None = None, interpolation: str = "bilinear",
           surface: tuple[np.ndarray, np.ndarray] | None = None,
           ) -> tuple[np.ndarray, np.ndarray]:
    """Render a parameter map into a camera.

    ``interpolation`` is ``bilinear`` (between texel centres, the default) or
    ``nearest`` (piecewise constant texels). ``surface``: this camera's
    :func:`surface_points` where the caller has them (several maps rendered into one
    view undistort its pixels once).

    Returns
    -------
    image : (H, W, 3) float32 linear radiance, NaN outside the sampled region.
    inside : (H, W) bool.
    """
    P, inside = surface or surface_points(intr, R, t, pm.width_mm, pm.height_mm, size)
    T, S = pm.shape
    out = np.full(P.shape[:2] + (3,), np.nan, np.float32)
    flat = np.flatnonzero(inside)
    C = camera_centre(R, t)[None]
    Pf = P.reshape(-1, 3)
    if pm.model == "best":
        out.reshape(-1, 3)[flat] = _render_best(pm, Pf[flat], C, interpolation)
        return out, inside
    res = np.empty((len(flat), 3), np.float32)
    # a chunk of pixels at a time: a 12 MP photo's pixels times an SH map's coefficients
    # would otherwise be gigabytes
    for s0 in range(0, len(flat), RENDER_CHUNK):
        Pi = Pf[flat[s0:s0 + RENDER_CHUNK]]
        row, col = plane_to_texel(Pi[:, 0], Pi[:, 1], S, T, pm.width_mm, pm.height_mm)
        d = unit(C - Pi)
        if interpolation == "nearest":
            prm = pm.params[np.clip(row.astype(int), 0, T - 1),
                            np.clip(col.astype(int), 0, S - 1)]
            res[s0:s0 + len(Pi)] = evaluate(pm.model, prm, d, Pi, pm.lights)
        else:
            res[s0:s0 + len(Pi)] = evaluate_bilinear(pm.model, pm.params, row, col, d, Pi,
                                                     pm.lights)
    out.reshape(-1, 3)[flat] = res
    return out, inside


def _render_best(pm: ParamMap, points: np.ndarray, C: np.ndarray,
                 interpolation: str) -> np.ndarray:
    """Radiance (M, 3) of a best map at surface points (M, 3) seen from the
    camera centre C (1, 3): each texel's radiance is the mean of its (one or two)
    candidates' radiance at that texel, and the texels' radiance is interpolated as for
    any map. (A candidate's whole render weighted by its interpolated share would mix a
    texel's model with its neighbour's parameters: next to a texel that kept its lobe, a
    diffuse texel's share would draw that neighbour's mean radiance.) One candidate at a
    time, over every pixel: a best map's candidates may be read from their files when
    used (:class:`parammap.stores.params.ParamMapFiles`), and a lab map's nine are
    gigabytes together."""
    parts = pm.parts or {}
    T, S = pm.shape
    shares = best_shares(pm.params, len(parts))
    acc = np.zeros((len(points), 3))
    for j, name in enumerate(parts):
        part = parts[name]
        for s0 in range(0, len(points), RENDER_CHUNK):
            Pi = points[s0:s0 + RENDER_CHUNK]
            row, col = plane_to_texel(Pi[:, 0], Pi[:, 1], S, T, pm.width_mm, pm.height_mm)
            if interpolation == "nearest":
                idx = [(np.clip(row.astype(int), 0, T - 1), np.clip(col.astype(int), 0, S - 1))]
                wts = [np.ones(len(row))]
            else:
                idx, wts = bilinear_corners((T, S), row, col)
            d = unit(C - Pi)
            a = acc[s0:s0 + RENDER_CHUNK]
            for (r, c), w in zip(idx, wts, strict=True):
                wj = w * shares[r, c, j]
                on = wj > 0
                if on.any():
                    a[on] += wj[on, None] * np.nan_to_num(
                        evaluate(part.model, part.params[r[on], c[on]], d[on], Pi[on],
                                 part.lights))
        del part
    return acc


def reproject_frame(frame: np.ndarray, intr: Intrinsics, R_src: np.ndarray,
                    t_src: np.ndarray, points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sample another view's frame (H', W', 3) at surface points (H, W, 3): the
    nearest-captured-view baseline (004 ch. 3.5). NaN where the point falls outside it."""
    out = np.full(points.shape[:2] + (3,), np.nan, np.float32)
    flat = np.flatnonzero(mask)
    pf, of = points.reshape(-1, 3), out.reshape(-1, 3)
    frame = np.asarray(frame, np.float32)
    for s0 in range(0, len(flat), RENDER_CHUNK):
        at = flat[s0:s0 + RENDER_CHUNK]
        uv = project_points(pf[at], intr.K, intr.dist, R_src, t_src)
        of[at] = sample_image(frame, uv[:, 0], uv[:, 1])
    return out
