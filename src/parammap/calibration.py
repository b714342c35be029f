"""Camera intrinsics from board photos, and each view's pose from surface markers.

OpenCV 5 APIs (``pitfalls.md``): ``CharucoDetector.detectBoard`` and
``ArucoDetector.detectMarkers``, then ``calibrateCamera`` / ``solvePnP``. Poses follow
conventions.md: ``p_cam = R @ p_world + t`` with the surface in z = 0 (mm).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import yaml

from .capture import Capture, aruco_dictionary
from .conventions import LUMINANCE
from .errors import InputError
from .geometry import (
    Intrinsics,
    camera_centre,
    distort_normalized,
    pixel_to_normalized,
    ray_jacobian,
)
from .imageio import ImageReadError, read_image
from .paths import Processed

logger = logging.getLogger(__name__)

__all__ = [
    "CalibrationError",
    "Intrinsics",
    "board_points",
    "calibrate",
    "detect_markers",
    "estimate_pose",
    "load_intrinsics",
    "marker_views",
    "refine_marker_corners",
    "refine_pose_edges",
    "rotation_sd_per_px",
    "run_calibration",
    "save_intrinsics",
    "to_gray8",
]


class CalibrationError(InputError):
    """Calibration cannot go on (too few usable board photos...)."""


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


def board_points(cap: Capture, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Detected board corners of one photo: (object points (N, 3) mm, image points
    (N, 2) px), or None if the board is not found. Squares across/down come from
    capture.yaml; OpenCV wants inner corners for chessboards."""
    c = cap.calibration
    sx, sy, sq = int(c["squares_x"]), int(c["squares_y"]), float(c["square_mm"])
    if c["board"] == "charuco":
        board = cv2.aruco.CharucoBoard((sx, sy), sq, float(c["marker_mm"]),
                                       aruco_dictionary(c["dictionary"]))
        det = cv2.aruco.CharucoDetector(board)
        corners, ids, _, _ = det.detectBoard(gray)
        if ids is None or len(ids) < 4:
            return None
        obj, img = board.matchImagePoints(corners, ids)
        return obj.reshape(-1, 3), img.reshape(-1, 2)
    pattern = (sx - 1, sy - 1)
    ok, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_ACCURACY)
    if not ok:
        return None
    gx, gy = np.meshgrid(np.arange(pattern[0]), np.arange(pattern[1]))
    obj = np.stack([gx.ravel() * sq, gy.ravel() * sq, np.zeros(gx.size)], 1)
    return obj.astype(np.float32), corners.reshape(-1, 2)


def calibrate(cap: Capture, min_images: int = 4, min_corners: int = 8,
              extra_views: list[tuple[str, np.ndarray, np.ndarray]] | None = None,
              guess: Intrinsics | None = None) -> Intrinsics:
    """Intrinsics from the capture's calibration photos.

    ``extra_views`` adds planar targets of known layout seen by the same camera, as
    (name, object points (n, 3), image points (n, 2)): the surface markers of the
    captured views (:func:`marker_views`). They are many, spread over the whole image
    and over many orientations, which pins down the principal point and tangential
    distortion far better than a few board photos. ``guess`` starts the solver.

    Raises
    ------
    CalibrationError
        If fewer than ``min_images`` photos show at least ``min_corners`` corners.
    """
    if not cap.calibration:
        raise CalibrationError(f"{cap.root / 'capture.yaml'}: no calibration section "
                               "(board photos or saved intrinsics are needed for poses)")
    objs, imgs, names, size = [], [], [], None
    for p in cap.calibration_images:
        try:
            img = read_image(p)
        except ImageReadError as exc:
            logger.info(f"calibration: skipping {exc}")
            continue
        if size is None:
            size = (img.shape[1], img.shape[0])
        elif size != (img.shape[1], img.shape[0]):
            logger.info(f"calibration: skipping {p.name}: size differs from the first photo")
            continue
        found = board_points(cap, to_gray8(img))
        n = 0 if found is None else len(found[0])
        if n < min_corners:
            logger.info(f"calibration: {p.name}: {n} board corners found, below "
                        f"{min_corners}; skipped")
            continue
        objs.append(found[0].astype(np.float32))
        imgs.append(found[1].astype(np.float32))
        names.append(p.name)
    if len(objs) < min_images:
        raise CalibrationError(
            f"{cap.root / 'capture.yaml'}: calibration.images: only {len(objs)} of "
            f"{len(cap.calibration_images)} photos show the {cap.calibration['board']} board "
            f"(need {min_images} with at least {min_corners} corners)")
    flags, K0, d0 = 0, None, None
    for name, o, i in extra_views or []:
        objs.append(np.asarray(o, np.float32))
        imgs.append(np.asarray(i, np.float32))
        names.append(name)
    if guess is not None:
        flags, K0, d0 = cv2.CALIB_USE_INTRINSIC_GUESS, guess.K.copy(), guess.dist.copy()
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, size, K0, d0, flags=flags)
    if extra_views:
        # one pass of outlier rejection over the marker views (a bad detection biases)
        per_view = []
        for o, i, r, t in zip(objs, imgs, rvecs, tvecs, strict=True):
            proj, _ = cv2.projectPoints(o, r, t, K, dist)
            per_view.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i) ** 2, 1)))))
        lim = 3 * float(np.median(per_view))
        keep = [k for k, e in enumerate(per_view) if e <= lim or k < len(objs) - len(extra_views)]
        if len(keep) < len(objs):
            logger.info(f"calibration: {len(objs) - len(keep)} marker views above "
                        f"{lim:.2f} px left out")
            objs, imgs, names = ([x[k] for k in keep] for x in (objs, imgs, names))
            rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, size, K, dist,
                                                             flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    per = {}
    for name, o, i, r, t in zip(names, objs, imgs, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        per[name] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i) ** 2, 1))))
    return Intrinsics(K, dist.ravel()[:5], size, float(rms), len(objs), per)


def marker_views(cap: Capture, intr: Intrinsics, frames, min_markers: int = 4,
                 ) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Surface-marker correspondences of captured views, for :func:`calibrate`.

    ``frames`` yields (view id, linear radiance (H, W, 3)). Corners are edge-refined
    with the board intrinsics ``intr``; only markers measured on all four edges are
    used, and views with fewer than ``min_markers`` of them are skipped.
    """
    out = [m for vid, rad in frames
           if (m := _marker_view(cap, intr, vid, rad, min_markers)) is not None]
    logger.info(f"calibration: {len(out)} captured views add their surface markers")
    return out


def _marker_view(cap: Capture, intr: Intrinsics, vid: str, rad: np.ndarray,
                 min_markers: int) -> tuple[str, np.ndarray, np.ndarray] | None:
    """One view's entry of :func:`marker_views`, or None."""
    if len(cap.marker_ids) == 0:
        return None
    known = {int(i): k for k, i in enumerate(cap.marker_ids)}
    cells = aruco_dictionary(cap.marker_dictionary).markerSize + 2
    ids, corners = detect_markers(to_gray8(rad), cap.marker_dictionary, cap.marker_ids)
    use = [k for k, i in enumerate(ids) if int(i) in known]
    if len(use) < min_markers:
        return None
    lum = np.asarray(rad, np.float32) @ LUMINANCE.astype(np.float32)
    c, measured = refine_marker_corners(lum, np.asarray(corners, float)[use], intr, cells,
                                        return_measured=True)
    # only markers measured on all four edges: ArUco's corners would bias the focal
    use, c = [k for k, ok in zip(use, measured, strict=True) if ok], c[measured]
    if len(use) < min_markers:
        return None
    obj = np.concatenate([np.c_[cap.marker_corners[known[int(ids[k])]], np.zeros(4)]
                          for k in use])
    return vid, obj, c.reshape(-1, 2)


