"""Camera intrinsics from board photos, and each view's pose from surface markers.

OpenCV 5 APIs (``pitfalls.md``): ``CharucoDetector.detectBoard`` and
``ArucoDetector.detectMarkers``, then ``calibrateCamera`` / ``solvePnP``. Poses follow
docs/reference/conventions.md: ``p_cam = R @ p_world + t`` with the surface in z = 0 (mm).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..config import default
from ..geometry import (
    Intrinsics,
)
from ..parallel import executor, progress
from ..stores.camera import CalibrationError, load_intrinsics, save_intrinsics
from ..stores.capture import Capture, aruco_dictionary
from ..stores.images import ImageReadError, read_image
from ..stores.metrics import write_metrics
from ..stores.paths import Processed
from ..vision.markers import (
    detect_markers,
    luminance,
    read_marker_frame,
    refine_marker_corners,
    to_gray8,
)
from ..vision.pattern import (
    PATTERN_JOINT_MAX_VIEWS,
    PATTERN_JOINT_MIN_VIEWS,
    PATTERN_JOINT_PIXELS,
    PATTERN_JOINT_VIEW_PIXELS,
    PATTERN_NOISE_FACTOR,
    PatternView,
    refine_intrinsics_pattern,
)
from ..vision.pose import estimate_pose

logger = logging.getLogger(__name__)

__all__ = ["Intrinsics", "board_points", "calibrate", "detect_markers", "estimate_pose",
           "load_intrinsics", "marker_views", "refine_marker_corners", "run_calibration",
           "save_intrinsics", "to_gray8"]


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


def calibrate(cap: Capture, min_images: int = default("calibration.min_images"),
              min_corners: int = default("calibration.min_corners"),
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

    ``frames`` yields (view id, linear radiance (H, W, 3) or a RAW frame's (H, W) marker
    image, :func:`~parammap.vision.markers.marker_image`). Corners are edge-refined
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
    lum = luminance(rad)
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
    cap, intr, vid, path, max_pixels = job
    img = read_marker_frame(path, cap)
    rec = estimate_pose(cap, intr, to_gray8(img), radiance=img,
                        pattern_max_pixels=max_pixels)
    if not rec["ok"] or rec["solution"] != "pattern":
        return None
    rvec, _ = cv2.Rodrigues(rec["R"])
    lum = luminance(img)
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

    # beyond PATTERN_JOINT_MAX_VIEWS a stride over the views (their order is the
    # capture's, unrelated to the intrinsics) keeps the stage's time bounded
    frames = list(frames)[::math.ceil(len(frames) / PATTERN_JOINT_MAX_VIEWS) or 1]
    lo, hi = PATTERN_JOINT_VIEW_PIXELS
    per_view = int(np.clip(PATTERN_JOINT_PIXELS / max(len(frames), 1), lo, hi))
    with executor(max(1, min(workers, len(frames)))) as ex:
        jobs = [(cap, intr, vid, p, per_view) for vid, p in frames]
        got = [g for g in progress(ex.map(_pattern_view_job, jobs), len(jobs),
                                   "calibration: pattern views", logger) if g is not None]
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
    cap, intr, vid, path, min_markers = job
    return _marker_view(cap, intr, vid, read_marker_frame(path, cap), min_markers)


def run_calibration(cap: Capture, processed: str | Path, config: dict[str, Any], *,
                    workers: int | None = None) -> Intrinsics:
    """The calibrate stage: intrinsics from the board photos, then (config
    ``calibration.use_marker_views``) a second pass that adds the surface markers seen
    in the captured views' HDR frames, started from the board's solution, and
    (``calibration.refine_on_pattern``) a third that fits the intrinsics and those views'
    poses together on their markers' whole pattern (:func:`refine_intrinsics_pattern`,
    from ``PATTERN_JOINT_MIN_VIEWS`` views with a pattern pose). A capture's saved
    intrinsics are used as they are. Writes ``camera/intrinsics.yaml`` and
    ``metrics/calibration.json``; ``config``: the validated workflow config (section
    ``calibration``); the marker views are measured on ``workers`` processes (default:
    config ``workers``)."""
    cfg = config["calibration"]
    workers = workers or config["workers"]

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

            jobs = [(cap, intr, vid, p, cfg["min_markers_per_view"]) for vid, p in hdr]
            with executor(max(1, min(workers, len(jobs)))) as ex:
                extra = [m for m in progress(ex.map(_marker_view_job, jobs), len(jobs),
                                             "calibration: marker views", logger)
                         if m is not None]
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


