"""Observation weights from the expected noise of each observation.

The HDR merge records each pixel's relative noise sd (:func:`parammap.stages.hdr.merge_noise`:
how many exposures saw it and at which levels of the response); the observation map
averages it over the texel's footprint. Fits weigh an
observation by ``1 / sd^2`` of that relative sd, normalised to a mean of 1 over the
texel's valid observations (so residual sums keep their scale, and BIC its meaning),
and bounded to ``[1 / MAX_RATIO, MAX_RATIO]`` of the texel's median so that no single
view dominates a fit.

Brightness is left out of the weights on purpose: the absolute sd is the relative sd
times the radiance, but weights ``1 / L^2`` from the observed radiance bias every fit
toward its darker observations (the classic bias of relative-error weighting); the
chi-square below uses the model's radiance instead.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MAX_RATIO", "noise_weights", "reduced_chi2"]

MAX_RATIO = 10.0


def noise_weights(noise: np.ndarray | None, valid: np.ndarray) -> np.ndarray:
    """(B, N) weights of the valid observations (0 elsewhere).

    Parameters
    ----------
    noise : (B, N) relative sd per observation, NaN where unknown; None: all equal.
    valid : (B, N) bool.
    """
    valid = np.asarray(valid, bool)
    w = valid.astype(float)
    if noise is None:
        return w
    sd = np.where(valid, np.asarray(noise, float), np.nan)
    known = np.isfinite(sd) & (sd > 0)
    rows = known.sum(1) == valid.sum(1)  # texels whose every observation has an sd
    rows &= valid.any(1)
    if not rows.any():
        return w
    inv = np.where(known, 1.0 / np.where(known, sd, 1.0) ** 2, np.nan)[rows]
    med = np.nanmedian(inv, axis=1, keepdims=True)
    inv = np.clip(inv, med / MAX_RATIO, med * MAX_RATIO)
    inv = np.where(valid[rows], inv, 0.0)
    inv /= inv.sum(1, keepdims=True) / valid[rows].sum(1, keepdims=True)
    w[rows] = inv
    return w


def reduced_chi2(radiance: np.ndarray, fitted: np.ndarray, noise: np.ndarray | None,
                 valid: np.ndarray, n_params: int | np.ndarray) -> np.ndarray:
    """(B,) chi-square per degree of freedom of each texel's fit: residuals over the
    expected sd (relative sd x the model's radiance, per channel, floored at 1 % of
    the texel's mean so that black channels do not divide by zero). NaN where the
    noise is unknown or there are no degrees of freedom.

    radiance, fitted : (B, N, 3); noise : (B, N); valid : (B, N) bool; n_params : the
    fitted parameters per texel (all channels), one number or (B,).
    """
    B = radiance.shape[0]
    if noise is None:
        return np.full(B, np.nan)
    valid = np.asarray(valid, bool)
    sd_rel = np.where(valid, np.asarray(noise, float), np.nan)
    scale = np.nanmean(np.where(valid[..., None], np.abs(fitted), np.nan), axis=(1, 2))
    level = np.maximum(np.abs(fitted), 0.01 * scale[:, None, None])
    with np.errstate(divide="ignore", invalid="ignore"):  # a black texel: NaN, below
        z2 = ((radiance - fitted) / (sd_rel[..., None] * level)) ** 2
    z2 = np.where(valid[..., None], z2, 0.0)
    dof = 3 * valid.sum(1) - np.asarray(n_params)
    known = np.isfinite(z2).all((1, 2)) & (dof > 0)
    out = np.full(B, np.nan)
    out[known] = z2[known].sum((1, 2)) / dof[known]
    return out
