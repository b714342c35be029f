"""Stage outputs measured against a generator's ground truth (tests and benchmarks).

The pipeline never imports this module: it reads the ``<capture>.truth`` folder that
:func:`parammap.synth.generate.generate` and :func:`parammap.synth.pbr.generate_pbr`
write beside a capture. Radiance is relative (one unknown global scale,
docs/reference/conventions.md), so every radiance comparison first fits that one scale
(median ratio).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..config import default
from ..conventions import LUMINANCE, SV_ALPHA
from ..geometry import plane_to_texel, texel_centres, unit
from ..models.lights import expand_lights
from ..models.radiometry import correct_frame
from ..models.svbrdf import metallic_roughness
from ..render import evaluate, render, surface_points, tone_map
from ..stages.hdr import load_bracket, merge_bracket
from ..stages.holdout import choose_gamma, compare, marker_pixels, pixel_regions, region_errors
from ..stores.camera import load_intrinsics, read_poses
from ..stores.capture import load_capture
from ..stores.hdr import read_hdr, read_rgb
from ..stores.observation import open_observation_map
from ..stores.params import best_shares, read_param_map
from ..stores.paths import Processed
from ..stores.radiometry import radiometry_for
from .generate import true_view_radiance
from .pbr import Light, light_extent, normal_reflectance, patch_labels, read_truth_radiance
from .scene import KIND_NAMES, load_scene, true_radiance

__all__ = ["albedo_against_truth", "directions_against_truth", "hdr_errors",
           "holdout_against_truth", "relit_against_truth",
           "intrinsics_errors", "pose_errors",
           "true_directions", "angle_deg"]


def _scale(ref: np.ndarray, est: np.ndarray) -> float:
    return float(np.median(ref / est))


def hdr_errors(capture: str | Path, truth: str | Path, processed: str | Path,
               view_ids: list[str], low: int = default("hdr.low"),
               high: int = default("hdr.high")) -> dict:
    """Relative radiance error of the merged HDR frames against the radiance the photos
    were exposed from (either generator), next to an oracle merge of the same photos with the true
    response, on the same pixels (unsaturated, not black, in both merges).

    Returns
    -------
    dict with ``median``, ``p95`` (ours) and ``oracle_median``, ``oracle_p95``, as
    fractions (the oracle's None for a linear capture: no response to know), and
    ``pixels``.
    """
    cap = load_capture(capture)
    exposure = np.load(Path(truth) / "response.npz")["exposure"]
    g_true = np.log(np.maximum(exposure, 1e-12))
    g_true = np.maximum.accumulate(g_true + 1e-9 * np.arange(256)[:, None], axis=0)
    ours, oracle = [], []
    pbr = (Path(truth) / "radiance").is_dir()
    for vid in view_ids:
        if pbr:
            true = read_truth_radiance(truth, vid)
        else:

            true = true_view_radiance(capture, truth, vid)
        rad, sat, dark = read_hdr(Processed(processed).hdr(vid))
        if cap.response == "linear":  # a RAW capture: no response, no oracle merge of it
            ok = ~(sat | dark) & (true.min(-1) > 0)
            ours.append((rad[ok], true[ok]))
            continue
        stack, t = load_bracket(cap.view(vid))
        orc, osat, odark = merge_bracket(stack, t, g_true, low, high)
        ok = ~(sat | dark | osat | odark) & (true.min(-1) > 0)
        ours.append((rad[ok], true[ok]))
        oracle.append((orc[ok], true[ok]))
    out = {}
    for name, pairs in (("", ours), ("oracle_", oracle)):
        if not pairs:
            out[f"{name}median"] = out[f"{name}p95"] = None
            continue
        est = np.concatenate([p[0] for p in pairs])
        ref = np.concatenate([p[1] for p in pairs])
        rel = np.abs(est * _scale(ref, est) - ref) / ref
        out[f"{name}median"] = float(np.median(rel))
        out[f"{name}p95"] = float(np.percentile(rel, 95))
    out["pixels"] = int(sum(len(p[0]) for p in ours))
    return out


def intrinsics_errors(truth: str | Path, processed: str | Path) -> dict:
    """Focal lengths (relative) and principal point (px) against the truth."""
    K = np.array(yaml.safe_load((Path(truth) / "camera.yaml").read_text())["K"])
    est = yaml.safe_load(Processed(processed).intrinsics.read_text())
    Ke = np.array(est["K"])
    return {"fx_rel": float(Ke[0, 0] / K[0, 0] - 1), "fy_rel": float(Ke[1, 1] / K[1, 1] - 1),
            "principal_px": float(np.hypot(Ke[0, 2] - K[0, 2], Ke[1, 2] - K[1, 2])),
            "rms_px": float(est["rms_px"])}


def pose_errors(truth: str | Path, processed: str | Path) -> dict:
    """Camera centre (mm) and rotation (deg) errors of every view with a pose, kept
    or not: ``{view id: {"centre_mm", "rotation_deg", "kept", "holdout"}}``."""
    P = np.load(Path(truth) / "poses.npz")
    ids = list(P["view_ids"])
    recs = read_poses(Processed(processed).poses)["views"]
    out = {}
    for r in recs:
        if "R" not in r:
            continue
        k = ids.index(r["id"])
        C = -P["R"][k].T @ P["t"][k]
        dR = np.array(r["R"]) @ P["R"][k].T
        out[r["id"]] = {
            "centre_mm": float(np.linalg.norm(np.array(r["centre_mm"]) - C)),
            "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
            "kept": bool(r["kept"]), "holdout": bool(r.get("holdout", False))}
    return out


def true_directions(truth: str | Path, view_ids: list[str], S: int, T: int, width_mm: float,
                    height_mm: float) -> np.ndarray:
    """True view directions (T, S, N, 3) of every texel centre in the given views."""
    P = np.load(Path(truth) / "poses.npz")
    ids = list(P["view_ids"])
    k = [ids.index(v) for v in view_ids]
    C = np.einsum("nji,nj->ni", P["R"][k], -P["t"][k])
    ctr = texel_centres(S, T, width_mm, height_mm)
    return unit(C[None, None] - ctr[:, :, None, :])


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (deg) between direction vectors ``a`` and ``b`` (..., 3), each normalised
    in float64 first and measured by atan2 of the cross and dot products: arccos of a
    float32 dot product reads a rounding of 1e-7 in a vector's length as 0.03 deg."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def holdout_against_truth(capture: str | Path, truth: str | Path, processed: str | Path,
                          models: list[str], per_patch: bool = False,
                          ) -> dict[str, dict[str, float]] | tuple[dict, dict]:
    """Mean 8-bit difference of each model's render against the clean (high-sample)
    render of every held-out view of a physically based capture.

    The pipeline's held-out stage compares with the held-out photo (noise included);
    this compares with what the photo should have shown. The clean render is brought to
    the capture's relative radiance scale (median ratio to the merged photo inside the
    region), then both are tone-mapped with the held-out stage's gamma for that view.

    Returns
    -------
    ``{view id: {model: mean 8-bit difference}}``; with ``per_patch`` also ``{patch:
    {model: mean 8-bit difference}}`` over all held-out views (pixel-weighted), each
    patch named ``<index> <kind> <parameters>`` from ``scene.json``.
    """
    cap = load_capture(capture)
    out, acc = {}, {}
    if per_patch:
        S, T = _map_size(processed, models)
        labels = patch_labels(truth, S, T, cap.width_mm, cap.height_mm)
        scene = json.loads((Path(truth) / "scene.json").read_text())["patches"]
        names = [f"{k} {p['kind']} " + " ".join(
            f"{a}={b:.3g}" for a, b in p.items() if isinstance(b, float) and a != "rect_mm")
            for k, p in enumerate(scene)]
    for vid, clean, images, mask, gamma, P, inside in _held_out_renders(
            cap, truth, processed, models):
        out[vid] = {name: compare(clean, img, mask, gamma)["mean_diff_8bit"]
                    for name, img in images.items()}
        if per_patch:
            px = pixel_regions(labels, P, inside, cap.width_mm, cap.height_mm)
            for name, img in images.items():
                for j, e in region_errors(clean, img, mask, gamma, px).items():
                    a = acc.setdefault(names[int(j)], {}).setdefault(name, [0.0, 0])
                    a[0] += e["mean_diff_8bit"] * e["pixels"]
                    a[1] += e["pixels"]
    if not per_patch:
        return out
    return out, {k: {m: v[0] / v[1] for m, v in d.items()} for k, d in sorted(acc.items())}


def _map_size(processed: str | Path, models: list[str]) -> tuple[int, int]:
    """(S, T) of the first of ``models``' parameter maps."""
    T, S = read_param_map(Processed(processed).params(models[0])).shape
    return S, T


