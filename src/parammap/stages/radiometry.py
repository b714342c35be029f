"""The radiometry stage: vignetting and the light's fall-off from the capture's white
card, the colour matrix from its colour chart (``camera/radiometry.json``,
``metrics/radiometry.json``; :mod:`parammap.radiometry` for the model).

The card's views and the chart's bracket are merged by the hdr stage like views; the
card's poses come from the surface markers around it, as a view's do (corners only: a
flat-field needs the texel a pixel sees, not the sub-pixel pose the maps need).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..conventions import LUMINANCE
from ..errors import InputError
from ..geometry import project_points, sample_image
from ..models.colour import (
    CHART_REFERENCES,
    chart_patch_means,
    chart_reference,
    fit_colour_matrix,
)
from ..models.radiometry import (
    Radiometry,
    field_radius2,
    fit_flatfield,
    smooth_irradiance,
    vignetting,
)
from ..stores.camera import load_intrinsics
from ..stores.capture import Capture
from ..stores.hdr import read_hdr, read_hdr_noise
from ..stores.metrics import write_metrics
from ..stores.paths import Processed
from ..stores.radiometry import write_radiometry
from ..vision.chart import detect_chart
from ..vision.markers import to_gray8
from ..vision.pose import estimate_pose

logger = logging.getLogger(__name__)

__all__ = ["card_samples", "run_radiometry"]

#: sample points per cell side: several reads per cell and view average the card's
#: own texture and the frame's noise
SAMPLES_PER_CELL = 4
#: at least this many card views with a pose: one view cannot separate the lens's
#: fall-off from the light's (each cell seen at one field angle only)
MIN_CARD_VIEWS = 2


def grid_shape(cap: Capture, cells: int) -> tuple[int, int]:
    """(ny, nx) cells of the irradiance grid: ``cells`` along the longer side, square
    cells as near as whole numbers allow."""
    side = max(cap.width_mm, cap.height_mm)
    return (max(2, round(cells * cap.height_mm / side)), max(2, round(cells * cap.width_mm / side)))


def _marker_free(cap: Capture, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Points off every surface marker (with a tenth of its size around it)."""
    ok = np.ones(x.shape, bool)
    for c in cap.marker_corners:
        lo, hi = c.min(0), c.max(0)
        pad = 0.1 * (hi - lo)
        ok &= ~((x >= lo[0] - pad[0]) & (x <= hi[0] + pad[0]) & (y >= lo[1] - pad[1])
                & (y <= hi[1] + pad[1]))
    return ok


