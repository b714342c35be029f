"""A self-contained WebGL2 viewer page for fitted parameter maps.

``write_viewer`` writes ``index.html`` (the shaders and controls, from this package)
and ``data.js`` beside it: surface size, camera intrinsics, the pose of every captured
and held-out view, and each model's parameter map. ``data.js`` is a plain script (not
fetched), so the page opens from the file system with no server and works offline.

Parameter maps travel as base64 float32, regrouped in RGBA layers of a 2-D texture
array (texel row 0 = texture row 0):

- MH: layer 0 = (Kd.R, Kd.G, Kd.B, m), then per lobe (Ks.R, Ks.G, Ks.B, 0) and
  (d.X, d.Y, d.Z, 0);
- SH: layer i = (sh.R.i, sh.G.i, sh.B.i, 0) for coefficient i (conventions.md basis);
- diffuse: layer 0 = (Kd.R, Kd.G, Kd.B, 0).

The fragment shader casts each pixel's ray exactly as :func:`parammap.render.render`
does (OpenCV intrinsics and distortion, bilinear texel lookup, the model evaluated in the
pixel's own view direction), so a snapped view matches the Python renderer.
"""

from __future__ import annotations

import base64
import json
import math
import shutil
from pathlib import Path

import numpy as np

from ..calibration import Intrinsics
from ..errors import InputError
from ..params import ParamMap

__all__ = ["viewer_layers", "write_viewer"]

TEMPLATE = Path(__file__).with_name("index.html")


def viewer_layers(pm: ParamMap) -> tuple[np.ndarray, dict]:
    """(L, T, S, 4) float32 texture layers of a map and its model description."""
    T, S, P = pm.params.shape
    p = np.nan_to_num(pm.params.astype(np.float32))
    if pm.model == "mh":
        K = (P - 4) // 6
        layers = [p[..., 0:4]]
        for k in range(K):
            z = np.zeros((T, S, 1), np.float32)
            layers += [np.concatenate([p[..., 4 + 6 * k: 7 + 6 * k], z], -1),
                       np.concatenate([p[..., 7 + 6 * k: 10 + 6 * k], z], -1)]
        info = {"model": "mh", "lobes": K}
    elif pm.model == "sh":
        nc = P // 3
        n = int(round(math.sqrt(nc)))
        if n > 10:
            raise InputError("the viewer evaluates SH up to 10 bands (100 coefficients)")
        c = p.reshape(T, S, 3, nc).transpose(3, 0, 1, 2)
        layers = list(np.concatenate([c, np.zeros((nc, T, S, 1), np.float32)], -1))
        info = {"model": "sh", "bands": n}
    elif pm.model == "diffuse":
        layers = [np.concatenate([p[..., 0:3], np.zeros((T, S, 1), np.float32)], -1)]
        info = {"model": "diffuse"}
    else:
        raise InputError(f"unknown model {pm.model!r}")
    return np.stack(layers).astype("<f4"), info


def write_viewer(out_dir: str | Path, surface_id: str, maps: dict[str, ParamMap],
                 intr: Intrinsics, views: list[dict], gamma: float) -> Path:
    """Write ``index.html`` and ``data.js`` into ``out_dir``.

    Parameters
    ----------
    maps : model name -> parameter map (all of one surface).
    views : dicts with ``id``, ``holdout``, ``R`` (3x3), ``t`` (3,) for every posed view.
    gamma : initial tone-mapping gamma.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    any_map = next(iter(maps.values()))
    models = []
    for name, pm in maps.items():
        layers, info = viewer_layers(pm)
        models.append({"name": name, "S": pm.shape[1], "T": pm.shape[0],
                       "nlayers": len(layers),
                       "data": base64.b64encode(layers.tobytes()).decode("ascii"), **info})
    data = {"surface": {"id": surface_id, "width_mm": any_map.width_mm,
                        "height_mm": any_map.height_mm},
            "camera": {"K": np.asarray(intr.K).tolist(), "dist": np.asarray(intr.dist).tolist(),
                       "image_size": list(intr.image_size)},
            "views": [{"id": v["id"], "holdout": bool(v["holdout"]),
                       "R": np.asarray(v["R"]).tolist(), "t": np.asarray(v["t"]).tolist()}
                      for v in views],
            "gamma": gamma, "models": models}
    tmp = out_dir / ".data.js.tmp"
    tmp.write_text("window.PARAMMAP_DATA = " + json.dumps(data) + ";\n")
    tmp.replace(out_dir / "data.js")
    shutil.copyfile(TEMPLATE, out_dir / "index.html")
    return out_dir / "index.html"
