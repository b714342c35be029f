"""The observation map: every texel seen from every kept view, in a zarr v3 store.

Layout (docs/reference/conventions.md, :mod:`parammap.stores.observation`): ``radiance``
``[T, S, N, 3]`` (log2-encoded), ``valid`` bool and ``noise`` ``[T, S, N]``, all chunked
``tile x tile x N``; the view directions (unit vectors toward the camera, surface frame)
follow from the camera centres. Held-out and dropped views never enter.

Footprint-aware sampling
------------------------
A texel usually covers several pixels (or a fraction of one). Reading the HDR frame at
the texel centre alone would alias print detail at low map resolution. Instead each
texel is supersampled on an ``s x s`` grid of points spread over the texel, with
``s = ceil(footprint)`` where footprint is the texel's largest projected edge length in
pixels in that view (capped by ``max_supersample``). The frame is read at each point
with bilinear interpolation and the points are averaged, i.e. a box filter over the
texel's footprint that follows perspective foreshortening (anisotropic footprints at
grazing views are covered by the same grid). The grid is inset from each texel edge by
the reach of a box-filtered pixel read bilinearly (``PIXEL_REACH``, 1.5 pixels: one of
interpolation support, half of the pixel's own area), per texel and per axis of its
projected footprint, so a texel at least three pixels across reads only its own surface
(half a pixel of inset left the demo's texels on material edges a blend of both sides
in every oblique view: RMSE 5x their neighbours'); a smaller texel is read at its
centre line. The view direction is the one
of the texel centre. An observation is valid when all of its points fall inside the
frame, the texel is in front of the camera, the direction's zenith is below
``max_zenith_deg``, no point is saturated in every exposure, the texel does not
overlap a surface marker. Nor is a read blended with its neighbours
(``max_blend``, 2 noise sd by default), where the photos resolve the map's texels (3 px
or more across at the median view, :func:`texel_pixels`): a grazing view foreshortens
a texel to a pixel or two across one axis and its read takes in the texels beside it;
where their differences in that view bias it, beyond the blend a frontal read from
the same distance would have, by more than ``max_blend`` noise sd
(:func:`blend_bias`: a material edge, a printed line, a marker seen edge-on), the read
is not of its texel. On the demo (texels 3.4 px across at the median view, textured
albedo): 15 % of its reads, held-out mh-auto 6.59 -> 6.40 and against the generator's
truth 2.24 -> 1.69, the shininess of the m = 150 patch steadier (CV 0.06 -> 0.02), no
stain left at material edges or printed lines; its SH fits, which lose views their
error is far above the bias of, 5 % worse. A map as fine as the photos (``auto``:
texels about a pixel across) keeps every read: each view blurs its texels, and leaving
out the most blended ones cost the physically based captures' held-out renders 1-3 %.

Building streams in two passes, so memory does not grow with the map: (1) each view is
sampled in row bands into a scratch store chunked per view; (2) the scratch store is
transposed band by band into the final ``tile x tile x N`` chunks. Everything is
written under a temporary name beside the target and renamed at the end, so an
interrupted build never leaves a store that later steps would accept.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .. import __version__
from ..config import default
from ..geometry import Intrinsics, sample_image, unit
from ..models.radiometry import correct_frame, describe_radiometry, frame_gain
from ..parallel import executor, progress
from ..stores.camera import PosesError, kept_poses, load_intrinsics, read_poses
from ..stores.capture import Capture
from ..stores.common import COMPLETE_ATTR, mtime_ns, store_bytes
from ..stores.hdr import read_hdr_mosaic, read_hdr_noise
from ..stores.metrics import digest, write_metrics
from ..stores.observation import (
    BYTES_PER_OBSERVATION,
    ObservationError,
    create_observation_map,
    create_scratch,
    finish_observation_map,
    open_scratch,
    read_scratch_band,
    set_build_attrs,
    write_band,
    write_view_rows,
)
from ..stores.paths import Processed
from ..stores.radiometry import Radiometry, radiometry_for
from ..vision.pose import point_uncertainty

logger = logging.getLogger(__name__)

__all__ = ["COMPLETE_ATTR", "ObservationError", "build_observation_map", "kept_poses",
           "run_observation", "marker_texel_mask", "blend_bias", "outside_fraction",
           "frontal_width", "photosite_planes", "texel_pixels", "sample_view", "texel_grid"]


def texel_grid(cap: Capture, texels_x: int | str, texels_y: int | None = None,
               poses_yaml: str | Path | None = None) -> tuple[int, int]:
    """Map size ``(S, T)``; T follows the region's aspect ratio when not given.
    ``texels_x`` ``auto`` takes the map the pose stage chose (``map`` in
    ``camera/poses.yaml``, see :mod:`parammap.stages.poses`)."""
    if texels_x == "auto":
        try:
            grid = read_poses(poses_yaml)["map"]
            return int(grid["S"]), int(grid["T"])
        except (PosesError, TypeError, KeyError) as exc:
            raise ObservationError(f"{poses_yaml}: observation.texels_x auto needs the map "
                                   f"the poses stage chose ({exc}); rerun poses") from None
    S = int(texels_x)
    T = int(texels_y) if texels_y else max(1, round(S * cap.height_mm / cap.width_mm))
    return S, T


def marker_texel_mask(cap: Capture, S: int, T: int, margin_mm: float = 0.0) -> np.ndarray:
    """(T, S) bool, True where a texel's square overlaps a marker's bounding box
    (grown by ``margin_mm``): those texels show the marker, not the surface."""
    mask = np.zeros((T, S), bool)
    tw, th = cap.width_mm / S, cap.height_mm / T
    for quad in cap.marker_corners:
        x0, y0 = quad.min(0) - margin_mm
        x1, y1 = quad.max(0) + margin_mm
        c0, c1 = math.floor(x0 / tw), math.ceil(x1 / tw)
        r0, r1 = math.floor((cap.height_mm - y1) / th), math.ceil((cap.height_mm - y0) / th)
        c0, r0 = max(c0, 0), max(r0, 0)
        if c0 < min(c1, S) and r0 < min(r1, T):
            mask[r0:min(r1, T), c0:min(c1, S)] = True
    return mask


def _project(P: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(R)
    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), rvec, t.reshape(3, 1), intr.K, intr.dist)
    return uv.reshape(P.shape[:-1] + (2,))


# How far from the point read a box-filtered pixel's surface reaches (pixels): a
# bilinear read 1.5 (1 of interpolation support, half the pixel's own area), a nearest
# read 1 (the pixel that holds the point).
PIXEL_REACH = {"bilinear": 1.5, "nearest": 1.0}


# The neighbours' second difference in a view is read from reads that are blended
# themselves: a feature a texel wide (an edge, a printed line) shows in them reduced by
# 1 - 2f (f the read's share from beyond its edges), so the bias is that much larger
# than the blended reads say; the amplification is capped at 1 / AMP_FLOOR where the
# reads are so blended (f near 1/2) that they say little either way.
AMP_FLOOR = 0.25


def outside_fraction(w: np.ndarray, nearest: np.ndarray | bool = False) -> np.ndarray:
    """Fraction of a texel's read that comes from beyond its edges along one axis, the
    texel ``w`` pixels across there (:func:`sample_view`'s reads). A bilinear read of
    box-filtered pixels weighs the surface by a quadratic B-spline of half-width
    :data:`PIXEL_REACH` (1.5 px); points inset by that reach (``w`` >= 3) read only
    the texel, a narrower texel is read on its centre line and takes in the B-spline's
    tails beyond +-w/2. Nearest reads (``w`` >= 2) stay inside."""
    h = np.asarray(w, float) / 2
    with np.errstate(invalid="ignore"):
        tail = np.where(h < 0.5, 1.0 - (1.5 * h - 2.0 * h ** 3 / 3.0),
                        np.clip(1.5 - h, 0.0, None) ** 3 / 3.0)
    return np.where(np.asarray(nearest) | ~np.isfinite(h), 0.0, tail)


def blend_bias(rad: np.ndarray, wx: np.ndarray, wy: np.ndarray, nearest: np.ndarray,
               frontal: np.ndarray) -> np.ndarray:
    """How far a view's reads of texels are pulled toward their neighbours by its
    foreshortening: (r, S, 3) bias of the core of (r + 2, S + 2) reads.

    A texel seen obliquely is narrow across one axis, and its read takes in the texels
    beside it there (:func:`outside_fraction` of ``wx`` across its columns, ``wy``
    across its rows, in pixels), half from each side: the bias is that share of the
    neighbours' second difference (``left + right - 2 x texel``), zero inside a uniform
    patch and across a smooth gradient (a highlight sweeping over the surface, which a
    sum of absolute differences would count), large at a material edge, a printed line
    or beside a marker, scaled up by ``1 / (1 - 2 f)`` (:data:`AMP_FLOOR`): the
    second difference of blended reads understates the surface's (on the demo, texels
    at the map's edge and by printed lines kept reads 30 % off). The share counted is
    what the foreshortening adds to the blend
    of a frontal read at the same distance (``frontal`` pixels across): a texel that no
    view resolves is blurred in every view, and that blur is part of what the map
    describes.

    Parameters
    ----------
    rad : (r + 2, S + 2, 3) reads of the band with a ring of one texel around it.
    wx, wy : (r + 2, S + 2) the texels' widths in pixels across columns and rows.
    nearest : (r + 2, S + 2) bool, read by whole pixels.
    frontal : (r + 2, S + 2) the texels' widths in pixels in a frontal view from the
        same distance (:func:`frontal_width`).
    """
    ref = outside_fraction(frontal)
    fx, fy = outside_fraction(wx, nearest), outside_fraction(wy, nearest)
    ex = (np.clip(fx - ref, 0.0, None) / np.maximum(1 - 2 * fx, AMP_FLOOR))[1:-1, 1:-1, None]
    ey = (np.clip(fy - ref, 0.0, None) / np.maximum(1 - 2 * fy, AMP_FLOOR))[1:-1, 1:-1, None]
    c = rad[1:-1, 1:-1]

    def curvature(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        # a side beyond the frame counts as the texel's own level
        return np.nan_to_num(a - c) + np.nan_to_num(b - c)

    return np.abs(0.5 * ex * curvature(rad[1:-1, :-2], rad[1:-1, 2:])
                  + 0.5 * ey * curvature(rad[:-2, 1:-1], rad[2:, 1:-1]))


def frontal_width(du: np.ndarray, dv: np.ndarray, cos_zenith: np.ndarray) -> np.ndarray:
    """Width in pixels of texels whose edges project to ``du``, ``dv`` (..., 2) in a
    view at ``cos_zenith`` (...), had the view looked at them frontally from the same
    distance: the square root of the projected area undone of its foreshortening."""
    area = np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
    return np.sqrt(area / np.maximum(cos_zenith, 1e-3))


def texel_pixels(intr: Intrinsics, R: np.ndarray, t: np.ndarray, S: int, T: int,
                 width_mm: float, height_mm: float) -> float:
    """Width in pixels of the map's centre texel as the view ``R``, ``t`` would see it
    frontally from its distance (:func:`frontal_width`): whether the photos resolve
    the map's texels (at least ``2 x PIXEL_REACH`` = 3 px: a frontal read takes in
    nothing of the neighbours)."""
    tw, th = width_mm / S, height_mm / T
    ctr = np.array([[width_mm / 2, height_mm / 2, 0.0]])
    uv0 = _project(ctr, intr, R, t)
    du = _project(ctr + [tw, 0, 0], intr, R, t) - uv0
    dv = _project(ctr + [0, th, 0], intr, R, t) - uv0
    d = -np.asarray(R).T @ np.asarray(t).ravel() - ctr[0]
    return float(frontal_width(du, dv, np.array([d[2] / np.linalg.norm(d)]))[0])


# The least share of a texel's footprint samples that one filter's photosites must carry
# for its channel to be read from them (a Bayer filter's red carries a quarter)
MIN_FILTER_SHARE = 0.1


def photosite_planes(mosaic: tuple[np.ndarray, np.ndarray],
                     gain: np.ndarray | None = None) -> np.ndarray:
    """A RAW frame's merged photosites (:func:`parammap.stores.hdr.read_hdr_mosaic`) as
    (H, W, 6) float32 planes for :func:`sample_view`: each filter's photosites (0
    elsewhere), then each filter's mask; divided by the flat-field's ``gain`` (H, W)
    where given."""
    m, colors = mosaic
    if gain is not None:
        m = m / gain
    out = np.zeros(m.shape + (6,), np.float32)
    for c in range(3):
        mask = colors == c
        out[..., c] = np.where(mask, m, 0.0)
        out[..., 3 + c] = mask
    return out


def sample_view(
    radiance: np.ndarray,
    saturated: np.ndarray,
    intr: Intrinsics,
    R: np.ndarray,
    t: np.ndarray,
    rows: slice,
    S: int,
    T: int,
    width_mm: float,
    height_mm: float,
    max_zenith_deg: float = default("observation.max_zenith_deg"),
    max_supersample: int = default("observation.max_supersample"),
    noise: np.ndarray | None = None, cov: np.ndarray | None = None,
    max_texel_shift: float | None = None,
    max_blend: float | None = None,
    stats: dict[str, int] | None = None,
    resolved: bool | None = None,
    sites: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Sample one HDR frame at the texels of rows ``rows`` of the map.

    Parameters
    ----------
    radiance : (H, W, 3) float32 linear radiance; saturated : (H, W) bool.
    intr, R, t : camera and pose (``p_cam = R p_world + t``, mm).
    rows : texel rows to sample; S, T, width_mm, height_mm : the map.
    noise : (H, W) relative noise sd of the frame's pixels (:func:`merge_noise`).
    cov, max_texel_shift : a partial view's pose covariance and limit: texels whose
        surface point the pose leaves more uncertain (1 sd, in sampling widths; see
        :func:`parammap.stages.poses.point_uncertainty`) are not valid.
    max_blend : with ``noise``, where the photos resolve the map's texels, an
        observation whose read takes in the neighbouring texels, by a bias over
        ``max_blend`` times its noise sd, is not valid (:func:`blend_bias`); None keeps
        every one.
    stats : counts added to: ``blended`` (observations dropped by ``max_blend``).
    sites : (H, W, 6) a RAW frame's photosites by filter and the filters' masks
        (:func:`photosite_planes`): each channel is read from its own photosites, the
        footprint's bilinear samples of them (a texel read by whole pixels: the
        photosites its points fall on) over those of their mask, instead of from the
        demosaiced ``radiance``, whose interpolation reaches a photosite further.
    resolved : whether the photos resolve the map's texels (:func:`texel_pixels` at
        the median view at least 3 px); None: this view's frontal width of the band's
        texels decides. A map as fine as the photos keeps every read: each view blurs
        its texels, and leaving out the most blended ones left directions unobserved
        that cost the physically based captures' held-out renders 1-3 %.

    Returns
    -------
    radiance : (r, S, 3) float32, NaN where a point fell outside the frame.
    direction : (r, S, 3) float32 unit vectors from the texel centre to the camera.
    valid : (r, S) bool (before the marker mask).
    noise : (r, S) float32 relative sd of each observation (None without ``noise``):
        the mean sd of the footprint's pixels. Not divided by the square root of the
        footprint's pixel count: the merged frames' errors are correlated between
        neighbouring pixels (one response error for every pixel at a level, lens blur),
        so averaging does not shrink them so; with that division the demo's fits had
        a median chi-square near 100 and weighted frontal views up to 10x, which cost
        held-out accuracy (mh-2 10.2 -> 10.5).
    """
    # the band and a ring of one texel around it (beyond the map's edge too): what a
    # read that reaches past its texel takes in (:func:`blend_bias`)
    r0, r1 = rows.indices(T)[:2]
    ii, jj = np.arange(r0 - 1, r1 + 1), np.arange(-1, S + 1)
    tw, th = width_mm / S, height_mm / T
    X, Y = np.meshgrid((jj + 0.5) * tw, height_mm - (ii + 0.5) * th)
    ctr = np.stack([X, Y, np.zeros_like(X)], -1)  # (r + 2, S + 2, 3)
    C = -R.T @ t
    d = unit(C - ctr)
    depth = (ctr @ R.T + t)[..., 2]
    # Footprint from the projected texel edges at the centres.
    uv0 = _project(ctr, intr, R, t)
    du = _project(ctr + [tw, 0, 0], intr, R, t) - uv0
    dv = _project(ctr + [0, th, 0], intr, R, t) - uv0
    foot = np.maximum(np.linalg.norm(du, axis=-1), np.linalg.norm(dv, axis=-1))
    finite = np.isfinite(foot) & (depth > 0)
    core = (slice(1, -1), slice(1, -1))
    fmax = float(np.max(foot[core][finite[core]])) if finite[core].any() else 1.0
    s = int(np.clip(math.ceil(fmax), 1, max_supersample))
    # Sub-sample offsets in texel units, inset from each texel edge by the reach of a
    # pixel read (PIXEL_REACH): the points read only this texel's surface. Per texel and
    # axis: the pixel distance between opposite edges is the texel's projected area over
    # the other edge's length (foreshortening is anisotropic). A texel too narrow for a
    # bilinear core but two pixels wide is read by whole pixels (nearest) instead.
    area = np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
    frontal = frontal_width(du, dv, d[..., 2])
    wx = area / np.maximum(np.linalg.norm(dv, axis=-1), 1e-9)
    wy = area / np.maximum(np.linalg.norm(du, axis=-1), 1e-9)
    wmin = np.nan_to_num(np.minimum(wx, wy), nan=0.0)
    near = (wmin < 2 * PIXEL_REACH["bilinear"]) & (wmin >= 2 * PIXEL_REACH["nearest"])
    reach = np.where(near, PIXEL_REACH["nearest"], PIXEL_REACH["bilinear"])
    with np.errstate(invalid="ignore", divide="ignore"):
        ix = np.nan_to_num(np.clip(reach / wx, 0.0, 0.5), nan=0.5)
        iy = np.nan_to_num(np.clip(reach / wy, 0.0, 0.5), nan=0.5)
    base = ((np.arange(s) + 0.5) / s - 0.5) if s > 1 else np.zeros(1)
    gx, gy = np.meshgrid(base, base)
    ox = gx.ravel() * (1.0 - 2 * ix[..., None]) * tw  # (r, S, s*s)
    oy = gy.ravel() * (1.0 - 2 * iy[..., None]) * th
    P = ctr[:, :, None, :] + np.stack([ox, -oy, np.zeros_like(ox)], -1)
    uv = _project(P, intr, R, t).astype(np.float32)  # (r, S, s*s, 2)
    H, W = radiance.shape[:2]
    inside = ((uv[..., 0] >= 0) & (uv[..., 0] <= W - 1) & (uv[..., 1] >= 0)
              & (uv[..., 1] <= H - 1)).all(-1)
    samp = sample_image(radiance, uv[..., 0], uv[..., 1])  # (r, S, s*s, 3)
    if near.any():
        samp[near] = sample_image(radiance, uv[near][..., 0], uv[near][..., 1], nearest=True)
    rad = samp.mean(axis=2)
    if sites is not None:
        ps = sample_image(sites, uv[..., 0], uv[..., 1]).mean(axis=2)  # (r, S, 6)
        with np.errstate(invalid="ignore", divide="ignore"):
            own = ps[..., :3] / ps[..., 3:]
        if near.any():
            # a texel read by whole pixels takes each point's own photosite: the
            # demosaiced pixel there reaches a photosite past the inset (on the demo's
            # DNGs, oblique dark reads 11-27 % off at the median); where the points hit
            # too few of a filter's photosites, its bilinear read reaches half a pixel past
            pn = sample_image(sites, uv[near][..., 0], uv[near][..., 1],
                              nearest=True).mean(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                own[near] = np.where(pn[:, 3:] >= MIN_FILTER_SHARE, pn[:, :3] / pn[:, 3:],
                                     own[near])
        # a footprint that holds too few of a filter's photosites keeps the demosaiced read
        rad = np.where(ps[..., 3:] >= MIN_FILTER_SHARE, own, rad)
    sat = sample_image(saturated.astype(np.uint8), uv[..., 0], uv[..., 1], nearest=True,
                       border=0) > 0
    sat = sat.reshape(uv.shape[:3]).any(axis=2)
    zen_ok = d[..., 2] >= math.cos(math.radians(max_zenith_deg))
    valid = inside & (depth > 0) & zen_ok & ~sat & np.isfinite(rad).all(-1)
    rad = np.where(inside[..., None], rad, np.nan)
    sd = None
    if noise is not None:
        nz = sample_image(np.asarray(noise, np.float32)[..., None], uv[..., 0],
                          uv[..., 1])[..., 0].mean(axis=2)
        sd = np.where(inside, nz, np.nan).astype(np.float32)
        if resolved is None:
            seen = frontal[core][finite[core]]
            resolved = seen.size > 0 and float(np.median(seen)) >= 2 * PIXEL_REACH["bilinear"]
        if max_blend is not None and resolved:
            bias = blend_bias(rad, wx, wy, near, frontal)
            # (a colour-corrected read may have a channel below 0: out of the gamut)
            level = sd[core] * np.abs(np.nanmean(rad[core], -1))
            with np.errstate(invalid="ignore"):
                blended = valid[core] & (np.nanmax(bias, -1) > max_blend * level)
            if stats is not None:
                stats["blended"] = stats.get("blended", 0) + int(blended.sum())
            valid[core] &= ~blended
        sd = sd[core]
    rad, d, valid, ctr = rad[core], d[core], valid[core], ctr[core]
    if cov is not None:

        _, rel = point_uncertainty(cov, R, t, intr, ctr.reshape(-1, 3), tw)
        valid &= (rel <= max_texel_shift).reshape(valid.shape)
    return rad.astype(np.float32), d.astype(np.float32), valid, sd


# ---------------------------------------------------------------------------------
# Store building


def _pass1_view(job: tuple) -> tuple[str, float, int, float, int]:
    """Sample one view into the scratch store; returns (id, valid fraction, bytes read,
    seconds, observations dropped as blended with their neighbours)."""
    (scratch, n, view, intr, S, T, w_mm, h_mm, band, max_zen, max_ss, max_blend,
     resolved, radiometry) = job
    t0 = time.perf_counter()
    rad, sat, _, noise = read_hdr_noise(view.hdr)
    if (rad.shape[1], rad.shape[0]) != tuple(intr.image_size):
        raise ObservationError(f"{view.hdr}: frame {rad.shape[1]}x{rad.shape[0]} does not "
                               f"match the intrinsics image size {intr.image_size}")
    sites = None
    mosaic = read_hdr_mosaic(view.hdr)
    # the photosites are read where no colour matrix mixes the channels per pixel
    if mosaic is not None and (radiometry is None or radiometry.colour_matrix is None):
        gain = None if radiometry is None else frame_gain(
            intr, view.R, view.t, w_mm, h_mm, radiometry, (rad.shape[1], rad.shape[0]))
        sites = photosite_planes(mosaic, gain)
    rad = correct_frame(rad, intr, view.R, view.t, w_mm, h_mm, radiometry)
    g = open_scratch(scratch)
    nvalid = 0
    stats: dict[str, int] = {}
    for r0 in range(0, T, band):
        rows = slice(r0, min(r0 + band, T))
        r, _, v, sd = sample_view(rad, sat, intr, view.R, view.t, rows, S, T, w_mm, h_mm,
                                  max_zen, max_ss, noise, view.cov, view.max_texel_shift,
                                  max_blend, stats, resolved, sites)
        write_view_rows(g, n, rows, r, v, sd)
        nvalid += int(v.sum())
    return (view.id, nvalid / (S * T), rad.nbytes + sat.nbytes, time.perf_counter() - t0,
            stats.get("blended", 0))


def band_columns(S: int, rows: int, N: int, tile: int, max_mib: float) -> int:
    """Columns of a band of ``rows`` texel rows transposed at once: a multiple of the
    tile within ``max_mib`` (the band's arrays take about three copies of
    ``BYTES_PER_OBSERVATION`` per texel and view: read, moved, written), at least one
    tile."""
    per_col = 3 * rows * N * BYTES_PER_OBSERVATION
    cols = int(max_mib * 2**20 // max(per_col, 1)) // tile * tile
    return int(min(S, max(tile, cols)))


def _pass2_band(job: tuple) -> int:
    """Transpose one band of tile rows from the scratch store into the final store, a
    block of ``cols`` columns at a time (memory bounded whatever the map's width)."""
    scratch, final, r0, r1, marker, cols = job
    S, nvalid = marker.shape[1], 0
    for c0 in range(0, S, cols):
        c1 = min(c0 + cols, S)
        rad, valid, noise = read_scratch_band(scratch, r0, r1, c0, c1)  # (r, c, N, ...)
        valid &= ~marker[r0:r1, c0:c1, None]
        write_band(final, r0, r1, rad, valid, noise, c0, c1)
        nvalid += int(valid.sum())
    return nvalid


def build_observation_map(
    cap: Capture,
    processed: str | Path,
    out: str | Path,
    texels_x: int | str = default("observation.texels_x"),
    texels_y: int | None = None,
    tile: int = default("observation.tile"),
    max_zenith_deg: float = default("observation.max_zenith_deg"),
    max_supersample: int = default("observation.max_supersample"),
    workers: int = 1,
    config: dict[str, Any] | None = None,
    max_blend: float | None = None,
    max_band_mib: float = default("observation.max_band_mib"),
    radiometry: Radiometry | None = None,
) -> dict[str, Any]:
    """Build ``observation.zarr`` from a processed capture's poses and HDR frames.

    Parameters
    ----------
    cap : the parsed capture (surface size, markers).
    processed : ``data/processed/<id>`` with ``camera/intrinsics.yaml``,
        ``camera/poses.yaml`` and ``hdr/<view>.exr``.
    out : the store to write (replaced atomically).
    texels_x, texels_y : map size S x T (T from the aspect ratio when None); ``auto``
        uses the map chosen by the pose stage.
    tile : texel tile edge of the chunks.
    max_blend : observations biased by their neighbours beyond this many noise sd by
        the view's foreshortening are not valid (:func:`blend_bias`), where the photos
        resolve the map's texels (3 px or more across at the median view,
        :func:`texel_pixels`); None keeps them.
    max_band_mib : memory (MiB) one process gives a block of the transpose
        (:func:`band_columns`).
    radiometry : the flat-field and colour correction each frame is read through
        (:func:`parammap.radiometry.correct_frame`); None reads frames as merged.

    Returns
    -------
    dict of figures for ``metrics/observation.json``.
    """
    t_start = time.perf_counter()
    proc = Processed(processed)
    out = Path(out)
    intr = load_intrinsics(proc.intrinsics)
    views, held = kept_poses(proc)
    for v in views:
        if not v.hdr.is_file():
            raise ObservationError(f"{v.hdr}: HDR frame of kept view {v.id} is missing")
    S, T = texel_grid(cap, texels_x, texels_y, proc.poses)
    N = len(views)
    logger.info(f"observation: map {S}x{T} texels ({cap.width_mm / S:.3f} mm) x {N} views"
                + (" (auto: about one texel per photo pixel at the median view)"
                   if texels_x == "auto" else ""))
    tile = int(min(tile, S, T))
    # A partial store under a fixed name and a marker per finished view and band: a
    # build that was killed resumes when run again on the same frames and settings.
    tmp = out.with_name(f".{out.name}.partial")
    marks = out.with_name(f".{out.name}.views")
    scratch = tmp / "scratch.zarr"
    final = tmp / "store.zarr"
    key = digest({"views": [(v.id, v.R, v.t, mtime_ns(v.hdr)) for v in views],
                  "K": intr.K, "dist": intr.dist, "grid": [S, T, tile],
                  "sampling": [max_zenith_deg, max_supersample, max_blend],
                  "config": config or {}, "radiometry": radiometry and asdict(radiometry),
                  "surface": [cap.width_mm, cap.height_mm, cap.marker_corners],
                  "software": __version__})
    resume = tmp.is_dir() and (marks / "key").is_file() and (marks / "key").read_text() == key
    band = tile
    if resume:
        logger.info(f"observation: resuming an interrupted build, "
                    f"{len(list(marks.glob('view-*')))} of {N} views sampled")
    else:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(marks, ignore_errors=True)
        tmp.mkdir(parents=True)
        marks.mkdir(parents=True)
        # Scratch: one view per chunk row band, fast compression, deleted at the end.
        create_scratch(scratch, N, T, S, band)
        (marks / "key").write_text(key)
    done = {n: json.loads((marks / f"view-{n}").read_text()) for n in range(N)
            if (marks / f"view-{n}").is_file()}
    texel_px = float(np.median([texel_pixels(intr, v.R, v.t, S, T, cap.width_mm,
                                             cap.height_mm) for v in views]))
    resolved = texel_px >= 2 * PIXEL_REACH["bilinear"]
    if max_blend is not None:
        logger.info(f"observation: texels {texel_px:.1f} px across at the median view: "
                    + (f"reads blended with their neighbours by over {max_blend:g} noise sd "
                       "are left out" if resolved else
                       "the photos do not resolve them, every read is kept"))
    jobs = [(str(scratch), n, v, intr, S, T, cap.width_mm, cap.height_mm, band,
             max_zenith_deg, max_supersample, max_blend, resolved, radiometry)
            for n, v in enumerate(views) if n not in done]
    with executor(workers) as ex:
        sampled = progress(ex.map(_pass1_view, jobs), len(jobs), "observation: views sampled",
                           logger, done=len(done), of=N)
        for job, res in zip(jobs, sampled, strict=True):
            done[job[1]] = [*res[:3], res[4]]
            (marks / f"view-{job[1]}").write_text(json.dumps(done[job[1]]))
    per_view = {done[n][0]: done[n][1] for n in range(N)}
    bytes_read = sum(done[n][2] for n in range(N))
    blended = sum(done[n][3] for n in range(N))
    t_sample = time.perf_counter() - t_start

    marker = marker_texel_mask(cap, S, T)
    if not (marks / "final").is_file():
        create_observation_map(final, S, T, N, tile)
        (marks / "final").touch()
    set_build_attrs(
        final, width_mm=cap.width_mm, height_mm=cap.height_mm, S=S, T=T, tile=tile,
        view_ids=[v.id for v in views], held_out_view_ids=held,
        camera_centres_mm=[v.centre.tolist() for v in views],
        calibration={"K": intr.K.tolist(), "dist": intr.dist.tolist(),
                     "image_size": list(intr.image_size), "rms_px": intr.rms_px},
        sampling={"method": "texel footprint supersampling, bilinear",
                  "max_supersample": max_supersample,
                  "max_zenith_deg": max_zenith_deg, "max_blend_sd": max_blend,
                  "texel_px": texel_px, "blend_check": bool(max_blend is not None
                                                            and resolved)},
        marker_texels=int(marker.sum()), surface_id=cap.surface_id, config=config or {},
        radiometry=describe_radiometry(radiometry or Radiometry()))
    written = {r0: int((marks / f"band-{r0}").read_text()) for r0 in range(0, T, tile)
               if (marks / f"band-{r0}").is_file()}
    cols = band_columns(S, tile, N, tile, max_band_mib)
    bands = [(str(scratch), str(final), r0, min(r0 + tile, T), marker, cols)
             for r0 in range(0, T, tile) if r0 not in written]
    with executor(workers) as ex:
        rows = progress(ex.map(_pass2_band, bands), len(bands), "observation: tile rows written",
                        logger, done=len(written), of=len(range(0, T, tile)))
        for job, nv in zip(bands, rows, strict=True):
            written[job[2]] = nv
            (marks / f"band-{job[2]}").write_text(str(nv))
    nvalid = sum(written.values())
    shutil.rmtree(scratch)
    finish_observation_map(final, out)
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.rmtree(marks, ignore_errors=True)
    seconds = time.perf_counter() - t_start
    on_disk = store_bytes(out)
    uncompressed = T * S * N * BYTES_PER_OBSERVATION
    return {
        "texels": S * T, "S": S, "T": T, "texel_mm": cap.width_mm / S,
        "resolution": "auto" if texels_x == "auto" else "config",
        "views": N, "held_out_views": len(held),
        "valid_fraction": nvalid / (S * T * N), "build_seconds": seconds,
        "blended_fraction": blended / (S * T * N), "texel_px": texel_px,
        "blend_check": bool(max_blend is not None and resolved),
        "sample_seconds": t_sample, "hdr_bytes_read": bytes_read,
        "read_mb_per_s": bytes_read / 1e6 / max(t_sample, 1e-9),
        "bytes_on_disk": on_disk, "bytes_uncompressed": uncompressed,
        "bytes_per_observation": on_disk / (S * T * N),
        "compression_ratio": uncompressed / max(on_disk, 1),
        "valid_fraction_per_view": per_view, "tile": tile,
    }


def run_observation(cap: Capture, processed: str | Path, config: dict[str, Any], *,
                    workers: int | None = None) -> dict[str, Any]:
    """The observe stage: build ``observation.zarr`` with the config section
    ``observation`` of the whole (validated) ``config``, write
    ``metrics/observation.json``."""
    proc = Processed(processed)
    cfg = config["observation"]
    m = build_observation_map(
        cap, proc.root, proc.observation, cfg["texels_x"], cfg["texels_y"], cfg["tile"],
        cfg["max_zenith_deg"], cfg["max_supersample"], workers or config["workers"],
        config=config, max_blend=cfg["max_blend_sd"], max_band_mib=cfg["max_band_mib"],
        radiometry=radiometry_for(cap, proc))
    write_metrics(proc.metrics("observation"), m)
    logger.info(f"observation: {m['S']}x{m['T']} texels x {m['views']} views, valid "
                f"{m['valid_fraction']:.3f} ({m['blended_fraction']:.4f} left out as "
                f"blended with their neighbours), {m['bytes_on_disk'] / 1e6:.1f} MB in "
                f"{m['build_seconds']:.1f} s")
    return m


