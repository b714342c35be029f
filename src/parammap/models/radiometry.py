"""Flat-field and colour: the lens's vignetting, the light's fall-off over the surface and
the camera's colour, measured from a white card and a colour chart and divided out of
every frame (``docs/models.md``, section "Flat-field and colour").

A frame's radiance at pixel ``p`` that sees surface point ``x`` is taken as

    L_frame(p) = V(p) G(x) M^-1 L(x)

- ``V`` the vignetting, a function of the field angle only:
  ``ln V = sum_k b_k rho^(2k)``, ``rho^2 = ((u - cx)/fx)^2 + ((v - cy)/fy)^2``,
  ``V = 1`` on the optical axis;
- ``G`` the relative irradiance of the surface (mean 1 over it): the lights' fall-off
  and cosine, measured on the card, which a model without lights would otherwise fold
  into each texel's albedo;
- ``M`` the colour correction from the camera's RGB to a scene-linear space (linear
  sRGB / Rec.709 or ACEScg): a matrix on the RGB's terms (:func:`colour_terms`),
  fitted on a chart (:mod:`parammap.models.colour`), scaled to keep the neutral
  patches' luminance (the exposure's scale is the merge's, not the chart's).

The card is Lambertian and lies where the surface lies, so in every view a point's
radiance is ``V(p) G(x)`` up to one constant: with the card seen from several places
the two separate (each surface cell is seen at several field angles), a linear
least-squares problem in ``ln`` with one free level per cell (:func:`fit_flatfield`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import Intrinsics, pixel_to_plane

__all__ = ["COLOUR_INTEROP_IDS", "COLOUR_MODELS", "RADIOMETRY_KEYS", "VIGNETTING_TERMS",
           "IrradianceGrid", "Radiometry", "apply_colour", "colour_terms", "correct_frame",
           "describe_radiometry", "field_radius2", "fit_flatfield",
           "frame_gain", "irradiance_at", "smooth_irradiance", "vignetting"]

#: terms of the vignetting polynomial ``ln V = sum_k b_k rho^(2k)`` (rho^2, rho^4, rho^6)
VIGNETTING_TERMS = 3
#: colour corrections: the root-polynomial of Finlayson, Mackiewicz & Hurlbert (2015),
#: degree 2, is exposure-invariant like a 3 x 3 matrix and follows a camera whose
#: sensitivities are not a linear transform of the eye's (``docs/models.md`` gives the
#: measured difference); ``linear`` is the plain 3 x 3
COLOUR_MODELS = ("root-polynomial", "linear")
#: the OpenEXR ``colorInteropID`` (the Color Interop Forum's name) of each scene-linear
#: space a colour correction maps to (:data:`parammap.models.colour.COLOUR_SPACES`),
#: which an EXR of radiance in it carries so that other tools know its primaries
COLOUR_INTEROP_IDS = {"srgb-linear": "lin_rec709_scene", "acescg": "lin_ap1_scene"}
#: the keys of :func:`describe_radiometry`, which headers and attributes carry
RADIOMETRY_KEYS = ("flatfield", "colour", "colour_space")
#: pixels whose colour terms are made at once (their memory, not the frame's)
COLOUR_STRIP = 1 << 20
#: the gain is evaluated every GAIN_STRIDE pixels and interpolated between: the
#: vignetting and the light's fall-off are smooth over far more than that
GAIN_STRIDE = 8


@dataclass
class Radiometry:
    """What divides out of every frame; None for a part not measured.

    vignetting : (VIGNETTING_TERMS,) coefficients ``b_k`` of ``ln V``.
    field_max : the largest squared field radius ``rho^2`` the card was seen at; the
        vignetting is held at its value there beyond (a polynomial is not extrapolated).
    irradiance : (ny, nx) relative irradiance G at the centres of a regular grid of
        cells over the surface (row 0 at y = height, as texel rows), mean 1.
    colour_matrix : (3, n) camera RGB -> ``colour_space`` on the terms of
        ``colour_model`` (:func:`parammap.radiometry.apply_colour`).
    colour_space : name of the scene-linear space of the matrix.
    colour_model : ``linear`` (3 x 3) or ``root-polynomial`` (3 x 6).
    irradiance_scale : ``pi L / rho`` of a white card of stated reflectance ``rho``
        where ``irradiance`` is 1 (its mean over the surface): the lights' absolute
        irradiance there, in the merged frames' radiance units (luminance). Nothing
        divides by it; it gives a relightable map's albedo its scale
        (:func:`parammap.models.svbrdf.card_scale`).
    """

    vignetting: np.ndarray | None = None
    irradiance: np.ndarray | None = None
    colour_matrix: np.ndarray | None = None
    colour_space: str | None = None
    field_max: float | None = None
    colour_model: str | None = None
    irradiance_scale: float | None = None

    @property
    def identity(self) -> bool:
        """Nothing measured: frames are read as merged."""
        return (self.vignetting is None and self.irradiance is None
                and self.colour_matrix is None)


def describe_radiometry(rad: Radiometry) -> dict[str, str]:
    """What a correction divided out of the radiance, in words, for the headers and
    attributes of what is made from corrected frames: ``flatfield``, ``colour`` and,
    where a colour matrix was applied, ``colour_space`` (its scene-linear space's name).
    """
    parts = []
    if rad.vignetting is not None:
        parts.append(f"lens vignetting ({VIGNETTING_TERMS} terms in rho^2, held beyond "
                     f"rho^2 = {rad.field_max:.4g})")
    if rad.irradiance is not None:
        ny, nx = np.shape(rad.irradiance)
        parts.append(f"light irradiance over the surface ({ny} x {nx} grid, mean 1)")
    out = {"flatfield": " and ".join(parts) + " divided out (white card)" if parts
           else "none (no white card, or the flat-field turned off)"}
    if rad.colour_matrix is None:
        out["colour"] = "camera RGB (no colour chart, or the colour turned off)"
    else:
        out["colour"] = (f"scene-linear {rad.colour_space} via a {rad.colour_model} "
                         "colour correction (colour chart)")
        out["colour_space"] = str(rad.colour_space)
    return out


@dataclass(frozen=True)
class IrradianceGrid:
    """The relative irradiance of a surface (:attr:`Radiometry.irradiance`) as a
    function of surface points: what a frame read through :func:`correct_frame` was
    divided by, which a model with its own lights puts back."""

    grid: np.ndarray  # (ny, nx), row 0 at y = height
    width_mm: float
    height_mm: float

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """G at surface points (..., 3) or (..., 2) mm -> (...)."""
        p = np.asarray(points, float)
        return irradiance_at(p[..., 0], p[..., 1], np.asarray(self.grid, float),
                             self.width_mm, self.height_mm)


def field_radius2(u: np.ndarray, v: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Squared field radius ``rho^2`` (tangent of the field angle, squared, before the
    lens's distortion) of pixel coordinates; same shape as ``u``."""
    K = intr.K
    return ((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2


def _powers(rho2: np.ndarray) -> np.ndarray:
    """(..., VIGNETTING_TERMS) rho^2, rho^4, rho^6."""
    return np.stack([rho2 ** (k + 1) for k in range(VIGNETTING_TERMS)], -1)


def vignetting(rho2: np.ndarray, coeffs: np.ndarray, field_max: float = np.inf) -> np.ndarray:
    """Relative illumination ``V`` (1 on the axis) at squared field radii ``rho2``,
    held at its ``field_max`` value beyond it."""
    return np.exp(_powers(np.minimum(rho2, field_max)) @ np.asarray(coeffs, float))


def fit_flatfield(cell: np.ndarray, rho2: np.ndarray, log_y: np.ndarray, n_cells: int,
                  ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Vignetting and per-cell irradiance from card samples.

    Parameters
    ----------
    cell : (N,) int surface cell of each sample; rho2 : (N,) its squared field radius;
    log_y : (N,) ln of its luminance (any scale); n_cells : number of cells.

    Returns
    -------
    coeffs : (VIGNETTING_TERMS,) ``ln V`` coefficients.
    log_g : (n_cells,) ``ln G`` per cell (NaN where no sample), mean 0 over the
        cells seen.
    stats : ``level``, the luminance ``exp(ln G)`` was divided by (the card's mean
        over the cells seen, vignetting divided out, in ``log_y``'s units),
        ``residual_rms`` (ln units), ``coeff_sd`` (their standard errors), ``samples``,
        ``cells``.

    Notes
    -----
    Fixed effects: each cell's own mean is removed from ``ln y`` and from the powers of
    ``rho^2``, so the vignetting is estimated only from how a cell's brightness changes
    with where it falls in the frame, whatever the light does across the surface.
    """
    X = _powers(rho2)
    counts = np.bincount(cell, minlength=n_cells).astype(float)
    seen = counts > 0

    def demean(a: np.ndarray) -> np.ndarray:
        if a.ndim == 1:
            return a - (np.bincount(cell, a, n_cells) / np.maximum(counts, 1))[cell]
        return np.stack([demean(a[:, k]) for k in range(a.shape[1])], -1)

    Xd, yd = demean(X), demean(log_y)
    n = len(yd)
    best = None
    # as many terms as the field the card covered supports (BIC): a card seen only near
    # the axis pins rho^2 and leaves rho^6 to the noise
    for k in range(1, VIGNETTING_TERMS + 1):
        ck, *_ = np.linalg.lstsq(Xd[:, :k], yd, rcond=None)
        res = yd - Xd[:, :k] @ ck
        dof = max(n - int(seen.sum()) - k, 1)
        s2 = float(res @ res) / dof
        bic = n * np.log(max(s2, 1e-300)) + k * np.log(n)
        if best is None or bic < best[0]:
            best = (bic, k, ck, s2)
    _, k, ck, s2 = best
    coeffs = np.zeros(VIGNETTING_TERMS)
    coeffs[:k] = ck
    cov = s2 * np.linalg.pinv(Xd[:, :k].T @ Xd[:, :k])
    log_g = np.full(n_cells, np.nan)
    log_g[seen] = (np.bincount(cell, log_y - X @ coeffs, n_cells) / np.maximum(counts, 1))[seen]
    level = float(np.mean(np.exp(log_g[seen])))
    log_g -= np.log(level)
    return coeffs, log_g, {"level": level, "residual_rms": float(np.sqrt(s2)), "terms": k,
                           "coeff_sd": np.sqrt(np.diag(cov)).tolist(),
                           "field_max": float(rho2.max()),
                           "samples": int(len(yd)), "cells": int(seen.sum())}


#: highest total degree of the polynomial the card's irradiance is smoothed with
MAX_IRRADIANCE_DEGREE = 8


def smooth_irradiance(log_g: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, int]:
    """The card's per-cell ``ln G`` (ny, nx) (NaN where unseen) as a smooth surface: a
    polynomial in the cell's position of the total degree (1 to
    ``MAX_IRRADIANCE_DEGREE``) that BIC prefers, fitted with each cell weighed by its
    reads ``counts`` (ny, nx). A light's irradiance is smooth over the surface (over its
    own distance), while each cell's level carries its reads' noise (on a Monte Carlo
    render, 1 % a cell); the polynomial keeps the one and averages out the other, and
    fills cells no view saw. Returns the smoothed ``ln G`` (mean of ``G`` 1) and the
    degree."""
    ny, nx = log_g.shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    u, v = (2 * xx + 1) / nx - 1, (2 * yy + 1) / ny - 1
    seen = np.isfinite(log_g) & (counts > 0)
    w = np.sqrt(counts[seen] / counts[seen].mean())
    n = int(seen.sum())
    best = None
    for deg in range(1, MAX_IRRADIANCE_DEGREE + 1):
        basis = np.stack([u ** i * v ** j for i in range(deg + 1) for j in range(deg + 1 - i)],
                         -1)
        k = basis.shape[-1]
        if k >= n:
            break
        c, *_ = np.linalg.lstsq(basis[seen] * w[:, None], log_g[seen] * w, rcond=None)
        rss = float(np.sum((w * (log_g[seen] - basis[seen] @ c)) ** 2))
        bic = n * np.log(max(rss / n, 1e-300)) + k * np.log(n)
        if best is None or bic < best[0]:
            best = (bic, deg, basis @ c)
    _, deg, smooth = best
    return smooth - np.log(np.mean(np.exp(smooth))), deg


def irradiance_at(x: np.ndarray, y: np.ndarray, grid: np.ndarray, width_mm: float,
                  height_mm: float) -> np.ndarray:
    """Relative irradiance ``G`` at surface points (mm), bilinear between the grid's
    cell centres, constant beyond the outer centres (and off the surface)."""
    grid = np.asarray(grid, float)
    ny, nx = grid.shape
    # fractional cell indices of the points (row 0 at y = height, as texels)
    fx = np.clip(np.asarray(x, float) / width_mm * nx - 0.5, 0, nx - 1)
    fy = np.clip((height_mm - np.asarray(y, float)) / height_mm * ny - 0.5, 0, ny - 1)
    fx, fy = np.nan_to_num(fx), np.nan_to_num(fy)
    i0 = np.minimum(fy.astype(int), max(ny - 2, 0))
    j0 = np.minimum(fx.astype(int), max(nx - 2, 0))
    i1, j1 = np.minimum(i0 + 1, ny - 1), np.minimum(j0 + 1, nx - 1)
    ty, tx = fy - i0, fx - j0
    return ((1 - ty) * ((1 - tx) * grid[i0, j0] + tx * grid[i0, j1])
            + ty * ((1 - tx) * grid[i1, j0] + tx * grid[i1, j1]))


def frame_gain(intr: Intrinsics, R: np.ndarray, t: np.ndarray, width_mm: float,
               height_mm: float, rad: Radiometry, size: tuple[int, int] | None = None,
               ) -> np.ndarray | None:
    """(H, W) gain ``V(p) G(x(p))`` of a frame taken with pose ``R, t``; None when the
    radiometry measures neither."""
    if rad.vignetting is None and rad.irradiance is None:
        return None
    W, H = size or intr.image_size
    us = np.append(np.arange(0, W, GAIN_STRIDE), W - 1).astype(float)
    vs = np.append(np.arange(0, H, GAIN_STRIDE), H - 1).astype(float)
    u, v = np.meshgrid(us, vs)
    gain = np.ones_like(u)
    if rad.vignetting is not None:
        gain *= vignetting(field_radius2(u, v, intr), rad.vignetting, rad.field_max)
    if rad.irradiance is not None:
        P, hit = pixel_to_plane(np.stack([u, v], -1), intr.K, intr.dist, R, t)
        g = irradiance_at(P[..., 0], P[..., 1], rad.irradiance, width_mm, height_mm)
        gain *= np.where(hit, g, 1.0)
    # piecewise bilinear between the coarse points, exactly at them: two small
    # interpolation matrices, so a 24 MP frame costs its own size and no more
    return (_linear_weights(vs, H) @ gain.astype(np.float32)
            @ _linear_weights(us, W).T).astype(np.float32)


def _linear_weights(knots: np.ndarray, n: int) -> np.ndarray:
    """(n, len(knots)) float32 weights of linear interpolation at 0 .. n - 1 between
    increasing ``knots`` (the first at 0, the last at n - 1)."""
    x = np.arange(n, dtype=float)
    j = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
    f = (x - knots[j]) / (knots[j + 1] - knots[j])
    out = np.zeros((n, len(knots)), np.float32)
    out[np.arange(n), j] = 1 - f
    out[np.arange(n), j + 1] += f
    return out


def _spow_sqrt(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.sqrt(np.abs(x))


def colour_terms(rgb: np.ndarray, model: str) -> np.ndarray:
    """The terms (..., n) a colour correction of ``model`` is linear in:
    ``R, G, B`` (``linear``, n = 3), and ``sqrt(RG), sqrt(GB), sqrt(RB)`` with their
    products' signs (``root-polynomial``, degree 2 of Finlayson, Mackiewicz & Hurlbert
    2015, n = 6: each term scales with the exposure, as the RGB does)."""
    rgb = np.asarray(rgb, float)
    if model == "linear":
        return rgb
    if model != "root-polynomial":
        raise ValueError(f"unknown colour model {model!r}; one of {', '.join(COLOUR_MODELS)}")
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return np.stack([r, g, b, _spow_sqrt(r * g), _spow_sqrt(g * b), _spow_sqrt(r * b)], -1)


def apply_colour(rgb: np.ndarray, matrix: np.ndarray | None, model: str | None,
                 ) -> np.ndarray:
    """The colour correction ``matrix`` (3, n) of ``model`` applied to RGB (..., 3):
    ``matrix @ colour_terms(rgb)``; unchanged without a matrix."""
    if matrix is None:
        return rgb
    m = np.asarray(matrix, float).T
    flat = np.asarray(rgb).reshape(-1, 3)
    out = np.empty(flat.shape, rgb.dtype)
    for i in range(0, len(flat), COLOUR_STRIP):  # the terms of a strip at a time
        out[i:i + COLOUR_STRIP] = colour_terms(flat[i:i + COLOUR_STRIP], model) @ m
    return out.reshape(np.shape(rgb))


def correct_frame(radiance: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray,
                  width_mm: float, height_mm: float, rad: Radiometry | None) -> np.ndarray:
    """A merged frame (H, W, 3) with the flat-field divided out and the colour matrix
    applied: what every stage that reads radiance from a frame reads."""
    if rad is None or rad.identity:
        return radiance
    out = apply_colour(radiance, rad.colour_matrix, rad.colour_model)
    gain = frame_gain(intr, R, t, width_mm, height_mm, rad,
                      (radiance.shape[1], radiance.shape[0]))
    if gain is not None:
        out = out / gain[..., None]
    return out.astype(np.float32, copy=False)


