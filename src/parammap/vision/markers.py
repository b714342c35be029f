"""Markers on the surface: detection, sub-pixel corners from the markers' edges, a
view's pose and its uncertainty (OpenCV 5 ``ArucoDetector``, ``solvePnP``; poses as in
``docs/reference/conventions.md``: ``p_cam = R @ p_world + t``, the surface in z = 0, mm)."""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from ..conventions import LUMINANCE
from ..geometry import (
    Intrinsics,
    distort_normalized,
    pixel_to_normalized,
)
from ..stores.capture import Capture, aruco_dictionary
from ..stores.hdr import read_hdr, read_hdr_mosaic

logger = logging.getLogger(__name__)


def to_gray8(img: np.ndarray) -> np.ndarray:
    """8-bit grey for detection, from 8/16-bit RGB or float radiance.

    Radiance is scaled linearly (99th percentile to 255, clipped): a nonlinear tone
    curve would shift the anti-aliased edges that sub-pixel corner refinement relies
    on (measured: 0.4 px inward on marker corners with ``1 - exp(-gamma L)``).
    """
    if img.dtype == np.uint8:
        g = img
    elif img.dtype == np.uint16:
        g = (img >> 8).astype(np.uint8)
    else:
        lum = np.asarray(img, np.float32)
        p99 = float(np.percentile(lum, 99)) if lum.size else 1.0
        g = np.clip(np.round(255 * lum / max(p99, 1e-12)), 0, 255).astype(np.uint8)
    return cv2.cvtColor(g, cv2.COLOR_RGB2GRAY) if g.ndim == 3 else g


def luminance(img: np.ndarray) -> np.ndarray:
    """(H, W) float32 luminance of linear (H, W, 3) radiance; an (H, W) image as it is."""
    img = np.asarray(img, np.float32)
    return img if img.ndim == 2 else img @ LUMINANCE.astype(np.float32)


# The share of a marker region's photosites of each filter that is taken as the white
# of the paper (the brightest), and the quiet zone's width in cells around a marker.
WHITE_SHARE, QUIET_CELLS = 0.4, 1.0


def neutral_gains(mosaic: np.ndarray, colors: np.ndarray, quads: np.ndarray,
                  cells: int) -> np.ndarray | None:
    """Each filter's response to the markers' white paper, relative to green: the
    median of the brightest ``WHITE_SHARE`` of its photosites inside the markers and
    their quiet zones (``quads`` (M, 4, 2) px, widened by ``QUIET_CELLS`` of the
    ``cells`` a marker is across). None where a filter has no photosite there.

    Returns
    -------
    (3,) float gains (R, G, B), G = 1.
    """
    mask = np.zeros(mosaic.shape, np.uint8)
    for q in np.asarray(quads, float):
        c = q.mean(0)
        poly = c + (q - c) * (cells + 2 * QUIET_CELLS) / cells
        cv2.fillConvexPoly(mask, np.round(poly * 16).astype(np.int32), 1, shift=4)
    inside = mask > 0
    white = []
    for c in range(3):
        v = mosaic[inside & (colors == c)]
        if v.size < 10:
            return None
        white.append(float(np.median(v[v >= np.quantile(v, 1 - WHITE_SHARE)])))
    if min(white) <= 0:
        return None
    return np.array(white) / white[1]


def marker_image(radiance: np.ndarray, mosaic: tuple[np.ndarray, np.ndarray] | None,
                 cap: Capture) -> np.ndarray:
    """The image a view's geometry is measured on: its (H, W, 3) radiance or, for a
    frame merged from camera RAWs (``mosaic``: photosites and filters,
    :func:`parammap.stores.hdr.read_hdr_mosaic`), an (H, W) float32 image of its
    photosites each divided by its filter's response to the markers' white
    (:func:`neutral_gains`). The markers are grey, so there every photosite samples the
    same image at full resolution, where demosaicing interpolates two of every three
    colours (on the demo's 640 x 480 DNGs the poses were ten times worse)."""
    if mosaic is None or len(cap.marker_ids) == 0:
        return radiance
    ids, corners = detect_markers(to_gray8(radiance), cap.marker_dictionary, cap.marker_ids)
    known = np.isin(ids, cap.marker_ids)
    if not known.any():
        return radiance
    sites, colors = mosaic
    gains = neutral_gains(sites, colors, corners[known],
                          aruco_dictionary(cap.marker_dictionary).markerSize + 2)
    if gains is None:
        return radiance
    return (sites / gains[colors]).astype(np.float32)


