"""Physically based synthetic captures rendered with Mitsuba 3 (``parammap synth
--preset pbr-*``; needs the optional extra ``pip install parammap[pbr]``).

An independent test bed next to the analytic generator of :mod:`.generate`: nothing
here is in the MH or SH family. The surface is a grid of patches with microfacet
BSDFs (rough plastic and rough conductors with GGX, Disney's principled BSDF, matte
paper) over a finely printed albedo, lit by rectangular and disc area lights and a dim
environment, rendered by Monte Carlo path tracing (so the photos carry sampling
noise). The rig is part of the preset and varies between presets: image size, focal
length, principal point, lens distortion, marker dictionary, count (4-12) and layout,
ChArUco board and its dictionary, the number and spacing of exposures, a filmic
response with a toe and a shoulder, sensor noise.

Mitsuba has no lens distortion: each view is rendered through a pinhole camera wide
enough to cover the distorted image at ``render_scale`` times the resolution, then
resampled through OpenCV's distortion model, ``render_scale**2`` bilinear samples per
photo pixel (a box filter over the pixel's area). The clean and relit truths, which are
compared with renders of the maps only on the surface, give the preset's samples only to
the render pixels that see the surface or a marker; the card around is rendered at a
quarter of the resolution and smoothed (most of a view's pixels, and of its time). The
photos are rendered whole: cropped, they cost pbr-bench's poses a factor of 2-4
(docs/results.md, session 45).

The capture follows ``docs/reference/capture-format.md`` exactly. The ground truth goes
to a separate folder the pipeline never reads: ``camera.yaml`` (K, distortion), ``poses.npz`` (R, t
per view and per board photo), ``response.npz`` (normalised exposure per 8-bit level),
``radiance/<view>.exr`` (the radiance each photo was exposed from, Monte Carlo noise
included), ``clean/<view>.exr`` (high-sample renders of the held-out views),
``scene.json`` (patches, materials, lights) and ``generator.json``.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from ..errors import InputError
from ..geometry import texel_centres, undistort_normalized
from ..stores.capture import aruco_dictionary
from ..stores.hdr import read_rgb, write_rgb
from ..stores.images import write_image_atomic
from .generate import (
    CARD_ALBEDO,
    _expose,
    board_poses,
    partial_dirs,
    publish,
    resolve_preset,
    view_pose,
    view_rig,
    write_capture_yaml,
    write_rig_truth,
)
from .sampling import sample_directions

logger = logging.getLogger(__name__)

__all__ = ["PBR_PRESETS", "FilmicResponse", "Light", "PbrPreset", "generate_pbr",
           "light_irradiance", "normal_reflectance", "novel_lights", "patch_labels",
           "light_extent", "read_truth_radiance", "render_relit", "render_white_card",
           "sky_share", "stated_lights"]


@dataclass(frozen=True)
class Light:
    """An area light aimed at the surface's centre.

    ``shape`` rect (``size_mm`` = width, height) or disc (``size_mm[0]`` = radius);
    ``position_mm`` relative to the surface's centre; ``radiance`` RGB.
    """

    shape: str = "rect"
    position_mm: tuple[float, float, float] = (120.0, 160.0, 520.0)
    size_mm: tuple[float, float] = (90.0, 60.0)
    radiance: tuple[float, float, float] = (30.0, 29.0, 27.0)


@dataclass(frozen=True)
class FilmicResponse:
    """Hable's filmic curve (a toe and a shoulder) followed by a display gamma, the
    same in every channel: ``level = 255 * (h(w X) / h(w)) ** (1 / gamma)`` with
    ``h(x) = (x (a x + c b) + d e) / (x (a x + b) + d f) - e / f``, X the normalised
    exposure (1 = white, level 255)."""

    a: float = 0.15  # shoulder strength
    b: float = 0.50  # linear strength
    c: float = 0.10  # linear angle
    d: float = 0.20  # toe strength
    e: float = 0.02  # toe numerator
    f: float = 0.30  # toe denominator
    white: float = 11.2
    gamma: float = 2.2

    def _h(self, x):
        a, b, c, d, e, f = self.a, self.b, self.c, self.d, self.e, self.f
        return (x * (a * x + c * b) + d * e) / (x * (a * x + b) + d * f) - e / f

    def __call__(self, X: np.ndarray) -> np.ndarray:
        x = np.clip(np.asarray(X, float), 0.0, 1.0) * self.white
        return 255.0 * np.clip(self._h(x) / self._h(self.white), 0, 1) ** (1 / self.gamma)

    def inverse(self, level: np.ndarray) -> np.ndarray:
        """Normalised exposure at real-valued levels in [0, 255] (numerical inverse)."""
        X = np.geomspace(1e-7, 1.0, 20001)
        return np.interp(np.asarray(level, float), self(X), X)


@dataclass(frozen=True)
class PbrPreset:
    """Everything about one physically based capture and its rig."""

    width_mm: float = 200.0
    height_mm: float = 150.0
    patches: tuple[int, int] = (3, 2)  # columns, rows of material patches
    texture_px_per_mm: float = 4.0
    image_size: tuple[int, int] = (640, 480)
    focal_px: float = 760.0
    aspect: float = 1.0015  # fy / fx
    principal_offset: tuple[float, float] = (0.02, -0.015)  # of the image size
    dist: tuple[float, ...] = (-0.09, 0.04, 0.0005, -0.0004, 0.0)
    scheme: str = "spiral"
    views: int = 30
    max_zenith_deg: float = 75.0
    holdout: int = 3
    exposures: int = 3
    stops: float = 2.0  # between neighbouring exposures
    markers: int = 5
    marker_dictionary: str = "DICT_5X5_250"
    marker_frac: float = 0.22  # marker edge over the shorter side of the region
    board: tuple[int, int] = (9, 7)  # ChArUco squares across, down
    board_max_tilt_deg: float = 55.0
    board_dictionary: str = "DICT_5X5_100"
    calib_images: int = 24
    spp: int = 4  # samples per render pixel (render_scale^2 render pixels per photo pixel)
    # Mitsuba's sampler of the photos: 4 independent samples leave 18 % of Monte Carlo
    # noise a pixel, far above a camera's own (about 1 % at mid-grey); "multijitter"
    # leaves about 3 % in the same time (docs/results.md, session 41)
    sampler: str = "independent"
    # the held-out views' clean renders (and relit truths). Their Monte Carlo noise (6 %
    # rms a pixel on pbr-tiny) is part of every figure measured against them; "multijitter"
    # at 8 leaves a fifth of it in a third of the time (docs/results.md, session 40)
    clean_spp: int = 32
    clean_sampler: str = "independent"
    render_scale: int = 2
    lights: tuple[Light, ...] = (Light(),)
    environment: float = 0.03
    response: FilmicResponse = field(default_factory=FilmicResponse)
    shot_noise: float = 3e-5
    read_noise: float = 3e-4
    image_format: str = "png"
    jpeg_quality: int = 95
    holdout_specular: int = 0  # of the held-out views, near the first light's mirror direction
    # capture.yaml lists the lights (shape, size, centre) as a lab that measured them would
    state_lights: bool = False
    # GGX alpha drawn per patch: rough plastic, rough conductor
    plastic_alpha: tuple[float, float] = (0.06, 0.3)
    metal_alpha: tuple[float, float] = (0.1, 0.35)


PBR_PRESETS = {
    # test suite: about a minute of rendering on 2 cores
    "pbr-tiny": PbrPreset(),
    # benchmarks: larger photos, more views and exposures, another rig
    "pbr-bench": PbrPreset(
        width_mm=240.0, height_mm=180.0, patches=(4, 3), image_size=(1024, 768),
        focal_px=1180.0, aspect=0.999, principal_offset=(-0.015, 0.02),
        dist=(0.06, -0.11, -0.0006, 0.0003, 0.02), views=96, max_zenith_deg=80.0,
        holdout=6, exposures=5, stops=1.5, markers=10, marker_dictionary="DICT_6X6_250",
        marker_frac=0.14, board=(9, 7), board_dictionary="DICT_APRILTAG_36h11",
        calib_images=16,
        spp=4, clean_spp=48, response=FilmicResponse(white=8.0, gamma=2.0),
        image_format="jpg"),
    # pbr-tiny photographed with about a camera's noise (stratified samples) and held out
    # against 5x cleaner truths: what the Monte Carlo noise of pbr-tiny's photos hides
    # (benchmarks; issue 49's speckle)
    "pbr-tiny-camera": PbrPreset(sampler="multijitter", clean_spp=8,
                                 clean_sampler="multijitter"),
    # two area lights (a rectangle and a disc): two highlights per texel
    "pbr-two-lights": PbrPreset(
        views=40, markers=8, marker_dictionary="DICT_4X4_100", marker_frac=0.18,
        exposures=4, stops=1.7, board=(8, 6), board_dictionary="DICT_4X4_50",
        lights=(Light("rect", (140.0, 120.0, 480.0), (80.0, 50.0), (26.0, 25.0, 24.0)),
                Light("disc", (-160.0, -90.0, 430.0), (30.0, 0.0), (14.0, 16.0, 20.0))),
        response=FilmicResponse(a=0.22, d=0.3, white=9.0, gamma=2.4)),
    # pbr-two-lights' scene seen from 100 views, with a response unlike the others': the
    # capture issue 49's MH regression was looked for on (benchmarks, --seed 3)
    "pbr-two-lights-dense": PbrPreset(
        views=100, max_zenith_deg=72.0, holdout=6, markers=8,
        marker_dictionary="DICT_4X4_100", marker_frac=0.18, exposures=4, stops=1.7,
        board=(8, 6), board_dictionary="DICT_4X4_50",
        lights=(Light("rect", (140.0, 120.0, 480.0), (80.0, 50.0), (26.0, 25.0, 24.0)),
                Light("disc", (-160.0, -90.0, 430.0), (30.0, 0.0), (14.0, 16.0, 20.0))),
        response=FilmicResponse(a=0.3, b=0.35, c=0.05, d=0.35, e=0.01, f=0.25, white=6.0,
                                gamma=1.8)),
    # near-mirror plastic and metal (GGX alpha 0.02-0.08) under one small disc light:
    # highlights a few degrees wide, seen by few views
    "pbr-mirror": PbrPreset(
        patches=(4, 2), views=60, max_zenith_deg=70.0, holdout=6, holdout_specular=3,
        exposures=5, stops=2.0,
        markers=6, marker_dictionary="DICT_4X4_250", board=(8, 6),
        board_dictionary="DICT_6X6_100", focal_px=700.0, principal_offset=(-0.01, 0.01),
        dist=(-0.05, 0.02, 0.0, 0.0, 0.0),
        lights=(Light("disc", (-90.0, 140.0, 500.0), (14.0, 0.0), (260.0, 250.0, 240.0)),),
        plastic_alpha=(0.02, 0.08), metal_alpha=(0.02, 0.08),
        response=FilmicResponse(a=0.18, d=0.25, white=10.0, gamma=2.2)),
}

MATERIAL_KINDS = ("roughplastic", "roughconductor", "principled", "diffuse")
#: stratified samples per render pixel of a board photo: its squares' edges, with half
#: the Monte Carlo noise of 4 independent samples a pixel and half their time
BOARD_SPP = 2


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError:
        raise InputError("the pbr presets need Mitsuba 3: pip install 'parammap[pbr]'") from None
    # the scalar CPU variant: no JIT compiler needed, multi-threaded over image blocks
    mi.set_variant("scalar_rgb")
    return mi


def _quad_transform(tl, tr, bl):
    """Mitsuba ``rectangle`` ([-1, 1]^2 in local x, y) onto the quad with corners
    top-left ``tl``, top-right ``tr``, bottom-left ``bl``; its normal is
    (tr - tl) x (tl - bl)."""
    tl, tr, bl = (np.asarray(p, float) for p in (tl, tr, bl))
    ex, ey = (tr - tl) / 2, (tl - bl) / 2
    ez = np.cross(ex, ey)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2] = ex, ey, ez / np.linalg.norm(ez)
    M[:3, 3] = tl + ex - ey
    import mitsuba as mi

    return mi.ScalarTransform4f(M.tolist())


def _bitmap(mi, image: np.ndarray, nearest: bool = False) -> dict:
    """Texture from an (h, w, 3) float image whose row 0 is the quad's top edge
    (Mitsuba's v runs bottom-up)."""
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(
        np.flipud(image), np.float32)), "filter_type": "nearest" if nearest else "bilinear",
        "raw": True}


