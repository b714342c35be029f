"""A colour chart as a camera sees it under a tinted light: the patches' measured
spectral reflectances times a light's spectrum through a real camera's spectral
sensitivities (colour-science's data), so no 3 x 3 matrix maps it back exactly (as
with a real camera, whose sensitivities are not a linear transform of the eye's)."""

from __future__ import annotations

import colour
import numpy as np

from ..models.colour import chart_reference

__all__ = ["CHART_LAYOUT_MM", "chart_camera_rgb", "chart_shade", "chart_size_mm"]

#: the ColorChecker Classic's layout: 6 x 4 patches, patch, gap and border (mm)
CHART_LAYOUT_MM = {"columns": 6, "rows": 4, "patch": 40.0, "gap": 5.0, "border": 10.0}
#: the analytic generator's RGB camera (no spectra: linear sRGB under a white light)
SRGB_CAMERA = "srgb"
#: spectral data that go with each reference (colour-science's names)
_SPECTRA = {"BabelColor Average": "BabelColor Average"}
_SHAPE = colour.SpectralShape(400, 700, 10)


def chart_size_mm() -> tuple[float, float]:
    """(width, height) of the chart (mm)."""
    L = CHART_LAYOUT_MM
    return (2 * L["border"] + L["columns"] * L["patch"] + (L["columns"] - 1) * L["gap"],
            2 * L["border"] + L["rows"] * L["patch"] + (L["rows"] - 1) * L["gap"])


def chart_camera_rgb(camera: str, light: str, reference: str = "BabelColor Average",
                     ) -> np.ndarray:
    """(24, 3) linear camera RGB of the chart's patches, the white patch's largest
    channel 1: reflectance x light x the camera's sensitivities, summed over 400-700 nm.

    camera : a name in ``colour.MSDS_CAMERA_SENSITIVITIES`` (e.g. ``Nikon 5100 (NPL)``),
        or ``srgb``: the analytic generator's own camera, whose RGB is linear sRGB under
        a white light (the chart's reference colours; ``light`` unused), consistent with
        the colours of that generator's surfaces.
    light : a name in ``colour.SDS_ILLUMINANTS`` (``A``: tungsten, ``FL2``...).
    reference : the chart data whose spectra are rendered.
    """
    if camera == SRGB_CAMERA:
        rgb = np.clip(chart_reference(reference).rgb, 0.0, None)
        return rgb / rgb[18].max()
    sds = colour.SDS_COLOURCHECKERS[_SPECTRA[reference]]
    refl = np.array([sds[n].copy().align(_SHAPE).values for n in chart_reference(reference).names])
    ill = colour.SDS_ILLUMINANTS[light].copy().align(_SHAPE).values
    cam = colour.MSDS_CAMERA_SENSITIVITIES[camera].copy().align(_SHAPE).values
    rgb = (refl * ill) @ cam
    return rgb / rgb[18].max()


def chart_shade(rgb: np.ndarray, origin_mm: tuple[float, float], scale: float,
                background: np.ndarray):
    """A shading function for :func:`parammap.synth.generate.render_radiance`: the chart
    (patch colours ``rgb`` (24, 3), black frame) with its top-left corner at
    ``origin_mm`` on the plane, ``scale`` plane mm per chart mm, ``background`` (3,)
    radiance around it. Patch 0 top left, reading order (the chart's own)."""
    L = CHART_LAYOUT_MM
    w, h = chart_size_mm()
    pitch = L["patch"] + L["gap"]
    black = 0.03 * rgb[18]

    def shade(P: np.ndarray, C: np.ndarray) -> np.ndarray:
        x = (P[:, 0] - origin_mm[0]) / scale
        y = (origin_mm[1] - P[:, 1]) / scale  # down the chart from its top edge
        out = np.tile(np.asarray(background, float), (len(P), 1))
        on = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        out[on] = black
        cx, cy = (x - L["border"]) / pitch, (y - L["border"]) / pitch
        col, row = np.floor(cx).astype(int), np.floor(cy).astype(int)
        inpatch = (on & (col >= 0) & (col < L["columns"]) & (row >= 0) & (row < L["rows"])
                   & ((cx - col) * pitch < L["patch"]) & ((cy - row) * pitch < L["patch"]))
        out[inpatch] = rgb[row[inpatch] * L["columns"] + col[inpatch]]
        return out

    return shade
