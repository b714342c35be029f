"""Renders of every model compared against the held-out photos (004 ch. 16).

For every held-out view with a pose: render each parameter map into that camera
(:mod:`parammap.render`), tone-map render and photo with the same
``1 - exp(-gamma L)``, and compare inside the sampled region (pixels whose plane point
lies on a marker, or that are saturated in every exposure of the photo, are left out):

- mean and standard deviation of the absolute 8-bit difference over pixels and
  channels (004 tables 16.1 and 16.2);
- PSNR on linear radiance, ``10 log10(peak^2 / MSE)`` with peak the photo's 99th
  percentile inside the mask.

gamma is chosen from each photo: the 99th percentile of its radiance in the region maps
to 0.95 (``gamma = ln 20 / p99``), so highlights stay below white. Two baselines share
the table: ``diffuse`` (per-texel mean radiance of the observation map) and
``nearest-view`` (the kept view nearest in direction, its HDR frame reprojected through
the plane, 004 ch. 3.5).
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from scipy.cluster.vq import kmeans2

from ..conventions import LUMINANCE
from ..geometry import Intrinsics, plane_to_texel
from ..models.display import tone_gamma
from ..models.radiometry import correct_frame
from ..render import render, reproject_frame, surface_points, tone_map
from ..stores.camera import kept_poses, load_intrinsics, read_poses
from ..stores.capture import Capture
from ..stores.hdr import read_hdr
from ..stores.images import write_image_atomic
from ..stores.metrics import write_metrics
from ..stores.observation import open_observation_map
from ..stores.params import ParamMap, ParamMapFiles
from ..stores.paths import Processed
from ..stores.radiometry import radiometry_for

logger = logging.getLogger(__name__)

__all__ = ["choose_gamma", "compare", "holdout_comparison", "marker_pixels", "pixel_regions",
           "region_errors", "run_holdout", "texel_regions"]

REGIONS = 6  # clusters of similar texels the held-out errors are broken down by


def texel_regions(obs_path: str | Path, k: int = REGIONS, seed: int = 0,
                  ) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Cluster the texels of an observation map into ``k`` regions of similar
    appearance, for held-out errors per region where no material map is known.

    Features per texel (standardised, k-means): log mean radiance per channel (colour
    and albedo) and the log ratio of the 95th percentile to the median of its
    luminance over the views (how glossy). Texels without observations get -1.

    Returns
    -------
    labels : (T, S) int; regions : one dict per label (texels, mean radiance,
        gloss ratio), ordered by label.
    """
    g = open_observation_map(obs_path)
    T, S, _ = g.shape
    feat = np.full((T, S, 4), np.nan)
    for sl in g.tiles():
        v = g.valid[sl]
        L = np.where(v[..., None], g.radiance[sl], np.nan)
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)  # texels with no views
            mean = np.nanmean(L, 2)
            lum = L @ LUMINANCE
            gloss = np.nanpercentile(lum, 95, 2) / np.nanmedian(lum, 2)
        feat[sl] = np.concatenate([np.log(np.maximum(mean, 1e-6)),
                                   np.log(np.maximum(gloss, 1.0))[..., None]], -1)
    ok = np.isfinite(feat).all(-1)
    labels = np.full((T, S), -1, int)
    x = feat[ok]
    if len(x) < k:
        return labels, []
    mu, sd = x.mean(0), x.std(0) + 1e-9
    _, lab = kmeans2((x - mu) / sd, k, minit="++", seed=seed)
    # order regions by brightness so that labels are stable to read
    order = np.argsort(np.argsort([x[lab == j, :3].mean() if (lab == j).any() else np.inf
                                   for j in range(k)]))
    labels[ok] = order[lab]
    regions = []
    for j in range(k):
        sel = labels[ok] == j
        regions.append({"region": j, "texels": int(sel.sum()),
                        "mean_radiance": np.exp(x[sel, :3].mean(0)).tolist()
                        if sel.any() else None,
                        "gloss_ratio": float(np.exp(x[sel, 3].mean())) if sel.any() else None})
    return labels, regions


