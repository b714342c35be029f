"""The pose stage: each view's pose from the surface markers, the map resolution, and
which views the map can use.

A view is good enough when what the map needs from it is good enough, not when its
rotation is below a fixed angle: the uncertainty of a planar pose is mostly a tilt
traded against a shift that barely moves the surface in the image. The predicted pose
covariance (residual noise x marker geometry, from the pose solve of
:func:`parammap.stages.calibration.estimate_pose`, on the measured marker edges where it can)
is propagated to two figures, each 1 sd:

- ``texel_shift``: how far the surface point seen at a pixel moves, worst over the
  region, as a fraction of the width a texel's observation averages over in that view
  (the texel, widened by the view's pixel footprint; ``poses.max_texel_shift``);
- ``direction_sd_deg``: how far the view direction from the region's centre to the
  camera turns, against the angular spacing of the captured views (median
  nearest-neighbour angle; ``poses.max_direction_fraction``).

With ``poses.partial_views`` (off by default), a view whose worst point exceeds
``max_texel_shift`` but whose nearer part of the region is within it (a grazing view:
its far side is foreshortened and uncertain) is kept as *partial*:
``camera/poses.yaml`` records its covariance and the share of the region it measures
well, and the observation stage leaves its other texels out. Measured on the
physically based captures, such poses were worse than their near-side shift says
(up to 9 mm and 0.9 deg off, directions up to 0.8 deg), so the default drops them.

The noise is each view's residual corrected for the six fitted pose parameters, at
least the capture's median for that kind of solve (a view with few points can fit its
own noise). Held-out views are never dropped by this policy: a poor one is kept with a
``warning`` that the held-out comparison reports.

``observation.texels_x: auto`` picks about one texel per photo pixel at the median view
(:func:`map_resolution`), capped only where the observation map would not fit its disk
budget: ``observation.max_map_gib``, or when unset half the free space on the processed
folder's disk (the build's scratch copy needs the other half); the choice is logged
either way and written to ``camera/poses.yaml`` (``map``) so the observation stage uses
the same map the policy judged.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from ..geometry import Intrinsics, unit
from ..parallel import executor, progress
from ..stores.camera import load_intrinsics
from ..stores.capture import Capture
from ..stores.common import free_disk_gib
from ..stores.exr import ExrError
from ..stores.metrics import write_metrics
from ..stores.observation import BYTES_PER_OBSERVATION
from ..stores.paths import Processed
from ..vision.markers import read_marker_frame, to_gray8
from ..vision.pattern import PATTERN_NOISE_FACTOR
from ..vision.pose import _plane_jac, estimate_pose, point_uncertainty

logger = logging.getLogger(__name__)

__all__ = ["corner_gate", "map_resolution", "px_per_mm", "run_poses", "view_spacing_deg",
           "view_uncertainty"]

PARTIAL_GRID = 17  # points per side where a view's usable part of the region is judged


def _region_grid(cap: Capture, n: int = 5) -> np.ndarray:
    x = np.linspace(0, cap.width_mm, n)
    y = np.linspace(0, cap.height_mm, n)
    X, Y = np.meshgrid(x, y)
    return np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)


def px_per_mm(cap: Capture, R, t, intr: Intrinsics) -> float:
    """Photo pixels per mm of surface at the region's centre (geometric mean of the two
    axes, so foreshortening counts)."""
    c = np.array([[cap.width_mm / 2, cap.height_mm / 2, 0.0]])
    return float(math.sqrt(abs(np.linalg.det(_plane_jac(c, R, t, intr)[0]))))


def view_uncertainty(cov: np.ndarray, R: np.ndarray, t: np.ndarray, intr: Intrinsics,
                     cap: Capture, texel_mm: float) -> dict[str, float]:
    """Surface-point shift and view-direction error, 1 sd, of a pose with covariance
    ``cov`` (rvec, tvec).

    Returns
    -------
    dict with ``shift_mm`` (worst over a 5x5 grid of the region), ``texel_shift`` (the
    shift over the width a texel's observation averages over in this view: the texel
    widened by the photo pixel's footprint on the surface, per direction, so a grazing
    view whose pixels span several texels is judged at its own resolution; worst over
    the grid) and ``direction_sd_deg`` (at the region's centre).
    """
    shift_mm, rel_all = point_uncertainty(cov, R, t, intr, _region_grid(cap), texel_mm)
    shift, rel = float(shift_mm.max()), float(rel_all.max())
    # camera centre C = -R^T t as a function of (rvec, tvec), by central differences
    rvec, _ = cv2.Rodrigues(np.asarray(R, float))
    p0 = np.r_[rvec.ravel(), np.asarray(t, float).ravel()]

    def centre(p):
        Rm, _ = cv2.Rodrigues(p[:3])
        return -Rm.T @ p[3:]
    JC = np.stack([(centre(p0 + e) - centre(p0 - e)) / 2e-6 for e in np.eye(6) * 1e-6], 1)
    cC = JC @ cov @ JC.T
    X0 = np.array([cap.width_mm / 2, cap.height_mm / 2, 0.0])
    v = centre(p0) - X0
    dist = float(np.linalg.norm(v))
    u = v / dist
    Pp = np.eye(3) - np.outer(u, u)
    ang = math.sqrt(max(float(np.trace(Pp @ cC @ Pp)), 0.0)) / dist
    return {"shift_mm": shift, "texel_shift": rel, "direction_sd_deg": math.degrees(ang)}


def view_spacing_deg(centres: np.ndarray, cap: Capture) -> float:
    """Median angle (deg) from each view direction (region centre to camera) to its
    nearest neighbour: the angular spacing of the captured views."""
    if len(centres) < 2:
        return 180.0
    X0 = np.array([cap.width_mm / 2, cap.height_mm / 2, 0.0])
    d = unit(np.asarray(centres, float) - X0)
    cosang = np.clip(d @ d.T, -1, 1)
    np.fill_diagonal(cosang, -1)
    return float(np.degrees(np.median(np.arccos(cosang.max(1)))))


def map_resolution(cap: Capture, ppmm: list[float], n_views: int, texels_x: int | str,
                   texels_y: int | None, max_gib: float) -> dict[str, Any]:
    """The map size: ``texels_x`` as configured, or for ``auto`` about one texel per
    photo pixel at the median view (``ppmm``: pixels per mm of each fitted view),
    capped so the observation map (``n_views`` views) stays within ``max_gib``.

    Returns
    -------
    dict with ``S``, ``T``, ``texel_mm``, ``source`` (config | auto), and for auto
    ``px_per_mm_median`` and ``capped_by_budget``.
    """
    out: dict[str, Any] = {}
    if texels_x == "auto":
        med = float(np.median(ppmm)) if len(ppmm) else 1.0
        S = max(8, int(round(cap.width_mm * med)))
        T = int(texels_y) if texels_y else max(8, int(round(S * cap.height_mm / cap.width_mm)))
        per_texel = BYTES_PER_OBSERVATION * max(n_views, 1)
        budget = max_gib * 2**30 / per_texel
        photos = (S, T)
        capped = S * T > budget
        if capped:
            k = math.sqrt(budget / (S * T))
            S, T = max(8, int(S * k)), max(8, int(T * k))
        out = {"source": "auto", "px_per_mm_median": med, "capped_by_budget": bool(capped),
               "max_map_gib": max_gib, "photos_S": photos[0], "photos_T": photos[1],
               "photos_map_gib": photos[0] * photos[1] * per_texel / 2**30}
    else:
        S = int(texels_x)
        T = int(texels_y) if texels_y else max(1, round(S * cap.height_mm / cap.width_mm))
        out = {"source": "config"}
    return {"S": S, "T": T, "texel_mm": cap.width_mm / S, **out}


def _view_pose(job: tuple) -> dict[str, Any]:
    """The pose of one view from its HDR frame (a process pool's job)."""
    cap, intr, path, cfg = job
    try:
        img = read_marker_frame(path, cap)
    except ExrError as exc:
        return {"ok": False, "reason": str(exc)}
    return estimate_pose(cap, intr, to_gray8(img), cfg["min_markers"], radiance=img)


def corner_gate(recs: list[dict], max_rms_px: float) -> None:
    """Drop views whose corner solution misses ``max_rms_px`` (the guard against wrong
    detections), unless their pose was refined on the markers' pattern and that fit's
    residual is no more than ``PATTERN_NOISE_FACTOR`` times the capture's median one:
    at grazing views detected corners are pixels off while the pattern pins the pose
    (pbr-bench's 80 deg view: corners 2.2 px, pattern pose 0.23 mm off). Changes
    ``recs`` (estimate_pose records) in place; a waived view gets ``rms_waived``."""
    typical = [r["noise_px"] for r in recs if r["ok"] and r["solution"] == "pattern"]
    limit = PATTERN_NOISE_FACTOR * float(np.median(typical)) if typical else -math.inf
    for rec in recs:
        if not rec["ok"] or rec["rms_px"] <= max_rms_px:
            continue
        what = f"corner reprojection RMS {rec['rms_px']:.2f} px above {max_rms_px} px"
        if rec["solution"] == "pattern" and rec["noise_px"] <= limit:
            rec["rms_waived"] = (f"{what}; kept: its pattern residual {rec['noise_px']:.3f} "
                                 f"is within {PATTERN_NOISE_FACTOR} x the capture's median")
        else:
            rec.update(ok=False, reason=what)


def run_poses(cap: Capture, processed: str | Path, config: dict[str, Any], *,
              workers: int | None = None) -> dict[str, Any]:
    """The poses stage: the pose of every view (on ``workers`` processes), the map
    resolution and the view policy; writes ``camera/poses.yaml`` and
    ``metrics/poses.json`` and returns the latter's figures. ``config``: the validated
    workflow config (sections ``poses`` and ``observation``)."""
    cfg, obs_cfg = config["poses"], config["observation"]
    workers = workers or config["workers"]
    out = Processed(processed)
    intr = load_intrinsics(out.intrinsics)
    jobs = [(cap, intr, out.hdr(v.id), cfg) for v in cap.views]
    recs = []
    with executor(max(1, min(workers, len(jobs)))) as ex:
        posed_views = progress(ex.map(_view_pose, jobs), len(jobs), "poses: views", logger)
        for v, rec in zip(cap.views, posed_views, strict=True):
            found = set(rec.get("pattern_markers") or []) - set(rec.get("detected") or [])
            logger.info(f"poses: {v.id} " + (f"{rec.get('solution')} solution, "
                                             f"{len(rec['markers'])} markers"
                                             + (f" (+{len(found)} the detector missed, "
                                                "found on their pattern)" if found else "")
                                             if rec["ok"] else rec["reason"]))
            recs.append((v, rec))
    corner_gate([r for _, r in recs], cfg["max_rms_px"])
    for v, rec in recs:
        if rec.get("rms_waived"):
            logger.info(f"poses: {v.id}: {rec['rms_waived']}")
    posed = [(v, r) for v, r in recs if r["ok"]]
    fitted = [(v, r) for v, r in posed if not v.holdout]
    max_gib = obs_cfg["max_map_gib"]
    if max_gib is None and obs_cfg["texels_x"] == "auto":
        free = free_disk_gib(out.root)
        max_gib = free / 2
        logger.info(f"poses: observation map budget {max_gib:.1f} GiB, half the {free:.1f} "
                    f"GiB free on {out.root}'s disk (observation.max_map_gib unset)")
    grid = map_resolution(cap, [px_per_mm(cap, r["R"], r["t"], intr) for _, r in fitted],
                          len(fitted), obs_cfg["texels_x"], obs_cfg["texels_y"], max_gib)
    spacing = view_spacing_deg(np.array([r["centre_mm"] for _, r in fitted]), cap)
    max_dir = cfg["max_direction_fraction"] * spacing
    max_shift_mm = cfg["max_texel_shift"] * grid["texel_mm"]
    # noise floors per kind of solution (corners, edge points and the marker pattern
    # measure different noises)
    med = {kind: float(np.median([r["noise_px"] for _, r in posed
                                  if r["solution"] == kind] or [0.0]))
           for kind in {r["solution"] for _, r in posed}}
    if grid.get("capped_by_budget"):  # never silently coarser than the photos
        logger.warning(f"poses: the photos resolve {grid['photos_S']}x{grid['photos_T']} "
                       f"texels ({grid['photos_map_gib']:.1f} GiB of observations); "
                       f"the disk budget of {grid['max_map_gib']:.3g} GiB caps the map at "
                       f"{grid['S']}x{grid['T']}: raise observation.max_map_gib (or free "
                       "disk space) to keep the photos' resolution")
    elif grid["source"] == "auto":
        logger.info(f"poses: the map follows the photos' resolution "
                    f"({grid['photos_map_gib']:.2f} GiB of observations, within the "
                    f"disk budget of {grid['max_map_gib']:.3g} GiB)")
    logger.info(f"poses: map {grid['S']}x{grid['T']} texels ({grid['texel_mm']:.3f} mm, "
                f"{grid['source']}); view spacing {spacing:.2f} deg; limits (1 sd) "
                f"{cfg['max_texel_shift']} texel = {max_shift_mm:.3f} mm, "
                f"direction {max_dir:.3f} deg")
    records = []
    for v, rec in recs:
        row: dict[str, Any] = {"id": v.id, "holdout": v.holdout}
        if rec["ok"]:
            # a view can fit its own noise: at least the capture's median noise level
            noise = max(rec["noise_px"], med[rec["solution"]])
            cov = rec["cov"] * (noise / max(rec["noise_px"], 1e-9)) ** 2
            u = view_uncertainty(cov, rec["R"], rec["t"], intr, cap, grid["texel_mm"])
            rot = math.degrees(math.sqrt(max(float(np.trace(cov[:3, :3])), 0.0)))
            rec.update(texel_shift=u["texel_shift"], shift_mm=u["shift_mm"],
                       direction_sd_deg=u["direction_sd_deg"], rotation_sd_deg=rot,
                       corner_noise_px=noise)
            why = []
            if rec["texel_shift"] > cfg["max_texel_shift"]:
                # a grazing view measures its near side well and its far side poorly:
                # keep it where its surface points are certain enough (the observation
                # map leaves out the rest, texel by texel)
                _, rel = point_uncertainty(cov, rec["R"], rec["t"], intr,
                                           _region_grid(cap, PARTIAL_GRID), grid["texel_mm"])
                covered = float(np.mean(rel <= cfg["max_texel_shift"]))
                if covered > 0 and not v.holdout and cfg.get("partial_views", False):
                    rec.update(partial=covered, cov=cov)
                else:
                    why.append(f"surface points uncertain by {rec['shift_mm']:.2f} mm = "
                               f"{rec['texel_shift']:.2f} of the sampling width (1 sd) above "
                               f"{cfg['max_texel_shift']}")
            if rec["direction_sd_deg"] > max_dir:
                why.append(f"view direction uncertain by {rec['direction_sd_deg']:.3f} deg "
                           f"(1 sd) above {cfg['max_direction_fraction']} x {spacing:.2f} deg "
                           "view spacing")
            if cfg.get("max_rotation_sd_deg") is not None and rot > cfg["max_rotation_sd_deg"]:
                why.append(f"rotation uncertain: {rot:.3f} deg (1 sd) above "
                           f"{cfg['max_rotation_sd_deg']}")
            if why and v.holdout:
                row["warning"] = "; ".join(why)
                logger.info(f"poses: held-out view {v.id} kept for the comparison, but "
                            f"{row['warning']}")
            elif why:
                rec.update(ok=False, reason="; ".join(why))
        if not rec["ok"]:
            logger.info(f"poses: dropping view {v.id}: {rec['reason']}")
        row["kept"] = bool(rec["ok"])
        if not rec["ok"]:
            row["reason"] = rec["reason"]
        row.update({k: np.asarray(rec[k]).tolist() for k in ("R", "t", "centre_mm") if k in rec})
        row.update({k: float(rec[k]) for k in ("rms_px", "corner_noise_px", "texel_shift",
                                               "shift_mm", "direction_sd_deg",
                                               "rotation_sd_deg") if k in rec})
        if rec["ok"] and "partial" in rec:
            # the observation stage masks the texels this view sees too uncertainly
            row.update(partial=rec["partial"], cov=np.asarray(rec["cov"]).tolist(),
                       max_texel_shift=float(cfg["max_texel_shift"]))
            logger.info(f"poses: view {v.id} kept for {100 * rec['partial']:.0f} % of the region "
                        f"(elsewhere surface points uncertain by up to {rec['shift_mm']:.2f} mm = "
                        f"{rec['texel_shift']:.2f} of the sampling width)")
        if "edge_points" in rec:
            row["edge_points"] = int(rec["edge_points"])
        if "solution" in rec:
            row["pose_solution"] = rec["solution"]
            row["pattern_pixels"] = int(rec["pattern_pixels"])
            if rec.get("pattern_markers"):
                row["pattern_markers"] = [int(i) for i in rec["pattern_markers"]]
        if rec["ok"] and "rms_waived" in rec:
            row["rms_waived"] = rec["rms_waived"]
        row["markers"] = rec.get("markers", [])
        if "detected" in rec:
            row["detected"] = rec["detected"]
        records.append(row)
    path = out.poses
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(yaml.safe_dump({"map": grid, "view_spacing_deg": spacing,
                                   "views": records}, sort_keys=False))
    tmp.replace(path)
    kept = [r for r in records if r["kept"]]
    rms = [r["rms_px"] for r in kept]
    logger.info(f"poses: kept {len(kept)} of {len(records)} views")
    m = {
        "views": len(records), "kept": len(kept),
        "kept_fraction": len(kept) / max(len(records), 1),
        "dropped": {r["id"]: r["reason"] for r in records if not r["kept"]},
        "partial": {r["id"]: r["partial"] for r in records if "partial" in r},
        "held_out_warnings": {r["id"]: r["warning"] for r in records if "warning" in r},
        "corner_rms_waived": {r["id"]: r["rms_waived"] for r in records if "rms_waived" in r},
        "map": grid, "view_spacing_deg": spacing,
        "limits": {"max_texel_shift": cfg["max_texel_shift"],
                   "max_shift_mm": max_shift_mm, "max_direction_sd_deg": max_dir},
        "median_rms_px": float(np.median(rms)) if rms else None,
        "max_rms_px": float(np.max(rms)) if rms else None,
        "max_texel_shift": max((r["texel_shift"] for r in kept), default=None),
        "max_direction_sd_deg": max((r["direction_sd_deg"] for r in kept), default=None),
        "rms_px": {r["id"]: r["rms_px"] for r in kept}}
    write_metrics(out.metrics("poses"), m)
    return m
