"""The lights, found from an MH fit's lobes (issue 48 item 1): ``camera/lights.yaml``,
``metrics/lights.json`` and a figure of the lobe rays meeting at each light.

Every lobe the views determine casts a ray from its texel's centre along the mirror
image of its direction (:mod:`parammap.models.lights`). Which lobes count: a texel the
fit left OK, a lobe it uses, whose specular colour is at least ``MIN_KS_SD`` of its own
sd from zero (a lobe that might be nothing says nothing about a light), and whose
direction's sd is known. Each ray is weighted by that sd; the lights are the points the
most rays meet, found one after another on the rays the ones before leave, while a
light gathers at least ``MIN_SHARE`` of the rays (fewer are the rays of texels whose
lobe is not a light's mirror: a material's sheen, a poor fit).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..conventions import (
    MH_HEAD,
    MH_M,
    FitArray,
    FitStatus,
    mh_dir,
    mh_ks,
    mh_lobes,
    mh_sd_dir,
)
from ..geometry import texel_centres
from ..models.lights import MIN_RAYS, fit_lights, mirror_to_light
from ..plots import plot_light_rays
from ..stores.fit import FitError, open_fit
from ..stores.lights import write_lights
from ..stores.metrics import write_metrics
from ..stores.paths import Processed

logger = logging.getLogger(__name__)

__all__ = ["lobe_rays", "match_measured", "run_lights"]

MIN_KS_SD = 3.0  # a lobe's Ks (summed over channels) this many of its sd above zero
MIN_SHARE = 0.02  # a light gathers at least this share of the rays
MAX_SCALE = 2.0  # its rays miss it by at most twice their own sd (robust scale)
MIN_COVERAGE = 0.5  # its rays come from half the map's blocks that have lobes


def lobe_rays(fit_path: str | Path) -> dict[str, np.ndarray]:
    """The rays of every determined lobe of an MH fit store: ``origins`` (n, 3) texel
    centres (mm), ``dirs`` (n, 3) toward the light, ``sd_rad`` (n,), ``texel`` (n,)
    flat texel index, ``lobe`` (n,), ``half_rad`` (n,) the lobe's half width at half
    maximum."""
    g = open_fit(fit_path)
    if g.model != "mh":
        raise FitError(f"{fit_path}: lights come from an MH fit, not {g.model}")
    sd_arr = g.get(FitArray.SD)
    if sd_arr is None:
        raise FitError(f"{fit_path}: no parameter sd in this fit store (written before "
                       "they were recorded): fit it again")
    T, S = g.T, g.S
    P = np.asarray(g[FitArray.PARAMS][:], float).reshape(T * S, -1)
    SD = np.asarray(sd_arr[:], float).reshape(T * S, -1)
    ok = (np.asarray(g[FitArray.STATUS][:]) == FitStatus.OK).ravel()
    k_used = g.get(FitArray.K_USED)
    K = mh_lobes(P.shape[1])
    used = np.asarray(k_used[:]).ravel() if k_used is not None else np.full(T * S, K)
    ctr = texel_centres(S, T, g.width_mm, g.height_mm).reshape(-1, 3)
    # lobes of one texel closer than their half width are one highlight drawn by two
    # lobes (a highlight that is not a Phong lobe): the weaker one is left out
    half = np.arccos(np.clip(0.5 ** (1 / np.maximum(P[:, MH_M], 1.0)), -1, 1))
    strength = np.stack([P[:, mh_ks(k)].sum(1) for k in range(K)], 1)
    dirs = np.stack([P[:, mh_dir(k)] for k in range(K)], 1)
    parts = []
    for k in range(K):
        ks = strength[:, k]
        ks_sd = np.sqrt((SD[:, MH_HEAD + 4 * k:MH_HEAD + 4 * k + 3] ** 2).sum(1))
        d_sd = SD[:, mh_sd_dir(k)]
        sel = ok & (used > k) & np.isfinite(ks) & np.isfinite(d_sd) & (d_sd > 0) \
            & (ks > MIN_KS_SD * ks_sd)
        for j in range(K):
            if j == k:
                continue
            ang = np.arccos(np.clip(np.einsum("ni,ni->n", dirs[:, k], dirs[:, j]), -1, 1))
            sel &= ~((used > j) & (ang < half) & (strength[:, j] > ks))
        idx = np.flatnonzero(sel)
        d = dirs[idx, k]
        parts.append((ctr[idx], mirror_to_light(d / np.linalg.norm(d, axis=1, keepdims=True)),
                      np.radians(d_sd[idx]), idx, np.full(len(idx), k), half[idx]))
    cat = [np.concatenate(a) for a in zip(*parts, strict=True)]
    return dict(zip(("origins", "dirs", "sd_rad", "texel", "lobe", "half_rad"), cat,
                    strict=True))


def _coverage(texels: np.ndarray, all_texels: np.ndarray, S: int, block: int) -> float:
    """Share of the map's blocks (``block`` texels square) holding a determined lobe that
    hold one of ``texels``."""
    def blocks(t: np.ndarray) -> set[tuple[int, int]]:
        return set(zip((t // S // block).tolist(), (t % S // block).tolist(), strict=True))

    every = blocks(all_texels)
    return len(blocks(texels) & every) / max(len(every), 1)


def find_lights(rays: dict[str, np.ndarray], max_lights: int, S: int, T: int,
                ) -> list[dict[str, Any]]:
    """The lights of :func:`lobe_rays`' rays (at most ``max_lights``), each a record of
    ``position_mm``, ``sd_mm``, ``rays`` (its inliers), ``scale`` (the robust spread of
    its rays' misses in their own sd: 1 where the fit's sds are right), ``coverage``
    and ``kept``.

    A light is kept where its rays meet (``scale`` at most ``MAX_SCALE``) and come from
    over the surface: a light shines on all of it, so wherever a glossy texel's views
    see its mirror direction a lobe points back to it, and the blocks of the map
    (eighths of its side) holding its rays are at least ``MIN_COVERAGE`` of those
    holding any determined lobe. The rays of one material whose lobe is not at the
    mirror direction (a microfacet highlight's off-specular peak) meet at a displaced
    copy of a light, from that material's patch alone. Of two kept lights closer in
    direction (from the surface's centre) than the stronger one's lobes' median half
    width, the weaker is left out: one highlight cannot tell them apart.
    """
    n = len(rays["origins"])
    fits = fit_lights(rays["origins"], rays["dirs"], rays["sd_rad"], max_lights)
    need = max(MIN_RAYS, int(np.ceil(MIN_SHARE * n)))
    block = max(1, max(S, T) // 8)
    out = []
    for f in fits:
        if f.inliers.sum() < need:
            continue
        cov = _coverage(rays["texel"][f.inliers], rays["texel"], S, block)
        out.append({"position_mm": [round(float(x), 3) for x in f.position_mm],
                    "sd_mm": [round(float(x), 3) for x in f.sd_mm],
                    "rays": int(f.inliers.sum()), "scale": round(float(f.scale), 3),
                    "coverage": round(cov, 3),
                    "kept": bool(f.scale <= MAX_SCALE and cov >= MIN_COVERAGE),
                    "inliers": f.inliers})
    # two lights closer, seen from the surface, than the highlights are wide make one
    # highlight: the lobes cannot tell them apart, the one with fewer rays goes
    centre = np.median(rays["origins"], axis=0)
    kept = sorted((lt for lt in out if lt["kept"]), key=lambda lt: -lt["rays"])
    for i, a in enumerate(kept):
        da = np.asarray(a["position_mm"]) - centre
        width = float(np.median(rays["half_rad"][a["inliers"]]))
        for b in kept[i + 1:]:
            db = np.asarray(b["position_mm"]) - centre
            ang = np.arccos(np.clip(da @ db / np.linalg.norm(da) / np.linalg.norm(db), -1, 1))
            if b["kept"] and ang < width:
                b["kept"] = False
    return out


def against_measured(found: list[dict[str, Any]], measured: list[dict[str, Any]],
                     centre: np.ndarray) -> list[dict[str, Any]]:
    """Each measured light (the capture's ``lights``) with the nearest light found: the
    distance (mm) and its share of the measured light's distance from ``centre`` (the
    surface's centre)."""
    out = []
    for m in measured:
        p = np.asarray(m["position_mm"], float)
        d = [float(np.linalg.norm(np.asarray(f["position_mm"]) - p)) for f in found]
        k = int(np.argmin(d)) if d else None
        out.append({**m, "nearest_found": k, "distance_mm": d[k] if d else None,
                    "relative": d[k] / float(np.linalg.norm(p - centre)) if d else None})
    return out


def match_measured(found: list[dict[str, Any]], measured: list[dict[str, Any]]) -> None:
    """Give each found light what the lab measured of the light it is (the measured
    light it is the nearest found light to and that is the nearest measured light to
    it, each pair mutual nearest neighbours): its centre as ``measured_mm`` (a start the
    svbrdf fit's refinement weighs against the found one) and, where a size was
    measured, its ``extent`` (``shape``, ``size_mm``, maybe ``normal``), which the lobes
    do not give."""
    if not found or not measured:
        return
    f = np.array([lt["position_mm"] for lt in found], float)
    m = np.array([lt["position_mm"] for lt in measured], float)
    d = np.linalg.norm(f[:, None] - m[None], axis=-1)
    for i, j in enumerate(d.argmin(1)):
        if d[:, j].argmin() != i:
            continue
        lt = measured[j]
        found[i]["measured_mm"] = [float(x) for x in lt["position_mm"]]
        if lt.get("size_mm"):
            found[i]["extent"] = {"shape": lt.get("shape", "rect"),
                                  "size_mm": [float(x) for x in lt["size_mm"]],
                                  **({"normal": [float(x) for x in lt["normal"]]}
                                     if lt.get("normal") else {})}


def run_lights(processed: str | Path, config: dict[str, Any], *,
               figures: str | Path | None = None,
               measured: list[dict[str, Any]] | None = None,
               ambient: dict[str, Any] | None = None) -> dict[str, Any]:
    """The lights stage: lights from the MH fit ``lights.source`` (at most
    ``lights.max_lights``) into ``camera/lights.yaml`` and ``metrics/lights.json``; a
    figure of the rays in ``figures`` when given. ``measured``: the lights the capture
    lists (:attr:`parammap.stores.capture.Capture.lights`), recorded beside the found
    ones with how far each is from the nearest found, each found one given its measured
    light's centre and shape (:func:`match_measured`), and used where the lobes meet at
    no light. ``ambient``: the room's light the
    capture states (:attr:`parammap.stores.capture.Capture.ambient`), passed on to the
    relightable fit."""
    proc = Processed(processed)
    cfg = config["lights"]
    src = proc.fit(cfg["source"])
    rays = lobe_rays(src)
    g = open_fit(src)
    found = find_lights(rays, cfg["max_lights"], g.S, g.T)
    lights = [lt for lt in found if lt["kept"]]
    for lt in found:
        if not lt["kept"]:
            logger.info(f"lights: {lt['rays']} lobes meeting at {lt['position_mm']} mm left "
                        f"out (rays' spread {lt['scale']:g} sd, from {lt['coverage']:.0%} of "
                        "the map): not a light over the whole surface")
    info: dict[str, Any] = {"source": cfg["source"], "lobes": int(len(rays["origins"]))}
    records = [{k: v for k, v in lt.items() if k not in ("inliers", "kept")} for lt in lights]
    if ambient:
        info["ambient"] = ambient
        logger.info(f"lights: the room's light, {ambient['share']} of a white card's at "
                    f"{ambient['at_mm']} mm with the lamps off (the capture's ambient)")
    if measured:
        centre = np.array([g.width_mm / 2, g.height_mm / 2, 0.0])
        info["measured"] = against_measured(records, measured, centre)
        match_measured(records, measured)
        if not records:  # the lobes meet nowhere: the lab's lights, as it measured them
            records = [{"position_mm": [float(x) for x in lt["position_mm"]],
                        "sd_mm": None, "rays": 0, "measured": True} for lt in measured]
            match_measured(records, measured)
            logger.warning(f"lights: the {info['lobes']} determined lobes of "
                           f"{cfg['source']} meet at no light; the capture's "
                           f"{len(records)} measured light(s) are used")
        for m in info["measured"]:
            logger.info(f"lights: measured light at {m['position_mm']} mm: "
                        + (f"the nearest found {m['distance_mm']:.1f} mm off "
                           f"({100 * m['relative']:.1f} % of its distance)"
                           if m["distance_mm"] is not None else "none found"))
    write_lights(proc.lights, records, info)
    for k, lt in enumerate(records):
        logger.info(f"lights: light {k + 1} at {lt['position_mm']} mm (sd {lt['sd_mm']}), "
                    f"{lt['rays']} of {info['lobes']} lobes"
                    + (f"; an area light, {lt['extent']['shape']} {lt['extent']['size_mm']} mm "
                       "(the capture's)" if "extent" in lt else ""))
    if not records:
        logger.warning(f"lights: the {info['lobes']} determined lobes of {cfg['source']} "
                       "meet at no light")
    m = {**info, "lights": records,
         "left_out": [{k: v for k, v in lt.items() if k not in ("inliers", "kept")}
                      for lt in found if not lt["kept"]]}
    write_metrics(proc.metrics("lights"), m)
    if figures is not None:
        plot_light_rays(rays, lights, Path(figures) / "lights.png")
    return m