def _albedo_texture(preset: PbrPreset, rng) -> np.ndarray:
    """(h, w, 3) albedo in [0.05, 0.85]: a base colour per patch, smooth blotches and
    fine print (text, hairlines, dots) finer than most photos resolve."""
    ppmm = preset.texture_px_per_mm
    w, h = int(round(preset.width_mm * ppmm)), int(round(preset.height_mm * ppmm))
    nx, ny = preset.patches
    base = rng.uniform(0.25, 0.8, (ny, nx, 3))
    tex = cv2.resize(base.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    blot = cv2.resize(rng.uniform(0.8, 1.2, (6, 8, 3)).astype(np.float32), (w, h),
                      interpolation=cv2.INTER_CUBIC)
    tex = tex * blot
    ink = np.zeros((h, w), np.uint8)
    words = ["parammap", "glossy", "foil", "lobe", "texel", "capture", "GGX", "0.4 mm"]
    for _ in range(int(0.02 * w * h / 100)):
        org = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.putText(ink, str(rng.choice(words)), org, cv2.FONT_HERSHEY_SIMPLEX,
                    float(rng.uniform(0.3, 0.9)), 255, 1, cv2.LINE_AA)
    for _ in range(int(w * h / 8000)):
        p0 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        p1 = (p0[0] + int(rng.integers(-200, 200)), p0[1] + int(rng.integers(-200, 200)))
        cv2.line(ink, p0, p1, 255, 1, cv2.LINE_AA)
    for _ in range(int(w * h / 3000)):
        cv2.circle(ink, (int(rng.integers(0, w)), int(rng.integers(0, h))),
                   int(rng.integers(1, 4)), 255, -1, cv2.LINE_AA)
    a = (ink.astype(np.float32) / 255.0)[..., None]
    inkcol = rng.uniform(0.02, 0.15, 3).astype(np.float32)
    return np.clip(tex * (1 - a) + inkcol * a, 0.05, 0.85)


def _materials(preset: PbrPreset, rng) -> list[dict]:
    """One BSDF description per patch, every kind present, seeded."""
    n = preset.patches[0] * preset.patches[1]
    kinds = [MATERIAL_KINDS[k % len(MATERIAL_KINDS)] for k in range(n)]
    rng.shuffle(kinds)
    out = []
    for kind in kinds:
        if kind == "roughplastic":
            out.append({"kind": kind, "alpha": float(rng.uniform(*preset.plastic_alpha)),
                        "int_ior": 1.5})
        elif kind == "roughconductor":
            out.append({"kind": kind, "alpha": float(rng.uniform(*preset.metal_alpha)),
                        "material": str(rng.choice(["Au", "Cu", "Al", "Ag"]))})
        elif kind == "principled":
            out.append({"kind": kind, "roughness": float(rng.uniform(0.25, 0.6)),
                        "metallic": float(rng.uniform(0.0, 0.5)), "specular": 0.5})
        else:
            out.append({"kind": kind})
    return out


def _bsdf(mi, m: dict, albedo: np.ndarray) -> dict:
    tex = _bitmap(mi, albedo)
    if m["kind"] == "roughplastic":
        return {"type": "roughplastic", "distribution": "ggx", "alpha": m["alpha"],
                "int_ior": m["int_ior"], "diffuse_reflectance": tex}
    if m["kind"] == "roughconductor":
        return {"type": "roughconductor", "distribution": "ggx", "alpha": m["alpha"],
                "material": m["material"]}
    if m["kind"] == "principled":
        return {"type": "principled", "base_color": tex, "roughness": m["roughness"],
                "metallic": m["metallic"], "specular": m["specular"]}
    return {"type": "diffuse", "reflectance": tex}


def _marker_layout(preset: PbrPreset, rng) -> list[dict]:
    """``preset.markers`` (4-12) markers outside the region: the corners first, then
    the edge midpoints, then points at a quarter of each edge; random ids."""
    W, H = preset.width_mm, preset.height_mm
    s = preset.marker_frac * min(W, H)
    g = 0.06 * min(W, H)
    lo_x, hi_x, lo_y, hi_y = -g - s, W + g, -g - s, H + g
    cands = [(lo_x, hi_y), (hi_x, hi_y), (hi_x, lo_y), (lo_x, lo_y),
             (W / 2 - s / 2, hi_y), (hi_x, H / 2 - s / 2), (W / 2 - s / 2, lo_y),
             (lo_x, H / 2 - s / 2),
             (W / 4 - s / 2, hi_y), (hi_x, 3 * H / 4 - s / 2), (3 * W / 4 - s / 2, lo_y),
             (lo_x, H / 4 - s / 2)]
    n = int(np.clip(preset.markers, 4, len(cands)))
    size = aruco_dictionary(preset.marker_dictionary).bytesList.shape[0]
    ids = sorted(int(i) for i in rng.choice(size, n, replace=False))
    items = []
    for k, (x0, y0) in enumerate(cands[:n]):
        corners = [[x0, y0 + s], [x0 + s, y0 + s], [x0 + s, y0], [x0, y0]]
        items.append({"id": ids[k],
                      "corners_mm": [[round(a, 4), round(b, 4)] for a, b in corners]})
    return items


def _regions_mm(preset: PbrPreset, items: list[dict]) -> list[np.ndarray]:
    """What a view's measurements read, as (4, 3) world corners (mm, z = 0) of
    rectangles: the surface, and each marker with its quiet zone."""
    cell = min(abs(it["corners_mm"][1][0] - it["corners_mm"][0][0]) for it in items) \
        / (aruco_dictionary(preset.marker_dictionary).markerSize + 2)
    boxes = [np.array([[0.0, 0.0], [preset.width_mm, preset.height_mm]])]
    boxes += [np.array(it["corners_mm"], float) for it in items]
    return [_rect_mm(b.min(0) - 2 * cell, b.max(0) + 2 * cell) for b in boxes]


def _rect_mm(lo, hi) -> np.ndarray:
    """(4, 3) the corners of the rectangle [lo, hi] (mm) in the plane z = 0."""
    (x0, y0), (x1, y1) = lo, hi
    return np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])