def _held_out_renders(cap, truth: str | Path, processed: str | Path, models: list[str],
                      maps: dict | None = None, relit: bool = False):
    """For every kept held-out view of a physically based capture: its id, the clean
    render on the merged photo's relative scale (median ratio inside the region), each
    model's render, the mask compared (region, unsaturated, off the markers), the
    held-out stage's gamma, and the plane point of each pixel with its ``inside`` mask.
    ``maps``: the models' maps (default read from ``processed``); ``relit``: the clean
    render under the novel lights (``<truth>/relit``) in place of the captured one, on
    the captured one's scale."""
    proc = Processed(processed)
    intr = load_intrinsics(proc.intrinsics)
    maps = maps or {m: read_param_map(proc.params(m)) for m in models}
    radiometry = radiometry_for(cap, proc)
    for r in read_poses(proc.poses)["views"]:
        if not (r.get("holdout") and r.get("kept")):
            continue
        R, t = np.asarray(r["R"], float), np.asarray(r["t"], float)

        def frame(radiance: np.ndarray, R=R, t=t) -> np.ndarray:
            # as the held-out stage reads a frame, and the maps were fitted: the
            # flat-field and colour out
            return correct_frame(radiance, intr, R, t, cap.width_mm, cap.height_mm,
                                 radiometry)

        photo, sat, _ = read_hdr(proc.hdr(r["id"]))
        photo = frame(photo)
        clean = frame(read_truth_radiance(truth, r["id"], clean=True))
        P, inside = surface_points(intr, R, t, cap.width_mm, cap.height_mm,
                                   (photo.shape[1], photo.shape[0]))
        mask = inside & ~sat & ~marker_pixels(cap, P)
        ok = mask[..., None] & (clean > 0) & (photo > 0)
        scale = float(np.median(photo[ok] / clean[ok]))
        clean = scale * (frame(read_rgb(Path(truth) / "relit" / f"{r['id']}.exr")) if relit
                         else clean)
        images = {name: render(pm, intr, R, t, surface=(P, inside))[0]
                  for name, pm in maps.items()}
        yield r["id"], clean, images, mask, choose_gamma(photo, mask), P, inside


