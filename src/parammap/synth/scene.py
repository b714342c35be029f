"""The synthetic surface: per-texel materials, lights, and its true radiance.

Appearance is constant within a texel (the map resolution of the preset), so the
true radiance of texel ``[i, j]`` seen from direction ``v`` is well defined:
:func:`true_radiance`. Lights are fixed relative to the surface (004 fig. 16.2).

Material kinds (one per patch; ``KIND_NAMES``):

- ``diffuse``: view independent.
- ``phong``: exactly the MH model (docs/reference/conventions.md) with one lobe per light, the lobe
  direction being the mirror direction of the light at the texel centre.
- ``blinn``: Blinn-Phong half-vector lobe (not an MH lobe).
- ``area``: Phong lobes summed over many points of a disc light (not one MH lobe).
- ``ggx``: microfacet lobe with GGX distribution and Smith shadowing.

Radiance is relative (unitless); kd already includes the incident irradiance.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..conventions import MH_KD, MH_M, mh_dir, mh_ks, mh_size
from ..geometry import texel_centres, unit

__all__ = [
    "KIND_NAMES",
    "Scene",
    "build_scene",
    "load_scene",
    "mh_truth",
    "true_radiance",
]

KIND_NAMES = ("diffuse", "phong", "blinn", "area", "ggx")
DIFFUSE, PHONG, BLINN, AREA, GGX = range(5)

# (kind, albedo RGB, specular RGB, shininess or GGX alpha) per patch, in reading order.
PATCHES = [
    (DIFFUSE, (0.80, 0.75, 0.62), (0.0, 0.0, 0.0), 1.0),
    (PHONG, (0.55, 0.12, 0.10), (1.2, 1.2, 1.2), 30.0),
    (PHONG, (0.20, 0.35, 0.60), (0.6, 0.6, 0.6), 6.0),
    (PHONG, (0.15, 0.45, 0.20), (1.5, 1.5, 1.5), 150.0),
    (PHONG, (0.08, 0.08, 0.09), (3.0, 2.6, 1.8), 900.0),
    (BLINN, (0.60, 0.50, 0.20), (1.0, 1.0, 1.0), 80.0),
    (AREA, (0.30, 0.30, 0.32), (2.0, 2.0, 2.0), 200.0),
    (GGX, (0.10, 0.10, 0.12), (0.9, 0.75, 0.5), 0.25),
    (DIFFUSE, (0.35, 0.30, 0.55), (0.0, 0.0, 0.0), 1.0),
]


@dataclass
class Scene:
    """Ground-truth appearance of the surface.

    Attributes
    ----------
    width_mm, height_mm : size of the sampled region.
    kind : (T, S) int, material kind per texel.
    kd : (T, S, 3) view-independent radiance.
    ks : (T, S, 3) specular amplitude (per unit light intensity).
    m : (T, S) Phong/Blinn shininess, or GGX roughness alpha.
    light_pos : (L, 3) light positions (mm, surface frame).
    light_int : (L,) light intensities.
    area_radius_mm, area_points : the disc light around light 0 for ``area`` texels.
    """

    width_mm: float
    height_mm: float
    kind: np.ndarray
    kd: np.ndarray
    ks: np.ndarray
    m: np.ndarray
    light_pos: np.ndarray
    light_int: np.ndarray
    area_radius_mm: float
    area_points: int = 24

    @property
    def shape(self) -> tuple[int, int]:
        return self.kind.shape

    def save(self, path: str | Path) -> None:
        np.savez_compressed(
            path, width_mm=self.width_mm, height_mm=self.height_mm, kind=self.kind,
            kd=self.kd, ks=self.ks, m=self.m, light_pos=self.light_pos,
            light_int=self.light_int, area_radius_mm=self.area_radius_mm,
            area_points=self.area_points, kind_names=np.array(KIND_NAMES))

    def area_light_points(self) -> np.ndarray:
        """Points of the disc light, (P, 3), facing the surface centre."""
        c = self.light_pos[0]
        n = unit(c - np.array([self.width_mm / 2, self.height_mm / 2, 0.0]))
        a = unit(np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0]))
        b = np.cross(n, a)
        k = np.arange(self.area_points)
        r = self.area_radius_mm * np.sqrt((k + 0.5) / self.area_points)
        ang = k * np.pi * (3 - np.sqrt(5))  # golden-angle disc
        return c + r[:, None] * (np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b)


def load_scene(path: str | Path) -> Scene:
    z = np.load(path)
    return Scene(float(z["width_mm"]), float(z["height_mm"]), z["kind"], z["kd"], z["ks"],
                 z["m"], z["light_pos"], z["light_int"], float(z["area_radius_mm"]),
                 int(z["area_points"]))


def _print_texture(S: int, T: int, rng: np.random.Generator) -> np.ndarray:
    """Text-like ink coverage in [0, 1] at texel resolution, (T, S)."""
    scale = 8
    canvas = np.zeros((T * scale, S * scale), np.uint8)
    words = ["parammap", "gloss", "foil", "MH", "SH", "lsop", "texel", "zarr", "view"]
    line_h = max(int(0.11 * T * scale), 10)
    y = line_h
    while y < T * scale:
        x = int(rng.integers(0, 2 * scale))
        while x < S * scale:
            w = str(rng.choice(words))
            cv2.putText(canvas, w, (x, y), cv2.FONT_HERSHEY_SIMPLEX, line_h / 30.0, 255,
                        max(1, line_h // 10), cv2.LINE_AA)
            x += int(len(w) * line_h * 0.6 + rng.integers(scale, 4 * scale))
        y += int(line_h * 1.6)
    ink = cv2.resize(canvas.astype(np.float32) / 255.0, (S, T), interpolation=cv2.INTER_AREA)
    return np.clip(ink * 1.5, 0, 1)


def build_scene(
    S: int, T: int, width_mm: float, height_mm: float, seed: int = 0, grid: int = 3
) -> Scene:
    """Lay out ``grid x grid`` material patches with printed text over the region."""
    rng = np.random.default_rng(seed)
    size = max(width_mm, height_mm)
    centre = np.array([width_mm / 2, height_mm / 2, 0.0])
    # Light 0 as in 004 ch. 11.3 ([1500, 1500, 2000] for a 1000-wide surface); light 1
    # far from it so the two highlights are well apart (004 ch. 11.3.2).
    light_pos = centre + size * np.array([[1.5, 1.5, 2.0], [-1.6, -0.4, 1.6]])
    light_int = np.array([1.0, 0.5])
    rows = np.minimum(np.arange(T) * grid // T, grid - 1)
    cols = np.minimum(np.arange(S) * grid // S, grid - 1)
    patch = rows[:, None] * grid + cols[None, :]
    patch = patch % len(PATCHES)
    kind = np.array([p[0] for p in PATCHES])[patch]
    albedo = np.array([p[1] for p in PATCHES])[patch]
    ks = np.array([p[2] for p in PATCHES])[patch]
    m = np.array([p[3] for p in PATCHES], float)[patch]
    ink = _print_texture(S, T, rng)
    albedo = albedo * (1 - 0.85 * ink[..., None])
    # Irradiance on the (flat, lambertian) base layer at each texel centre.
    ctr = texel_centres(S, T, width_mm, height_mm)
    irr = np.zeros((T, S))
    for p, inten in zip(light_pos, light_int, strict=True):
        irr += inten * np.clip(unit(p - ctr)[..., 2], 0, None)
    kd = albedo * irr[..., None]
    return Scene(width_mm, height_mm, kind.astype(np.int8), kd.astype(np.float64),
                 ks.astype(np.float64), m, light_pos, light_int,
                 area_radius_mm=0.12 * size)


def _reflect(l_dir: np.ndarray) -> np.ndarray:
    return l_dir * np.array([-1.0, -1.0, 1.0])


def _ggx(ndoth, ndotv, ndotl, alpha):
    a2 = alpha**2
    d = a2 / (np.pi * (ndoth**2 * (a2 - 1) + 1) ** 2)

    def g1(x):
        return 2 * x / (x + np.sqrt(a2 + (1 - a2) * x**2))

    # Normalised so the peak at normal incidence is about one.
    return d * g1(ndotv) * g1(ndotl) / (4 * np.maximum(ndotv, 1e-6)) * (4 * np.pi * a2)


def true_radiance(
    scene: Scene, rows: np.ndarray, cols: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """True radiance of texels ``[rows, cols]`` seen from unit directions ``v``.

    Parameters
    ----------
    rows, cols : (N,) int texel indices.
    v : (N, 3) unit view directions, surface frame (toward the camera).

    Returns
    -------
    (N, 3) float64 relative radiance.
    """
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    v = np.asarray(v, float)
    T, S = scene.shape
    out = scene.kd[rows, cols].copy()
    kind = scene.kind[rows, cols]
    ks = scene.ks[rows, cols]
    m = scene.m[rows, cols]
    ctr = np.stack([(cols + 0.5) * scene.width_mm / S,
                    scene.height_mm - (rows + 0.5) * scene.height_mm / T,
                    np.zeros(rows.shape)], axis=-1)
    vz = np.clip(v[:, 2], 0, None)
    for lp, inten in zip(scene.light_pos, scene.light_int, strict=True):
        l_dir = unit(lp - ctr)
        sel = kind == PHONG
        if sel.any():
            c = np.clip(np.sum(_reflect(l_dir[sel]) * v[sel], -1), 0, None)
            out[sel] += inten * ks[sel] * (c ** m[sel])[:, None]
        sel = kind == BLINN
        if sel.any():
            h = unit(l_dir[sel] + v[sel])
            out[sel] += inten * ks[sel] * (np.clip(h[:, 2], 0, None) ** m[sel])[:, None]
        sel = kind == GGX
        if sel.any():
            h = unit(l_dir[sel] + v[sel])
            f = _ggx(np.clip(h[:, 2], 0, 1), vz[sel], np.clip(l_dir[sel, 2], 0, 1), m[sel])
            out[sel] += inten * ks[sel] * f[:, None]
    sel = kind == AREA
    if sel.any():
        pts = scene.area_light_points()
        acc = np.zeros(sel.sum())
        for p in pts:
            c = np.clip(np.sum(_reflect(unit(p - ctr[sel])) * v[sel], -1), 0, None)
            acc += c ** m[sel]
        out[sel] += scene.light_int[0] * ks[sel] * (acc / len(pts))[:, None]
    return out


def mh_truth(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """True MH parameters (docs/reference/conventions.md order, K = number of lights) of the
    ``phong`` texels.

    Returns
    -------
    params : (T, S, 4 + 6K) float64, NaN where the texel is not exactly MH.
    mask : (T, S) bool, True on exact-MH texels.
    """
    T, S = scene.shape
    ctr = texel_centres(S, T, scene.width_mm, scene.height_mm)
    L = len(scene.light_pos)
    p = np.full((T, S, mh_size(L)), np.nan)
    mask = scene.kind == PHONG
    p[..., MH_KD] = scene.kd
    p[..., MH_M] = scene.m
    for k, (lp, inten) in enumerate(zip(scene.light_pos, scene.light_int, strict=True)):
        p[..., mh_ks(k)] = inten * scene.ks
        p[..., mh_dir(k)] = _reflect(unit(lp - ctr))
    p[~mask] = np.nan
    return p, mask
