"""Synthetic capture generator (``parammap synth``).

Writes exactly the layout of ``docs/reference/capture-format.md`` into ``out`` and the ground truth
(response curve, intrinsics, poses, scene) into a separate ``truth`` folder that the
pipeline never reads. Seeded and deterministic: the same preset and seed give the
same bytes.
"""

from __future__ import annotations

import functools
import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..errors import InputError
from ..geometry import (
    look_at,
    normalized_to_plane,
    pixel_to_normalized,
    pixel_to_plane,
    plane_to_texel,
    project_points,
    texel_centres,
    unit,
)
from ..parallel import executor
from ..sheets import marker_layout
from ..stores.capture import aruco_dictionary
from ..stores.images import write_image_atomic
from .chart import chart_camera_rgb, chart_shade, chart_size_mm
from .sampling import sample_directions
from .scene import Scene, build_scene, load_scene, mh_truth, true_radiance

logger = logging.getLogger(__name__)

__all__ = ["PRESETS", "Preset", "Response", "generate", "render_radiance"]


@dataclass(frozen=True)
class Preset:
    texels: int = 64
    width_mm: float = 160.0
    height_mm: float = 160.0
    image_size: tuple[int, int] = (640, 480)  # width, height (px)
    focal_px: float = 560.0
    dist: tuple[float, ...] = (-0.12, 0.06, 0.0008, -0.0006, 0.0)
    scheme: str = "icosahedron"
    scheme_args: tuple[tuple[str, float], ...] = (("level", 2),)
    max_zenith_deg: float = 70.0
    holdout: int = 4
    exposures: int = 3
    calib_images: int = 24
    supersample: int = 2
    edge_supersample: int = 8  # samples per side on marker and board edges (0: off)
    marker_dictionary: str = "DICT_4X4_50"
    shot_noise: float = 2e-5  # variance per unit of normalised exposure
    read_noise: float = 2e-4  # std, normalised exposure units
    image_format: str = "png"
    # flat-field and colour (docs/synthetic.md): the lens's fall-off at the frame's
    # corner (0.3: 30 %), the light's irradiance varying by +-light_gradient/2 across
    # the surface on top of the lights' own cosine, photos of a white card where the
    # surface lies, and a colour chart photo through a real camera's spectral
    # sensitivities (colour-science's name) under a light (its illuminant name)
    vignetting: float = 0.0
    light_gradient: float = 0.0
    card_views: int = 0
    chart_camera: str = ""
    chart_light: str = "A"


PRESETS = {
    "tiny": Preset(texels=24, width_mm=96.0, height_mm=96.0, image_size=(320, 240),
                   focal_px=290.0, scheme="icosahedron", scheme_args=(("level", 1),),
                   max_zenith_deg=65.0, holdout=2, exposures=2, calib_images=8),
    "demo": Preset(scheme="stratified", scheme_args=(("n_side", 9),), max_zenith_deg=72.0),
    "paper": Preset(texels=512, width_mm=300.0, height_mm=300.0, image_size=(1600, 1200),
                    focal_px=1400.0, scheme="icosahedron", scheme_args=(("level", 3),),
                    max_zenith_deg=88.0, holdout=8, supersample=1, calib_images=20),
    # a lab's capture at its real scale (issue 47): 12 MP JPEGs of a 400 x 300 mm
    # poster, 121 views and 6 held out, a benchmark's input (hours to run), not a test's
    "lab": Preset(texels=512, width_mm=400.0, height_mm=300.0, image_size=(4000, 3000),
                  focal_px=3300.0, dist=(-0.05, 0.02, 0.0004, -0.0003, 0.0),
                  scheme="stratified", scheme_args=(("n_side", 11),), max_zenith_deg=70.0,
                  holdout=6, calib_images=12, image_format="jpg"),
}


@dataclass(frozen=True)
class Response:
    """A camera response: normalised exposure X (>= 0) to 8-bit level.

    ``level = 255 * clip((1 + a) y / (1 + a y), 0, 1)`` with ``y = (k X) ** (1 / gamma)``,
    per channel: a monotonic gamma curve with a soft shoulder. ``k`` white-balances the
    channels at mid-grey (level 128 is the same X in every channel), the assumption
    every response recovery needs to fix the channels' relative scale.
    """

    gamma: tuple[float, float, float] = (2.1, 2.2, 2.35)
    shoulder: tuple[float, float, float] = (0.25, 0.3, 0.35)

    def _base_inverse(self, level):
        a = np.asarray(self.shoulder)
        f = np.clip(np.asarray(level, float) / 255.0, 0, 1)
        return (f / (1 + a - a * f)) ** np.asarray(self.gamma)

    @property
    def _k(self) -> np.ndarray:
        x128 = self._base_inverse(np.full(3, 128.0))
        return x128 / x128[0]

    def __call__(self, X: np.ndarray) -> np.ndarray:
        y = np.clip(np.asarray(X) * self._k, 0, None) ** (1 / np.asarray(self.gamma))
        a = np.asarray(self.shoulder)
        return 255.0 * np.clip((1 + a) * y / (1 + a * y), 0, 1)

    def inverse(self, level: np.ndarray) -> np.ndarray:
        """Normalised exposure at a (real-valued) level in [0, 255]."""
        return self._base_inverse(level) / self._k