def _pattern_view_job(job: tuple) -> tuple[str, PatternView, list, np.ndarray, float] | None:
    """A captured view's pose on its markers' pattern and the pixels it was fitted on
    (at most ``max_pixels``), for :func:`refine_intrinsics_pattern`: (view id,
    view, blurred textures, pose (6,), residual noise), or None without a pattern pose.
    A process pool's job."""
    from .hdr import read_hdr

    cap, intr, vid, path, max_pixels = job
    rad = read_hdr(path)[0]
    rec = estimate_pose(cap, intr, to_gray8(rad), radiance=rad,
                        pattern_max_pixels=max_pixels)
    if not rec["ok"] or rec["solution"] != "pattern":
        return None
    rvec, _ = cv2.Rodrigues(rec["R"])
    lum = np.asarray(rad, np.float32) @ LUMINANCE.astype(np.float32)
    view = PatternView(lum, cap, rec["pattern_markers"] or rec["detected"], rvec, rec["t"], intr,
                       max_pixels)
    if not view.markers:
        return None
    return (vid, view, view.textures(rec["pattern_blur_px"]), np.r_[rvec.ravel(), rec["t"]],
            float(rec["noise_px"]))


def pattern_views(cap: Capture, intr: Intrinsics, frames: list[tuple[str, Path]],
                  workers: int = 1) -> list[tuple[str, PatternView, list, np.ndarray]]:
    """The captured views whose pose the markers' pattern gives, ready for
    :func:`refine_intrinsics_pattern`; ``frames``: (view id, HDR frame path). Views whose
    pattern residual exceeds ``PATTERN_NOISE_FACTOR`` times the median are left out
    (a misidentified marker would pull the intrinsics). At most
    ``PATTERN_JOINT_MAX_VIEWS`` evenly strided views are used; they share
    ``PATTERN_JOINT_PIXELS``, each within ``PATTERN_JOINT_VIEW_PIXELS``."""
    from .stores import executor

    # beyond PATTERN_JOINT_MAX_VIEWS a stride over the views (their order is the
    # capture's, unrelated to the intrinsics) keeps the stage's time bounded
    frames = list(frames)[::math.ceil(len(frames) / PATTERN_JOINT_MAX_VIEWS) or 1]
    lo, hi = PATTERN_JOINT_VIEW_PIXELS
    per_view = int(np.clip(PATTERN_JOINT_PIXELS / max(len(frames), 1), lo, hi))
    with executor(max(1, min(workers, len(frames)))) as ex:
        got = [g for g in ex.map(_pattern_view_job, [(cap, intr, vid, p, per_view)
                                                     for vid, p in frames]) if g is not None]
    if not got:
        return []
    limit = PATTERN_NOISE_FACTOR * float(np.median([g[4] for g in got]))
    out = [g[:4] for g in got if g[4] <= limit]
    if len(out) < len(got):
        logger.info(f"calibration: {len(got) - len(out)} views with a pattern residual above "
                    f"{PATTERN_NOISE_FACTOR} x the median left out of the pattern refinement")
    return out


def _marker_view_job(job: tuple) -> tuple[str, np.ndarray, np.ndarray] | None:
    """:func:`_marker_view` of a view's HDR frame on disk (a process pool's job)."""
    from .hdr import read_hdr

    cap, intr, vid, path, min_markers = job
    return _marker_view(cap, intr, vid, read_hdr(path)[0], min_markers)


def run_calibration(cap: Capture, processed: str | Path, cfg: dict,
                    workers: int = 1) -> Intrinsics:
    """The calibrate stage: intrinsics from the board photos, then (config
    ``calibration.use_marker_views``) a second pass that adds the surface markers seen
    in the captured views' HDR frames, started from the board's solution, and
    (``calibration.refine_on_pattern``) a third that fits the intrinsics and those views'
    poses together on their markers' whole pattern (:func:`refine_intrinsics_pattern`,
    from ``PATTERN_JOINT_MIN_VIEWS`` views with a pattern pose). A capture's saved
    intrinsics are used as they are. Writes ``camera/intrinsics.yaml`` and
    ``metrics/calibration.json``; ``cfg``: config section ``calibration``; the marker
    views are measured on ``workers`` processes."""
    from .metrics import write_metrics

    out = Processed(processed)
    joint: dict = {}
    if cap.intrinsics_path is not None:
        intr = load_intrinsics(cap.intrinsics_path)
        logger.info(f"calibrate: using saved intrinsics {cap.intrinsics_path}")
    else:
        intr = calibrate(cap, cfg["min_images"], cfg["min_corners"])
        hdr = [(v.id, out.hdr(v.id)) for v in cap.fitted_views]
        if cfg["use_marker_views"] and len(cap.marker_ids):
            missing = [str(p) for _, p in hdr if not p.is_file()]
            if missing:
                raise CalibrationError(f"calibration.use_marker_views: HDR frames missing "
                                       f"(run the hdr stage first): {missing[0]}...")
            from .stores import executor

            jobs = [(cap, intr, vid, p, cfg["min_markers_per_view"]) for vid, p in hdr]
            with executor(max(1, min(workers, len(jobs)))) as ex:
                extra = [m for m in ex.map(_marker_view_job, jobs) if m is not None]
            logger.info(f"calibration: {len(extra)} captured views add their surface markers")
            if extra:
                intr = calibrate(cap, cfg["min_images"], cfg["min_corners"],
                                 extra_views=extra, guess=intr)
            if cfg["refine_on_pattern"]:
                views = pattern_views(cap, intr, hdr, workers)
                if len(views) >= PATTERN_JOINT_MIN_VIEWS:
                    logger.info(f"calibration: refining the intrinsics on the markers' pattern "
                                f"of {len(views)} views")
                    intr, joint, _ = refine_intrinsics_pattern(intr, views, workers)
                else:
                    logger.info(f"calibration: {len(views)} views with a pattern pose, below "
                                f"{PATTERN_JOINT_MIN_VIEWS}: intrinsics from the corners")
    save_intrinsics(out.intrinsics, intr)
    write_metrics(out.metrics("calibration"), {
        "rms_px": intr.rms_px, "images_used": intr.images_used,
        "images_total": len(cap.calibration_images), "fx_px": intr.K[0, 0],
        "fy_px": intr.K[1, 1], "cx_px": intr.K[0, 2], "cy_px": intr.K[1, 2],
        "dist": intr.dist, "per_image_rms_px": intr.per_image_rms_px,
        "pattern_refinement": joint or None})
    logger.info(f"calibrate: rms {intr.rms_px:.3f} px from {intr.images_used} photos")
    return intr


