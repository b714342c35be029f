"""A view's pose from the markers it sees, and how uncertain it leaves each surface point:
detected corners, refined on the markers' edges and on the printed pattern, then
``solvePnP``; the rotation's and the points' standard deviations from the fit's
covariance (``docs/reference/conventions.md``)."""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

from ..config import default
from ..geometry import Intrinsics, camera_centre
from ..stores.capture import Capture, aruco_dictionary
from .markers import detect_markers, luminance, refine_marker_corners, refine_pose_edges
from .pattern import refine_pose_pattern

logger = logging.getLogger(__name__)

__all__ = ["MIN_MEASURED_MARKERS", "estimate_pose", "point_uncertainty", "rotation_sd_per_px"]


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
    cap: Capture, intr: Intrinsics, gray: np.ndarray,
    min_markers: int = default("poses.min_markers"),
    radiance: np.ndarray | None = None, pattern_max_pixels: int = 40000,
) -> dict:
    """Pose of one view from the surface markers.

    IPPE on all detected corners (planar), then Levenberg-Marquardt refinement. With
    ``radiance`` (H, W, 3 linear, or its (H, W) luminance) the corners are first
    refined on the marker edges (:func:`refine_marker_corners`), and when at least
    ``MIN_MEASURED_MARKERS`` markers had all four edges measured only those enter the
    solve.

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
        lum = luminance(radiance)
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
        lum = luminance(radiance)
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


def point_uncertainty(cov: np.ndarray, R: np.ndarray, t: np.ndarray, intr: Intrinsics,
                      P: np.ndarray, texel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Shift (1 sd) of the surface points P (m, 3) a view's pixels see, from its pose
    covariance ``cov`` (rvec, tvec): in mm, and relative to the sampling width there
    (the texel widened by the pixel's footprint on the surface).

    Returns
    -------
    (m,) shift in mm, (m,) shift over the sampling width (NaN where P is behind the
    camera).
    """
    _, B = _proj_jac(P, R, t, intr)
    A = _plane_jac(P, R, t, intr)
    # the plane point seen at a fixed pixel moves by -A^-1 B dp
    with np.errstate(all="ignore"):
        M = np.linalg.solve(A, B)  # (m, 2, 6)
        cxy = np.einsum("mij,jk,mlk->mil", M, cov, M)
        shift = np.sqrt(np.trace(cxy, axis1=1, axis2=2))
        Ai = np.linalg.inv(A)  # a pixel's footprint on the surface (mm per px)
        width2 = texel_mm**2 * np.eye(2) + Ai @ np.swapaxes(Ai, 1, 2)
        rel = np.sqrt(np.trace(np.linalg.solve(width2, cxy), axis1=1, axis2=2))
    return shift, rel


def _proj_jac(P: np.ndarray, R, t, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions (m, 2) of plane points P (m, 3) and their Jacobian (m, 2, 6)."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, float))
    uv, J = cv2.projectPoints(P.astype(np.float64), rvec, np.asarray(t, float),
                              intr.K, intr.dist)
    return uv.reshape(-1, 2), J[:, :6].reshape(-1, 2, 6)


def _plane_jac(P: np.ndarray, R, t, intr: Intrinsics, eps: float = 1e-3) -> np.ndarray:
    """d(pixel)/d(plane x, y) at plane points P: (m, 2, 2)."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, float))
    cols = []
    for d in ([eps, 0, 0], [0, eps, 0]):
        a, _ = cv2.projectPoints((P + d).astype(np.float64), rvec, np.asarray(t, float),
                                 intr.K, intr.dist)
        b, _ = cv2.projectPoints((P - d).astype(np.float64), rvec, np.asarray(t, float),
                                 intr.K, intr.dist)
        cols.append((a - b).reshape(-1, 2) / (2 * eps))
    return np.stack(cols, -1)
