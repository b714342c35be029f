"""Conventions every stage shares (``../shared/docs/conventions.md``), spelled out once.

Fitters, renderer, EXR code, figures and viewer read these names instead of repeating
the numbers.
"""

from __future__ import annotations

import numpy as np

__all__ = ["HDR_CHANNELS", "LUMINANCE", "NOISE_CHANNEL"]

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
LUMINANCE.setflags(write=False)

#: Channels of a merged HDR frame (``hdr/<view>.exr``): radiance, the masks, and the
#: relative noise sd per pixel that the fits weigh observations by.
NOISE_CHANNEL = "noise"
HDR_CHANNELS = ("R", "G", "B", "saturated", "dark", NOISE_CHANNEL)