def save_intrinsics(path: str | Path, intr: Intrinsics) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {
        "image_size": [int(v) for v in intr.image_size],
        "K": np.asarray(intr.K).tolist(),
        "dist": np.asarray(intr.dist).ravel().tolist(),
        "dist_model": "opencv k1 k2 p1 p2 k3",
        "rms_px": float(intr.rms_px),
        "images_used": int(intr.images_used),
        "per_image_rms_px": intr.per_image_rms_px or {},
    }
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(yaml.safe_dump(data, sort_keys=False))
    tmp.replace(path)
    return path


def load_intrinsics(path: str | Path) -> Intrinsics:
    path = Path(path)
    try:
        d = yaml.safe_load(path.read_text())
        K = np.array(d["K"], float).reshape(3, 3)
        dist = np.array(d["dist"], float).ravel()
        size = tuple(int(v) for v in d["image_size"])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise CalibrationError(f"{path}: not an intrinsics file ({exc})") from None
    return Intrinsics(K, dist, size, float(d.get("rms_px", float("nan"))),
                      int(d.get("images_used", 0)), d.get("per_image_rms_px"))


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
    from scipy.special import ndtr

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
    from scipy.optimize import least_squares

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


# Pattern refinement (refine_pose_pattern): texture samples per marker cell, and
# sub-samples per pixel edge (a pixel integrates the pattern over its area)
PATTERN_TEXELS_PER_CELL = 12
PATTERN_SUBSAMPLES = 3
PATTERN_MARGIN_CELLS = 0.3  # the outer border's outer edge meets an unknown surround
PATTERN_BLURS_PX = (0.05, 0.15, 0.35, 0.7, 1.4, 2.8)  # optical blur (Gaussian sd) tried per view


def _marker_pattern(dictionary: str, marker_id: int, cells: int, blur_texels: float,
                    ) -> np.ndarray:
    """The marker's black-and-white pattern, black border included, (n, n) floats in
    [0, 1] with ``PATTERN_TEXELS_PER_CELL`` samples per cell, blurred by
    ``blur_texels`` (Gaussian sd, samples)."""
    import scipy.ndimage as ndi

    img = aruco_dictionary(dictionary).generateImageMarker(
        int(marker_id), cells * PATTERN_TEXELS_PER_CELL).astype(float) / 255.0
    return ndi.gaussian_filter(img, blur_texels) if blur_texels > 0 else img


