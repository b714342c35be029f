"""The synthetic test set-ups of 004 (ch. 11.3, 12.5, 13), as observation arrays.

004's basic scene (fig. 11.5): a 1000 x 1000 surface sampled in 16 x 16 points, normal
+z, one white point light at [1500, 1500, 2000] relative to the surface centre, Phong
materials, cameras on a hemisphere around the centre (icosahedron scheme). Here the
surface frame of docs/reference/conventions.md is used (origin at the bottom-left corner), and the
radiance of each texel comes from :func:`parammap.synth.scene.true_radiance`, i.e. the
same physics as the rendered captures, evaluated at the texel centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import texel_centres, unit
from .sampling import icosahedron
from .scene import DIFFUSE, PHONG, Scene, mh_truth, true_radiance

__all__ = ["Case", "patches_case", "phong_case"]

SIZE_MM = 1000.0
CENTRE = np.array([500.0, 500.0, 0.0])


@dataclass
class Case:
    """Observations of every texel: radiance (T, S, N, 3), direction (T, S, N, 3),
    valid (T, S, N), and the true MH parameters (T, S, 4 + 6L) with L the lights."""

    radiance: np.ndarray
    direction: np.ndarray
    valid: np.ndarray
    truth: np.ndarray
    scene: Scene


def phong_case(
    colour=(200, 15, 15),
    ks: float = 1.0,
    m: float = 30.0,
    lights=((1500.0, 1500.0, 2000.0),),
    intensities=(1.0,),
    level: int = 3,
    max_zenith_deg: float = 88.0,
    texels: int = 16,
    camera_distance_mm: float = 3000.0,
    noise: float = 0.0,
    seed: int = 0,
    directions: np.ndarray | None = None,
) -> Case:
    """A Phong-material surface under point lights, seen from icosahedron views.

    Parameters
    ----------
    colour : 8-bit surface colour (004 uses [200, 15, 15]); Kd = colour / 255.
    ks, m : specular amplitude and Phong shininess.
    lights : positions relative to the surface centre (mm), 004's convention.
    level : icosahedron subdivision level (3: 305 views up to 88 degrees; 004: 289).
    noise : relative Gaussian noise on the radiance (the HDR error of a capture).
    directions : camera directions (N, 3) instead of the icosahedron.
    """
    rng = np.random.default_rng(seed)
    kd = np.broadcast_to(np.asarray(colour, float) / 255.0, (texels, texels, 3)).copy()
    scene = Scene(
        SIZE_MM, SIZE_MM, np.full((texels, texels), PHONG), kd,
        np.full((texels, texels, 3), float(ks)), np.full((texels, texels), float(m)),
        np.asarray(lights, float) + CENTRE, np.asarray(intensities, float), 0.0)
    cams = CENTRE + camera_distance_mm * (
        icosahedron(level, max_zenith_deg) if directions is None else np.asarray(directions))
    return _observe(scene, cams, noise, rng)


def _observe(scene: Scene, cams: np.ndarray, noise: float, rng: np.random.Generator) -> Case:
    """Radiance of every texel of ``scene`` seen from camera positions ``cams`` (N, 3)."""
    T, S = scene.kind.shape
    ctr = texel_centres(S, T, scene.width_mm, scene.height_mm)
    d = unit(cams[None, None] - ctr[:, :, None, :])
    N = len(cams)
    rows = np.repeat(np.arange(T), S * N)
    cols = np.tile(np.repeat(np.arange(S), N), T)
    L = true_radiance(scene, rows, cols, d.reshape(-1, 3)).reshape(T, S, N, 3)
    if noise:
        L = L * (1 + noise * rng.standard_normal(L.shape))
    truth, _ = mh_truth(scene)
    return Case(L.astype(np.float32), d.astype(np.float32), np.ones((T, S, N), bool),
                truth, scene)


def patches_case(
    materials=((1.0, 1.0, 1.0, 12.0), (1.2, 0.9, 0.5, 60.0), (0.8, 0.8, 0.8, 300.0)),
    texels: int = 12,
    level: int = 2,
    max_zenith_deg: float = 75.0,
    noise: float = 0.0,
    seed: int = 0,
) -> tuple[Case, np.ndarray]:
    """Vertical bands of Phong materials (Ks.R, Ks.G, Ks.B, m each) and one diffuse
    band, over a printed albedo (Kd varies texel to texel), one point light: a test of
    basis materials.

    Returns
    -------
    the case, and (T, S) int: the material of each texel (0 the diffuse band, j + 1
    ``materials[j]``).
    """
    rng = np.random.default_rng(seed)
    T = S = texels
    band = np.minimum(np.arange(S) * (len(materials) + 1) // S, len(materials))
    label = np.broadcast_to(band, (T, S)).copy()
    kind = np.where(label == 0, DIFFUSE, PHONG)
    ks = np.zeros((T, S, 3))
    m = np.ones((T, S))
    for j, (r, g, b, mj) in enumerate(materials):
        ks[label == j + 1] = (r, g, b)
        m[label == j + 1] = mj
    kd = rng.uniform(0.05, 0.8, (T, S, 3))  # the print: no two texels alike
    scene = Scene(SIZE_MM, SIZE_MM, kind, kd, ks, m,
                  np.array([[1500.0, 1500.0, 2000.0]]) + CENTRE, np.ones(1), 0.0)
    cams = CENTRE + 3000.0 * icosahedron(level, max_zenith_deg)
    return _observe(scene, cams, noise, rng), label