def _marker_image(dictionary: str, marker_id: int, cell_px: int = 12) -> np.ndarray:
    """Marker with a one-cell white quiet zone, albedo 0.04 / 0.8, (h, w, 3)."""
    d = aruco_dictionary(dictionary)
    n = (d.markerSize + 2) * cell_px
    img = cv2.aruco.generateImageMarker(d, marker_id, n, borderBits=1)
    img = cv2.copyMakeBorder(img, cell_px, cell_px, cell_px, cell_px, cv2.BORDER_CONSTANT,
                             value=255)
    return np.repeat(np.where(img > 127, 0.8, 0.04).astype(np.float32)[..., None], 3, -1)


def _light_axes(L: Light) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The light's local x, y and emitting normal (toward the surface's centre), as
    Mitsuba's ``look_at`` of :func:`_light` sets them."""
    p = np.asarray(L.position_mm, float)
    n = -p / np.linalg.norm(p)
    up = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, n)
    x /= np.linalg.norm(x)
    return x, np.cross(n, x), n


def light_irradiance(L: Light, point_mm: np.ndarray, n: int = 48) -> np.ndarray:
    """(3,) the irradiance an area light gives a point of the surface (mm relative to the
    surface's centre; normal +z), by midpoint quadrature over the light's area."""
    x, y, nl = _light_axes(L)
    g = (np.arange(n) + 0.5) / n
    if L.shape == "disc":
        r, t = L.size_mm[0] * np.sqrt(g)[:, None], 2 * np.pi * g[None, :]
        q = r[..., None] * (np.cos(t)[..., None] * x + np.sin(t)[..., None] * y)
        area = np.pi * L.size_mm[0] ** 2
    else:
        u, v = (2 * g - 1)[:, None], (2 * g - 1)[None, :]
        q = (u[..., None] * L.size_mm[0] / 2 * x + v[..., None] * L.size_mm[1] / 2 * y)
        area = L.size_mm[0] * L.size_mm[1]
    d = np.asarray(L.position_mm, float) + q - np.asarray(point_mm, float)
    r2 = (d * d).sum(-1)
    cos_s = np.clip(d[..., 2], 0, None) / np.sqrt(r2)
    cos_l = np.clip(-(d @ nl), 0, None) / np.sqrt(r2)
    return np.asarray(L.radiance, float) * float(np.mean(cos_s * cos_l / r2)) * area