def _rays(size: tuple[int, int], K: np.ndarray, dist, ss: int, rows: slice) -> np.ndarray:
    """Pixel sample coordinates (n_rows, W, ss*ss, 2) for a block of image rows."""
    w = size[0]
    off = (np.arange(ss) + 0.5) / ss - 0.5
    r = np.arange(rows.start, rows.stop)
    ou, ov = np.meshgrid(off, off)
    u = np.arange(w)[None, :, None] + ou.ravel()[None, None, :]
    v = r[:, None, None] + ov.ravel()[None, None, :]
    u, v = np.broadcast_arrays(u, v)
    return np.stack([u, v], axis=-1)


@dataclass
class _World:
    scene: Scene
    marker_img: list[np.ndarray]  # uint8 marker images, 1 = white
    marker_H: list[np.ndarray]  # homographies surface mm -> marker image px
    marker_bbox: np.ndarray  # (M, 4) xmin, xmax, ymin, ymax
    paper: float
    marker_white: float
    marker_black: float
    gradient: float = 0.0  # Preset.light_gradient
    card: bool = False  # a white card (albedo CARD_ALBEDO) in place of the surface


#: the flat-field card's albedo
CARD_ALBEDO = 0.8


def light_gradient(x: np.ndarray, y: np.ndarray, width_mm: float, height_mm: float,
                   g: float) -> np.ndarray:
    """The extra irradiance factor over the surface (``Preset.light_gradient``): a ramp
    that rises by ``g`` across the width and ``g / 2`` across the height, mean 1."""
    return 1.0 + g * ((x / width_mm - 0.5) + 0.5 * (y / height_mm - 0.5))


def lens_vignetting(size: tuple[int, int], K: np.ndarray, v: float) -> np.ndarray:
    """(H, W) relative illumination ``1 - v q^2`` of the generator's lens, ``q`` the
    pixel's distance from the principal point over the farthest corner's."""
    w, h = size
    u, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    r2 = (u - K[0, 2]) ** 2 + (vv - K[1, 2]) ** 2
    corners = [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)]
    r2max = max((cu - K[0, 2]) ** 2 + (cv - K[1, 2]) ** 2 for cu, cv in corners)
    return (1.0 - v * r2 / r2max).astype(np.float32)


def _cosine_irradiance(scene: Scene, P: np.ndarray) -> np.ndarray:
    """The lights' intensity times cosine at plane points (N,) (what the scene's kd
    holds over its albedo)."""
    irr = np.zeros(len(P))
    for lp, inten in zip(scene.light_pos, scene.light_int, strict=True):
        irr += inten * np.clip(unit(lp - P)[:, 2], 0, None)
    return irr


