"""The viewer's texel inspector: what the page shows for a clicked texel.

For texels on a regular grid over the map (every texel of a small map; every k-th row
and column where the map would exceed :data:`INSPECTOR_BYTES`), the payload holds each
view's direction (zenith and azimuth in degrees, quantised to bytes), the observed
luminance and each model's prediction of it (float16), and each model's parameters
(float32, in the docs/reference/conventions.md layout named by ``params``). The page plots the
observations against the models and lists the parameters; nothing is evaluated in the
browser, so the plot shows exactly what :func:`parammap.render.evaluate` predicts.

Payload (deflated, little-endian), in order: zenith u8 (t, s, N) (255: no observation),
azimuth u8 (t, s, N), observed luminance f16 (t, s, N), then per model its predicted
luminance f16 (t, s, N) and its parameters f32 (t, s, P); each array starts at a
multiple of 4 bytes (``offsets`` in the entry).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..conventions import LUMINANCE
from ..geometry import texel_centres
from ..render import evaluate
from ..stores.params import ParamMap, best_shares, channel_names

__all__ = ["INSPECTOR_BYTES", "decode_inspector", "inspector_payload"]

# the inspector's share of the page on disk before deflate: above it, texels are sampled
# every k-th row and column (the click snaps to the nearest sampled texel)
INSPECTOR_BYTES = 32 * 2 ** 20
PREDICT_ROWS = 1 << 16  # observations whose prediction is evaluated at once


def _per_texel_bytes(N: int, maps: Mapping[str, ParamMap]) -> int:
    return 4 * N + sum(2 * N + 4 * pm.params.shape[-1] for pm in maps.values())


def _take(a, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``a[rows][:, cols]`` of a numpy or zarr array (zarr reads only those)."""
    if hasattr(a, "oindex"):
        return np.asarray(a.oindex[rows, cols])
    return np.asarray(a)[np.ix_(rows, cols)]


def inspector_payload(maps: Mapping[str, ParamMap], radiance: np.ndarray, direction: np.ndarray,
                      valid: np.ndarray, budget: int = INSPECTOR_BYTES
                      ) -> tuple[dict[str, Any], bytes]:
    """The inspector's manifest entry and payload.

    Parameters
    ----------
    maps : model name -> parameter map, all of the observation map's shape (T, S).
    radiance, direction : (T, S, N, 3) observations (surface frame); valid : (T, S, N)
        (numpy or zarr arrays: only the sampled texels are read).
    budget : bytes before deflate; sets the texel step.
    """
    T, S, N = valid.shape
    step = max(1, math.ceil(math.sqrt(T * S * _per_texel_bytes(N, maps) / budget)))
    rows, cols = np.arange(0, T, step), np.arange(0, S, step)
    sel = np.ix_(rows, cols)
    v = _take(valid, rows, cols).astype(bool)
    d = _take(direction, rows, cols).astype(float)
    lum = _take(radiance, rows, cols).astype(float) @ LUMINANCE
    zen = np.degrees(np.arccos(np.clip(d[..., 2], -1, 1)))
    azi = np.degrees(np.arctan2(d[..., 1], d[..., 0])) % 360
    ok = v & np.isfinite(lum) & np.isfinite(zen)
    arrays = [np.where(ok, np.round(np.clip(zen, 0, 90)), 255).astype(np.uint8),
              np.where(ok, np.round(azi / 360 * 255) % 255, 0).astype(np.uint8),
              np.where(ok, lum, 0).astype("<f2")]
    models = []
    t, s = len(rows), len(cols)
    dd = np.where(ok[..., None], d, [0.0, 0.0, 1.0]).reshape(-1, 3)
    first = next(iter(maps.values()))
    pts = texel_centres(S, T, first.width_mm, first.height_mm, rows, cols).reshape(-1, 3)

    # predictions a block of sampled texels at a time: every sampled texel's views at
    # once were GBs for a lab map's SH coefficients in float64
    block = max(1, PREDICT_ROWS // N)

    def predict(pm, P: np.ndarray) -> np.ndarray:
        """Luminance (t s, N) that ``pm`` (parameters ``P`` (t s, P) at the sampled
        texels) predicts for the observations."""
        if pm.model == "best":  # each texel's candidates, with their shares
            parts = list((pm.parts or {}).items())
            shares = best_shares(P, len(parts))
            out = np.zeros((t * s, N))
            for j, (_, part) in enumerate(parts):
                Pj = np.nan_to_num(np.asarray(part.params[sel], float)).reshape(t * s, -1)
                out += shares[:, j:j + 1] * predict(part, Pj)
            return out
        out = np.empty((t * s, N))
        for a in range(0, t * s, block):
            b = min(t * s, a + block)
            out[a:b] = (evaluate(pm.model, np.repeat(P[a:b], N, axis=0), dd[a * N:b * N],
                                 np.repeat(pts[a:b], N, axis=0), pm.lights)
                        @ LUMINANCE).reshape(b - a, N)
        return out

    for name, pm in maps.items():
        P = np.nan_to_num(np.asarray(pm.params[sel], float))  # (t, s, P)
        pred = predict(pm, P.reshape(t * s, -1))
        arrays += [np.where(ok, pred.reshape(t, s, N), 0).astype("<f2"), P.astype("<f4")]
        models.append({"name": name, "params": channel_names(pm.model, P.shape[-1])})
    offsets, blob, pos = [], [], 0
    for a in arrays:
        pad = -pos % 4
        blob.append(b"\0" * pad)
        pos += pad
        offsets.append(pos)
        raw = np.ascontiguousarray(a).tobytes()
        blob.append(raw)
        pos += len(raw)
    entry = {"step": step, "rows": t, "cols": s, "views": N, "models": models,
             "offsets": offsets}
    return entry, zlib.compress(b"".join(blob), 6)


def decode_inspector(entry: dict[str, Any], payload: bytes) -> dict[str, np.ndarray]:
    """The arrays of an inspector payload (what the page reads): ``zenith``, ``azimuth``,
    ``observed``, and per model ``<name>:predicted`` and ``<name>:params``."""
    raw = zlib.decompress(payload)
    t, s, N = entry["rows"], entry["cols"], entry["views"]
    off = iter(entry["offsets"])

    def take(dtype, shape):
        o = next(off)
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
        return np.frombuffer(raw[o:o + n], dtype).reshape(shape)

    out = {"zenith": take("u1", (t, s, N)), "azimuth": take("u1", (t, s, N)),
           "observed": take("<f2", (t, s, N))}
    for m in entry["models"]:
        out[f"{m['name']}:predicted"] = take("<f2", (t, s, N))
        out[f"{m['name']}:params"] = take("<f4", (t, s, len(m["params"])))
    return out