def _power(light: dict) -> np.ndarray:
    """(3,) intensity toward the surface of a generator's area light (``scene.json``:
    radiance times area; the lights face the surface's centre)."""
    L = Light(**light)
    w, h = L.size_mm
    area = w * h if L.shape == "rect" else math.pi * w * w
    return np.asarray(L.radiance, float) * area


def relit_against_truth(capture: str | Path, truth: str | Path, processed: str | Path,
                        models: list[str]) -> dict[str, dict[str, float]]:
    """Mean 8-bit difference of each model's render against the clean render of every
    held-out view under lights the capture never had (:func:`parammap.synth.pbr.
    render_relit`, ``<truth>/relit``). A relightable map (svbrdf) is rendered under the
    new lights: their positions as given, their intensities in the map's units from
    its own lights' (each fitted light matched to the nearest true one, its relative
    intensity over that light's power); the other models cannot move their light and
    are rendered as fitted. The clean renders take the captured clean render's scale
    (:func:`holdout_against_truth`), the tone map the held-out photo's gamma, the
    comparison its pixels (:func:`_held_out_renders`)."""
    cap = load_capture(capture)
    proc = Processed(processed)
    truth = Path(truth)
    scene = json.loads((truth / "scene.json").read_text())
    new = json.loads((truth / "relit" / "lights.json").read_text())
    centre = np.array([cap.width_mm / 2, cap.height_mm / 2, 0.0])
    true_pos = np.array([centre + np.asarray(L["position_mm"]) for L in scene["lights"]])
    maps = {}
    for m in models:
        pm = read_param_map(proc.params(m))
        if pm.lights is not None:
            # a map fitted under area lights holds their points; its lamps are the lights
            pos, w = pm.lamps or pm.lights[:2]
            near = [int(np.argmin(np.linalg.norm(true_pos - p[:3], axis=1))) for p in pos]
            unit = np.mean([w[j] / _power(scene["lights"][k]) for j, k in enumerate(near)], 0)
            at = np.array([centre + np.asarray(L["position_mm"]) for L in new])
            power = np.array([unit * _power(L) for L in new])
            lamps = None
            if pm.lamps is not None:  # the new lamps drawn with their shapes too
                extents = [light_extent(L["shape"], L["size_mm"]) for L in new]
                lamps = (at, power, extents)
                at, group = expand_lights(at, extents, centre)
                power = group @ power
            pm = pm.relit(at, power, lamps=lamps)
        maps[m] = pm
    return {vid: {m: compare(ref, img, mask, gamma)["mean_diff_8bit"]
                  for m, img in images.items()}
            for vid, ref, images, mask, gamma, _, _ in _held_out_renders(
                cap, truth, processed, models, maps, relit=True)}