def pixel_regions(labels: np.ndarray, points: np.ndarray, inside: np.ndarray,
                  width_mm: float, height_mm: float) -> np.ndarray:
    """(H, W) region label of each pixel's texel (-1 outside the region)."""
    T, S = labels.shape
    out = np.full(points.shape[:2], -1, int)
    P = points[inside]
    row, col = plane_to_texel(P[:, 0], P[:, 1], S, T, width_mm, height_mm)
    out[inside] = labels[np.clip(row.astype(int), 0, T - 1), np.clip(col.astype(int), 0, S - 1)]
    return out


def _diff8(photo: np.ndarray, image: np.ndarray, gamma: float) -> np.ndarray:
    """(H, W, 3) int16 absolute difference of the two images' 8-bit tone maps."""
    return np.abs(tone_map(photo, gamma).astype(np.int16) - tone_map(image, gamma))


def region_errors(photo: np.ndarray, image: np.ndarray, mask: np.ndarray, gamma: float,
                  regions: np.ndarray) -> dict[str, dict[str, float]]:
    """Mean absolute 8-bit difference per region label (``regions``: (H, W) ints, -1
    ignored), with the pixel count of each: ``{label: {mean_diff_8bit, pixels}}``."""
    ok = mask & np.isfinite(image).all(-1) & (regions >= 0)
    d = _diff8(photo, image, gamma).mean(-1, dtype=float)[ok]
    lab = regions[ok]
    out = {}
    for j in np.unique(lab):
        sel = lab == j
        out[str(int(j))] = {"mean_diff_8bit": float(d[sel].mean()), "pixels": int(sel.sum())}
    return out


def choose_gamma(photo: np.ndarray, mask: np.ndarray) -> float:
    """Tone-mapping gamma putting the photo's 99th percentile at 0.95."""
    return tone_gamma(photo[mask])


def marker_pixels(cap: Capture, points: np.ndarray, margin_mm: float = 1.0) -> np.ndarray:
    """(H, W) bool: pixels whose plane point lies on a marker (grown by a margin)."""
    out = np.zeros(points.shape[:2], bool)
    for quad in cap.marker_corners:
        x0, y0 = quad.min(0) - margin_mm
        x1, y1 = quad.max(0) + margin_mm
        out |= (points[..., 0] >= x0) & (points[..., 0] <= x1) & (points[..., 1] >= y0) \
            & (points[..., 1] <= y1)
    return out


def compare(photo: np.ndarray, image: np.ndarray, mask: np.ndarray, gamma: float) -> dict:
    """Figures of one render against the photo inside ``mask``."""
    ok = mask & np.isfinite(image).all(-1)
    diff = _diff8(photo, image, gamma)[ok]
    lin = (image[ok] - photo[ok]).astype(float)
    peak = float(np.percentile(photo[mask], 99)) if mask.any() else 1.0
    mse = float(np.mean(lin ** 2)) if lin.size else float("nan")
    return {"mean_diff_8bit": float(diff.mean()) if diff.size else None,
            "std_diff_8bit": float(diff.std()) if diff.size else None,
            "psnr_db": 10 * math.log10(peak ** 2 / mse) if mse > 0 else None,
            "pixels": int(ok.sum()), "coverage": float(ok.sum() / max(mask.sum(), 1))}


