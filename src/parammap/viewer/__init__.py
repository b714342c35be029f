"""A self-contained WebGL2 viewer page for fitted parameter maps.

``write_viewer`` writes ``index.html`` (the shaders and controls, from this package),
``data.js`` (surface size, camera intrinsics, the pose of every captured and held-out
view, and the manifest of the models), ``manifest.json`` (the same manifest), one
``payload-<model>.js`` per model (maps above 1024 texels a side: one
``payload-<model>-<i>.js`` per tile of 1024 x 1024, and mip levels down to one tile),
which the page loads when the model is first shown, and ``inspect.js``
(:mod:`parammap.viewer.inspect`), loaded at the first click on a texel.
All are plain scripts (not fetched), so the page opens from the file system with no
server and works offline.

A payload holds the model's texture layers quantised to 8 bits per plane, filtered and
deflated (:mod:`parammap.viewer.compact`: 7-9 bytes per texel for MH-2, against 80 as
float32), in a UTF-16 script that carries 15 bits per code unit
(:func:`payload_script`: 7 % over the binary size, where base64 adds 33 %); the page
inflates them into RGBA layers of a 2-D texture array (texel row 0
= texture row 0), 8-bit for MH (dequantised in the shader), float for SH and diffuse:

- MH: layer 0 = (Kd.R, Kd.G, Kd.B, m), then per lobe k (Ks.R, Ks.G, Ks.B, 0) at layer
  ``1 + 2k`` and (d.X, d.Y, d.Z, 0) at ``2 + 2k``;
- SH: layer i = (sh.R.i, sh.G.i, sh.B.i, 0) for coefficient i (docs/reference/conventions.md basis);
- svbrdf: layer 0 = (Kd.R, Kd.G, Kd.B, alpha), layer 1 = (Ks.R, Ks.G, Ks.B, coat);
- diffuse: layer 0 = (Kd.R, Kd.G, Kd.B, 0).

A map in tiles (other than SH and a best map's choices) is streamed: the page loads its
coarsest mip level (one tile) and shows it, then, frame by frame, the tiles on screen
of the level whose texels are nearest the canvas's pixels (never coarser than the
"map resolution" control asks), and draws from the finest level whose tiles on screen
have all arrived. An SH map and a best map's candidates are loaded whole.

The fragment shader casts each pixel's ray exactly as :func:`parammap.render.render`
does (OpenCV intrinsics and distortion, bilinear texel lookup, the model evaluated in the
pixel's own view direction), so a snapped view matches the Python renderer.

Nothing the Python side defines is re-derived in the page: the shader's constants (SH
normalisation K_l^m and band limit, the MH texture layout) are generated here from
:mod:`parammap.conventions` (:func:`glsl_constants`, spliced into the shader), and the
undistortion of every pixel comes from :func:`parammap.geometry.undistort_normalized`
on a grid over the image (:func:`undistortion_grid`), interpolated bilinearly.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..conventions import sh_norms
from ..geometry import Intrinsics, undistort_normalized
from ..models.svbrdf import (
    ALPHA_RANGE,
    COAT_IOR,
    REFERENCE_MM,
    coat_sky_transmittance,
    ggx_albedo_table,
)
from ..stores.camera import load_intrinsics, read_poses
from ..stores.capture import Capture
from ..stores.metrics import read_metrics
from ..stores.observation import open_observation_map
from ..stores.params import ParamMap, ParamMapFiles, read_param_map
from ..stores.paths import Processed
from .compact import FLOAT_LAYER_BUDGET_MB, TILE, encode_map, quantisation_error
from .inspect import inspector_payload
from .layers import MH_LAYERS_PER_LOBE, MH_MAX_LOBES, SH_MAX_BANDS, SV_MAX_LIGHTS, layer_info

__all__ = ["glsl_constants", "layer_info", "payload_script", "read_payload_script",
           "undistortion_grid", "write_surface_viewer", "write_viewer"]

UNDISTORT_STEP_PX = 16  # spacing of the undistortion grid (the distortion is smooth)


# Payload scripts are UTF-16LE (a byte-order mark tells the browser so, from the file
# system too) and carry 15 bits per code unit in one string literal, as the code units
# TEXT_BASE ... TEXT_BASE + 2^15 - 1: none is a quote, a backslash, a line terminator or
# a surrogate. 16 bits on disk for 15 of payload, where base64 takes 32 for 24.
TEXT_BASE = 0x2100
TEXT_BITS = 15


def payload_script(target: str, payload: bytes) -> bytes:
    """The bytes of a script that assigns ``[len(payload), text]`` to the JavaScript
    expression ``target``, ``text`` holding ``payload`` 15 bits per UTF-16 code unit
    (the page's ``textBytes`` decodes it)."""
    data = np.frombuffer(payload, np.uint8)
    body = []
    # 15 bytes are 8 code units exactly: chunks of whole groups keep memory flat
    for i in range(0, len(data), 15 << 16):
        bits = np.unpackbits(data[i:i + (15 << 16)])
        bits = np.r_[bits, np.zeros(-len(bits) % TEXT_BITS, np.uint8)].reshape(-1, TEXT_BITS)
        # a leading zero bit makes each 15-bit group a big-endian 16-bit integer
        units = np.packbits(np.c_[np.zeros(len(bits), np.uint8), bits], axis=1).view(">u2")
        body.append((units.ravel() + TEXT_BASE).astype("<u2").tobytes())
    head = f'{target} = [{len(payload)}, "'.encode("utf-16-le")
    return b"\xff\xfe" + head + b"".join(body) + '"];\n'.encode("utf-16-le")


def read_payload_script(data: bytes) -> bytes:
    """The payload of a :func:`payload_script` (what the page decodes)."""
    text = data.decode("utf-16")
    head = text.index("= [") + 3
    n = int(text[head:text.index(",", head)])
    body = text[text.index('"', head) + 1:text.rindex('"')]
    units = np.frombuffer(body.encode("utf-16-le"), "<u2").astype(np.uint32) - TEXT_BASE
    bits = ((units[:, None] >> np.arange(TEXT_BITS - 1, -1, -1)) & 1).astype(np.uint8)
    return np.packbits(bits.ravel())[:n].tobytes()


def glsl_constants() -> str:
    """GLSL ES 3.0 declarations of the conventions the fragment shader uses."""
    K = sh_norms(SH_MAX_BANDS)
    mu, la, E = ggx_albedo_table()
    alb = ", ".join(f"{x:.7e}" for x in E.ravel())  # a float literal even where 1
    klm = ", ".join(f"{K[l, m]:.9g}" if m <= l else "0.0"
                    for l in range(SH_MAX_BANDS) for m in range(SH_MAX_BANDS))
    return "\n".join([
        f"const int SH_MAX_BANDS = {SH_MAX_BANDS};",
        f"const float KLM[{SH_MAX_BANDS ** 2}] = float[{SH_MAX_BANDS ** 2}]({klm});",
        f"const int MH_MAX_LOBES = {MH_MAX_LOBES};",
        f"const int MH_LAYERS_PER_LOBE = {MH_LAYERS_PER_LOBE};",
        f"const int SV_MAX_LIGHTS = {SV_MAX_LIGHTS};",
        f"const float SV_ALPHA_MIN = {ALPHA_RANGE[0]!r};",
        f"const float SV_REFERENCE_MM = {REFERENCE_MM!r};",
        f"const float SV_COAT_IOR = {COAT_IOR!r};",
        f"const float SV_COAT_SKY = {coat_sky_transmittance()!r};",
        f"const int SV_ALB_NMU = {E.shape[0]}; const int SV_ALB_NA = {E.shape[1]};",
        f"const float SV_ALB_MU0 = {float(mu[0])!r}; "
        f"const float SV_ALB_DMU = {float(mu[1] - mu[0])!r};",
        f"const float SV_ALB_LA0 = {float(la[0])!r}; "
        f"const float SV_ALB_DLA = {float(la[1] - la[0])!r};",
        f"const float SV_ALB[{E.size}] = float[{E.size}]({alb});",
    ])


def undistortion_grid(intr: Intrinsics, step_px: float = UNDISTORT_STEP_PX) -> dict:
    """Undistorted normalised coordinates (x, y) on a grid of image pixels.

    Nodes are spaced at most ``step_px`` apart from pixel centre 0 to the last pixel
    centre in u and v; ``xy`` is (rows, cols, 2) float32, base64, row-major.
    """
    W, H = intr.image_size
    gw = max(2, math.ceil((W - 1) / step_px) + 1)
    gh = max(2, math.ceil((H - 1) / step_px) + 1)
    u, v = np.meshgrid(np.linspace(0, W - 1, gw), np.linspace(0, H - 1, gh))
    K = np.asarray(intr.K, float)
    yd = (v - K[1, 2]) / K[1, 1]
    xd = (u - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    xy = undistort_normalized(np.stack([xd, yd], -1), np.asarray(intr.dist, float))
    return {"cols": gw, "rows": gh,
            "xy": base64.b64encode(xy.astype("<f4").tobytes()).decode("ascii")}

logger = logging.getLogger(__name__)

TEMPLATE = Path(__file__).with_name("index.html")


def write_viewer(out_dir: str | Path, surface_id: str, maps: Mapping[str, ParamMap],
                 intr: Intrinsics, views: list[dict], gamma: float,
                 error_poses: list | None = None,
                 inspector: tuple[dict, bytes] | None = None, tile: int | None = None,
                 budget_mb: float | None = None) -> Path:
    """Write ``index.html``, ``data.js``, ``manifest.json`` and the payload scripts of
    every model into ``out_dir``.

    Each model's texture layers travel in 8 bits per plane
    (:func:`parammap.viewer.compact.encode_map`) in ``payload-<model>.js`` (maps wider
    or taller than ``tile`` texels: one ``payload-<model>-<i>.js`` per tile, and their
    mip levels, ``payload-<model>-m<f>[-<i>].js``, :func:`parammap.viewer.compact.mip_levels`),
    which the page loads when the model is first shown (a tiled map: its coarsest level,
    then the tiles on screen of the level the zoom asks for; scripts, so that the page
    also works from the file system). ``manifest.json`` (also inside ``data.js``) describes the
    surface, the models, their planes, tiles and quantisation, payload sizes and, where
    ``error_poses`` are given, the quantisation error (mean 8-bit levels) per model.

    Parameters
    ----------
    maps : model name -> parameter map (all of one surface).
    views : dicts with ``id``, ``holdout``, ``R`` (3x3), ``t`` (3,) for every posed view.
    gamma : initial tone-mapping gamma (also the SH payload's error budget).
    error_poses : (R, t) pairs whose renders measure each payload's quantisation error
        (:func:`parammap.viewer.compact.quantisation_error`).
    inspector : the texel inspector's entry and payload
        (:func:`parammap.viewer.inspect.inspector_payload`), written as ``inspect.js``.
    tile : tile size in texels (default :data:`parammap.viewer.compact.TILE`).
    budget_mb : the page's float-layer budget (default
        :data:`parammap.viewer.compact.FLOAT_LAYER_BUDGET_MB`): an SH map shown reduced
        under it also travels at that reduction (``payload-<model>-f<f>.js``), which is
        all the page then loads.
    """
    budget_mb = budget_mb or FLOAT_LAYER_BUDGET_MB

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    any_map = next(iter(maps.values()))
    models = []
    for name, pm in maps.items():
        info, nlayers = layer_info(pm)
        entry, payloads = encode_map(pm, gamma, tile or TILE, budget_mb)
        files, sizes, n = [], [], len(entry["tiles"])
        # payload groups: the map's tiles, then SH's stored level or the mip levels
        groups = [(f"payload-{name}", 0, n)]
        if "level" in entry:
            groups.append((f"payload-{name}-f{entry['level']['f']}", n, len(payloads) - n))
        groups += [(f"payload-{name}-m{m['f']}", m["first"], len(m["tiles"]))
                   for m in entry.get("mips", [])]
        for i, payload in enumerate(payloads):
            stem, first, count = next(g for g in groups if g[1] <= i < g[1] + g[2])
            files.append(f"{stem}.js" if count == 1 else f"{stem}-{i - first}.js")
            text = payload_script("(window.PARAMMAP_PAYLOAD = window.PARAMMAP_PAYLOAD || {})"
                                  f"[{json.dumps(f'{name}#{i}')}]", payload)
            _write_atomic(out_dir / files[-1], text)
            sizes.append(len(text))
        size = sum(sizes[:n])
        err = None
        if error_poses is not None:
            err = quantisation_error(pm, entry, payloads, intr, error_poses, gamma)
            logger.info(f"viewer: {name} payload quantisation error {err:.3f} 8-bit levels")
        T, S = pm.shape
        # the page loads the stored level where it shows the map at that reduction
        shown = sum(sizes[n:]) if "level" in entry else size
        models.append({"name": name, "S": S, "T": T, "nlayers": nlayers, "files": files,
                       "bytes": size, "bytes_per_texel": size / (S * T),
                       "bytes_mips": sum(sum(sizes[m["first"]:m["first"] + len(m["tiles"])])
                                         for m in entry.get("mips", [])),
                       "bytes_loaded": shown,
                       "quantisation_error_8bit": err, "compact": entry, **info})
    manifest = {"surface": {"id": surface_id, "width_mm": any_map.width_mm,
                            "height_mm": any_map.height_mm},
                "models": models}
    if inspector is not None:
        entry, payload = inspector
        text = payload_script("window.PARAMMAP_INSPECT", payload)
        _write_atomic(out_dir / "inspect.js", text)
        manifest["inspector"] = {**entry, "file": "inspect.js", "bytes": len(text)}
    data = {**manifest,
            "camera": {"K": np.asarray(intr.K).tolist(), "dist": np.asarray(intr.dist).tolist(),
                       "image_size": list(intr.image_size),
                       "undistort": undistortion_grid(intr)},
            "glsl": glsl_constants(),
            "views": [{"id": v["id"], "holdout": bool(v["holdout"]),
                       "R": np.asarray(v["R"]).tolist(), "t": np.asarray(v["t"]).tolist()}
                      for v in views],
            "gamma": gamma, "float_layer_budget_mb": budget_mb}
    _write_atomic(out_dir / "manifest.json", json.dumps(manifest, indent=1))
    _write_atomic(out_dir / "data.js", "window.PARAMMAP_DATA = " + json.dumps(data) + ";\n")
    shutil.copyfile(TEMPLATE, out_dir / "index.html")
    return out_dir / "index.html"


def _write_atomic(path: Path, text: str | bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    if isinstance(text, bytes):
        tmp.write_bytes(text)
    else:
        tmp.write_text(text)
    tmp.replace(path)


def write_surface_viewer(cap: Capture, processed: str | Path, models: list[str],
                         out_dir: str | Path) -> Path:
    """The viewer stage: the page for the exported maps ``params/<model>.exr`` of
    ``models``, with every kept view's pose to snap to; the initial gamma is the
    median of the held-out comparison's (1 before that stage has run)."""
    proc = Processed(processed)
    names = list(models)
    for name in models:  # the best map's candidates are shown by it
        names += [p for p in (read_param_map(proc.params(name), with_sd=False).parts or {})
                  if p not in names]
    # each map read when it is used, without its sds: a lab capture's ten maps held at
    # once were 3 GB, with their sds (which the page does not show) 6
    maps = ParamMapFiles({name: proc.params(name) for name in names})
    views = [r for r in read_poses(proc.poses)["views"] if r["kept"]]
    gamma = 1.0
    if proc.metrics("holdout").is_file():
        g = [v["gamma"] for v in read_metrics(proc.metrics("holdout"))["views"].values()]
        gamma = float(np.median(g)) if g else gamma
    intr = load_intrinsics(proc.intrinsics)
    # the payload's quantisation error, measured where it is looked at: renders of the
    # held-out views (else three captured views) at the report's gamma
    shown = [v for v in views if v.get("holdout")] or views[:: max(1, len(views) // 3)][:3]
    poses = [(np.asarray(v["R"], float), np.asarray(v["t"], float)) for v in shown]

    g = open_observation_map(proc.observation)
    inspector = inspector_payload(maps, g.radiance, g.direction, g.valid)
    logger.info(f"viewer: inspector every {inspector[0]['step']} texel(s), "
                f"{len(inspector[1]) / 1e6:.1f} MB")
    path = write_viewer(out_dir, cap.surface_id, maps, intr, views, gamma, poses, inspector)
    logger.info(f"viewer: open {path}")
    return path
