"""What the experiments share: the published conditions, the published figures, and
the helpers that fit, tabulate and plot a case."""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import default
from ..conventions import LUMINANCE, FitArray
from ..models.mh import (
    K_MAX_AUTO,
    MhFitConfig,
    fit_mh_tile,
    mh_eval,
)
from ..plots import plot_lobes
from ..synth.cases import Case, phong_case

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Conditions:
    """The published set-up, with a value for what 004 leaves unstated (``why``)."""

    colour: tuple[int, int, int] = (200, 15, 15)
    light: tuple[float, float, float] = (1500.0, 1500.0, 2000.0)
    texels: int = 16
    # 004: "289 directions following the icosahedron sampling scheme"; the level-3
    # subdivision has 289 vertices up to 85 deg (305 up to the ring at 85.35 deg).
    views_level: int = 3
    views_max_zenith_deg: float = 85.0
    ks: float = 1.0
    m: float = 30.0
    camera_distance_mm: float = 3000.0
    area_pitch_mm: float = 150.0
    second_light_intensity: float = 0.8
    why: dict[str, str] = field(default_factory=lambda: {
        "ks, m": "unstated; a white specular of 255 levels at its peak and shininess 30, "
                 "a moderately glossy 3ds Max Phong material",
        "diffuse level": "the surface colour is the diffuse level under one light; "
                         "lights add (with two lights red exceeds 255 everywhere, which "
                         "is why 004's red residual is 0.00 in ch. 11.3.2)",
        "camera distance": "unstated; 3000 mm from the centre (views see the surface "
                           "from nearly one direction per view)",
        "area light": "'8 point light sources at the same height around' the first: a "
                      "3 x 3 grid, 150 mm pitch, each 1/9 of the intensity",
        "second light": "'slightly lower intensity': 0.8",
        "texel [8, 8]": "004's map position (s, t) = (8, 8), t upwards: our row 7, col 8",
    })


CONDITIONS = Conditions()


#: 004's published figures (mean percentage residual per channel, R G B).
PUBLISHED = {
    "point light [8, 8]": (0.94, 2.34, 2.34),
    "point light [14, 14]": (0.89, 2.27, 2.27),
    "area light [8, 8]": (0.69, 4.30, 4.30),
    "second light at [450, 450]": (0.00, 9.89, 9.89),
    "second light at [-450, -450]": (0.00, 20.58, 20.58),
    "second light at [-1500, -1500]": (0.00, 22.07, 22.07),
    "sh-lsop-100": (11.61, 16.03, 16.03),
    "sh-zh-100": (7.67, 16.72, 16.72),
}


def quantise_8bit(radiance: np.ndarray) -> np.ndarray:
    """Radiance as 004's renders stored it: 8-bit levels, clipped at 255, back in
    radiance units (level / 255)."""
    return np.clip(np.round(np.asarray(radiance) * 255.0), 0, 255) / 255.0


def _st(s: int, t: int, c: Conditions = CONDITIONS) -> tuple[int, int]:
    """(row, col) of 004's map position (s, t) with t upwards."""
    return c.texels - 1 - t, s


def published_case(lights, intensities, c: Conditions = CONDITIONS) -> Case:
    """004's scene with the given lights (positions from the surface centre), observed
    from the published 289 views and quantised to 8 bits."""
    total = float(np.sum(intensities))
    case = phong_case(colour=tuple(np.asarray(c.colour) * total), ks=c.ks, m=c.m,
                      lights=lights, intensities=intensities, level=c.views_level,
                      max_zenith_deg=c.views_max_zenith_deg, texels=c.texels,
                      camera_distance_mm=c.camera_distance_mm)
    case.radiance = quantise_8bit(case.radiance).astype(np.float32)
    return case


def _fit_mh(case: Case, K, init: str, polish: str = default("fit.mh.polish")) -> dict[str,
                                                                                      np.ndarray]:
    return fit_mh_tile(case.radiance, case.direction, case.valid, K,
                       MhFitConfig(init=init, polish=polish),
                       K_max=K_MAX_AUTO if K == "auto" else K)


def _row(experiment: str, case: str, published, ours_pub, ours_def, note: str = ""):
    def f(v) -> str:
        return "" if v is None else " ".join(f"{x:.2f}" for x in np.ravel(v))

    return {"experiment": experiment, "case": case, "published": f(published),
            "ours_published_method": f(ours_pub), "ours_defaults": f(ours_def),
            "note": note}


def _lobe_figure(out_dir: str | Path | None, name: str, entries: list[dict],
                 title: str) -> None:
    """Measured and fitted radiance over the hemisphere with percentage residuals, as
    004's figures draw them (``<out_dir>/<name>.png``)."""
    if out_dir is not None and entries:

        plot_lobes(entries, Path(out_dir) / f"{name}.png", title)


def _entry(label: str, case: Case, texel: tuple[int, int], fitted: np.ndarray) -> dict:
    r, col = texel
    return {"label": label, "direction": case.direction[r, col].astype(float),
            "measured": case.radiance[r, col].astype(float), "fitted": fitted}


def _mh_fitted(o: dict, case: Case, texel: tuple[int, int]) -> np.ndarray:

    r, col = texel
    return mh_eval(o[FitArray.PARAMS][r, col].astype(float), case.direction[r, col].astype(float))


def _luminance(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, float) @ LUMINANCE


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
    return path
