"""The viewer's compact payload: a map's texture layers in 8 bits per plane.

The page used to carry every layer as base64 float32 (16 bytes per texel and layer:
107 bytes per texel for MH-2, 770 for SH-36). Here each plane (one channel of one
layer of :func:`parammap.viewer.viewer_layers`) is quantised to 8 bits between its own
minimum and maximum after a transfer that spreads the levels where they matter:

- ``sqrt`` for radiance-like planes (Kd, Ks: the display's tone curve is steep near
  black, so levels go there, as a display gamma does),
- ``log`` for the MH shininess (its effect on a lobe is relative),
- ``linear`` for the MH lobe direction in hemi-octahedral coordinates (two planes:
  the unit upper hemisphere mapped onto a square with bounded distortion, so a level
  moves a direction by about the same angle at the pole and at the horizon; z is
  derived when decoding), and planes that are constant over the map (the layers'
  padding, absent lobes) cost nothing.

SH maps are first reduced by PCA across texels (coefficients of neighbouring bands are
strongly correlated over a surface): the components that leave less than
:data:`PCA_UNEXPLAINED` of the variance are kept, and their weights quantised linearly.

The planes are concatenated (plane after plane, texel row 0 first) and deflated
(zlib), which the browser inflates natively (``DecompressionStream("deflate")``); the
page rebuilds the float layers from the manifest entry :func:`encode_layers` returns.
:func:`decode_layers` is the same decoding in Python, for tests and for measuring the
quantisation error (:func:`quantisation_error`).
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np

from ..conventions import MH_HEAD, mh_dir, mh_ks, mh_size
from . import MH_LAYERS_PER_LOBE  # the viewer's texture layout (viewer_layers)

__all__ = ["PCA_UNEXPLAINED", "decode_layers", "encode_layers", "layers_to_params",
           "quantisation_error"]

LEVELS = 255  # 8 bits per plane
PCA_UNEXPLAINED = 1e-6  # SH: keep components until this fraction of the variance is left


def _forward(x: np.ndarray, transfer: str) -> np.ndarray:
    if transfer == "sqrt":
        return np.sqrt(np.maximum(x, 0.0))
    if transfer == "log":
        return np.log(np.maximum(x, 1e-12))
    return x


def _inverse(y: np.ndarray, transfer: str) -> np.ndarray:
    if transfer == "sqrt":
        return y * y
    if transfer == "log":
        return np.exp(y)
    return y


def _quantise(y: np.ndarray) -> tuple[np.ndarray, float, float]:
    lo, hi = float(np.min(y)), float(np.max(y))
    step = (hi - lo) / LEVELS if hi > lo else 1.0
    return np.clip(np.round((y - lo) / step), 0, LEVELS).astype(np.uint8), lo, hi


def _dequantise(q: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return lo + q.astype(np.float64) * ((hi - lo) / LEVELS)


def _hemioct(d: np.ndarray) -> np.ndarray:
    """Unit directions (..., 3) of the upper hemisphere (z < 0 is put on the horizon)
    to hemi-octahedral coordinates (..., 2) in [-1, 1]^2."""
    d = np.asarray(d, np.float64)
    z = np.maximum(d[..., 2], 0.0)
    s = np.abs(d[..., 0]) + np.abs(d[..., 1]) + z
    px, py = d[..., 0] / np.maximum(s, 1e-12), d[..., 1] / np.maximum(s, 1e-12)
    return np.stack([px + py, px - py], -1)


def _from_hemioct(uv: np.ndarray) -> np.ndarray:
    px, py = 0.5 * (uv[..., 0] + uv[..., 1]), 0.5 * (uv[..., 0] - uv[..., 1])
    d = np.stack([px, py, 1.0 - np.abs(px) - np.abs(py)], -1)
    return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)


def _mh_role(layer: int, channel: int) -> str:
    """What a channel of an MH texture layer holds: head (Kd, m), Ks, or direction."""
    if layer == 0:
        return "m" if channel == 3 else "kd"
    return "ks" if (layer - 1) % MH_LAYERS_PER_LOBE == 0 else "dir"


def encode_layers(layers: np.ndarray, info: dict[str, Any]) -> tuple[dict, bytes]:
    """Quantise a map's texture layers.

    Parameters
    ----------
    layers : (L, T, S, 4) float32, :func:`parammap.viewer.viewer_layers` (NaN-free).
    info : its model description (``model``: mh, sh or diffuse).

    Returns
    -------
    (manifest entry, payload): the entry lists the planes in payload order (``layer``,
    ``channel``, ``transfer``, ``lo``, ``hi``; or ``const``; or ``derived``) and, for
    SH, the PCA's ``components`` and ``values``; the payload is the deflated 8-bit
    planes, then (SH) at the next multiple of 4 bytes the PCA mean and basis as
    little-endian float32 (``values`` x (1 + ``components``)).
    """
    L, T, S, _ = layers.shape
    x = np.asarray(layers, np.float64)
    planes, data = [], []
    entry: dict[str, Any] = {"encoding": "u8-planes+deflate", "planes": planes}
    if info["model"] == "sh":
        X = x[..., :3].transpose(1, 2, 0, 3).reshape(T * S, L * 3)
        mean = X.mean(0)
        Xc = X - mean
        w, V = np.linalg.eigh(Xc.T @ Xc)
        w, V = w[::-1].clip(min=0), V[:, ::-1]
        left = 1.0 - np.cumsum(w) / max(float(w.sum()), 1e-300)
        k = int(np.argmax(left <= PCA_UNEXPLAINED)) + 1 if (left <= PCA_UNEXPLAINED).any() \
            else len(w)
        W = Xc @ V[:, :k]
        for j in range(k):
            q, lo, hi = _quantise(W[:, j])
            data.append(q)
            planes.append({"component": j, "transfer": "linear", "lo": lo, "hi": hi})
        entry["pca"] = {"components": k, "values": L * 3}
        pad = -(k * T * S) % 4
        data += [np.zeros(pad, np.uint8),
                 np.r_[mean, V[:, :k].T.ravel()].astype("<f4").view(np.uint8)]
    else:
        mh = info["model"] == "mh"
        for layer in range(L):
            if mh and _mh_role(layer, 0) == "dir":
                x[layer, ..., :2] = _hemioct(x[layer, ..., :3])
            for ch in range(4):
                y = x[layer, ..., ch]
                role = _mh_role(layer, ch) if mh else "kd"
                spec: dict[str, Any] = {"layer": layer, "channel": ch}
                if mh and role == "dir" and ch == 2:
                    planes.append({**spec, "derived": "hemioct"})
                    continue
                if (y == y.flat[0]).all():
                    planes.append({**spec, "const": float(y.flat[0])})
                    continue
                transfer = {"m": "log", "dir": "linear"}.get(role, "sqrt")
                if transfer == "sqrt" and (y < 0).any():
                    transfer = "linear"
                q, lo, hi = _quantise(_forward(y, transfer))
                data.append(q.ravel())
                planes.append({**spec, "transfer": transfer, "lo": lo, "hi": hi})
    payload = zlib.compress(np.concatenate(data).tobytes() if data else b"", 9)
    return entry, payload


def decode_layers(entry: dict, payload: bytes, shape: tuple[int, int, int]) -> np.ndarray:
    """The float layers (L, T, S, 4) of a manifest entry and its payload (``shape`` =
    L, T, S); what the page does, in numpy."""
    L, T, S = shape
    raw = np.frombuffer(zlib.decompress(payload), np.uint8)
    out = np.zeros((L, T, S, 4))
    n, pos = T * S, 0
    if "pca" in entry:
        k, nv = entry["pca"]["components"], entry["pca"]["values"]
        W = np.empty((n, k))
        for j, p in enumerate(entry["planes"]):
            W[:, j] = _dequantise(raw[pos:pos + n], p["lo"], p["hi"])
            pos += n
        pos += -pos % 4
        f = raw[pos:pos + 4 * nv * (k + 1)].view("<f4").astype(np.float64)
        X = f[:nv] + W @ f[nv:].reshape(k, nv)
        out[..., :3] = X.reshape(T, S, L, 3).transpose(2, 0, 1, 3)
        return out.astype(np.float32)
    derived = []
    for p in entry["planes"]:
        if "derived" in p:
            derived.append(p)
        elif "const" in p:
            out[p["layer"], ..., p["channel"]] = p["const"]
        else:
            y = _dequantise(raw[pos:pos + n], p["lo"], p["hi"]).reshape(T, S)
            out[p["layer"], ..., p["channel"]] = _inverse(y, p["transfer"])
            pos += n
    for p in derived:  # lobe directions from their hemi-octahedral coordinates
        out[p["layer"], ..., :3] = _from_hemioct(out[p["layer"], ..., :2])
    return out.astype(np.float32)


def layers_to_params(layers: np.ndarray, info: dict[str, Any]) -> np.ndarray:
    """Parameters (T, S, P) in the conventions.md layout from texture layers (the
    inverse of :func:`parammap.viewer.viewer_layers`)."""
    L, T, S, _ = layers.shape
    if info["model"] == "mh":
        K = (L - 1) // MH_LAYERS_PER_LOBE  # a head layer, then the lobes' layers
        p = np.zeros((T, S, mh_size(K)), np.float32)
        p[..., :MH_HEAD] = layers[0]
        for k in range(K):
            p[..., mh_ks(k)] = layers[1 + MH_LAYERS_PER_LOBE * k, ..., :3]
            p[..., mh_dir(k)] = layers[2 + MH_LAYERS_PER_LOBE * k, ..., :3]
        return p
    if info["model"] == "sh":
        return layers[..., :3].transpose(1, 2, 3, 0).reshape(T, S, 3 * L)
    return layers[0, ..., :3].copy()


def quantisation_error(pm, layers: np.ndarray, info: dict, intr, poses, gamma: float) -> float:
    """Mean 8-bit difference, at the report's tone mapping ``gamma``, of renders of the
    map from its compact payload against renders of the float map, over ``poses``
    (R, t) pairs and the surface pixels of each."""
    from dataclasses import replace

    from ..render import render, tone_map

    entry, payload = encode_layers(layers, info)
    back = decode_layers(entry, payload, layers.shape[:3])
    q = replace(pm, params=layers_to_params(back, info))
    diffs = []
    for R, t in poses:
        a, inside = render(pm, intr, R, t)
        b, _ = render(q, intr, R, t)
        diffs.append(np.abs(tone_map(a, gamma).astype(int) - tone_map(b, gamma).astype(int))
                     [inside])
    return float(np.concatenate(diffs).mean()) if diffs else float("nan")