HIGHLIGHT_RANGE_8BIT = 32  # a patch shows a highlight: its 99th percentile this above its median
PATCH_MARGIN_PX = 2  # pixels left out along each patch's edge


def _neighbour_variation(img: np.ndarray, region: np.ndarray) -> tuple[float, int]:
    """Sum of squared differences between horizontally and vertically neighbouring
    pixels of ``img`` (H, W) both in ``region``, and how many pairs."""
    h = (img[:, 1:] - img[:, :-1])[region[:, 1:] & region[:, :-1]]
    v = (img[1:] - img[:-1])[region[1:] & region[:-1]]
    return float(np.sum(h * h) + np.sum(v * v)), h.size + v.size


def highlight_speckle(capture: str | Path, truth: str | Path, processed: str | Path,
                      models: list[str]) -> dict[str, dict[str, float]]:
    """Texel-to-texel variation of each model's held-out renders inside the patches'
    highlights, against the clean render's own (issue 49's speckle check).

    In every kept held-out view, each patch of the truth whose clean 8-bit levels (the
    held-out comparison's tone map) have their 99th percentile at least
    :data:`HIGHLIGHT_RANGE_8BIT` above their median over its interior
    (``PATCH_MARGIN_PX`` from its edges; printed detail darkens, a highlight brightens)
    shows a highlight; its highlight pixels are the interior ones above the midpoint of
    the two. The variation of an
    image there is the RMS 8-bit difference between horizontally and vertically
    neighbouring pixels, both in the highlight (a pixel is about a texel in these
    captures). A smooth highlight drawn smooth gives a ratio near 1; salt-and-pepper
    lobes give more. The clean render's own Monte Carlo noise counts in the truth's
    variation: on the pbr presets' 32 independent samples it is most of it.

    Returns
    -------
    ``{model: {"ratio": RMS over every highlight against the truth's, "worst": the
    largest ratio of one (view, patch)}}`` and ``"highlights"``: how many were seen.
    """
    cap = load_capture(capture)
    S, T = _map_size(processed, models)
    labels = patch_labels(truth, S, T, cap.width_mm, cap.height_mm)
    sums = {m: [0.0, 0.0] for m in models}
    worst = dict.fromkeys(models, 0.0)
    seen = 0
    kernel = np.ones((2 * PATCH_MARGIN_PX + 1,) * 2, np.uint8)
    for _, clean, images, mask, gamma, P, inside in _held_out_renders(
            cap, truth, processed, models):
        px = pixel_regions(labels, P, inside, cap.width_mm, cap.height_mm)
        truth8 = tone_map(clean, gamma).astype(float).mean(-1)
        for j in np.unique(px[px >= 0]):
            core = cv2.erode(((px == j) & mask).astype(np.uint8), kernel).astype(bool)
            if core.sum() < 16:
                continue
            med, hi = np.percentile(truth8[core], [50, 99])
            if hi - med < HIGHLIGHT_RANGE_8BIT:
                continue
            hl = core & (truth8 >= (med + hi) / 2)
            t2, n = _neighbour_variation(truth8, hl)
            if n < 16 or t2 <= 0:
                continue
            seen += 1
            for m, img in images.items():
                m2, _ = _neighbour_variation(
                    tone_map(np.nan_to_num(img), gamma).astype(float).mean(-1), hl)
                sums[m][0] += m2
                sums[m][1] += t2
                worst[m] = max(worst[m], float(np.sqrt(m2 / t2)))
    out = {m: {"ratio": float(np.sqrt(a / b)) if b > 0 else float("nan"), "worst": worst[m]}
           for m, (a, b) in sums.items()}
    return out | {"highlights": seen}