def light_extent(shape: str, size_mm) -> dict:
    """A generator's light's shape as the capture format states it (a disc's size its
    diameter, where :class:`Light` holds its radius)."""
    return {"shape": shape,
            "size_mm": list(map(float, size_mm)) if shape == "rect" else [2.0 * size_mm[0]] * 2}


def stated_lights(preset: PbrPreset) -> list[dict]:
    """The capture format's ``lights`` for a preset's lights, as a lab that measured
    them would write them: centres in the surface frame (mm) and their extents
    (:func:`light_extent`)."""
    centre = np.array([preset.width_mm / 2, preset.height_mm / 2, 0.0])
    return [{"position_mm": np.round(centre + L.position_mm, 3).tolist(),
             **light_extent(L.shape, L.size_mm)} for L in preset.lights]


def sky_share(preset: PbrPreset) -> list[float]:
    """(R, G, B) share of a white card's light at the surface's centre that its even
    sky gives (what stays with the lamps off): ``pi sky / (E_lamps + pi sky)``."""
    e = sum(light_irradiance(L, np.zeros(3)) for L in preset.lights)
    sky = np.pi * preset.environment
    return np.round(sky / (e + sky), 6).tolist()


def _light(L: Light, target: np.ndarray) -> dict:
    import mitsuba as mi

    pos = target + np.asarray(L.position_mm, float)
    axis = np.asarray(L.position_mm, float) / np.linalg.norm(L.position_mm)
    to = mi.ScalarTransform4f().look_at(origin=pos.tolist(), target=target.tolist(),
                                        up=[0, 0, 1] if abs(axis[2]) < 0.9 else [0, 1, 0])
    if L.shape == "disc":
        shape = {"type": "disk", "to_world": to @ mi.ScalarTransform4f().scale(
            [L.size_mm[0], L.size_mm[0], 1.0])}
    elif L.shape == "rect":
        shape = {"type": "rectangle", "to_world": to @ mi.ScalarTransform4f().scale(
            [L.size_mm[0] / 2, L.size_mm[1] / 2, 1.0])}
    else:
        raise InputError(f"unknown light shape {L.shape!r}; rect or disc")
    shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": list(L.radiance)}}
    return shape


def _specular_holdout(preset: PbrPreset, all_dirs: np.ndarray, is_hold: np.ndarray,
                      poses: list, K: np.ndarray, items: list[dict], seed: int) -> None:
    """Move the last ``preset.holdout_specular`` held-out views (in place) to within
    about 8 deg of the first light's mirror direction at the surface's centre, so that
    they see the highlights; drawn with a generator of their own (the other views
    stay as they were)."""
    rng = np.random.default_rng(seed + 7)
    p = np.asarray(preset.lights[0].position_mm, float)
    mirror = np.array([-p[0], -p[1], p[2]]) / np.linalg.norm(p)
    zmax = math.radians(preset.max_zenith_deg - 5)
    for k in np.flatnonzero(is_hold)[-preset.holdout_specular:]:
        while True:
            d = mirror + rng.normal(0.0, math.sin(math.radians(8.0)) / 2, 3)
            d /= np.linalg.norm(d)
            if d[2] >= math.cos(zmax):
                break
        all_dirs[k] = d
        poses[k] = view_pose(d, preset, K, items, rng)


def _surface_scene(mi, preset: PbrPreset, items: list[dict], mats: list[dict],
                   albedo: np.ndarray):
    W, H = preset.width_mm, preset.height_mm
    ppmm = preset.texture_px_per_mm
    d: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": 3}}
    ext = 3 * max(W, H)
    # a mid-grey card under everything, 0.3 mm below the surface plane
    d["card"] = {"type": "rectangle", "to_world": _quad_transform(
        [W / 2 - ext, H / 2 + ext, -0.3], [W / 2 + ext, H / 2 + ext, -0.3],
        [W / 2 - ext, H / 2 - ext, -0.3]),
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.45, 0.45, 0.42]}}}
    nx, ny = preset.patches
    th, tw = albedo.shape[:2]
    for k, m in enumerate(mats):
        i, j = divmod(k, nx)  # patch row from the top, column
        x0, x1 = j * W / nx, (j + 1) * W / nx
        y1, y0 = H - i * H / ny, H - (i + 1) * H / ny
        crop = albedo[int(round((H - y1) * ppmm)):int(round((H - y0) * ppmm)) or th,
                      int(round(x0 * ppmm)):int(round(x1 * ppmm)) or tw]
        d[f"patch{k}"] = {"type": "rectangle",
                          "to_world": _quad_transform([x0, y1, 0], [x1, y1, 0], [x0, y0, 0]),
                          "bsdf": _bsdf(mi, m, crop)}
    for it in items:
        c = np.asarray(it["corners_mm"], float)
        cell = (c[1, 0] - c[0, 0]) / (aruco_dictionary(preset.marker_dictionary).markerSize + 2)
        tl, tr, bl = c[0] + [-cell, cell], c[1] + [cell, cell], c[3] + [-cell, -cell]
        d[f"marker{it['id']}"] = {
            "type": "rectangle",
            "to_world": _quad_transform(np.r_[tl, 0], np.r_[tr, 0], np.r_[bl, 0]),
            "bsdf": {"type": "diffuse", "reflectance": _bitmap(
                mi, _marker_image(preset.marker_dictionary, it["id"]), nearest=True)}}
    centre = np.array([W / 2, H / 2, 0.0])
    for k, L in enumerate(preset.lights):
        d[f"light{k}"] = _light(L, centre)
    if preset.environment > 0:
        d["env"] = {"type": "constant",
                    "radiance": {"type": "rgb", "value": [preset.environment] * 3}}
    return mi.load_dict(d)