def card_samples(cap: Capture, intr, radiance: np.ndarray, saturated: np.ndarray,
                 dark: np.ndarray, R: np.ndarray, t: np.ndarray, shape: tuple[int, int],
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reads of one card frame on a grid of surface points.

    Returns
    -------
    cell : (n,) flat index of each read's cell in the ``shape`` (ny, nx) grid (row 0 at
        y = height); rho2 : (n,) its squared field radius; log_y : (n,) ln luminance.
    """
    ny, nx = shape
    k = SAMPLES_PER_CELL
    fy = (np.arange(ny * k) + 0.5) / (ny * k)
    fx = (np.arange(nx * k) + 0.5) / (nx * k)
    X, Y = np.meshgrid(fx * cap.width_mm, cap.height_mm * (1 - fy))
    cell = (np.arange(ny * k)[:, None] // k) * nx + np.arange(nx * k)[None, :] // k
    P = np.stack([X, Y, np.zeros_like(X)], -1).reshape(-1, 3)
    uv = project_points(P, intr.K, intr.dist, R, t)
    H, W = radiance.shape[:2]
    lum = (radiance @ LUMINANCE).astype(np.float32)
    y = sample_image(lum, uv[:, 0], uv[:, 1]).ravel()
    bad = sample_image((saturated | dark).astype(np.uint8), uv[:, 0], uv[:, 1],
                       nearest=True, border=1).ravel() > 0
    depth = (P @ R.T + t)[:, 2]
    ok = (np.isfinite(y) & (y > 0) & ~bad & (depth > 0) & (uv[:, 0] >= 0)
          & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
          & _marker_free(cap, P[:, 0], P[:, 1]))
    return (cell.ravel()[ok], field_radius2(uv[ok, 0], uv[ok, 1], intr),
            np.log(y[ok]).astype(float))


def _flatfield(cap: Capture, proc: Processed, intr, cfg: dict) -> tuple[dict, dict]:
    """The vignetting and irradiance grid from the card's frames, and their record."""
    shape = grid_shape(cap, cfg["cells"])
    cells, rho2s, logs, used, dropped = [], [], [], [], {}
    for v in cap.flatfield:
        rad, sat, dark = read_hdr(proc.hdr(v.id))
        pose = estimate_pose(cap, intr, to_gray8(rad))
        if not pose["ok"]:
            dropped[v.id] = pose["reason"]
            logger.warning(f"radiometry: card view {v.id} left out: {pose['reason']}")
            continue
        c, r2, ly = card_samples(cap, intr, rad, sat, dark, pose["R"], pose["t"], shape)
        cells.append(c)
        rho2s.append(r2)
        logs.append(ly)
        used.append(v.id)
    if len(used) < MIN_CARD_VIEWS:
        raise InputError(f"{cap.root / 'capture.yaml'}: flatfield: {len(used)} card view(s) "
                         f"with a pose, at least {MIN_CARD_VIEWS} needed to separate the "
                         f"lens's fall-off from the light's ({dropped or 'none listed'})")
    coeffs, log_g, stats = fit_flatfield(np.concatenate(cells), np.concatenate(rho2s),
                                         np.concatenate(logs), shape[0] * shape[1])
    cells_all = np.concatenate(cells)
    counts = np.bincount(cells_all, minlength=shape[0] * shape[1]).reshape(shape)
    log_smooth, degree = smooth_irradiance(log_g.reshape(shape), counts)
    grid = np.exp(log_smooth)
    stats["irradiance_degree"] = degree
    seen = np.isfinite(log_g)
    stats["irradiance_cell_rms"] = float(np.sqrt(np.mean(
        (log_g[seen] - log_smooth.ravel()[seen]) ** 2)))
    edge = float(vignetting(np.array(stats["field_max"]), coeffs))
    # the card's luminance where the relative irradiance is 1, over its stated
    # reflectance: the light's absolute irradiance (a Lambertian card, L = rho E / pi)
    scale = None
    if cap.card_reflectance is not None:
        scale = math.pi * stats["level"] / float(np.asarray(cap.card_reflectance) @ LUMINANCE)
        stats["card_reflectance"] = list(cap.card_reflectance)
        stats["irradiance_scale"] = scale
    rec = {"card_views": used, "card_views_left_out": dropped, "grid": list(shape),
           "vignetting_at_field_max": 1 - edge, "irradiance_min": float(grid.min()),
           "irradiance_max": float(grid.max()), **stats}
    logger.info(f"radiometry: vignetting {100 * (1 - edge):.1f} % at the widest field the "
                f"card covered (rho {np.sqrt(stats['field_max']):.2f}), "
                f"light {grid.min():.3f}-{grid.max():.3f} of its mean over the surface "
                f"(degree {degree}; cells {stats['irradiance_cell_rms']:.4f} about it in ln), "
                f"{len(used)} card views, residual {stats['residual_rms']:.4f} in ln")
    if scale is not None:
        logger.info(f"radiometry: the card's stated reflectance makes the light's "
                    f"irradiance absolute: {scale:.5g} (radiance units) on average")
    return {"vignetting": coeffs, "field_max": stats["field_max"],
            "irradiance": grid if cfg["light_falloff"] else None,
            "irradiance_scale": scale}, rec