def _shade_surface(world: _World, P: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Radiance at plane points P (N, 3) seen from camera centre C."""
    sc = world.scene
    T, S = sc.shape
    # Paper and markers are lit by the point lights: cosine and inverse-square falloff,
    # normalised to 1 at the region's centre.
    ctr = np.array([sc.width_mm / 2, sc.height_mm / 2, 0.0])
    irr = np.zeros(len(P))
    irr0 = 0.0
    for lp, inten in zip(sc.light_pos, sc.light_int, strict=True):
        d = lp - P
        r2 = np.sum(d * d, axis=1)
        irr += inten * d[:, 2] / r2**1.5
        irr0 += inten * (lp - ctr)[2] / np.sum((lp - ctr) ** 2) ** 1.5
    shade = (irr / irr0)[:, None]
    out = world.paper * shade * np.ones((1, 3))
    inside = (P[:, 0] >= 0) & (P[:, 0] < sc.width_mm) & (P[:, 1] > 0) & (P[:, 1] <= sc.height_mm)
    if inside.any():
        r, c = plane_to_texel(P[inside, 0], P[inside, 1], S, T, sc.width_mm, sc.height_mm)
        r = np.clip(np.floor(r).astype(int), 0, T - 1)
        c = np.clip(np.floor(c).astype(int), 0, S - 1)
        if world.card:
            out[inside] = CARD_ALBEDO * _cosine_irradiance(sc, P[inside])[:, None]
        else:
            out[inside] = true_radiance(sc, r, c, unit(C - P[inside]))
        if world.gradient:
            out[inside] *= light_gradient(P[inside, 0], P[inside, 1], sc.width_mm,
                                          sc.height_mm, world.gradient)[:, None]
    for img, H, bb in zip(world.marker_img, world.marker_H, world.marker_bbox, strict=True):
        sel = (P[:, 0] >= bb[0]) & (P[:, 0] <= bb[1]) & (P[:, 1] >= bb[2]) & (P[:, 1] <= bb[3])
        if not sel.any():
            continue
        q = cv2.perspectiveTransform(P[sel, None, :2].astype(np.float64), H)[:, 0]
        n = img.shape[0]
        ok = (q[:, 0] >= 0) & (q[:, 0] < n) & (q[:, 1] >= 0) & (q[:, 1] < n)
        idx = np.flatnonzero(sel)[ok]
        val = img[q[ok, 1].astype(int), q[ok, 0].astype(int)]
        out[idx] = np.where(val[:, None] > 0, world.marker_white, world.marker_black) * shade[idx]
    return out


def render_radiance(shade, size, K, dist, R, t, ss: int = 2, block: int = 64,
                    edge_ss: int = 0, refine=None) -> np.ndarray:
    """Render a plane z = 0 as a camera sees it, box-filtering ``ss x ss`` samples.

    A pixel integrates radiance over its whole area. ``ss x ss`` samples on a regular
    grid quantise a sharp edge to 1/ss of a pixel, and along an edge nearly parallel
    to the pixel grid that error does not average out (it biased marker corners by
    ~0.1 px, and poses with them). So pixels whose samples disagree, and where
    ``refine`` (points (N, 3) -> bool, default all) holds for all of them, are
    rendered again with ``edge_ss x edge_ss`` samples: cheap where the shading is
    cheap (markers, boards), which is where edge positions matter.

    Parameters
    ----------
    shade : callable(points (N, 3), camera centre (3,)) -> (N, 3) radiance.
    size : (width, height) in pixels.
    edge_ss : samples per side on edge pixels (0: no refinement).

    Returns
    -------
    (H, W, 3) float32 linear radiance; 0 where a ray misses the plane.
    """
    w, h = size
    out = np.zeros((h, w, 3), np.float32)
    inner = np.zeros((h, w), bool)  # the pixel's own samples disagree
    cheap = np.ones((h, w), bool)
    C = -np.asarray(R).T @ np.asarray(t).ravel()
    n = ss * ss
    K, dist = np.asarray(K, float), np.asarray(dist, float)
    for r0 in range(0, h, block):
        rows = slice(r0, min(h, r0 + block))
        xn = _block_rays(tuple(size), K.tobytes(), dist.tobytes(), ss, rows.start, rows.stop)
        rad, ok = _shade_samples(shade, None, K, dist, R, t, C, refine, xn=xn)
        rad = rad.reshape(rows.stop - rows.start, w, n, 3)
        # reductions over the few samples of a pixel slice by slice: numpy's reduce
        # over a short strided axis was a quarter of the generator's time (the same
        # values: sequential sums, as numpy's over a non-contiguous axis)
        samples = [rad[:, :, i] for i in range(n)]
        mean = functools.reduce(np.add, samples) / n
        out[rows] = mean
        if edge_ss > ss:
            spread = (functools.reduce(np.maximum, samples)
                      - functools.reduce(np.minimum, samples)).max(-1)
            inner[rows] = spread > 0.02 * mean.max(-1)
            if refine is not None:
                cheap[rows] = ok.reshape(rows.stop - rows.start, w, n).all(-1)
    if edge_ss <= ss:
        return out
    # An edge, not smooth shading: samples, or neighbouring pixels, differ by more than
    # 2 %. Neighbours too, because an edge can pass between two pixels' sample grids.
    k3 = np.ones((3, 3), np.uint8)
    hi = cv2.dilate(out, k3).max(-1)
    lo = cv2.erode(out, k3).min(-1)
    edge = (inner | (hi - lo > 0.02 * hi + 1e-6 * float(out.max()))) & cheap
    yy, xx = np.nonzero(edge)
    off = (np.arange(edge_ss) + 0.5) / edge_ss - 0.5
    ou, ov = (a.ravel() for a in np.meshgrid(off, off))
    step = max(1, (block * w * n) // (edge_ss * edge_ss))
    for i in range(0, len(yy), step):
        y, x = yy[i:i + step], xx[i:i + step]
        uv2 = np.stack([x[:, None] + ou, y[:, None] + ov], -1)
        rad2, _ = _shade_samples(shade, uv2.reshape(-1, 2), K, dist, R, t, C)
        out[y, x] = rad2.reshape(len(y), -1, 3).mean(1)
    return out


@functools.lru_cache(maxsize=128)
def _block_rays(size: tuple[int, int], K: bytes, dist: bytes, ss: int, r0: int, r1: int,
                ) -> np.ndarray:
    """Undistorted normalised coordinates (M, 2) of the samples of image rows r0:r1
    (:func:`_rays`; K and dist as float64 bytes): the same for every view of a camera,
    so undistorted once (the generator's most expensive step otherwise)."""
    Km, dm = np.frombuffer(K).reshape(3, 3), np.frombuffer(dist)
    xn = pixel_to_normalized(_rays(size, Km, dm, ss, slice(r0, r1)).reshape(-1, 2), Km, dm)
    xn.flags.writeable = False
    return xn


def _shade_samples(shade, uv, K, dist, R, t, C, refine=None, xn=None):
    """Radiance (M, 3) at pixel positions uv (M, 2) (or at the undistorted normalised
    coordinates ``xn`` of their rays) (0 where the ray misses the plane) and, with
    ``refine``, whether each sample's plane point satisfies it (M,)."""
    P, hit = pixel_to_plane(uv, K, dist, R, t) if xn is None else normalized_to_plane(xn, R, t)
    if hit.all():  # the usual case: no masked copies of every sample
        rad = np.array(shade(P, C), float, copy=True)
        return rad, (np.asarray(refine(P), bool) if refine is not None
                     else np.zeros(P.shape[0], bool))
    rad = np.zeros((P.shape[0], 3))
    ok = np.zeros(P.shape[0], bool)
    if hit.any():
        rad[hit] = shade(P[hit], C)
        if refine is not None:
            ok[hit] = refine(P[hit])
    return rad, ok


def _expose(radiance, t_s, response: Response, preset: Preset, rng) -> np.ndarray:
    X = radiance * t_s
    sigma = np.sqrt(preset.shot_noise * np.clip(X, 0, None) + preset.read_noise**2)
    X = X + sigma * rng.standard_normal(X.shape)
    return np.clip(np.round(response(X)), 0, 255).astype(np.uint8)


def _marker_layout(preset: Preset) -> list[dict]:
    """Eight markers around the sampled region: corners and edge midpoints
    (:func:`parammap.sheets.marker_layout`, what a lab prints)."""
    side = min(preset.width_mm, preset.height_mm)
    return marker_layout(preset.width_mm, preset.height_mm, 0.2 * side, 0.05 * side, 8)


def _world(scene: Scene, preset: Preset, items: list[dict]) -> _World:
    dictionary = aruco_dictionary(preset.marker_dictionary)
    n = 6 * 20
    imgs, Hs, bbs = [], [], []
    for it in items:
        img = cv2.aruco.generateImageMarker(dictionary, it["id"], n, borderBits=1)
        imgs.append((img > 127).astype(np.uint8))
        c = np.asarray(it["corners_mm"], np.float64)
        Hs.append(cv2.getPerspectiveTransform(
            c.astype(np.float32), np.float32([[0, 0], [n, 0], [n, n], [0, n]])).astype(np.float64))
        bbs.append([c[:, 0].min(), c[:, 0].max(), c[:, 1].min(), c[:, 1].max()])
    irr = float(np.sum(scene.light_int * unit(scene.light_pos - [
        scene.width_mm / 2, scene.height_mm / 2, 0])[:, 2]))
    return _World(scene, imgs, Hs, np.array(bbs), paper=0.55 * irr, marker_white=0.8 * irr,
                  marker_black=0.04 * irr, gradient=preset.light_gradient)


def view_pose(direction, preset: Preset, K, items, rng):
    """Camera pose for a view direction at a varying distance, framing all markers."""
    W, H = preset.width_mm, preset.height_mm
    pts = np.array([c for it in items for c in it["corners_mm"]], float)
    extent = max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1]))
    d = preset.focal_px * extent / (0.75 * min(preset.image_size)) * rng.uniform(0.95, 1.2)
    target = np.array([W / 2, H / 2, 0.0]) + np.r_[rng.uniform(-0.04, 0.04, 2) * [W, H], 0]
    roll = np.radians(rng.uniform(-8, 8))
    corners3 = np.c_[pts, np.zeros(len(pts))]
    margin = 0.04 * min(preset.image_size)
    for _ in range(40):
        R, t = look_at(target + d * np.asarray(direction), target, roll)
        uv = project_points(corners3, K, preset.dist, R, t)
        if (uv.min() > margin and uv[:, 0].max() < preset.image_size[0] - margin
                and uv[:, 1].max() < preset.image_size[1] - margin):
            break
        d *= 1.06
    return R, t


