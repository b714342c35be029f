"""How radiance is shown when renders are compared with photos (000 ch. 6, 004 ch.
7.3.2): the tone map ``1 - exp(-gamma L)`` and its gamma, chosen so that the 99th
percentile of the radiance shown maps to 0.95 (highlights stay below white)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["display_weights", "tone_gamma", "tone_map"]

TONE_CHUNK = 1 << 20  # values tone-mapped at once


def tone_gamma(values: np.ndarray) -> float:
    """``gamma = ln 20 / p99`` of the radiance ``values`` (1/radiance units)."""
    values = np.asarray(values)
    p99 = float(np.percentile(values, 99)) if values.size else 1.0
    return math.log(20.0) / max(p99, 1e-12)


def tone_map(radiance: np.ndarray, gamma: float) -> np.ndarray:
    """``1 - exp(-gamma L)`` (000 ch. 6, 004 ch. 7.3.2) as 8-bit (NaN -> 0), any shape;
    made a chunk of values at a time (a 12 MP frame's float64 temporaries would be
    gigabytes)."""
    r = np.asarray(radiance)
    out = np.empty(r.shape, np.uint8)
    src, dst = r.reshape(-1), out.reshape(-1)
    for s0 in range(0, src.size, TONE_CHUNK):
        x = 1 - np.exp(-gamma * np.nan_to_num(src[s0:s0 + TONE_CHUNK].astype(float), nan=0.0))
        dst[s0:s0 + TONE_CHUNK] = np.clip(np.round(255 * x), 0, 255)
    return out


def display_weights(radiance: np.ndarray, gamma: float,
                    fitted: np.ndarray | None = None) -> np.ndarray:
    """Per-observation weights that turn a least-squares fit of radiance into one of
    the values shown, ``t(L) = 1 - exp(-gamma L)``: the squared slope of the tone map
    between each observation y and the fit's value f there (the secant, so that
    ``slope^2 (f - y)^2 = (t(f) - t(y))^2`` exactly and a fit reweighted until it stops
    moving minimises the shown error; the derivative at y where no fit is given),
    averaged over the channels and scaled so that each texel's largest weight is 1.

    Parameters
    ----------
    radiance : (B, N, 3) observations y (relative linear radiance, >= 0).
    gamma : the tone map's gamma (1/radiance units, :func:`tone_gamma`).
    fitted : (B, N, 3) the fit's radiance f at the same views (negative values are
        shown as 0), or None.

    Returns
    -------
    (B, N) weights in [0, 1].
    """
    y = np.maximum(np.asarray(radiance, float), 0.0)
    f = y if fitted is None else np.maximum(np.asarray(fitted, float), 0.0)
    d = gamma * np.abs(f - y)
    # log of the secant slope gamma e^(-gamma min) (1 - e^-d) / d: finite where the
    # weights themselves underflow (a texel whose every view is bright)
    log_ratio = np.log(np.where(d > 1e-12, -np.expm1(-d) / np.where(d > 1e-12, d, 1.0),
                                1.0))
    log_w = 2.0 * (log_ratio - gamma * np.minimum(f, y))
    top = np.max(log_w, axis=(1, 2), keepdims=True)
    return np.exp(log_w - top).mean(-1)