def read_marker_frame(path, cap: Capture) -> np.ndarray:
    """:func:`marker_image` of the merged HDR frame at ``path``."""
    return marker_image(read_hdr(path)[0], read_hdr_mosaic(path), cap)


def detect_markers(gray: np.ndarray, dictionary_name: str,
                   expected: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ArUco markers with sub-pixel corners: ids (M,), corners (M, 4, 2).

    With ``expected`` (the ids the capture lists), a second pass looks for the missing
    ones in the image upsampled 2x with a finer bit sampling: markers foreshortened to a
    few pixels a cell at grazing views are often found there, and every marker a grazing
    pose gains constrains it in a new direction.
    """
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementMinAccuracy = 0.01
    params.cornerRefinementMaxIterations = 60
    det = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary_name), params)
    corners, ids, _ = det.detectMarkers(gray)
    ids = np.zeros(0, int) if ids is None else ids.ravel().astype(int)
    found = np.array([c.reshape(4, 2) for c in corners], float).reshape(-1, 4, 2)
    missing = set() if expected is None else set(int(i) for i in expected) - set(ids.tolist())
    if missing:
        params.perspectiveRemovePixelPerCell = 8
        params.perspectiveRemoveIgnoredMarginPerCell = 0.2
        big = cv2.resize(gray, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
        c2, i2, _ = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary_name), params) \
            .detectMarkers(big)
        add = [k for k, i in enumerate(np.ravel(i2) if i2 is not None else []) if int(i) in missing]
        if add:
            # pixel centres: x_big = 2 x + 0.5
            more = (np.array([c2[k].reshape(4, 2) for k in add], float) - 0.5) / 2.0
            ids = np.r_[ids, np.ravel(i2)[add].astype(int)]
            found = np.concatenate([found, more])
    return ids, found


def _to_normalized(uv: np.ndarray, intr: Intrinsics, guess: np.ndarray | None = None,
                   ) -> np.ndarray:
    return pixel_to_normalized(uv, intr.K, intr.dist, guess=guess)


def _to_pixels(xy: np.ndarray, intr: Intrinsics) -> np.ndarray:
    d = distort_normalized(xy, intr.dist)
    K = intr.K
    return np.stack([K[0, 0] * d[..., 0] + K[0, 1] * d[..., 1] + K[0, 2],
                     K[1, 1] * d[..., 1] + K[1, 2]], -1)


def _robust_line(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A straight-line fit of ``y`` against ``x`` (both (n,)) with one round of outlier
    rejection (3 robust sd), evaluated at ``x``; the median for fewer than 6 points."""
    if len(x) < 6:
        return np.full(len(x), float(np.median(y)))
    keep = np.ones(len(x), bool)
    for _ in range(2):
        c = np.polyfit(x[keep], y[keep], 1)
        r = y - np.polyval(c, x)
        lim = 3.0 * 1.4826 * float(np.median(np.abs(r[keep])))
        new = np.abs(r) <= max(lim, 1e-12)
        if new.sum() < 6 or (new == keep).all():
            break
        keep = new
    return np.polyval(c, x)


def _fit_step_columns(vals: np.ndarray, lo: float, span: np.ndarray, e0: np.ndarray,
                      use: np.ndarray, iters: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Edge positions of column profiles by least squares on a blurred step.

    Every column ``vals[i]`` (dark end first, pixel centres at 0, 1, ...) is modelled as
    ``lo + span[i]`` times a step at ``e[i]`` blurred by a Gaussian of sd ``w`` and
    integrated over each pixel (the exact ramp of a sharp step as ``w`` -> 0), ``w``
    shared by the edge's columns (chosen on a grid, on the columns ``use``). Only
    pixels on the slope weigh in, so the noise of the plateau pixels, which the area sum
    adds up, drops out; the model is symmetric about ``e``, so a symmetric blur of
    another shape does not shift it. Starts from the area method's ``e0``.

    Returns
    -------
    e : (n,) positions; ok : (n,) columns that converged inside the window with a
        residual not far above the edge's median (a second edge in the window is not).
    """
    j = np.arange(vals.shape[1], dtype=float)[None, :]
    target = (vals - lo) / np.maximum(span, 1e-12)[:, None]

    def model(e, w):
        # a Gaussian-blurred step integrated over each pixel (exact ramp as w -> 0); e
        # (..., n), w (..., 1, 1): every width at once
        a, b = (j - 0.5 - e[..., None]) / w, (j + 0.5 - e[..., None]) / w
        G = lambda z: z * ndtr(z) + np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)  # noqa: E731
        return w * (G(b) - G(a)), -(ndtr(b) - ndtr(a))  # value, d value / d e

    def solve(w):
        e = np.broadcast_to(e0, w.shape[:-2] + e0.shape).copy()
        for _ in range(iters):
            m, g = model(e, w)
            step = (g * (target - m)).sum(-1) / np.maximum((g * g).sum(-1), 1e-12)
            e = e + np.clip(step, -0.5, 0.5)
        m, _ = model(e, w)
        return e, ((target - m) ** 2).mean(-1)

    widths = np.geomspace(0.05, 3.0, 14)
    es, res = solve(widths[:, None, None])  # Gauss-Newton on every width together
    best = int(np.argmin(np.median(res[:, use], axis=1)))
    e, res = es[best], res[best]
    ok = (e > 0) & (e < vals.shape[1] - 1) & (np.abs(e - e0) < 1.5) \
        & (res <= 4.0 * np.median(res[use]))
    return e, ok


def _edge_points(lum: np.ndarray, a: np.ndarray, b: np.ndarray, outward: np.ndarray,
                 dark_band: float, bright_reach: float = 3.0) -> np.ndarray:
    """Sub-pixel points of a dark-to-bright step edge near the segment a-b.

    Area method: along each pixel column (or row, for a steep edge) crossing the edge,
    the pixel values normalised between the dark and the bright level sum to the
    length of the bright part of the window, so the edge position is that length from
    the window's end: exact for a box-filtered straight step at any angle, and for
    any symmetric blur that fits in the window (no interpolation, no threshold).

    Parameters
    ----------
    lum : (H, W) linear luminance.
    a, b : (2,) approximate end points (pixels); the middle 60 % is measured.
    outward : (2,) unit normal pointing to the bright side.
    dark_band : width of the dark band behind the edge (pixels, along the normal):
        the window's dark side stays inside it.
    bright_reach : pixels taken on the bright side (along the normal).

    Returns
    -------
    (n, 2) edge points in pixels (x, y).
    """
    ax = 0 if abs(outward[1]) >= abs(outward[0]) else 1  # 0: walk columns, 1: walk rows
    if ax == 1:  # transpose the problem: swap x and y
        lum, a, b, outward = lum.T, a[::-1], b[::-1], outward[::-1]
    H, W = lum.shape
    x0, x1 = sorted((a[0] + 0.2 * (b[0] - a[0]), a[0] + 0.8 * (b[0] - a[0])))
    xs = np.arange(math.ceil(x0), math.floor(x1) + 1)
    if len(xs) < 4 or abs(b[0] - a[0]) < 1e-9:
        return np.zeros((0, 2))
    yc = np.round(a[1] + (xs - a[0]) * (b[1] - a[1]) / (b[0] - a[0])).astype(int)
    sgn = 1 if outward[1] > 0 else -1  # +1: the bright side is at larger y
    # along a column the band is 1/|n_y| times wider than along the normal
    band = dark_band / abs(outward[1])
    rb = max(2, int(math.ceil(bright_reach / abs(outward[1]))))
    # The detected corners can be pixels off on small markers: find each column's
    # step first (in a wider search window), then put the measuring window around it.
    o = np.arange(-3, rb + 4)
    rows = yc[:, None] + sgn * o
    ok = (rows.min(1) >= 0) & (rows.max(1) < H) & (xs >= 0) & (xs < W)
    xs, rows = xs[ok], rows[ok]
    if len(xs) < 4:
        return np.zeros((0, 2))
    prof = lum[rows, xs[:, None]].astype(float)
    mn = prof.min(1)
    below = prof < (mn + 0.15 * (prof.max(1) - mn))[:, None]  # clearly dark
    # the bright-most pixel of a dark run, nearest the expected edge (other edges,
    # e.g. printed texture beyond a narrow gap, may lie further out)
    step = below[:, :-1] & ~below[:, 1:]
    dist = np.where(step, np.abs(o[:-1]), np.inf)
    last = np.argmin(dist, axis=1)
    yt = rows[np.arange(len(xs)), last]
    # That pixel's centre lies 0.35-1.35 px inside the edge (>= 85 % dark), and the
    # window's dark end must stay inside the band: k more pixels.
    k = max(0, int(math.floor(band - 1.85)))
    o2 = np.arange(-k, rb + 1)  # dark end first
    rows = yt[:, None] + sgn * o2
    ok = step.any(1) & (rows.min(1) >= 0) & (rows.max(1) < H)
    xs, rows = xs[ok], rows[ok]
    if len(xs) < 4:
        return np.zeros((0, 2))
    vals = lum[rows, xs[:, None]].astype(float)  # (n, k + rb + 1), dark end first
    # The two levels are estimated along the edge, not per column: a column's own
    # bright pixels carry its noise (sensor or Monte Carlo), and normalising by them and
    # clipping at the levels biased the edge toward the bright side (0.1 px at 10 %
    # pixel noise, 0.25 px at 20 %). Unclipped, the noise of the sum averages out.
    lo = float(np.median(vals[:, 0]))  # the dark band: one level along the edge
    hi = _robust_line(xs.astype(float), vals[:, -2:].mean(1))  # light may vary along it
    span = hi - lo
    hi_col = vals[:, -2:].mean(1)
    good = (hi_col - lo > 0.25 * np.maximum(hi_col, 1e-12)) & (span > 0.25 * hi)
    u = np.clip((vals - lo) / np.maximum(span, 1e-12)[:, None], -1.0, 2.0)
    e = (1.0 - u).sum(1) - 0.5  # area method: edge position in window pixels (centres 0..)
    good &= (e > 0) & (e < vals.shape[1] - 1)
    if good.sum() < 4:
        return np.zeros((0, 2))
    e, ok = _fit_step_columns(vals, lo, span, e, good)
    y = rows[:, 0] + sgn * e
    good &= ok
    pts = np.stack([xs, y], 1)[good]
    return pts[:, ::-1] if ax == 1 else pts


def refine_marker_corners(
    lum: np.ndarray, corners: np.ndarray, intr: Intrinsics, cells: int = 6,
    max_shift_px: float = 1.5, return_measured: bool = False, return_edges: bool = False,
) -> np.ndarray | tuple:
    """Refine marker outer corners by fitting lines to the four outer edges.

    ArUco's corner refinement treats the convex marker corner like a saddle point and
    lands ~0.25 px inside it on anti-aliased edges. Here each outer edge (black border
    to the lighter surround) is located column by column with the area method of
    :func:`_edge_points` in *linear* radiance, away from the corners; a line is fitted
    to those points in undistorted normalised coordinates (so lens distortion does not
    bend it) and adjacent lines are intersected.

    Parameters
    ----------
    lum : (H, W) float linear luminance (not tone-mapped).
    corners : (M, 4, 2) ArUco corners in pixels (clockwise from top-left).
    intr : camera intrinsics, for the undistortion.
    cells : marker width in cells, border included (bits + 2).
    max_shift_px : a refined corner further than this from ArUco's is not trusted
        (with all four edges measured: up to a quarter of the shortest edge).
    return_measured : also return which markers had all four edges measured.
    return_edges : also return the measured edge points, per marker a list of four
        (n, 2) pixel arrays (edge k runs from corner k to corner k + 1; empty when
        that edge could not be measured), for :func:`refine_pose_edges`.

    Returns
    -------
    (M, 4, 2) refined corners; a marker whose edges cannot be measured keeps its input.
    With ``return_measured``, also (M,) bool; with ``return_edges``, also the edges.
    """
    lum = np.ascontiguousarray(lum, np.float32)
    out = np.array(corners, float, copy=True)
    done = np.zeros(len(out), bool)
    all_edges = []
    for m, quad in enumerate(np.asarray(corners, float)):
        centre = quad.mean(0)
        edges = np.linalg.norm(np.roll(quad, -1, axis=0) - quad, axis=1)
        lines, measured = [], 0
        all_edges.append([np.zeros((0, 2))] * 4)
        for k in range(4):
            a, b = quad[k], quad[(k + 1) % 4]
            length = np.linalg.norm(b - a)
            e = (b - a) / max(length, 1e-9)
            n = np.array([e[1], -e[0]])
            if np.dot((a + b) / 2 - centre, n) < 0:
                n = -n
            # the black border's width across this edge: the marker's extent along n
            # over the cell count; the window's dark side must stay inside it
            band = float(np.max((quad - a) @ -n)) / cells
            edge = np.zeros((0, 2))
            if band >= 2.0 and length >= 2.0 * cells:
                edge = _edge_points(lum, a, b, n, min(band, 6.0))
            if len(edge) >= 4:
                measured += 1
                all_edges[m][k] = edge
            else:  # too thin to measure: the line through the two detected corners
                edge = np.array([a, b])
            xy = _to_normalized(edge, intr)
            c = xy.mean(0)
            _, _, vt = np.linalg.svd(xy - c)
            nrm = vt[1]
            if len(xy) >= 5:
                resid = (xy - c) @ nrm
                keep = np.abs(resid) <= max(3 * np.median(np.abs(resid)), 1e-9)
                if keep.sum() >= 4 and not keep.all():
                    c = xy[keep].mean(0)
                    _, _, vt = np.linalg.svd(xy[keep] - c)
                    nrm = vt[1]
            lines.append((nrm, float(nrm @ c)))
        if measured == 0:
            continue
        new = []
        for k in range(4):
            (n1, d1), (n2, d2) = lines[(k - 1) % 4], lines[k]
            A = np.array([n1, n2])
            if abs(np.linalg.det(A)) < 1e-9:
                break
            new.append(np.linalg.solve(A, [d1, d2]))
        if len(new) != 4:
            continue
        px = _to_pixels(np.array(new), intr)
        # ArUco's corners of small, oblique markers can be pixels off; four measured
        # edges are trusted further than a mix with ArUco's own edges
        limit = max_shift_px if measured < 4 else max(max_shift_px, 0.25 * edges.min())
        if np.all(np.linalg.norm(px - quad, axis=1) <= limit):
            out[m] = px
            done[m] = measured == 4
    res = (out,) + ((done,) if return_measured else ()) + ((all_edges,) if return_edges else ())
    return res if len(res) > 1 else out


def refine_pose_edges(
    quads_mm: np.ndarray, edges: list[list[np.ndarray]], corners_px: np.ndarray,
    corner_used: np.ndarray, R: np.ndarray, t: np.ndarray, intr: Intrinsics,
    corner_noise_px: float,
) -> dict | None:
    """Refine a pose jointly on the measured marker edges and the remaining corners.

    Every measured edge point must lie on the line through its edge's two projected
    corners (in undistorted normalised coordinates, where lines stay straight): tens
    of points per edge instead of one corner, and usable where a marker's other edges
    are too thin to measure (foreshortened borders at grazing views, which constrain
    only one direction). Corners of markers not measured on all four edges
    (``corner_used``) keep the other direction pinned. Residuals are weighted by their
    noise, re-estimated from the solution (two rounds); the points of one edge share
    its systematic error (blur, dark level), so an edge counts as two independent
    measurements (offset and angle), not one per point.

    Parameters
    ----------
    quads_mm : (M, 4, 2) marker corners on the surface (mm), corner order of ``edges``.
    edges : per marker, four (n, 2) arrays of edge points in pixels (may be empty).
    corners_px : (M, 4, 2) image corners; corner_used : (M,) bool, markers whose
        corners enter.
    R, t : starting pose (the corner solution); corner_noise_px : its corner noise per
        coordinate.

    Returns
    -------
    None without at least 12 edge points; else a dict with ``R``, ``t``, ``cov`` (6, 6)
    covariance of (rvec, tvec), ``edge_noise_px``, ``n`` (edge points).
    """
    pts, xa, xb, n_edges = [], [], [], 0
    for quad, per in zip(quads_mm, edges, strict=True):
        for k, e in enumerate(per):
            if len(e) == 0:
                continue
            pts.append(_to_normalized(np.asarray(e, float), intr))
            xa.append(np.repeat([[*quad[k], 0.0]], len(e), 0))
            xb.append(np.repeat([[*quad[(k + 1) % 4], 0.0]], len(e), 0))
            n_edges += 1
    if not pts or sum(len(x) for x in pts) < 12:
        return None
    pts, xa, xb = (np.concatenate(a) for a in (pts, xa, xb))
    cobj = np.array([[*c, 0.0] for q, u in zip(quads_mm, corner_used, strict=True) if u
                     for c in q]).reshape(-1, 3)
    cimg = _to_normalized(np.asarray(corners_px, float)[np.asarray(corner_used, bool)]
                          .reshape(-1, 2), intr) if len(cobj) else np.zeros((0, 2))
    f = 0.5 * (intr.K[0, 0] + intr.K[1, 1])
    w_corr = math.sqrt(2.0 * n_edges / len(pts))

    def parts(p):
        Rm, _ = cv2.Rodrigues(p[:3])
        A = xa @ Rm.T + p[3:]
        B = xb @ Rm.T + p[3:]
        a, b = A[:, :2] / A[:, 2:], B[:, :2] / B[:, 2:]
        d = b - a
        n = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True)
        re = f * np.sum((pts - a) * n, 1)
        P = cobj @ Rm.T + p[3:]
        rc = f * (P[:, :2] / P[:, 2:] - cimg).ravel()
        return re, rc

    rvec, _ = cv2.Rodrigues(np.asarray(R, float))
    p = np.r_[rvec.ravel(), np.asarray(t, float).ravel()]
    s_e, s_c = 0.3, max(corner_noise_px, 1e-3)
    for _ in range(2):
        def whitened(q, se=s_e, sc=s_c):
            re, rc = parts(q)
            return np.r_[re * (w_corr / se), rc / sc]

        sol = least_squares(whitened, p, method="lm", x_scale="jac")
        p = sol.x
        re, rc = parts(p)
        s_e = max(float(np.sqrt(np.mean(re ** 2))), 1e-3)
        if len(rc) > 6:
            s_c = max(float(np.sqrt(np.mean(rc ** 2))), 1e-3)
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(cov).all():
        return None
    Rn, _ = cv2.Rodrigues(p[:3])
    return {"R": Rn, "t": p[3:].copy(), "cov": cov, "edge_noise_px": s_e, "n": len(pts)}


