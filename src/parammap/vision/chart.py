"""Colour charts in a merged frame: OpenCV's ``mcc`` detector (``cv2.mcc``, contrib)."""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import InputError

__all__ = ["ChartError", "detect_chart"]

#: chart types the detector knows, by the capture format's name
_CHART_TYPES = {"MCC24": cv2.mcc.MCC24}


class ChartError(InputError):
    """No colour chart found where the capture says one is."""


def _display(radiance: np.ndarray) -> np.ndarray:
    """8-bit BGR for the detector: the 99th percentile to white, an sRGB-like curve
    (the detector was trained on photos, not on linear values)."""
    rgb = np.asarray(radiance, np.float32)
    p99 = float(np.percentile(rgb, 99)) if rgb.size else 1.0
    disp = np.clip(rgb / max(p99, 1e-12), 0.0, 1.0) ** (1 / 2.2)
    return np.ascontiguousarray((255 * disp).round().astype(np.uint8)[..., ::-1])


def detect_chart(radiance: np.ndarray, chart: str = "MCC24", source: str = "frame",
                 ) -> tuple[np.ndarray, float]:
    """The patches of the best colour chart in a frame.

    Parameters
    ----------
    radiance : (H, W, 3) linear RGB.
    chart : the chart type (``MCC24``: the 24-patch ColorChecker Classic).
    source : what the frame is, for the error message.

    Returns
    -------
    polygons : (N, 4, 2) pixel corners of the central part of each patch, in the
        chart's reference order (dark skin first for MCC24).
    cost : the detector's fit cost (lower is better).

    Raises
    ------
    ChartError
        When no chart is found.
    """
    det = cv2.mcc.CCheckerDetector.create()
    det.setColorChartType(_CHART_TYPES[chart])
    if not det.process(_display(radiance), 1):
        raise ChartError(f"{source}: no {chart} colour chart found")
    best = det.getBestColorChecker()
    pts = np.asarray(best.getColorCharts(), float).reshape(-1, 4, 2)
    return pts, float(best.getCost())
