"""The advisor stage: where to shoot next (:mod:`parammap.models.advisor`).

From a finished MH fit (``advisor.source``, default ``mh-auto``) and its observation
map: a sample of the fitted texels (whole tiles, as the materials stage samples) and
their own views give each texel's information matrix; candidate camera directions
spread evenly over the hemisphere up to ``observation.max_zenith_deg`` are ranked by
greedy design (``advisor.criterion``): ``volume`` (default, D-optimal), by how much a
view there would shrink the volume of the texels' parameter uncertainty;
``prediction`` (I-optimal), the variance of their renders over the hemisphere. On the
analytic demo, judged against its truth in 256 directions over five sets of eight views
set aside, three D-optimal views cut the error 3.5x as much as three random ones, the
I-optimal 2x (``benchmarks/advisor_pbr.py --preset demo``). Texels without a
lobe gain little from any view: where no sampled texel has one (every highlight fell
between the views, or the surface is matte), the candidates are ranked by their angle to
the nearest captured view instead (filling the largest gaps), and the advice says so.

Writes ``metrics/advice.json`` (the ranked directions: zenith and azimuth in degrees in
the surface frame, docs/reference/conventions.md, and each one's gain) and, with a report folder,
``advice.png``: the gain of every candidate on the hemisphere, the captured views and
the advised ones numbered.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..conventions import mh_ks, mh_lobes
from ..geometry import unit
from ..models.advisor import advise_directions, hemisphere_candidates
from ..stores.camera import read_poses
from ..stores.fit import open_mh_source
from ..stores.metrics import write_metrics
from ..stores.observation import sample_texel_observations
from ..stores.paths import Processed

logger = logging.getLogger(__name__)

__all__ = ["run_advisor"]


def _angles(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zenith and azimuth (degrees) of unit directions (..., 3)."""
    zen = np.degrees(np.arccos(np.clip(d[..., 2], -1, 1)))
    az = np.degrees(np.arctan2(d[..., 1], d[..., 0])) % 360
    return zen, az


def run_advisor(source: str | Path, processed: str | Path, config: dict[str, Any], *,
                figures: str | Path | None = None) -> dict[str, Any]:
    """The advisor stage (module docstring); ``config`` the validated workflow config
    (sections ``advisor`` and ``observation``). Returns what ``metrics/advice.json``
    holds."""
    src, proc = Processed(source), Processed(processed)
    cfg = config["advisor"]
    _, obs, P, fitted = open_mh_source(src.root, cfg["source"], "advisor.source")
    T, S, _ = obs.shape
    tile = obs.tile
    ok = np.flatnonzero(fitted)
    rng = np.random.default_rng(int(cfg["seed"]))
    cand = hemisphere_candidates(int(cfg["candidates"]),
                                 float(config["observation"]["max_zenith_deg"]))
    # the captured views' directions from the region's centre
    X0 = np.array([obs.width_mm / 2, obs.height_mm / 2, 0.0])
    views = [r for r in read_poses(src.poses)["views"] if r["kept"] and not r["holdout"]] \
        if src.poses.is_file() else []
    captured = unit(np.array([r["centre_mm"] for r in views]) - X0) if views else \
        np.zeros((0, 3))
    idx, V, L, W, w = sample_texel_observations(obs, ok, S, tile, int(cfg["sample"]), rng)
    Ps = P[idx]
    K = mh_lobes(P.shape[1])
    lobed = sum((Ps[:, mh_ks(k)].sum(1) > 0) for k in range(K)) > 0 if K else \
        np.zeros(len(Ps), bool)
    count = int(cfg["count"])
    if lobed.any():
        order, gain, first = advise_directions(Ps[lobed], V[lobed], L[lobed], W[lobed],
                                               w[lobed], cand, count, cfg["criterion"])
        basis = ("I-optimal design: the variance of renders of the fitted lobes"
                 if cfg["criterion"] == "prediction" else "D-optimal design on the fitted lobes")
    else:  # no highlight to pin down: fill the largest gaps between the views
        order, gain = [], []
        first = np.degrees(np.arccos(np.clip((cand @ captured.T).max(1), -1, 1))) \
            if len(captured) else np.zeros(len(cand))
        gap = first.copy()
        for _ in range(min(count, len(cand))):
            best = int(np.argmax(gap))
            order.append(best)
            gain.append(float(gap[best]))
            gap = np.minimum(gap, np.degrees(np.arccos(np.clip(cand @ cand[best], -1, 1))))
        order, gain = np.array(order, int), np.array(gain)
        basis = "no sampled texel has a lobe: the largest gaps between the captured views"
    zen, az = _angles(cand[order])
    advice = [{"rank": k + 1, "zenith_deg": float(z), "azimuth_deg": float(a),
               "gain": float(g)} for k, (z, a, g) in enumerate(zip(zen, az, gain, strict=True))]
    m = {"source": cfg["source"], "basis": basis, "texels_sampled": int(len(idx)),
         "texels_with_lobe": int(lobed.sum()), "candidates": int(len(cand)),
         "captured_views": int(len(captured)), "advice": advice}
    write_metrics(proc.metrics("advice"), m)
    logger.info(f"advisor ({basis}): next views " + ", ".join(
        f"{a['zenith_deg']:.0f}/{a['azimuth_deg']:.0f}" for a in advice[:5])
        + " (zenith/azimuth deg)")
    if figures:
        _figure(Path(figures) / "advice.png", cand, first, captured, cand[order], basis)
    return m


def _figure(path: Path, cand, score, captured, advised, basis: str) -> Path:
    """The hemisphere seen from above (radius: zenith angle): candidates coloured by
    their first-round gain, captured views, and the advised views numbered."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def xy(d):
        zen, az = _angles(d)
        return zen * np.cos(np.radians(az)), zen * np.sin(np.radians(az))

    fig, ax = plt.subplots(figsize=(6.4, 6))
    sc = ax.scatter(*xy(cand), c=score, s=18, cmap="viridis")
    fig.colorbar(sc, ax=ax, label="gain of one more view (first round)")
    if len(captured):
        ax.scatter(*xy(captured), marker="x", c="w", s=22, label="captured views")
        ax.scatter(*xy(captured), marker="x", c="k", s=10)
    ax_x, ax_y = xy(advised)
    ax.scatter(ax_x, ax_y, facecolors="none", edgecolors="r", s=120, label="advised")
    for k, (px, py) in enumerate(zip(ax_x, ax_y, strict=True)):
        ax.annotate(str(k + 1), (px, py), color="r", ha="center", va="center", fontsize=8)
    for r in (30, 60, 90):
        ax.add_patch(plt.Circle((0, 0), r, fill=False, lw=0.5, color="0.5"))
    ax.set_aspect("equal")
    ax.set_xlabel("zenith x cos(azimuth) (deg)")
    ax.set_ylabel("zenith x sin(azimuth) (deg)")
    ax.set_title(f"Where to shoot next\n({basis})", fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path