def _board_scene(mi, calib: dict, board_img: np.ndarray):
    """The ChArUco board in its own frame (x right, y down, z into the board) under a
    uniform white sky, a grey wall 0.5 mm behind it."""
    bw = calib["squares_x"] * calib["square_mm"]
    bh = calib["squares_y"] * calib["square_mm"]
    ext = 4 * max(bw, bh)
    alb = np.repeat(np.where(board_img > 127, 0.8, 0.04).astype(np.float32)[..., None], 3, -1)
    # cosine-weighted BSDF samples of a uniform sky are exact on the board (nothing in
    # front of it): sampling the sky as well only adds noise
    d = {"type": "scene", "integrator": {"type": "direct", "emitter_samples": 0,
                                         "bsdf_samples": 1},
         "board": {"type": "rectangle",
                   "to_world": _quad_transform([0, 0, 0], [bw, 0, 0], [0, bh, 0]),
                   "bsdf": {"type": "diffuse", "reflectance": _bitmap(mi, alb, nearest=True)}},
         "wall": {"type": "rectangle",
                  "to_world": _quad_transform([-ext, -ext, 0.5], [ext, -ext, 0.5],
                                              [-ext, ext, 0.5]),
                  "bsdf": {"type": "diffuse",
                           "reflectance": {"type": "rgb", "value": [0.3, 0.3, 0.3]}}},
         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}
    return mi.load_dict(d)