def directions_against_truth(truth: str | Path, processed: str | Path, models: list[str],
                             directions: np.ndarray, samples: int = 256, seed: int = 0,
                             by_kind: bool = False) -> dict:
    """Mean 8-bit difference between each model's map and the analytic generator's
    truth in every one of ``directions`` (Q, 3), surface frame, at every texel centre:
    how a map predicts directions no view of it was taken from, without the noise and
    the few views of a held-out comparison. ``by_kind``: ``{kind: {model: error}}`` over
    the texels of each material kind of the scene (``scene.KIND_NAMES``) instead.

    The capture's radiance scale is fitted once (median ratio of the observation map to
    the truth at the observed directions of up to ``samples`` texels); the tone map is
    the held-out comparison's, its gamma from the truth's 99th percentile over the
    directions (:func:`parammap.stages.holdout.choose_gamma`). Texels are looked up in the
    truth scene at their centres (any map size).
    """
    scene = load_scene(Path(truth) / "scene.npz")
    proc = Processed(processed)
    maps = {m: read_param_map(proc.params(m)) for m in models}
    T, S = next(iter(maps.values())).shape
    ctr = texel_centres(S, T, scene.width_mm, scene.height_mm).reshape(-1, 3)
    Ts, Ss = scene.shape
    r, c = plane_to_texel(ctr[:, 0], ctr[:, 1], Ss, Ts, scene.width_mm, scene.height_mm)
    rows = np.clip(r.astype(int), 0, Ts - 1)
    cols = np.clip(c.astype(int), 0, Ss - 1)
    obs = open_observation_map(proc.observation)
    rng = np.random.default_rng(seed)
    pick = rng.choice(T * S, min(samples, T * S), replace=False)
    L = np.asarray(obs.radiance[...], float).reshape(T * S, -1, 3)[pick]
    V = np.asarray(obs.direction[...], float).reshape(T * S, -1, 3)[pick]
    W = np.asarray(obs.valid[...], bool).reshape(T * S, -1)[pick] & np.isfinite(L).all(-1)
    n, N = W.shape
    true_obs = true_radiance(scene, np.repeat(rows[pick], N), np.repeat(cols[pick], N),
                             V.reshape(-1, 3)).reshape(n, N, 3)
    ok = W[..., None] & (true_obs > 0) & (L > 0)
    scale = float(np.median(L[ok] / true_obs[ok]))
    Q = len(directions)
    d = np.broadcast_to(np.asarray(directions, float), (T * S, Q, 3)).reshape(-1, 3)
    truth_rad = scale * true_radiance(scene, np.repeat(rows, Q), np.repeat(cols, Q), d)
    gamma = choose_gamma(truth_rad[None], np.ones((1, len(truth_rad)), bool))
    ref = tone_map(truth_rad, gamma).astype(float)
    out = {}

    def predict(pm):
        if pm.model == "best":  # each texel the mean of its two candidates
            parts = list((pm.parts or {}).values())
            share = np.repeat(best_shares(pm.params, len(parts)).reshape(T * S, -1), Q, 0)
            return sum(share[:, j:j + 1] * predict(part) for j, part in enumerate(parts)
                       if share[:, j].any())
        return np.nan_to_num(evaluate(pm.model, np.repeat(pm.params.reshape(T * S, -1), Q,
                                                          axis=0), d,
                                      np.repeat(ctr, Q, axis=0), pm.lights))

    kind = np.repeat(scene.kind[rows, cols], Q)
    for name, pm in maps.items():
        err = np.abs(tone_map(predict(pm), gamma).astype(float) - ref).mean(-1)
        if not by_kind:
            out[name] = float(err.mean())
            continue
        for k in np.unique(kind):
            out.setdefault(KIND_NAMES[k], {})[name] = float(err[kind == k].mean())
    return out