def board_poses(rng, n: int, bw: float, bh: float, focal_px: float,
                size: tuple[int, int], max_tilt_deg: float = 42.0,
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera poses (R, t) of ``n`` calibration photos of a ``bw x bh`` mm board.

    Board frame: x right, y down, z into the board; the camera sits at z < 0, tilted
    5 to ``max_tilt_deg`` deg, aimed off-centre so the board also covers the image's
    edges and corners, where distortion is strongest.
    """
    out = []
    for _ in range(n):
        tilt = np.radians(rng.uniform(5, max_tilt_deg))
        az = rng.uniform(0, 2 * np.pi)
        dvec = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        d = focal_px * max(bw, bh) / (rng.uniform(0.5, 0.8) * min(size))
        shift = rng.uniform(-0.45, 0.45, 2) * [bw, bh]
        target = np.array([bw / 2 + shift[0], bh / 2 + shift[1], 0.0])
        out.append(look_at(target + d * dvec, target, np.radians(rng.uniform(-180, 180))))
    return out


def _board(calib: dict) -> cv2.aruco.CharucoBoard:
    return cv2.aruco.CharucoBoard(
        (calib["squares_x"], calib["squares_y"]), float(calib["square_mm"]),
        float(calib["marker_mm"]), aruco_dictionary(calib["dictionary"]))


def _near_markers(world: _World):
    """Points on or just around a surface marker: cheap to shade, and where edge
    positions matter (poses)."""
    bb = world.marker_bbox
    pad = 0.1 * np.minimum(bb[:, 1] - bb[:, 0], bb[:, 3] - bb[:, 2])

    def f(P: np.ndarray) -> np.ndarray:
        x, y = P[:, 0:1], P[:, 1:2]
        return ((x >= bb[:, 0] - pad) & (x <= bb[:, 1] + pad) & (y >= bb[:, 2] - pad)
                & (y <= bb[:, 3] + pad)).any(1)
    return f


def _render_view_job(args):
    (world, preset, K, R, t, exposures_s, response, seed) = args[:8]
    shade = args[8] if len(args) > 8 else (lambda P, C: _shade_surface(world, P, C))
    rad = render_radiance(shade, preset.image_size, K,
                          preset.dist, R, t, ss=preset.supersample,
                          edge_ss=preset.edge_supersample, refine=_near_markers(world))
    if preset.vignetting:
        rad *= lens_vignetting(preset.image_size, K, preset.vignetting)[..., None]
    rng = np.random.default_rng(seed)
    return [_expose(rad, te, response, preset, rng) for te in exposures_s]


def _render_board_job(args):
    (tex, ppmm, preset, K, R, t, exposure_s, response, seed, white, black) = args
    h, w = tex.shape

    def shade(P, C):
        u = P[:, 0] * ppmm
        v = P[:, 1] * ppmm
        ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        val = np.full(len(P), 0.55 * white)
        val[ok] = np.where(tex[v[ok].astype(int), u[ok].astype(int)] > 127, white, black)
        return np.repeat(val[:, None], 3, axis=1)

    rad = render_radiance(shade, preset.image_size, K, preset.dist, R, t,
                          ss=max(2, preset.supersample), edge_ss=preset.edge_supersample)
    if preset.vignetting:
        rad *= lens_vignetting(preset.image_size, K, preset.vignetting)[..., None]
    return _expose(rad, exposure_s, response, preset, np.random.default_rng(seed))


def _radiance_range(scene: Scene, rng) -> tuple[float, float]:
    """Smallest and largest true radiance over the region (dense direction grid)."""
    T, S = scene.shape
    step = max(1, S // 64)
    rr, cc = np.meshgrid(np.arange(0, T, step), np.arange(0, S, step), indexing="ij")
    dirs = sample_directions("icosahedron", 89.0, level=4)
    lo, hi = np.inf, 0.0
    rr, cc = rr.ravel(), cc.ravel()
    batch = 64  # texels per call: whole batches, not one texel at a time
    for i in range(0, len(rr), batch):
        r, c = rr[i:i + batch], cc[i:i + batch]
        L = true_radiance(scene, np.repeat(r, len(dirs)), np.repeat(c, len(dirs)),
                          np.tile(dirs, (len(r), 1)))
        lo, hi = min(lo, L.min()), max(hi, L.max())
    return float(lo), float(hi)


def _exposure_times(lo: float, hi: float, n: int, response: Response) -> list[float]:
    """Exposure times (s) from long to short so the brightest radiance stays below
    saturation in the shortest and the darkest reaches level ~50 in the longest."""
    t_short = 0.8 / hi
    t_long = float(np.max(response.inverse(60.0))) / max(lo, 1e-6)
    if n == 1:
        return [t_short]
    t_long = max(t_long, t_short * 4.0 ** (n - 1))
    ts = np.geomspace(t_long, t_short, n)
    return [float(f"{x:.6g}") for x in ts]


def resolve_preset(preset, table: dict) -> tuple[str, object]:
    """(name, preset) for a preset name in ``table`` or a preset object ("custom")."""
    if not isinstance(preset, str):
        return "custom", preset
    try:
        return preset, table[preset]
    except KeyError:
        raise InputError(f"unknown preset {preset!r}; one of {sorted(table)}") from None


def partial_dirs(out: str | Path, truth: str | Path | None
                 ) -> tuple[Path, Path, Path, Path]:
    """(out, truth, temporary out, temporary truth): the truth defaults to
    ``<out>.truth``; the temporary folders are made empty."""
    out = Path(out)
    truth = Path(truth) if truth else out.with_name(out.name + ".truth")
    tmp_out = out.with_name(f".{out.name}.partial")
    tmp_truth = truth.with_name(f".{truth.name}.partial")
    for p in (tmp_out, tmp_truth):
        shutil.rmtree(p, ignore_errors=True)
        p.mkdir(parents=True)
    return out, truth, tmp_out, tmp_truth


def write_rig_truth(tmp_truth: Path, view_ids: list[str], is_hold: np.ndarray, poses,
                    directions: np.ndarray, cposes, size, K: np.ndarray, dist) -> None:
    """The rig's ground truth: ``poses.npz`` (views and board photos) and
    ``camera.yaml``."""
    np.savez_compressed(
        tmp_truth / "poses.npz", view_ids=np.array(view_ids), holdout=is_hold,
        R=np.array([p[0] for p in poses]), t=np.array([p[1] for p in poses]),
        directions=directions, calib_R=np.array([p[0] for p in cposes]),
        calib_t=np.array([p[1] for p in cposes]))
    (tmp_truth / "camera.yaml").write_text(yaml.safe_dump({
        "image_size": list(size), "K": np.asarray(K).tolist(), "dist": list(dist)}))


def write_capture_yaml(tmp_out: Path, header: str, sid: str, preset, items: list[dict],
                       calib: dict, ext: str, views_yaml: list[dict],
                       extra: dict | None = None) -> None:
    """``capture.yaml`` of a generated capture (docs/reference/capture-format.md), under a comment
    ``header``; ``extra`` sections (the white card, the colour chart) after the views."""
    cap = {
        "surface": {"id": sid, "width_mm": preset.width_mm, "height_mm": preset.height_mm},
        "markers": {"dictionary": preset.marker_dictionary, "items": items},
        "calibration": {**calib, "images": f"calibration/*.{ext}", "intrinsics": None},
        "camera": {"response": "auto"},
        "views": views_yaml,
        **(extra or {}),
    }
    (tmp_out / "capture.yaml").write_text(
        f"# {header}\n"
        + yaml.safe_dump(cap, sort_keys=False, default_flow_style=None, width=100))


def view_rig(dirs: np.ndarray, preset, K: np.ndarray, items: list[dict], rng, seed: int,
             n_extra_seeds: int) -> tuple:
    """The captured views (``dirs``) plus ``preset.holdout`` held-out directions (a
    stratified set within 5 deg less zenith), a camera pose for each, view ids, and one
    noise seed per view and ``n_extra_seeds`` more.

    Returns
    -------
    (all directions, held-out flags, poses [(R, t)], view ids, seeds)
    """
    hold = sample_directions("stratified", preset.max_zenith_deg - 5, n_side=8,
                             seed=seed + 1)[rng.choice(64, preset.holdout, replace=False)]
    all_dirs = np.concatenate([dirs, hold])
    is_hold = np.r_[np.zeros(len(dirs), bool), np.ones(len(hold), bool)]
    poses = [view_pose(d, preset, K, items, rng) for d in all_dirs]
    view_ids = [f"v{k:03d}" for k in range(len(all_dirs))]
    seeds = rng.integers(0, 2**31, len(all_dirs) + n_extra_seeds)
    return all_dirs, is_hold, poses, view_ids, seeds


def publish(pairs) -> None:
    """Move each finished temporary folder onto its final name."""
    for tmp, final in pairs:
        shutil.rmtree(final, ignore_errors=True)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp.replace(final)


def generate(
    out: str | Path,
    truth: str | Path | None = None,
    preset: str | Preset = "demo",
    seed: int = 0,
    workers: int = 1,
    surface_id: str | None = None,
) -> Path:
    """Write a synthetic capture to ``out`` and its ground truth to ``truth``.

    Parameters
    ----------
    out : capture directory to create (replaced atomically when complete).
    truth : ground-truth directory; default ``<out>.truth`` beside it.
    preset : a name in :data:`PRESETS` or a :class:`Preset`.
    seed : random seed; same seed, same bytes.
    workers : processes used to render views.

    Returns
    -------
    Path of the capture directory.
    """
    name, preset = resolve_preset(preset, PRESETS)
    out, truth, tmp_out, tmp_truth = partial_dirs(out, truth)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    sid = surface_id or f"synth-{name}"

    scene = build_scene(preset.texels, preset.texels, preset.width_mm, preset.height_mm,
                        seed=seed)
    w, h = preset.image_size
    K = np.array([[preset.focal_px, 0, w / 2 - 0.5 + 0.03 * w],
                  [0, preset.focal_px * 1.002, h / 2 - 0.5 - 0.02 * h], [0, 0, 1]])
    response = Response()
    lo, hi = _radiance_range(scene, rng)
    items = _marker_layout(preset)
    world = _world(scene, preset, items)
    lo = min(lo, world.marker_black)
    times = _exposure_times(lo, max(hi, world.marker_white), preset.exposures, response)

    dirs = sample_directions(preset.scheme, preset.max_zenith_deg, **dict(preset.scheme_args))
    all_dirs, is_hold, poses, view_ids, seeds = view_rig(dirs, preset, K, items, rng, seed,
                                                         preset.calib_images)

    logger.info(f"synth {name}: {len(dirs)} views + {int(is_hold.sum())} held out, "
                f"{preset.exposures} exposures {times} s, {preset.texels}x{preset.texels} "
                f"texels, {w}x{h} px")
    jobs = [(world, preset, K, R, t, times, response, int(seeds[k]))
            for k, (R, t) in enumerate(poses)]
    views_yaml = []
    ext = preset.image_format
    with executor(workers) as ex:
        for k, photos in enumerate(ex.map(_render_view_job, jobs)):
            exps = []
            for e, img in enumerate(photos):
                rel = f"views/{view_ids[k]}_{e}.{ext}"
                write_image_atomic(tmp_out / rel, img)
                exps.append({"file": rel, "exposure_s": times[e]})
            views_yaml.append({"id": view_ids[k], "holdout": bool(is_hold[k]), "exposures": exps})
            if (k + 1) % 10 == 0 or k + 1 == len(jobs):
                logger.info(f"  rendered {k + 1}/{len(jobs)} views")

        # Calibration board photos from varied poses.
        sq = round(0.125 * preset.width_mm, 3)
        calib = {"board": "charuco", "squares_x": 7, "squares_y": 5, "square_mm": sq,
                 "marker_mm": round(0.72 * sq, 3), "dictionary": "DICT_5X5_100"}
        board = _board(calib)
        ppmm = 8.0
        bw, bh = calib["squares_x"] * sq, calib["squares_y"] * sq
        tex = board.generateImage((int(bw * ppmm), int(bh * ppmm)), marginSize=0)
        cposes = board_poses(rng, preset.calib_images, bw, bh, preset.focal_px, (w, h))
        bjobs = [(tex, ppmm, preset, K, R, t, 0.7 / 0.8, response,
                  int(seeds[len(all_dirs) + k]), 0.8, 0.04)
                 for k, (R, t) in enumerate(cposes)]
        for k, img in enumerate(ex.map(_render_board_job, bjobs)):
            write_image_atomic(tmp_out / f"calibration/board_{k:02d}.{ext}", img)

        extra = _radiometry_photos(tmp_out, world, preset, K, items, times, response, ex,
                                   seed, ext)

    write_capture_yaml(tmp_out, f"Synthetic capture written by parammap synth (preset {name}, "
                       f"seed {seed})", sid, preset, items, calib, ext, views_yaml, extra)

    # Ground truth, never read by the pipeline.
    scene.save(tmp_truth / "scene.npz")
    params, mask = mh_truth(scene)
    np.savez_compressed(tmp_truth / "mh_params.npz", params=params, mask=mask)
    np.savez_compressed(
        tmp_truth / "response.npz", levels=np.arange(256),
        exposure=response.inverse(np.arange(256)[:, None]),
        gamma=np.array(response.gamma), shoulder=np.array(response.shoulder))
    write_rig_truth(tmp_truth, view_ids, is_hold, poses, all_dirs, cposes, preset.image_size,
                    K, preset.dist)
    (tmp_truth / "generator.json").write_text(json.dumps(
        {"preset": name, "seed": seed, "settings": asdict(preset), "exposure_s": times,
         "radiance_range": [lo, hi], "shot_noise": preset.shot_noise,
         "read_noise": preset.read_noise}, indent=1))
    publish(((tmp_out, out), (tmp_truth, truth)))
    logger.info(f"synth {name}: wrote {out} and {truth} in {time.perf_counter() - t0:.1f} s")
    return out


def _write_bracket(tmp_out: Path, vid: str, photos: list, times: list[float], ext: str,
                   ) -> list[dict]:
    exps = []
    for e, img in enumerate(photos):
        rel = f"radiometry/{vid}_{e}.{ext}"
        write_image_atomic(tmp_out / rel, img)
        exps.append({"file": rel, "exposure_s": times[e]})
    return exps


def _radiometry_photos(tmp_out: Path, world: _World, preset: Preset, K: np.ndarray,
                       items: list[dict], times: list[float], response: Response, ex,
                       seed: int, ext: str) -> dict:
    """The white card's views and the colour chart's bracket of a preset that asks for
    them, as ``capture.yaml`` sections. Their own random stream: a preset without them
    keeps its bytes."""
    extra: dict = {}
    rng = np.random.default_rng(seed + 7919)
    if preset.card_views:
        card = replace(world, card=True)
        dirs = sample_directions("stratified", 50.0, n_side=max(2, int(np.ceil(np.sqrt(
            preset.card_views)))), seed=seed + 3)[:preset.card_views]
        jobs = [(card, preset, K, *view_pose(d, preset, K, items, rng), times, response,
                 int(rng.integers(2**31))) for d in dirs]
        views = []
        for k, photos in enumerate(ex.map(_render_view_job, jobs)):
            vid = f"card{k:02d}"
            views.append({"id": vid, "exposures": _write_bracket(tmp_out, vid, photos,
                                                                  times, ext)})
        extra["flatfield"] = {"reflectance": CARD_ALBEDO, "views": views}
    if preset.chart_camera:
        sc = world.scene
        cw, ch = chart_size_mm()
        scale = 0.9 * sc.width_mm / cw
        rgb = world.marker_white * chart_camera_rgb(preset.chart_camera, preset.chart_light)
        shade = chart_shade(rgb, ((sc.width_mm - scale * cw) / 2, (sc.height_mm + scale * ch) / 2),
                            scale, np.full(3, world.paper))
        centre = np.array([sc.width_mm / 2, sc.height_mm / 2, 0.0])
        d = preset.focal_px * scale * cw / (0.8 * preset.image_size[0])
        R, t = look_at(centre + d * unit(np.array([0.15, -0.1, 1.0])), centre,
                       np.radians(rng.uniform(-8, 8)))
        photos = _render_view_job((world, preset, K, R, t, times, response,
                                   int(rng.integers(2**31)), lambda P, C: shade(P, C)))
        extra["colour_chart"] = {"id": "chart", "chart": "MCC24",
                                 "reference": "BabelColor Average",
                                 "exposures": _write_bracket(tmp_out, "chart", photos, times,
                                                             ext)}
    return extra


def preset_with(name: str, **changes) -> Preset:
    """A named preset with some fields changed."""
    return replace(PRESETS[name], **changes)


def true_view_radiance(capture_dir: str | Path, truth_dir: str | Path, view_id: str,
                       supersample: int | None = None) -> np.ndarray:
    """Noise-free radiance image (H, W, 3) of a generated view, for tests against truth."""
    truth_dir = Path(truth_dir)
    gen = json.loads((truth_dir / "generator.json").read_text())
    s = gen["settings"]
    preset = Preset(**{k: tuple(tuple(x) if isinstance(x, list) else x for x in v)
                       if isinstance(v, list) else v for k, v in s.items()})
    cap = yaml.safe_load((Path(capture_dir) / "capture.yaml").read_text())

    world = _world(load_scene(truth_dir / "scene.npz"), preset, cap["markers"]["items"])
    cam = yaml.safe_load((truth_dir / "camera.yaml").read_text())
    poses = np.load(truth_dir / "poses.npz")
    k = list(poses["view_ids"]).index(view_id)
    return render_radiance(lambda P, C: _shade_surface(world, P, C), preset.image_size,
                           np.array(cam["K"]), preset.dist, poses["R"][k], poses["t"][k],
                           ss=supersample or preset.supersample,
                           edge_ss=preset.edge_supersample, refine=_near_markers(world))


def true_observations(
    truth_dir: str | Path, view_ids: list[str], rows: np.ndarray, cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """True view directions and radiances of texels ``[rows, cols]`` (each (M,)) in the
    given views, from the generator's poses: (M, N, 3) directions, (M, N, 3) radiance."""
    truth_dir = Path(truth_dir)
    scene = load_scene(truth_dir / "scene.npz")
    poses = np.load(truth_dir / "poses.npz")
    ids = list(poses["view_ids"])
    k = [ids.index(v) for v in view_ids]
    C = np.einsum("nji,nj->ni", poses["R"][k], -poses["t"][k])  # -R.T t
    T, S = scene.shape
    ctr = texel_centres(S, T, scene.width_mm, scene.height_mm)[rows, cols]
    d = unit(C[None] - ctr[:, None])
    M, N = d.shape[:2]
    rad = true_radiance(scene, np.repeat(rows, N), np.repeat(cols, N), d.reshape(-1, 3))
    return d, rad.reshape(M, N, 3)