@dataclass
class _Camera:
    """The pinhole Mitsuba renders and the resampling to the distorted photo."""

    f: float
    size: tuple[int, int]
    map_x: np.ndarray  # (H, W, n) render-pixel coordinates of each photo pixel's samples
    map_y: np.ndarray

    @classmethod
    def build(cls, K: np.ndarray, dist, size: tuple[int, int], scale: int) -> _Camera:
        w, h = size
        off = (np.arange(scale) + 0.5) / scale - 0.5
        ou, ov = (a.ravel() for a in np.meshgrid(off, off))
        u = np.arange(w)[None, :, None] + ou
        v = np.arange(h)[:, None, None] + ov
        u, v = np.broadcast_arrays(u, v)
        yd = (v - K[1, 2]) / K[1, 1]
        xd = (u - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        xy = undistort_normalized(np.stack([xd, yd], -1), dist)
        f = scale * K[0, 0]
        half = np.abs(xy).reshape(-1, 2).max(0) * f + 2
        rw, rh = 2 * int(math.ceil(half[0])), 2 * int(math.ceil(half[1]))
        mx = (f * xy[..., 0] + rw / 2 - 0.5).astype(np.float32)
        my = (f * xy[..., 1] + rh / 2 - 0.5).astype(np.float32)
        return cls(f, (rw, rh), mx, my)

    def sensor(self, mi, R: np.ndarray, t: np.ndarray, spp: int,
               sampler: str = "independent", crop: tuple[int, int, int, int] | None = None,
               coarse: int = 1) -> object:
        """Mitsuba's pinhole for pose (R, t): the whole render, or ``crop`` (x0, y0, x1,
        y1) of it in render pixels, or the whole at ``coarse`` times the pixel pitch."""
        C = -R.T @ t
        M = np.eye(4)
        # Mitsuba's camera looks down +z with x left and y up; OpenCV's x right, y down
        M[:3, :3] = R.T @ np.diag([-1.0, -1.0, 1.0])
        M[:3, 3] = C
        w, h = (-(-n // coarse) for n in self.size)
        fov = math.degrees(2 * math.atan(w * coarse / 2 / self.f))
        film = {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                "pixel_format": "rgb"}
        if crop is not None:
            x0, y0, x1, y1 = crop
            film |= {"crop_offset_x": x0, "crop_offset_y": y0, "crop_width": x1 - x0,
                     "crop_height": y1 - y0}
        return mi.load_dict({
            "type": "perspective", "fov": fov, "fov_axis": "x", "near_clip": 1.0,
            "far_clip": 1e5, "to_world": mi.ScalarTransform4f(M.tolist()), "film": film,
            "sampler": {"type": sampler, "sample_count": spp}})

    def region(self, R: np.ndarray, t: np.ndarray, points: np.ndarray,
               margin: int = 8) -> tuple[int, int, int, int] | None:
        """(x0, y0, x1, y1) the render pixels that see the convex hull of ``points``
        (n, 3) in the world, ``margin`` pixels around them (the photo's bilinear
        resampling reaches one render pixel out); None where a point is behind the
        camera or the region is most of the render."""
        X = np.asarray(points, float) @ np.asarray(R, float).T + np.asarray(t, float)
        if (X[:, 2] <= 1.0).any():
            return None
        u = self.f * X[:, 0] / X[:, 2] + self.size[0] / 2 - 0.5
        v = self.f * X[:, 1] / X[:, 2] + self.size[1] / 2 - 0.5
        x0, y0 = (max(0, int(math.floor(a.min())) - margin) for a in (u, v))
        x1 = min(self.size[0], int(math.ceil(u.max())) + margin + 1)
        y1 = min(self.size[1], int(math.ceil(v.max())) + margin + 1)
        if x1 <= x0 or y1 <= y0 or (x1 - x0) * (y1 - y0) > 0.6 * self.size[0] * self.size[1]:
            return None
        return x0, y0, x1, y1

    def upsample(self, coarse_img: np.ndarray, coarse: int) -> np.ndarray:
        """A render at ``coarse`` times the pixel pitch (:meth:`sensor`) resampled to the
        render's pixels (both centred on the optical axis)."""
        h, w = coarse_img.shape[:2]
        rw, rh = self.size
        A = np.array([[1 / coarse, 0.0, (0.5 - rw / 2) / coarse + w / 2 - 0.5],
                      [0.0, 1 / coarse, (0.5 - rh / 2) / coarse + h / 2 - 0.5]])
        return cv2.warpAffine(np.ascontiguousarray(coarse_img[..., :3], np.float32), A,
                              (rw, rh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)

    def photo(self, render: np.ndarray) -> np.ndarray:
        """Resample a pinhole render (rh, rw, 3) into the distorted photo (H, W, 3)."""
        src = np.ascontiguousarray(render[..., :3], np.float32)
        acc = np.zeros(self.map_x.shape[:2] + (3,), np.float32)
        for k in range(self.map_x.shape[2]):
            acc += cv2.remap(src, self.map_x[..., k], self.map_y[..., k], cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)
        return acc / self.map_x.shape[2]


#: the pitch, in render pixels, of the render outside the regions that matter: a plain
#: background that no measurement reads (a sixteenth of the samples, then smoothed)
COARSE = 4


def _render(mi, scene, cam: _Camera, R, t, spp: int, seed: int,
            sampler: str = "independent", regions_mm: list[np.ndarray] | None = None,
            ) -> np.ndarray:
    """The photo (H, W, 3) of pose (R, t). With ``regions_mm`` (a list of (n, 3) world
    points), the render pixels that see each one's hull get ``spp`` samples and the rest
    of the frame (the card or the wall around) is rendered at :data:`COARSE` times the
    pixel pitch and smoothed: most of a view's pixels and of its time."""
    crops = [cam.region(R, t, r) for r in regions_mm or []]
    if not crops or None in crops:
        img = np.array(mi.render(scene, sensor=cam.sensor(mi, R, t, spp, sampler),
                                 seed=seed, spp=spp))
        return cam.photo(img)
    # each render its own seed, far apart: Mitsuba seeds its pixels' samples from the seed
    # and their index, and nearby seeds would repeat one crop's noise in another
    seeds = np.random.SeedSequence(seed).generate_state(len(crops) + 1) % 2**31
    low = np.array(mi.render(scene, sensor=cam.sensor(mi, R, t, spp, sampler, coarse=COARSE),
                             seed=int(seeds[-1]), spp=spp))[..., :3]
    img = cam.upsample(cv2.GaussianBlur(low, (0, 0), 1.0), COARSE)
    for k, (x0, y0, x1, y1) in enumerate(crops):
        img[y0:y1, x0:x1] = np.array(mi.render(
            scene, sensor=cam.sensor(mi, R, t, spp, sampler, crop=(x0, y0, x1, y1)),
            seed=int(seeds[k]), spp=spp))[..., :3]
    return cam.photo(img)


def _write_photo(path: Path, img: np.ndarray, preset: PbrPreset) -> None:
    if preset.image_format == "jpg":
        path.parent.mkdir(parents=True, exist_ok=True)
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[..., ::-1]),
                               [cv2.IMWRITE_JPEG_QUALITY, preset.jpeg_quality])
        if not ok:
            raise OSError(f"{path}: could not encode JPEG")
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_bytes(buf.tobytes())
        tmp.replace(path)
    else:
        write_image_atomic(path, img)


def generate_pbr(
    out: str | Path,
    truth: str | Path | None = None,
    preset: str | PbrPreset = "pbr-tiny",
    seed: int = 0,
    surface_id: str | None = None,
) -> Path:
    """Render a physically based capture to ``out`` and its ground truth to ``truth``
    (default ``<out>.truth``); both replaced atomically when complete.

    Seeded: the same preset and seed give the same scene, rig and noise (Mitsuba's
    multi-threaded rendering is deterministic per seed as well).
    """
    mi = _mitsuba()
    name, preset = resolve_preset(preset, PBR_PRESETS)
    out, truth, tmp_out, tmp_truth = partial_dirs(out, truth)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    sid = surface_id or f"synth-{name}"
    w, h = preset.image_size
    K = np.array([[preset.focal_px, 0.0, w / 2 - 0.5 + preset.principal_offset[0] * w],
                  [0.0, preset.focal_px * preset.aspect,
                   h / 2 - 0.5 + preset.principal_offset[1] * h], [0.0, 0.0, 1.0]])
    cam = _Camera.build(K, preset.dist, preset.image_size, preset.render_scale)

    albedo = _albedo_texture(preset, rng)
    mats = _materials(preset, rng)
    items = _marker_layout(preset, rng)
    scene = _surface_scene(mi, preset, items, mats, albedo)

    kw = {"n": preset.views} if preset.scheme == "spiral" else {"n_side": int(
        math.ceil(math.sqrt(preset.views)))}
    dirs = sample_directions(preset.scheme, preset.max_zenith_deg, **kw)[: preset.views]
    all_dirs, is_hold, poses, view_ids, seeds = view_rig(dirs, preset, K, items, rng, seed,
                                                         preset.calib_images)
    if preset.holdout_specular:
        _specular_holdout(preset, all_dirs, is_hold, poses, K, items, seed)
    logger.info(f"synth {name}: {len(dirs)} views + {int(is_hold.sum())} held out, {w}x{h} px, "
                f"{len(mats)} material patches, {len(items)} {preset.marker_dictionary} markers, "
                f"{len(preset.lights)} light(s), Mitsuba {mi.__version__} scalar_rgb")

    regions = _regions_mm(preset, items)
    radiance = []
    for k, (R, t) in enumerate(poses):
        rad = _render(mi, scene, cam, R, t, preset.spp, int(seeds[k]) % 2**31,
                      preset.sampler)
        radiance.append(rad)
        write_rgb(tmp_truth / "radiance" / f"{view_ids[k]}.exr", rad,
                  {"view_id": view_ids[k], "units": "scene radiance (exposure = radiance * t)"})
        if is_hold[k]:
            clean = _render(mi, scene, cam, R, t, preset.clean_spp, int(seeds[k]) % 2**31 + 1,
                            preset.clean_sampler, regions)
            write_rgb(tmp_truth / "clean" / f"{view_ids[k]}.exr", clean,
                      {"view_id": view_ids[k], "spp": str(preset.clean_spp),
                       "sampler": preset.clean_sampler})
        if (k + 1) % 10 == 0 or k + 1 == len(poses):
            logger.info(f"  rendered {k + 1}/{len(poses)} views ({time.perf_counter() - t0:.0f} s)")

    # The bracket a photographer would choose: the shortest exposure keeps all but the
    # brightest 0.05 % of the surface below level ~240, then fixed steps of `stops`.
    hi = max(float(np.percentile(r.max(-1), 99.95)) for r in radiance)
    t_short = float(preset.response.inverse(240.0)) / hi
    times = [float(f"{t_short * 2.0 ** (preset.stops * k):.6g}")
             for k in range(preset.exposures)][::-1]
    views_yaml = []
    ext = preset.image_format
    for k, rad in enumerate(radiance):
        nrng = np.random.default_rng(int(seeds[k]))
        exps = []
        for e, te in enumerate(times):
            rel = f"views/{view_ids[k]}_{e}.{ext}"
            _write_photo(tmp_out / rel, _expose(rad, te, preset.response, preset, nrng), preset)
            exps.append({"file": rel, "exposure_s": te})
        views_yaml.append({"id": view_ids[k], "holdout": bool(is_hold[k]), "exposures": exps})

    sx, sy = preset.board
    sq = round(0.6 * min(preset.width_mm, preset.height_mm) / max(sx, sy), 3)
    calib = {"board": "charuco", "squares_x": sx, "squares_y": sy, "square_mm": sq,
             "marker_mm": round(0.75 * sq, 3), "dictionary": preset.board_dictionary}
    board = cv2.aruco.CharucoBoard((sx, sy), sq, calib["marker_mm"],
                                   aruco_dictionary(preset.board_dictionary))
    ppmm = 40.0 / sq  # 40 texture pixels per square
    board_img = board.generateImage((int(sx * sq * ppmm), int(sy * sq * ppmm)), marginSize=0)
    bscene = _board_scene(mi, calib, board_img)
    cposes = board_poses(rng, preset.calib_images, sx * sq, sy * sq, preset.focal_px, (w, h),
                         preset.board_max_tilt_deg)
    for k, (R, t) in enumerate(cposes):
        rad = _render(mi, bscene, cam, R, t, BOARD_SPP, int(seeds[len(all_dirs) + k]) % 2**31,
                      "multijitter")
        img = _expose(rad, 0.6 / 0.8, preset.response, preset,
                      np.random.default_rng(int(seeds[len(all_dirs) + k])))
        _write_photo(tmp_out / f"calibration/board_{k:02d}.{ext}", img, preset)
    logger.info(f"  rendered {len(cposes)} board photos ({time.perf_counter() - t0:.0f} s)")

    # the room's light as a lab measures it: a white card at the centre, lamps off / on
    extra = {"ambient": {"share": sky_share(preset)}} if preset.environment > 0 else {}
    if preset.state_lights:
        extra["lights"] = stated_lights(preset)
    write_capture_yaml(tmp_out, f"Physically based synthetic capture (Mitsuba 3; preset "
                       f"{name}, seed {seed})", sid, preset, items, calib, ext, views_yaml,
                       extra)

    np.savez_compressed(
        tmp_truth / "response.npz", levels=np.arange(256),
        exposure=np.repeat(preset.response.inverse(np.arange(256.0))[:, None], 3, 1))
    write_rig_truth(tmp_truth, view_ids, is_hold, poses, all_dirs, cposes, preset.image_size,
                    K, preset.dist)
    nx, ny = preset.patches
    (tmp_truth / "scene.json").write_text(json.dumps({
        "renderer": f"mitsuba {mi.__version__} scalar_rgb",
        "patches": [{"row": k // nx, "col": k % nx,
                     "rect_mm": [(k % nx) * preset.width_mm / nx,
                                 preset.height_mm - (k // nx + 1) * preset.height_mm / ny,
                                 (k % nx + 1) * preset.width_mm / nx,
                                 preset.height_mm - (k // nx) * preset.height_mm / ny],
                     **m} for k, m in enumerate(mats)],
        "lights": [asdict(L) for L in preset.lights], "environment": preset.environment},
        indent=1))
    np.savez_compressed(tmp_truth / "albedo.npz", albedo=albedo.astype(np.float16),
                        px_per_mm=preset.texture_px_per_mm)
    (tmp_truth / "generator.json").write_text(json.dumps(
        {"preset": name, "seed": seed, "settings": asdict(preset), "exposure_s": times,
         "radiance_p9995": hi}, indent=1))
    publish(((tmp_out, out), (tmp_truth, truth)))
    logger.info(f"synth {name}: wrote {out} and {truth} in {time.perf_counter() - t0:.1f} s")
    return out


def novel_lights(preset: str | PbrPreset) -> tuple[Light, ...]:
    """Lights a capture never had, for relighting tests: the first light moved a third
    of the way around the surface's normal (its height kept) and a smaller disc light
    added on the other side."""
    _, preset = resolve_preset(preset, PBR_PRESETS)
    first = preset.lights[0]
    x, y, z = first.position_mm
    a = 2 * math.pi / 3
    moved = replace(first, position_mm=(x * math.cos(a) - y * math.sin(a),
                                        x * math.sin(a) + y * math.cos(a), z))
    extra = Light("disc", (-0.6 * moved.position_mm[0], -0.6 * moved.position_mm[1], 0.8 * z),
                  (0.5 * max(first.size_mm), 0.0), tuple(0.6 * c for c in first.radiance))
    return moved, extra


def render_relit(truth: str | Path, lights: tuple[Light, ...] | None = None,
                 spp: int | None = None, sampler: str | None = None,
                 folder: str = "relit") -> Path:
    """Clean renders of a generated capture's held-out views under other lights
    (default :func:`novel_lights`): ``<truth>/<folder>/<view>.exr`` and
    ``<truth>/<folder>/lights.json`` (the lights, positions relative to the surface's
    centre as in ``scene.json``). The scene is rebuilt from the generator's preset and
    seed (``generator.json``), so it is the captured one but for its lights. ``spp`` and
    ``sampler`` (Mitsuba's) default to the preset's clean renders'; with the capture's
    own lights this re-renders its clean truth at another noise level."""
    mi = _mitsuba()
    truth = Path(truth)
    gen = json.loads((truth / "generator.json").read_text())
    name, preset = resolve_preset(gen["preset"], PBR_PRESETS)
    lights = lights or novel_lights(preset)
    spp, sampler = spp or preset.clean_spp, sampler or preset.clean_sampler
    rng = np.random.default_rng(gen["seed"])
    albedo = _albedo_texture(preset, rng)  # the generator's draws, in its order
    mats = _materials(preset, rng)
    items = _marker_layout(preset, rng)
    scene = _surface_scene(mi, replace(preset, lights=tuple(lights)), items, mats, albedo)
    cam_doc = yaml.safe_load((truth / "camera.yaml").read_text())
    cam = _Camera.build(np.array(cam_doc["K"]), tuple(cam_doc["dist"]),
                        tuple(cam_doc["image_size"]), preset.render_scale)
    rig = np.load(truth / "poses.npz")
    regions = _regions_mm(preset, items)
    out = truth / folder
    out.mkdir(exist_ok=True)
    for k in np.flatnonzero(rig["holdout"]):
        vid = str(rig["view_ids"][k])
        img = _render(mi, scene, cam, rig["R"][k], rig["t"][k], spp,
                      (gen["seed"] * 7919 + int(k)) % 2**31, sampler, regions)
        write_rgb(out / f"{vid}.exr", img, {"view_id": vid, "spp": str(spp), "sampler": sampler})
    (out / "lights.json").write_text(json.dumps([asdict(L) for L in lights], indent=1))
    logger.info(f"synth {name}: relit {int(rig['holdout'].sum())} held-out views under "
                f"{len(lights)} light(s) into {out}")
    return out


def render_white_card(capture: str | Path, truth: str | Path, views: int = 6,
                      seed: int = 0) -> list[str]:
    """White-card views (the flat-field, ``docs/models.md``) added to a generated
    capture: the scene rebuilt from its preset and seed with every patch a matte card of
    albedo ``CARD_ALBEDO`` under the capture's lights, photographed from ``views``
    directions up to 50 deg through the capture's response and exposure times into
    ``<capture>/radiometry/``; ``capture.yaml`` gains its ``flatfield`` section (written
    through a temporary name). Returns the card views' ids."""
    mi = _mitsuba()
    capture, truth = Path(capture), Path(truth)
    gen = json.loads((truth / "generator.json").read_text())
    name, preset = resolve_preset(gen["preset"], PBR_PRESETS)
    rng = np.random.default_rng(gen["seed"])
    albedo = _albedo_texture(preset, rng)  # the generator's draws, in its order
    mats = _materials(preset, rng)
    items = _marker_layout(preset, rng)
    scene = _surface_scene(mi, preset, items, [{"kind": "diffuse"}] * len(mats),
                           np.full_like(albedo, CARD_ALBEDO))
    cam_doc = yaml.safe_load((truth / "camera.yaml").read_text())
    K = np.array(cam_doc["K"], float)
    cam = _Camera.build(K, tuple(cam_doc["dist"]), tuple(cam_doc["image_size"]),
                        preset.render_scale)
    crng = np.random.default_rng(seed + 7919)
    dirs = sample_directions("stratified", 50.0, n_side=max(2, math.ceil(math.sqrt(views))),
                             seed=seed + 3)[:views]
    times = gen["exposure_s"]
    entries = []
    for k, d in enumerate(dirs):
        R, t = view_pose(d, preset, K, items, crng)
        rad = _render(mi, scene, cam, R, t, preset.spp, int(crng.integers(2**31)),
                      preset.sampler)
        nrng = np.random.default_rng(int(crng.integers(2**31)))
        vid, exps = f"card{k:02d}", []
        for e, te in enumerate(times):
            rel = f"radiometry/{vid}_{e}.{preset.image_format}"
            _write_photo(capture / rel, _expose(rad, te, preset.response, preset, nrng),
                         preset)
            exps.append({"file": rel, "exposure_s": te})
        entries.append({"id": vid, "exposures": exps})
    path = capture / "capture.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["flatfield"] = {"reflectance": CARD_ALBEDO, "views": entries}
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(f"# {name}, seed {gen['seed']}, with {views} white-card views\n"
                   + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100))
    tmp.replace(path)
    logger.info(f"synth {name}: {views} white-card views into {capture / 'radiometry'}")
    return [e["id"] for e in entries]


def read_truth_radiance(truth_dir: str | Path, view_id: str, clean: bool = False) -> np.ndarray:
    """The radiance (H, W, 3) a generated photo was exposed from (``clean``: the
    high-sample render of a held-out view)."""
    return read_rgb(Path(truth_dir) / ("clean" if clean else "radiance") / f"{view_id}.exr")


def normal_reflectance(truth_dir: str | Path) -> list[dict[str, Any]]:
    """Per patch of a generated capture (``scene.json``'s order), its reflectance lit
    and seen along the normal, from Mitsuba's own BSDFs: what a relightable map's
    albedo should come out as. ``specular`` (R, G, B): a conductor's Fresnel
    reflectance (glTF's base colour of a metal); ``diffuse``: the factor on the albedo
    texture of the diffuse light (1 on a matte patch; a rough plastic's coating lets
    less in and out); None where a patch has neither (``principled``, a mix)."""
    mi = _mitsuba()
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(0, 0, 1)
    out = []
    for p in json.loads((Path(truth_dir) / "scene.json").read_text())["patches"]:
        r: dict[str, Any] = {"specular": None, "diffuse": None}
        if p["kind"] == "roughconductor":
            bsdf = mi.load_dict({"type": "conductor", "material": p["material"]})
            _, w = bsdf.sample(mi.BSDFContext(), si, 0.5, mi.Point2f(0.5, 0.5))
            r["specular"] = [float(w[c]) for c in range(3)]
        elif p["kind"] == "roughplastic":
            bsdf = mi.load_dict({"type": "roughplastic", "distribution": "ggx",
                                 "alpha": p["alpha"], "int_ior": p["int_ior"],
                                 "diffuse_reflectance": {"type": "rgb", "value": [1, 1, 1]},
                                 "specular_reflectance": 0.0})
            r["diffuse"] = math.pi * float(bsdf.eval(mi.BSDFContext(), si,
                                                     mi.Vector3f(0, 0, 1))[0])
        elif p["kind"] == "diffuse":
            r["diffuse"] = 1.0
        out.append(r)
    return out


def patch_labels(truth_dir: str | Path, S: int, T: int, width_mm: float,
                 height_mm: float) -> np.ndarray:
    """(T, S) int: the material patch under each texel centre (docs/reference/conventions.md texel
    mapping), from ``scene.json``."""
    patches = json.loads((Path(truth_dir) / "scene.json").read_text())["patches"]
    ctr = texel_centres(S, T, width_mm, height_mm)
    lab = np.full((T, S), -1, int)
    for k, p in enumerate(patches):
        x0, y0, x1, y1 = p["rect_mm"]
        lab[(ctr[..., 0] >= x0) & (ctr[..., 0] < x1) & (ctr[..., 1] >= y0)
            & (ctr[..., 1] < y1)] = k
    return lab