def albedo_against_truth(truth: str | Path, processed: str | Path,
                         scale: float | None = None) -> dict[int, dict]:
    """A physically based capture's relightable map in glTF's terms against its truth,
    per material patch (median over its inner texels, 2 texels in from its edges):
    ``albedo``, a conductor's base colour over its Fresnel reflectance or another
    patch's ``baseColor (1 - metallic)`` over its diffuse reflectance along the normal
    (:func:`parammap.synth.pbr.normal_reflectance`; luminance), and ``alpha`` (fitted,
    true) where the patch has one. ``scale``: the albedo's scale k (default the one
    ``parammap material`` recorded). Patches with no such truth (``principled``) are
    left out."""
    proc = Processed(processed)
    rec = json.loads(proc.metrics("material-svbrdf-ggx").read_text())
    pm = read_param_map(proc.params("svbrdf-ggx"))
    mr = metallic_roughness(pm.params, pm.sd, rec["albedo_scale"] if scale is None else scale)
    T, S = pm.shape
    lab = patch_labels(truth, S, T, pm.width_mm, pm.height_mm)
    tex = cv2.resize(np.load(Path(truth) / "albedo.npz")["albedo"].astype(np.float32), (S, T),
                     interpolation=cv2.INTER_AREA) @ LUMINANCE
    base = mr["base_color"] @ LUMINANCE
    patches = json.loads((Path(truth) / "scene.json").read_text())["patches"]
    out = {}
    for k, (p, want) in enumerate(zip(patches, normal_reflectance(truth), strict=True)):
        inner = cv2.erode((lab == k).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        if want["specular"] is not None:
            ratio = np.median(base[inner]) / (np.asarray(want["specular"]) @ LUMINANCE)
        elif want["diffuse"] is not None:
            rho = base * (1 - mr["metallic"])
            ratio = np.median(rho[inner] / (want["diffuse"] * tex[inner]))
        else:
            continue
        out[k] = {"kind": p["kind"], "albedo": float(ratio), "scale_from": rec["scale_from"]
                  if scale is None else "given",
                  "alpha": (float(np.median(pm.params[..., SV_ALPHA][inner])), p["alpha"])
                  if "alpha" in p else None}
    return out
