"""Conventions every stage shares (``../shared/docs/conventions.md``), spelled out once.

Fitters, renderer, EXR code, figures and viewer read these names instead of repeating
the numbers.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

__all__ = ["HDR_CHANNELS", "LUMINANCE", "NOISE_CHANNEL", "FitStatus"]

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
LUMINANCE.setflags(write=False)

#: Channels of a merged HDR frame (``hdr/<view>.exr``): radiance, the masks, and the
#: relative noise sd per pixel that the fits weigh observations by.
NOISE_CHANNEL = "noise"
HDR_CHANNELS = ("R", "G", "B", "saturated", "dark", NOISE_CHANNEL)


class FitStatus(IntEnum):
    """Per-texel status codes of every fit store (``status`` array, int8)."""

    NOT_FITTED = 0
    OK = 1
    TOO_FEW = 2  # fewer observations than the model needs
    FAILED = 3  # the optimisation or projection failed; parameters are NaN