def holdout_comparison(
    cap: Capture, intr: Intrinsics, processed: str | Path, maps: Mapping[str, ParamMap],
    out_dir: str | Path, regions: tuple[np.ndarray, list[dict]] | None = None,
) -> dict[str, Any]:
    """Compare every model in ``maps`` (name -> map, a dict or maps read as each is
    needed, :class:`~parammap.stores.params.ParamMapFiles`; include the ``diffuse``
    baseline from :func:`diffuse_map`) and the nearest-view baseline with every held-out view.

    ``regions``: (T, S) labels and their descriptions (default :func:`texel_regions` of
    the observation map); every comparison is also broken down by region.

    Writes 8-bit images (photo, render and difference per model) under ``out_dir``;
    returns the metrics for ``metrics/holdout.json``."""
    proc = Processed(processed)
    out_dir = Path(out_dir)
    held = [r for r in read_poses(proc.poses)["views"] if r.get("holdout")]
    kept, _ = kept_poses(proc)
    centre = np.array([cap.width_mm / 2, cap.height_mm / 2, 0.0])
    kdir = np.array([(v.centre - centre) / np.linalg.norm(v.centre - centre) for v in kept])
    labels, described = regions or texel_regions(proc.observation)
    radiometry = radiometry_for(cap, proc)

    def frame(view_id: str, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # read as the observation map read its frames: the flat-field and colour out
        rad, sat, _ = read_hdr(proc.hdr(view_id))
        return correct_frame(rad, intr, R, t, cap.width_mm, cap.height_mm, radiometry), sat

    result: dict[str, Any] = {"views": {}, "models": list(maps) + ["nearest-view"],
                              "skipped": {}, "regions": described}
    for r in held:
        vid = str(r["id"])
        if not r.get("kept"):
            result["skipped"][vid] = r.get("reason", "no pose")
            logger.info(f"holdout: skipping {vid}: {result['skipped'][vid]}")
            continue
        R, t = np.asarray(r["R"], float), np.asarray(r["t"], float)
        photo, sat = frame(vid, R, t)
        P, inside = surface_points(intr, R, t, cap.width_mm, cap.height_mm,
                                   (photo.shape[1], photo.shape[0]))
        mask = inside & ~sat & ~marker_pixels(cap, P)
        gamma = choose_gamma(photo, mask)
        C = np.asarray(r["centre_mm"], float)
        near = kept[int(np.argmax(kdir @ ((C - centre) / np.linalg.norm(C - centre))))]
        row = {"gamma": gamma, "nearest_view": near.id, "models": {}, "regions": {}}
        px_regions = pixel_regions(labels, P, inside, cap.width_mm, cap.height_mm)
        if r.get("warning"):  # the pose policy would have dropped a fitted view like it
            row["pose_warning"] = r["warning"]
            logger.info(f"holdout: {vid}: poor pose, compared all the same: {r['warning']}")
        photo8 = tone_map(np.where(inside[..., None], photo, 0), gamma)
        write_image_atomic(out_dir / f"{vid}_photo.png", photo8)
        for name in [*maps, "nearest-view"]:  # one render at a time: a 12 MP frame each
            img = (render(maps[name], intr, R, t, surface=(P, inside))[0] if name in maps
                   else reproject_frame(frame(near.id, near.R, near.t)[0], intr, near.R,
                                        near.t, P, inside))
            row["models"][name] = compare(photo, img, mask, gamma)
            row["regions"][name] = region_errors(photo, img, mask, gamma, px_regions)
            img8 = tone_map(np.where(inside[..., None], img, 0), gamma)
            write_image_atomic(out_dir / f"{vid}_{name}.png", img8)
            d = np.abs(img8.astype(np.int16) - photo8).mean(-1)
            d = np.where(mask, d, 0)
            write_image_atomic(out_dir / f"{vid}_{name}_diff.png",
                               np.repeat(np.clip(d, 0, 255).astype(np.uint8)[..., None], 3, -1))
            logger.info(f"holdout: {vid} {name}: mean 8-bit difference "
                        f"{row['models'][name]['mean_diff_8bit']:.2f}")
        result["views"][vid] = row
    return result


def run_holdout(cap: Capture, processed: str | Path, config: dict[str, Any], *,
                models: list[str]) -> dict[str, Any]:
    """The holdout stage: render the exported maps ``params/<model>.exr`` of ``models``
    in every held-out view and compare (images under ``holdout/``, figures in
    ``metrics/holdout.json``, also returned)."""
    proc = Processed(processed)
    # each map read when its turn comes in a view (a lab capture's ten maps at once:
    # several GB)
    maps = ParamMapFiles({name: proc.params(name) for name in models})
    res = holdout_comparison(cap, load_intrinsics(proc.intrinsics), proc.root, maps,
                             proc.holdout_dir)
    write_metrics(proc.metrics("holdout"), res)
    return res