def _colour(cap: Capture, proc: Processed, cfg: dict, lens: tuple | None,
            ) -> tuple[np.ndarray, dict]:
    """The colour matrix from the chart's frame, and its record. ``lens``: (intrinsics,
    vignetting coefficients, field_max) when the card measured the lens, whose
    fall-off is divided out of the chart's frame first (a patch at the frame's edge
    would read darker than its colour)."""
    rad, sat, _, noise = read_hdr_noise(proc.hdr(cap.chart.id))
    if lens is not None:
        intr, coeffs, field_max = lens
        H, W = rad.shape[:2]
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        rad = rad / vignetting(field_radius2(u, v, intr), coeffs,
                               field_max).astype(np.float32)[..., None]
    # one pixel's relative noise, as the merge recorded it (the correction is judged on
    # noisy copies of the patches: it is applied to pixels, not to the patches' means)
    sigma = float(np.nanmedian(noise[~sat])) if noise is not None and (~sat).any() else 0.0
    polygons, cost = detect_chart(rad, cap.chart_type, str(proc.hdr(cap.chart.id)))
    ref_name = cap.chart_reference or CHART_REFERENCES[cap.chart_type]
    ref = chart_reference(ref_name, cfg["colour_space"])
    best = None
    # the detector's order, or the chart upside down: the one the matrix fits best
    for order in (np.arange(len(polygons)), np.arange(len(polygons))[::-1]):
        means, ok = chart_patch_means(rad, sat, polygons[order])
        if ok.sum() < 12 or not ref.neutral[ok].any():
            continue
        M, st = fit_colour_matrix(means[ok], ref.rgb[ok], ref.lab[ok], ref.to_lab,
                                  ref.neutral[ok], cfg["colour_model"], sigma)
        if best is None or st["delta_e_mean"] < best[1]["delta_e_mean"]:
            best = (M, st, ok)
    if best is None:
        raise InputError(f"{proc.hdr(cap.chart.id)}: too few unsaturated chart patches")
    M, st, ok = best
    rec = {"chart": cap.chart_type, "reference": ref_name, "space": cfg["colour_space"],
           "detector_cost": cost, "patches": int(ok.sum()), "pixel_noise": sigma,
           "vignetting_divided_out": lens is not None,
           "patches_left_out": [ref.names[i] for i in np.flatnonzero(~ok)], **st}
    logger.info(f"radiometry: {cfg['colour_model']} colour correction to "
                f"{cfg['colour_space']} from {int(ok.sum())} patches, mean CIEDE2000 "
                f"{st['delta_e_mean']:.2f} (each left out in turn {st['delta_e_loo_mean']:.2f})")
    return M, rec


def run_radiometry(cap: Capture, processed: str | Path, config: dict[str, Any]) -> dict:
    """The radiometry stage: ``camera/radiometry.json`` and ``metrics/radiometry.json``
    from the card's and the chart's merged frames (the identity when the capture has
    neither, or the config turns them off); ``config`` section ``radiometry``."""
    cfg = config["radiometry"]
    proc = Processed(processed)
    parts: dict[str, Any] = {}
    info: dict[str, Any] = {}
    if cap.flatfield and cfg["flatfield"]:
        intr = load_intrinsics(proc.intrinsics)
        parts, info["flatfield"] = _flatfield(cap, proc, intr, cfg)
    if cap.chart and cfg["colour"]:
        lens = ((load_intrinsics(proc.intrinsics), parts["vignetting"], parts["field_max"])
                if parts.get("vignetting") is not None else None)
        parts["colour_matrix"], info["colour"] = _colour(cap, proc, cfg, lens)
        parts["colour_space"] = cfg["colour_space"]
        parts["colour_model"] = cfg["colour_model"]
    rad = Radiometry(**parts)
    if rad.identity:
        logger.info("radiometry: no white card or colour chart; frames are read as merged")
    write_radiometry(proc.radiometry, rad, info)
    write_metrics(proc.metrics("radiometry"), info)
    return info
