"""Residual metrics shared by every model's fit (004's mean percentage residual)."""

from __future__ import annotations

import numpy as np

__all__ = ["mean_percentage_residual"]


def mean_percentage_residual(measured: np.ndarray, fitted: np.ndarray,
                             valid: np.ndarray | None = None) -> np.ndarray:
    """004's mean percentage residual per channel: mean of ``100 |fit - meas| / meas``
    over valid observations. (..., N, 3) inputs, (..., 3) output."""
    meas = np.asarray(measured, float)
    den = np.maximum(np.abs(meas), 1e-9 * np.nanmax(np.abs(meas), axis=-2, keepdims=True)
                     + 1e-30)
    pct = 100 * np.abs(np.asarray(fitted, float) - meas) / den
    if valid is None:
        return pct.mean(axis=-2)
    w = np.asarray(valid, float)[..., None]
    return (np.where(w > 0, pct, 0)).sum(-2) / np.maximum(w.sum(-2), 1)