def _plane_texture_coords(p: np.ndarray, nrm: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Pattern coordinates (n, 2) where the rays of undistorted normalised image points
    ``nrm`` (n, 2) of a camera with pose ``p`` (rvec, t) meet the surface plane z = 0,
    ``A`` (3, 3) mapping the plane (mm) to the pattern (samples)."""
    Rm, _ = cv2.Rodrigues(p[:3])
    C = -Rm.T @ p[3:]
    # the rays R^T (x, y, 1) in the surface frame, column by column (a thin matmul
    # would spin BLAS threads)
    x, y = nrm[:, 0], nrm[:, 1]
    s = -C[2] / (x * Rm[0, 2] + y * Rm[1, 2] + Rm[2, 2])
    X = C[0] + s * (x * Rm[0, 0] + y * Rm[1, 0] + Rm[2, 0])
    Y = C[1] + s * (x * Rm[0, 1] + y * Rm[1, 1] + Rm[2, 1])
    w = A[2, 0] * X + A[2, 1] * Y + A[2, 2]
    return np.stack([(A[0, 0] * X + A[0, 1] * Y + A[0, 2]) / w,
                     (A[1, 0] * X + A[1, 1] * Y + A[1, 2]) / w], -1)


class PatternView:
    """The pixels of one photo that see its markers' patterns, for pose refinement
    on the whole pattern (:func:`refine_pose_pattern`).

    Built at a starting pose: every pixel whose footprint lies inside a marker (its
    black border and its cells; the border's outer edge meets an unknown surround and is
    left out), ``PATTERN_SUBSAMPLES``^2 sub-pixel rays per pixel, flat cell interiors
    thinned to stay within ``max_pixels``. ``markers`` is empty when no marker lies
    wholly inside the photo.
    """

    def __init__(self, lum: np.ndarray, cap: Capture, marker_ids: list[int],
                 rvec: np.ndarray, tvec: np.ndarray, intr: Intrinsics,
                 max_pixels: int = 40000):
        known = {int(i): k for k, i in enumerate(cap.marker_ids)}
        self.dictionary = cap.marker_dictionary
        self.cells = aruco_dictionary(cap.marker_dictionary).markerSize + 2
        side = self.side = self.cells * PATTERN_TEXELS_PER_CELL
        H, W = lum.shape
        sub = (np.arange(PATTERN_SUBSAMPLES) + 0.5) / PATTERN_SUBSAMPLES - 0.5
        sub = np.stack(np.meshgrid(sub, sub), -1).reshape(-1, 2)
        self.ns = len(sub)
        lo_c = PATTERN_MARGIN_CELLS * PATTERN_TEXELS_PER_CELL
        hi_c = side - lo_c
        p0 = np.r_[np.ravel(rvec), np.ravel(tvec)]
        self.markers = []
        for mid in marker_ids:
            if int(mid) not in known:
                continue
            quad = np.asarray(cap.marker_corners[known[int(mid)]], np.float32)
            A = cv2.getPerspectiveTransform(quad, np.float32(
                [[0, 0], [side, 0], [side, side], [0, side]])).astype(float)
            proj, _ = cv2.projectPoints(np.c_[quad, np.zeros(4)].astype(float), p0[:3],
                                        p0[3:], intr.K, intr.dist)
            proj = proj.reshape(-1, 2)
            lo = np.floor(proj.min(0)).astype(int) - 1
            hi = np.ceil(proj.max(0)).astype(int) + 1
            if (lo < 0).any() or hi[0] >= W or hi[1] >= H:
                continue  # a marker cut by the frame: its pixels would be missing
            xs, ys = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
            px = np.c_[xs.ravel(), ys.ravel()].astype(float)
            # the rays of every sub-pixel sample, undistorted once
            rays = px[:, None, :] + sub[None]
            nrm = _to_normalized(rays.reshape(-1, 2), intr)
            uv = _plane_texture_coords(p0, nrm, A).reshape(len(px), self.ns, 2)
            inside = ((uv > lo_c) & (uv < hi_c)).all((1, 2))
            if inside.sum() < 20:
                continue
            # pattern samples per photo pixel along the marker's longer side
            scale = side / max(float(np.linalg.norm(np.roll(proj, -1, 0) - proj,
                                                    axis=1).max()), 1e-6)
            self.markers.append({"id": int(mid), "A": A, "scale": scale,
                                 "I": lum[ys.ravel(), xs.ravel()][inside].astype(float),
                                 "nrm": nrm.reshape(len(px), self.ns, 2)[inside],
                                 "px": rays[inside], "uv": uv[inside]})
        total = sum(len(m["I"]) for m in self.markers)
        if total > max_pixels:
            frac = max_pixels / total
            for m in self.markers:
                cell = m["uv"].mean(1) / PATTERN_TEXELS_PER_CELL
                edge = np.abs(cell - np.round(cell)).min(1) < 1.0  # near a cell edge
                rng = np.random.default_rng(m["id"])
                keep = edge | (rng.random(len(edge)) < 0.25 * frac)
                if keep.sum() > 1.5 * frac * len(edge):
                    keep &= rng.random(len(edge)) < 1.5 * frac * len(edge) / keep.sum()
                for k in ("I", "nrm", "px", "uv"):
                    m[k] = m[k][keep]
        # a marker thinned below what fits its levels is left out
        self.markers = [m for m in self.markers if len(m["I"]) >= 20]
        for m in self.markers:
            m["nrm"] = m["nrm"].reshape(-1, 2)
            m["px"] = m["px"].reshape(-1, 2)
            del m["uv"]
        self.pixels = sum(len(m["I"]) for m in self.markers)

    def set_intrinsics(self, intr: Intrinsics) -> None:
        """Re-cast every sub-pixel ray through the camera ``intr`` (the pixels and
        their photo values stay): for refining the intrinsics on the pattern."""
        for m in self.markers:
            m["nrm"] = _to_normalized(m["px"], intr, guess=m["nrm"])

    def textures(self, blur_px: float) -> list[np.ndarray]:
        """Each marker's pattern blurred by ``blur_px`` photo pixels."""
        return [_marker_pattern(self.dictionary, m["id"], self.cells, blur_px * m["scale"])
                for m in self.markers]

    def residuals(self, p: np.ndarray, textures: list[np.ndarray]) -> np.ndarray:
        """(pixels,) photo minus predicted luminance at pose ``p`` (rvec, tvec), each
        marker's black and white levels fitted (linear least squares), in units of its
        black-to-white step (markers in shade count alike)."""
        out = []
        for m, tex in zip(self.markers, textures, strict=True):
            e, coef = self._marker_residuals(m, tex, p)
            out.append(e / max(abs(coef[3]), 1e-12))
        return np.concatenate(out)

    def _marker_residuals(self, m: dict, tex: np.ndarray, p: np.ndarray,
                          ) -> tuple[np.ndarray, np.ndarray]:
        """Photo minus prediction (photo units) of marker ``m`` at pose ``p``, and its
        fitted levels (:func:`_levels`)."""
        from scipy.ndimage import map_coordinates

        from .pattern_kernel import pattern_predict

        if pattern_predict is not None:
            Rm, _ = cv2.Rodrigues(np.asarray(p[:3], float))
            C = -Rm.T @ np.asarray(p[3:], float)
            n = len(m["I"])
            pred, x, y = np.empty(n), np.empty(n), np.empty(n)
            pattern_predict(Rm, C, m["nrm"], m["A"], tex, self.ns, pred, x, y)
            x, y = x / self.side - 0.5, y / self.side - 0.5
        else:
            uv = _plane_texture_coords(p, m["nrm"], m["A"])
            pred = map_coordinates(tex, [uv[:, 1] - 0.5, uv[:, 0] - 0.5], order=1,
                                   mode="nearest").reshape(-1, self.ns).mean(1)
            x, y = (uv.reshape(-1, self.ns, 2).mean(1) / self.side - 0.5).T
        X, _, coef = _levels(pred, x, y, m["I"])
        return m["I"] - X @ coef, coef

    def residuals_jacobian(self, p: np.ndarray, textures: list[np.ndarray],
                           ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`residuals` and their Jacobian (pixels, 6) by the pose, analytic: the
        compiled kernel's derivatives of the prediction, with the levels refitted at
        the moved pose (variable projection) and the step they scale by. None where
        numba is missing."""
        from .pattern_kernel import pattern_predict_grad

        if pattern_predict_grad is None:
            return None
        Rm, dR = cv2.Rodrigues(np.asarray(p[:3], float))
        t = np.asarray(p[3:], float)
        C = -Rm.T @ t
        dR = np.ascontiguousarray(dR.reshape(3, 3, 3))
        rs, Js = [], []
        for m, tex in zip(self.markers, textures, strict=True):
            n = len(m["I"])
            f, x, y = np.empty(n), np.empty(n), np.empty(n)
            df, dx, dy = np.empty((n, 6)), np.empty((n, 6)), np.empty((n, 6))
            pattern_predict_grad(Rm, C, dR, t, m["nrm"], m["A"], tex, self.ns, f, x, y,
                                 df, dx, dy)
            x, y = x / self.side - 0.5, y / self.side - 0.5
            dx, dy = dx / self.side, dy / self.side
            X, G, c = _levels(f, x, y, m["I"])
            e = m["I"] - X @ c
            scale = max(abs(c[3]), 1e-12)
            r = e / scale
            # the design's derivative times the levels, then the levels' own change
            # (their refit at the moved pose) and the step's
            D = (c[1] + c[4] * f)[:, None] * dx + (c[2] + c[5] * f)[:, None] * dy \
                + (c[3] + c[4] * x + c[5] * y)[:, None] * df
            dXe = np.stack([np.zeros(6), e @ dx, e @ dy, e @ df,
                            e @ (df * x[:, None] + f[:, None] * dx),
                            e @ (df * y[:, None] + f[:, None] * dy)])  # (6 columns, 6)
            dc = np.linalg.solve(G, dXe - np.einsum("ni,nj->ij", X, D))  # (6 coef, 6)
            de = -(D + X @ dc)
            rs.append(r)
            Js.append(de / scale - np.outer(r, np.sign(c[3]) * dc[3] / scale))
        return np.concatenate(rs), np.concatenate(Js)

    def marker_fits(self, p: np.ndarray, textures: list[np.ndarray],
                    ) -> list[tuple[int, float, float]]:
        """Per marker at pose ``p``: (id, residual sd in units of its black-to-white
        step, that step over the marker's mean luminance). A marker that is not where
        the pose puts it (hidden, or not printed as listed) fits with a large residual
        and a small or negative step."""
        out = []
        for m, tex in zip(self.markers, textures, strict=True):
            e, c = self._marker_residuals(m, tex, p)
            out.append((m["id"], float(np.std(e)) / max(abs(c[3]), 1e-12),
                        float(c[3]) / max(float(np.mean(m["I"])), 1e-12)))
        return out


def _levels(pred: np.ndarray, x: np.ndarray, y: np.ndarray, lum: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A marker's black and white levels, each linear in the pattern position (the
    light may vary across a marker): the design X (n, 6), its normal matrix G and the
    least-squares coefficients for the photo's luminance ``lum``."""
    X = np.stack([np.ones_like(pred), x, y, pred, pred * x, pred * y], -1)
    # normal equations by einsum: BLAS would spin threads for these thin products, idle
    # work beside a pool's other workers
    G = np.einsum("ni,nj->ij", X, X)
    G[np.diag_indices(6)] += 1e-12 * np.trace(G)
    return X, G, np.linalg.solve(G, np.einsum("ni,n->i", X, lum))


def _pattern_noise(r: np.ndarray, free: int) -> tuple[float, float]:
    """Residual variance (``free`` fitted values) and the variance inflation of
    residuals correlated between neighbouring pixels (blur, demosaicing): the
    effective number of independent pixels, from the correlation of consecutive
    residuals (a 2-D field, correlated along both axes)."""
    n = len(r)
    s2 = float(r @ r) / max(n - free, 1)
    rho = float(np.clip(np.corrcoef(r[:-1], r[1:])[0, 1], 0.0, 0.95)) if n > 2 else 0.0
    return s2, ((1 + rho) / (1 - rho)) ** 2


def refine_pose_pattern(lum: np.ndarray, cap: Capture, marker_ids: list[int],
                        R: np.ndarray, t: np.ndarray, intr: Intrinsics,
                        max_pixels: int = 40000, others: Sequence[int] = ()) -> dict | None:
    """Refine a pose on the whole pattern of its markers, not only their outlines.

    Every pixel inside a marker (its black border and every black or white cell, whose
    layout the dictionary gives; :class:`PatternView`) is predicted from the pose: the
    pixel's footprint meets the surface plane and samples the marker's pattern blurred
    by the optics, and a per-marker black and white level turns that into luminance.
    The pose minimises the squared difference to the photo. Each inner cell edge
    constrains the pose, so a marker gives tens of edges instead of four: at grazing
    views, where a marker is a few pixels high, this is what pins the camera down
    (pbr-tiny's 74 deg view: 2.3 -> 0.3 mm). The blur (Gaussian sd in pixels) is the
    one of ``PATTERN_BLURS_PX`` that fits best.

    Markers the detector missed (``others``: at grazing views, markers a few pixels
    high, often the far ones that pin the rotation best) then join where the refined
    pose puts them wholly inside the photo and their pattern fits there as well as the
    detected markers' (residual within ``PATTERN_NOISE_FACTOR`` times theirs, a step at
    least half theirs: a hidden or misplaced marker fails both), and the pose is solved
    again on all of them (pbr-bench's 81 deg view: 4 of its 10 markers detected).

    Parameters
    ----------
    lum : (H, W) linear luminance; marker_ids : markers detected in the view;
    R, t : starting pose; max_pixels : pixels used at most; others : the capture's
    other markers.

    Returns
    -------
    None when no marker lies wholly in the photo or the solve fails; else a dict with
    ``R``, ``t``, ``cov`` (6, 6) covariance of (rvec, tvec) (inflated for correlated
    residuals, :func:`_pattern_noise`), ``noise`` (residual sd in units of the
    black-to-white step), ``blur_px``, ``pixels``, ``markers`` (how many),
    ``marker_ids`` (which: the detected ones and the others that joined).
    """
    from scipy.optimize import least_squares

    rvec, _ = cv2.Rodrigues(np.asarray(R, float))
    view = PatternView(lum, cap, marker_ids, rvec, np.asarray(t, float), intr, max_pixels)
    if not view.markers:
        return None
    p0 = np.r_[rvec.ravel(), np.asarray(t, float).ravel()]

    def solve(blur: float, view: PatternView = view, p0: np.ndarray = p0):
        tex = view.textures(blur)
        last: dict = {}

        def both(p):  # residuals and Jacobian in one pass, asked for at the same point
            if last.get("p") is None or not np.array_equal(last["p"], p):
                last.update(p=np.array(p, copy=True), rj=view.residuals_jacobian(p, tex))
            return last["rj"]

        analytic = view.residuals_jacobian(p0, tex) is not None
        try:
            if analytic:
                sol = least_squares(lambda p: both(p)[0], p0, jac=lambda p: both(p)[1],
                                    method="lm", x_scale="jac")
            else:
                sol = least_squares(lambda p: view.residuals(p, tex), p0, method="lm",
                                    x_scale="jac", diff_step=1e-7)
        except (ValueError, np.linalg.LinAlgError):
            return None
        return (float(sol.fun @ sol.fun), sol, blur) if np.all(np.isfinite(sol.x)) else None

    # the blur: solved at a middling one, then the others judged at that solution, and
    # solved again only if one fits clearly better there
    best = solve(PATTERN_BLURS_PX[len(PATTERN_BLURS_PX) // 2 - 1])
    if best is None:
        return None
    costs = {b: float(np.sum(view.residuals(best[1].x, view.textures(b)) ** 2))
             for b in PATTERN_BLURS_PX if b != best[2]}
    b = min(costs, key=costs.get)
    if costs[b] < 0.9 * best[0]:
        other = solve(b)
        if other is not None and other[0] < best[0]:
            best = other
    _, sol, blur = best
    marker_ids = [int(i) for i in marker_ids]
    others = [int(i) for i in others if int(i) not in marker_ids]
    if others:
        view, sol = _join_markers(lambda v, p: solve(blur, v, p), lum, cap, view, sol,
                                  marker_ids, others, blur, intr, max_pixels)
    s2, inflate = _pattern_noise(sol.fun, 6 + 6 * len(view.markers))
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2 * inflate
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(cov).all():
        return None
    Rn, _ = cv2.Rodrigues(sol.x[:3])
    return {"R": Rn, "t": sol.x[3:].copy(), "cov": cov, "noise": math.sqrt(s2),
            "blur_px": blur, "pixels": view.pixels, "markers": len(view.markers),
            "marker_ids": sorted(m["id"] for m in view.markers)}


def _join_markers(solve, lum: np.ndarray, cap: Capture, view: PatternView, sol,
                  detected: list[int], others: list[int], blur: float, intr: Intrinsics,
                  max_pixels: int):
    """Grow the pattern fit of the ``detected`` markers by those of ``others`` that
    show where the pose puts them (:func:`refine_pose_pattern`). A marker shows when
    its black-to-white step at the current pose is at least a quarter of the detected
    markers' (hidden, or listed where none is printed, it is near zero) and its residual
    sd within :data:`PATTERN_JOIN_LOOSE` times theirs. Each round, those that show
    with a residual within :data:`PATTERN_JOIN_FACTOR` times theirs join, or else the
    one that fits best, and the pose is solved again with them: a pose from a few near
    markers misplaces the far ones by a fraction of a cell, and each marker that joins
    brings the next into place.
    At the end every joined marker must fit within ``PATTERN_NOISE_FACTOR`` times the
    detected markers' residual. ``solve(view, p)``: (cost, solution, blur) or None.
    Returns the view and the solution."""
    joined: list[int] = []
    for _ in range(len(others)):
        rest = [i for i in others if i not in joined]
        if not rest:
            break
        trial = PatternView(lum, cap, detected + joined + rest, sol.x[:3], sol.x[3:], intr,
                            max_pixels)
        fits = {i: (sd, step) for i, sd, step in trial.marker_fits(sol.x, trial.textures(blur))}
        sd0 = float(np.median([fits[i][0] for i in detected if i in fits] or [np.inf]))
        step0 = float(np.median([fits[i][1] for i in detected if i in fits] or [np.inf]))
        shown = {i: fits[i][0] for i in rest if i in fits and fits[i][1] >= 0.25 * step0
                 and fits[i][0] <= PATTERN_JOIN_LOOSE * sd0}
        if not shown:
            break
        # those that fit well enough now, else the one that fits best
        new = [i for i in rest if shown.get(i, np.inf) <= PATTERN_JOIN_FACTOR * sd0] \
            or [min(shown, key=shown.get)]
        grown = PatternView(lum, cap, detected + joined + new, sol.x[:3], sol.x[3:], intr,
                            max_pixels)
        got = solve(grown, sol.x)
        if got is None:
            break
        joined += new
        view, sol = grown, got[1]
    if joined:
        fits = view.marker_fits(sol.x, view.textures(blur))
        sd0 = float(np.median([sd for i, sd, _ in fits if i in detected]))
        bad = [i for i, sd, _ in fits if i not in detected and sd > PATTERN_NOISE_FACTOR * sd0]
        if bad:
            keep = [i for i in joined if i not in bad]
            trimmed = PatternView(lum, cap, detected + keep, sol.x[:3], sol.x[3:], intr,
                                  max_pixels)
            got = solve(trimmed, sol.x)
            if got is not None:
                view, sol = trimmed, got[1]
    return view, sol


# The nine intrinsics the joint refinement frees, in the order of its vector
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
# pixels of all views together in the joint refinement, and per view at least and at most
PATTERN_JOINT_PIXELS = 250000
JOINT_POSE_EVALS = 12  # a view's pose follows a step of the intrinsics within a few
JOINT_TRIALS = 3  # damped steps tried per iteration before the refinement stops
PATTERN_JOINT_VIEW_PIXELS = (2000, 15000)
PATTERN_JOINT_MIN_VIEWS = 8  # fewer views leave the intrinsics to the corners
PATTERN_JOINT_MAX_VIEWS = 48  # views the joint refinement uses at most
# The intrinsics' finite differences move the image's edge by this much: the predicted
# pattern is bilinear between its samples, a few per pixel, so that smaller steps read
# the kinks of the interpolation rather than the slope of the blurred pattern
PATTERN_JOINT_STEP_PX = 0.1
PATTERN_JOINT_TOL_PX = 0.05  # the refinement stops when a step moves the edge less
# A view whose markers' pattern fits with a residual more than this many times the
# capture's median is suspect: one misidentified marker among a view's markers leaves
# about half of its cells wrong, which about doubles the residual sd.
PATTERN_NOISE_FACTOR = 1.5
# A marker the detector missed joins the pattern fit when, at the pose of the markers
# so far, its residual is within this many times theirs: a pose from a few near markers
# misplaces the far ones by a fraction of a cell, which about doubles their residual
PATTERN_JOIN_FACTOR = 3.0
PATTERN_JOIN_LOOSE = 10.0  # ... and it may join alone, as the best fit, within this


def _intrinsic_vector(intr: Intrinsics) -> np.ndarray:
    """(9,) fx, fy, cx, cy (px) and k1, k2, p1, p2, k3 of ``intr``."""
    d = np.zeros(5)
    d[:min(5, np.size(intr.dist))] = np.ravel(intr.dist)[:5]
    K = intr.K
    return np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], d]


def _with_intrinsics(intr: Intrinsics, th: np.ndarray) -> Intrinsics:
    """``intr`` with the nine intrinsics ``th`` (:func:`_intrinsic_vector`)."""
    K = np.array([[th[0], intr.K[0, 1], th[2]], [0.0, th[1], th[3]], [0.0, 0.0, 1.0]])
    return replace(intr, K=K, dist=np.asarray(th[4:9], float).copy())


def _intrinsic_steps(intr: Intrinsics, e: float = PATTERN_JOINT_STEP_PX) -> np.ndarray:
    """(9,) changes of the intrinsics that each move a point at the image's edge by
    about ``e`` px: the finite-difference steps and the solver's units."""
    f = float(intr.K[0, 0])
    r = 0.5 * max(intr.image_size) / f  # normalised radius of the image's edge
    return np.array([e / r, e / r, e, e, e / (f * r**3), e / (f * r**5),
                     e / (3 * f * r**2), e / (3 * f * r**2), e / (f * r**7)])


def _joint_view_pose(job: tuple) -> tuple[float, np.ndarray]:
    """One view's best pose at intrinsics ``th``, started from ``p``, and its sum of
    squared pattern residuals there: the poses follow each step of the intrinsics
    (variable projection), which keeps the solver out of the curved valley where
    linearised poses creep."""
    from scipy.optimize import least_squares

    view, tex, p, th, intr = job
    view.set_intrinsics(_with_intrinsics(intr, th))
    last: dict = {}

    def both(q):
        if last.get("q") is None or not np.array_equal(last["q"], q):
            last.update(q=np.array(q, copy=True), rj=view.residuals_jacobian(q, tex))
        return last["rj"]

    try:
        sol = least_squares(lambda q: both(q)[0], p, jac=lambda q: both(q)[1], method="lm",
                            x_scale="jac", max_nfev=JOINT_POSE_EVALS)
    except (ValueError, np.linalg.LinAlgError):
        return math.inf, p
    return (float(sol.fun @ sol.fun), sol.x) if np.all(np.isfinite(sol.x)) else (math.inf, p)


def _joint_view_terms(job: tuple) -> tuple | None:
    """One view's share of the joint normal equations: (H_pp (6, 6), H_tp (9, 6),
    g_p (6,), H_tt (9, 9), g_t (9,)) with the intrinsics in units of their steps
    (:func:`_intrinsic_steps`; central differences), the pose's part analytic.
    None where the compiled kernel is missing."""
    view, tex, p, th, intr, steps = job
    view.set_intrinsics(_with_intrinsics(intr, th))
    got = view.residuals_jacobian(p, tex)
    if got is None:
        return None
    r, Jp = got
    # the rays move with the intrinsics by their analytic Jacobian; the residuals'
    # response to that is a central difference (the pattern is bilinear between samples)
    at = _with_intrinsics(intr, th)
    base = [m["nrm"] for m in view.markers]
    D = [ray_jacobian(b, at.K, at.dist) for b in base]
    Jt = np.empty((len(r), len(th)))
    for j, h in enumerate(steps):
        for m, b, d in zip(view.markers, base, D, strict=True):
            m["nrm"] = b + h * d[:, :, j]
        rp = view.residuals(p, tex)
        for m, b, d in zip(view.markers, base, D, strict=True):
            m["nrm"] = b - h * d[:, :, j]
        Jt[:, j] = 0.5 * (rp - view.residuals(p, tex))
    for m, b in zip(view.markers, base, strict=True):
        m["nrm"] = b
    return Jp.T @ Jp, Jt.T @ Jp, Jp.T @ r, Jt.T @ Jt, Jt.T @ r


def refine_intrinsics_pattern(
    intr: Intrinsics, views: list[tuple[str, PatternView, list, np.ndarray]],
    workers: int = 1, max_iter: int = 15,
) -> tuple[Intrinsics, dict, dict[str, np.ndarray]]:
    """Refine the intrinsics jointly with the poses of the captured views on their
    markers' whole pattern: a bundle adjustment on pixels, not on corners.

    Corners leave a valley along which the principal point trades against tangential
    distortion and the focal length; where a capture's corners are biased (blur, a
    filmic response, small oblique markers) the calibration slides along it and the
    view directions turn with it (pbr-tiny: principal point 1.15 px off, directions up
    to 0.065 deg off). The pattern of every marker, predicted pixel by pixel as in
    :func:`refine_pose_pattern`, fits the intrinsics and the poses together, so that
    where the valley leaves the principal point the poses stay consistent with it
    (pbr-tiny: directions within 0.04 deg of the truth).

    Levenberg-Marquardt on the nine intrinsics (:data:`INTRINSIC_NAMES`) and six pose
    parameters per view; each view's pose is eliminated from the normal equations
    (Schur complement) and each view's pose is solved again at every trial step
    (:func:`_joint_view_pose`); the intrinsics' derivatives are central differences
    (``PATTERN_JOINT_STEP_PX``). It stops when a step moves the image's edge by less
    than ``PATTERN_JOINT_TOL_PX`` or lowers the cost by less than one pixel's residual
    variance (a change the noise explains).

    Parameters
    ----------
    intr : the starting intrinsics (the corners' solution), at which ``views`` were built.
    views : (view id, :class:`PatternView`, its blurred textures, pose (rvec, tvec) (6,)).
    workers : processes that share the views.

    Returns
    -------
    The refined intrinsics (``intr`` itself when no step lowered the cost); a summary:
    ``views``, ``pixels``, ``iterations``, ``cost_before``, ``cost_after`` (sums of
    squared residuals in units of the markers' black-to-white step) and ``change``
    (refined minus starting value of each intrinsic); each view's pose (rvec, tvec) (6,)
    with them.
    """
    from .stores import executor

    th0 = _intrinsic_vector(intr)
    steps = _intrinsic_steps(intr)
    pixels = max(sum(v[1].pixels for v in views), 1)
    th, ps = th0.copy(), [np.asarray(v[3], float) for v in views]
    lam, it = 1e-3, 0

    def total(ex, th, ps) -> tuple[float, list[np.ndarray]]:
        got = list(ex.map(_joint_view_pose, [(pv, tex, p, th, intr) for (_, pv, tex, _), p
                                             in zip(views, ps, strict=True)]))
        return float(sum(g[0] for g in got)), [g[1] for g in got]

    with executor(max(1, min(workers, len(views)))) as ex:
        cost0, ps = total(ex, th, ps)
        cost = cost0
        for it in range(1, max_iter + 1):
            terms = list(ex.map(_joint_view_terms, [(pv, tex, p, th, intr, steps) for
                                                    (_, pv, tex, _), p in zip(views, ps,
                                                                              strict=True)]))
            if any(t is None for t in terms):
                logger.info("calibration: no compiled pattern kernel; intrinsics left to "
                            "the corners")
                return intr, {}, {v[0]: np.asarray(v[3], float) for v in views}
            moved, before = None, cost
            for _ in range(JOINT_TRIALS):
                A, b, back = np.zeros((9, 9)), np.zeros(9), []
                for Hpp, Htp, gp, Htt, gt in terms:
                    Hi = np.linalg.inv(Hpp + lam * np.diag(np.diag(Hpp)))
                    HtpHi = Htp @ Hi
                    A += Htt - HtpHi @ Htp.T
                    b += gt - HtpHi @ gp
                    back.append((Hi, Htp, gp))
                A += lam * np.diag(np.diag(A))
                d = -np.linalg.solve(A, b)
                new_ps = [p - Hi @ (gp + Htp.T @ d) for p, (Hi, Htp, gp)
                          in zip(ps, back, strict=True)]
                new_cost, new_ps = total(ex, th + d * steps, new_ps)
                if np.isfinite(new_cost) and new_cost < cost:
                    th, ps, cost, moved = th + d * steps, new_ps, new_cost, float(np.abs(d).max())
                    lam = max(lam / 10, 1e-9)
                    break
                lam *= 10
            logger.info(f"calibration: pattern refinement step {it}: cost {cost:.3f}"
                        + ("" if moved is None else
                           f", edge moved {PATTERN_JOINT_STEP_PX * moved:.4f} px"))
            if moved is None or PATTERN_JOINT_STEP_PX * moved < PATTERN_JOINT_TOL_PX \
                    or before - cost < cost / pixels:
                break
    out = _with_intrinsics(intr, th) if cost < cost0 else intr
    return out, {"views": len(views), "pixels": int(pixels),
                 "iterations": it, "cost_before": cost0, "cost_after": min(cost, cost0),
                 "change": dict(zip(INTRINSIC_NAMES, (_intrinsic_vector(out) - th0).tolist(),
                                    strict=True))}, \
        {v[0]: p for v, p in zip(views, ps, strict=True)}


def rotation_sd_per_px(obj: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                       intr: Intrinsics) -> float:
    """Predicted standard deviation (degrees) of a pose's rotation for 1 px of
    independent corner noise: sqrt(trace) of the rotation block of (J^T J)^-1, J the
    Jacobian of the projected points (n, 3) with respect to the six pose parameters.
    Multiply by the corner noise (e.g. the reprojection RMS) for the pose's own.
    Large for few, small or grazing markers, where rotation trades against shift."""
    _, J = cv2.projectPoints(np.asarray(obj, np.float64), rvec, tvec, intr.K, intr.dist)
    J = J[:, :6]
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return math.inf
    return math.degrees(math.sqrt(max(float(np.trace(cov[:3, :3])), 0.0)))


MIN_MEASURED_MARKERS = 4  # markers with four measured edges that suffice for a pose


def estimate_pose(
    cap: Capture, intr: Intrinsics, gray: np.ndarray, min_markers: int = 2,
    radiance: np.ndarray | None = None, pattern_max_pixels: int = 40000,
) -> dict:
    """Pose of one view from the surface markers.

    IPPE on all detected corners (planar), then Levenberg-Marquardt refinement. With
    ``radiance`` (H, W, 3 linear) the corners are first refined on the marker edges
    (:func:`refine_marker_corners`), and when at least ``MIN_MEASURED_MARKERS``
    markers had all four edges measured only those enter the solve.

    Returns
    -------
    dict with ``ok``, ``reason`` (when not ok), ``R`` (3x3), ``t`` (3,), ``centre_mm``,
    ``rms_px``, ``markers`` (ids used in the solve), ``detected`` (surface marker ids
    found), ``rotation_sd_deg_per_px`` (:func:`rotation_sd_per_px`), ``cov`` (predicted
    covariance of rvec, tvec from the residuals' own noise), ``noise_px`` (that noise:
    per corner coordinate in pixels corrected for the six fitted parameters, per edge
    point after the edge refinement, or in units of the markers' black-to-white step
    after the pattern refinement), ``solution`` (``corners``, ``edges`` or
    ``pattern``: which noise that is), ``edge_points`` (0 when corners alone were used)
    ``pattern_pixels``, ``pattern_blur_px`` (the optical blur the pattern fit chose,
    None without it) and ``pattern_markers`` (the markers that fit used: the detected
    ones and any it found where the pose puts them).

    With ``radiance`` the pose is then refined on the measured edge points
    (:func:`refine_pose_edges`), when at least two markers have measured edges, and
    finally on the markers' whole pattern (:func:`refine_pose_pattern`, on at most
    ``pattern_max_pixels``); each
    refinement is taken where it agrees with the solution before it.
    """
    if len(cap.marker_ids) == 0:
        return {"ok": False, "reason": "capture.yaml lists no surface markers", "markers": []}
    ids, corners = detect_markers(gray, cap.marker_dictionary, cap.marker_ids)
    known = {int(i): k for k, i in enumerate(cap.marker_ids)}
    use = [k for k, i in enumerate(ids) if int(i) in known]
    known_found = list(use)
    if len(use) < min_markers:
        return {"ok": False, "reason": f"{len(use)} surface markers found, need {min_markers}",
                "markers": [int(ids[k]) for k in use]}
    edges = None
    if radiance is not None and len(use):
        lum = np.asarray(radiance, np.float32) @ LUMINANCE.astype(np.float32)
        cells = aruco_dictionary(cap.marker_dictionary).markerSize + 2
        corners = np.array(corners, float)
        corners[use], measured, edges = refine_marker_corners(
            lum, corners[use], intr, cells, return_measured=True, return_edges=True)
        edge_use = list(use)
        # Detected corners of small oblique markers can be pixels off: with enough
        # markers measured on all four edges, leave the others out of the solve.
        if measured.sum() >= MIN_MEASURED_MARKERS:
            use = [k for k, ok in zip(use, measured, strict=True) if ok]
    detected = sorted(int(ids[k]) for k in known_found)
    obj = np.concatenate([np.c_[cap.marker_corners[known[int(ids[k])]], np.zeros(4)]
                          for k in use]).astype(np.float64)
    img = np.concatenate([corners[k] for k in use]).astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, intr.K, intr.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return {"ok": False, "reason": "solvePnP failed", "markers": [int(ids[k]) for k in use]}
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, intr.K, intr.dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, intr.K, intr.dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, 1))))
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    # corner solution: covariance from the 2-D residuals' noise per coordinate
    n_res = 2 * len(obj)
    noise = rms / math.sqrt(2) * math.sqrt(n_res / max(n_res - 6, 1))
    _, J = cv2.projectPoints(obj, rvec, t, intr.K, intr.dist)
    try:
        cov = np.linalg.inv(J[:, :6].T @ J[:, :6]) * noise**2
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    edge_points = 0
    if edges is not None and np.isfinite(cov).all():
        quads = np.array([cap.marker_corners[known[int(ids[k])]] for k in edge_use])
        ref = refine_pose_edges(quads, edges, corners[edge_use], ~measured, R, t, intr, noise)
        # taken where it agrees with the corner solution within that solution's own
        # uncertainty (chi-square, 6 dof, 99.9 %)
        if ref is not None:
            r2, _ = cv2.Rodrigues(ref["R"])
            d = np.r_[r2.ravel() - rvec.ravel(), ref["t"] - t]
            if float(d @ np.linalg.solve(cov, d)) < 22.5:
                R, t, cov, noise = ref["R"], ref["t"], ref["cov"], ref["edge_noise_px"]
                rvec, _ = cv2.Rodrigues(R)
                edge_points = ref["n"]
    pattern_pixels, blur_px, pattern_ids = 0, None, []
    if radiance is not None and np.isfinite(cov).all():
        lum = np.asarray(radiance, np.float32) @ LUMINANCE.astype(np.float32)
        ref = refine_pose_pattern(lum, cap, detected, R, t, intr, pattern_max_pixels,
                                  others=[int(i) for i in cap.marker_ids])
        if ref is not None:
            # taken where it agrees with the solution so far within both their
            # uncertainties (chi-square, 6 dof, 99.9 %)
            r2, _ = cv2.Rodrigues(ref["R"])
            d = np.r_[r2.ravel() - rvec.ravel(), ref["t"] - t]
            if float(d @ np.linalg.solve(cov + ref["cov"], d)) < 22.5:
                R, t, cov, noise = ref["R"], ref["t"], ref["cov"], ref["noise"]
                rvec, _ = cv2.Rodrigues(R)
                pattern_pixels, blur_px = ref["pixels"], ref["blur_px"]
                pattern_ids = ref["marker_ids"]
    C = camera_centre(R, t)
    if C[2] <= 0:
        return {"ok": False, "reason": "camera below the surface plane", "rms_px": rms,
                "markers": [int(ids[k]) for k in use]}
    return {"ok": True, "R": R, "t": t, "centre_mm": C, "rms_px": rms, "detected": detected,
            "rotation_sd_deg_per_px": rotation_sd_per_px(obj, rvec, t, intr),
            "cov": cov, "noise_px": noise, "edge_points": edge_points,
            "pattern_pixels": pattern_pixels, "pattern_blur_px": blur_px,
            "pattern_markers": pattern_ids,
            "solution": "pattern" if pattern_pixels else "edges" if edge_points else "corners",
            "markers": sorted(int(ids[k]) for k in use)}
