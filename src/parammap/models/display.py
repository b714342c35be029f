"""How radiance is shown when renders are compared with photos (000 ch. 6, 004 ch.
7.3.2): the tone map ``1 - exp(-gamma L)`` and its gamma, chosen so that the 99th
percentile of the radiance shown maps to 0.95 (highlights stay below white)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["tone_gamma", "tone_map"]

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
