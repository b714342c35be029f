"""The viewer's compact payload: a map's texture layers in 8 bits per plane.

The page used to carry every layer as base64 float32 (16 bytes per texel and layer:
107 bytes per texel for MH-2, 770 for SH-36). Here each plane (one channel of one
layer of :func:`parammap.viewer.viewer_layers`) is quantised to 8 bits between its own
minimum and maximum after a transfer that spreads the levels where they matter:

- ``sqrt`` for radiance-like planes (Kd, Ks: the display's tone curve is steep near
  black, so levels go there, as a display gamma does),
- ``log`` for the MH shininess and the SVBRDF's GGX alpha (their effect on a lobe is
  relative),
- ``linear`` for the MH lobe direction in hemi-octahedral coordinates (two planes:
  the unit upper hemisphere mapped onto a square with bounded distortion, so a level
  moves a direction by about the same angle at the pole and at the horizon; z is
  derived when decoding), and planes that are constant over the map (the layers'
  padding, absent lobes) cost nothing.

SH maps are first reduced by PCA across texels (coefficients of neighbouring bands are
strongly correlated over a surface); each component's weights are quantised with the
step that spends an equal share of :data:`SH_ERROR_LEVELS` (the mean error a render
may gain at the report's tone mapping), components within one step left out
(:func:`_weight_steps`); deflate then codes a component of few levels in few bits.

Each byte plane is then filtered as PNG filters its rows (:func:`_filter`): stored as
it is, or as the difference to its left, upper, or left + upper - upper-left
neighbour, whichever deflates smallest on a sample of its rows (smooth maps such as
Kd, m and the leading SH components shrink several times; noise stays unfiltered).
The planes are concatenated (plane after plane, texel row 0 first) and deflated
(zlib), which the browser inflates natively (``DecompressionStream("deflate")``); the
page rebuilds the float layers from the manifest entry :func:`encode_layers` returns.
Maps above :data:`TILE` texels a side travel in tiles (:func:`tile_grid`), each its
own payload with its own filters, all quantised as one map (one set of levels, one
PCA), so that no payload script passes what a browser allows a string and the page
can decode (and, for SH, reduce) tile after tile; SH maps are encoded straight from
their parameters in row blocks (:func:`encode_map`: a 4096 x 4096 SH-64 map in little
more memory than its 12.9 GB of float32 parameters).
:func:`decode_layers` is the same decoding in Python, for tests and for measuring the
quantisation error (:func:`quantisation_error`).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import cv2
import numpy as np

from ..conventions import MH_HEAD, mh_dir, mh_ks, mh_size
from ..models.sh.basis import sh_basis
from ..render import render, tone_map
from .layers import (
    MH_LAYERS_PER_LOBE,  # the viewer's texture layout (viewer_layers)
    layer_info,
    viewer_layers,
)

__all__ = ["FLOAT_LAYER_BUDGET_MB", "SH_ERROR_LEVELS", "TILE", "decode_layers",
           "encode_layers", "encode_map", "layers_to_params", "mip_levels", "page_reduction",
           "quantisation_error", "tile_grid"]

LEVELS = 255  # 8 bits per plane
# SH: the mean error, in 8-bit levels at the report's tone mapping, that the components
# left out and the quantisation of those kept may add to a render (_weight_steps;
# rounding to display levels turns an error e < 1 level into a one-level change with
# probability |e|); below the viewer's target of half a level, with room for the views
# that are looked at differing from the directions it is judged on
SH_ERROR_LEVELS = 0.35


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


PCA_CHUNK = 1 << 18  # texels per block of the SH PCA's sums
PCA_SAMPLE = 4096  # texels on which the SH weights' steps are chosen
# maps wider or taller than this many texels travel in tiles of this size, one payload
# script each: a 4096 x 4096 SH-64 map in one script would pass the length a browser
# allows a string; the page decodes tile after tile (and reduces as it goes)
TILE = 1024
# the page shows an SH map reduced where its float layers would pass this (index.html
# reads it from data.js; ?budget=<MB> in the page's address overrides it)
FLOAT_LAYER_BUDGET_MB = 512
ERROR_TEXELS = 1 << 22  # texels on which quantisation_error renders at most
ERROR_LAYER_BYTES = 1 << 28  # and the float32 layers it decodes for them
ERROR_PIXELS = 1 << 20  # and the pixels of each render (a camera above: scaled down)
DECODE_BLOCK_VALUES = 1 << 22  # values decode_layers makes at once
FILTER_LEFT, FILTER_UP = 1, 2  # filter codes are bit sets: 3 = both (the plane predictor)
FILTER_SAMPLE_BYTES = 1 << 18  # bytes of a plane on which its filter is chosen


def _filter(q: np.ndarray, code: int) -> np.ndarray:
    """(T, S) uint8 plane minus its prediction, mod 256: ``code`` & FILTER_LEFT
    differences along rows, & FILTER_UP along columns (both: the plane predictor
    left + up - upper-left); outside the plane counts as 0."""
    r = q.astype(np.int16)
    if code & FILTER_LEFT:
        r = np.diff(r, axis=1, prepend=0)
    if code & FILTER_UP:
        r = np.diff(r, axis=0, prepend=0)
    return (r & 255).astype(np.uint8)


def _unfilter(r: np.ndarray, code: int) -> np.ndarray:
    """The inverse of :func:`_filter` (running sums mod 256)."""
    q = r.astype(np.int64)
    if code & FILTER_UP:
        q = np.cumsum(q, axis=0)
    if code & FILTER_LEFT:
        q = np.cumsum(q, axis=1)
    return (q & 255).astype(np.uint8)


def _best_filter(q: np.ndarray) -> int:
    """The filter under which a (T, S) plane deflates smallest, judged on a block of
    rows from its middle (about :data:`FILTER_SAMPLE_BYTES`)."""
    T, S = q.shape
    rows = max(2, min(T, FILTER_SAMPLE_BYTES // max(S, 1)))
    block = q[(T - rows) // 2:(T - rows) // 2 + rows]
    sizes = [len(zlib.compress(_filter(block, c).tobytes(), 6)) for c in range(4)]
    return int(np.argmin(sizes))


def _render_directions(count: int = 128, max_zenith_deg: float = 80.0) -> np.ndarray:
    """(count, 3) view directions spread evenly in solid angle over the upper hemisphere
    to ``max_zenith_deg`` (a Fibonacci spiral): where the payload's error is judged."""
    i = np.arange(count) + 0.5
    z = 1 - i / count * (1 - np.cos(np.radians(max_zenith_deg)))
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def _weight_steps(Xs: np.ndarray, V: np.ndarray, Ws: np.ndarray, span: np.ndarray,
                  gamma: float, budget: float = SH_ERROR_LEVELS) -> np.ndarray:
    """Quantisation step for each principal component's weights (inf: left out), such
    that renders change by ``budget`` mean 8-bit levels.

    Parameters
    ----------
    Xs : (t, 3 c) the SH coefficients of a sample of the map's texels
        (coefficient-major, RGB inside).
    V : (3 c, k) the PCA basis (same row order); Ws : (t, k) the sample's weights.
    span : (k,) each component's range of weights over the whole map.
    gamma : the tone curve ``1 - exp(-gamma L)``.

    Notes
    -----
    A weight error e of component j moves texel t's radiance in direction w, channel c,
    by ``e g_j(w, c)`` (``g_j`` the component's radiance function), and its display
    level by that times the tone curve's slope ``s`` at the texel's own radiance there.
    Transform coding's reverse water-filling: every component gets the step whose
    error variance ``step^2 / 12`` is one value theta per unit of its mean ``s^2 g_j^2``;
    one whose weights all lie within half a step is left out (its error is then its
    weight; quantisation errors shrink under the renders' bilinear interpolation).
    The errors of many components add up to a Gaussian of variance
    ``sigma^2(t, w, c)``, whose mean absolute value ``sqrt(2 / pi) sigma``, averaged over
    the sample and the directions of :func:`_render_directions`, is brought to
    ``budget`` by bisection on theta. Deflate's Huffman codes then spend few bits on a
    component whose weights span few steps (texel noise).
    """
    k = V.shape[1]
    nc = Xs.shape[1] // 3
    Y = sh_basis(_render_directions(64), int(round(np.sqrt(nc))))  # (M, c)
    Lr = np.einsum("tic,wi->twc", Xs.reshape(-1, nc, 3), Y)
    slope2 = ((255.0 * gamma * np.exp(-gamma * np.maximum(Lr, 0.0))) ** 2).reshape(len(Xs), -1)
    g2 = (np.einsum("ick,wi->kwc", V.reshape(nc, 3, k), Y) ** 2).reshape(k, -1)
    h = np.maximum((slope2 @ g2.T).mean(0) / g2.shape[1], 1e-300)  # mean s^2 g_j^2
    Wt2 = Ws ** 2

    def steps(theta: float) -> np.ndarray:
        st = np.sqrt(12 * theta / h)
        return np.where(span < 0.5 * st, np.inf, st)

    def mean_error(theta: float) -> float:
        st = steps(theta)
        # quantisation errors are independent texel to texel, and renders interpolate
        # four texels bilinearly: their variance shrinks by the mean sum of squared
        # weights over a texel, (2 / 3)^2
        var = np.where(np.isfinite(st), np.where(np.isfinite(st), st, 0) ** 2 / 12, 0)
        e2 = (4 / 9) * var[None, :] + np.where(np.isfinite(st), 0.0, Wt2)  # (t, k)
        sigma2 = slope2 * (e2 @ g2)  # (t, M 3)
        return float(np.sqrt(2 / np.pi) * np.sqrt(sigma2).mean())

    # bisection in log theta between no error and every component left out
    lo, hi = -60.0, np.log(max(float((Wt2 * h).sum(1).mean()), 1e-300)) + 1
    if mean_error(np.exp(hi)) <= budget:
        return steps(np.exp(hi))
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mean_error(np.exp(mid)) <= budget else (lo, mid)
    return steps(np.exp(lo))


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


def tile_grid(T: int, S: int, tile: int = TILE) -> list[tuple[int, int, int, int]]:
    """The tiles of a T x S map, row-major: (first row, first column, rows, columns)."""
    return [(r, c, min(tile, T - r), min(tile, S - c))
            for r in range(0, T, tile) for c in range(0, S, tile)]


def page_reduction(T: int, S: int, nlayers: int, budget_mb: float = FLOAT_LAYER_BUDGET_MB
                   ) -> int:
    """The power-of-two reduction at which the page shows an SH map: the smallest whose
    float layers (16 bytes per texel and layer) fit ``budget_mb`` (the page's
    ``minReduction``)."""
    f = 1
    while (S // f) * (T // f) * nlayers * 16 > budget_mb * 2 ** 20 and f < min(S, T):
        f *= 2
    return f


def encode_map(pm, gamma: float = 1.0, tile: int = TILE,
               budget_mb: float = FLOAT_LAYER_BUDGET_MB) -> tuple[dict, list[bytes]]:
    """A parameter map's compact payload (:func:`encode_layers`); SH maps are encoded
    straight from their parameters, a few row blocks at a time, so that a 4096 x 4096
    SH-64 map needs little more memory than its own parameters, and those the page shows
    reduced (:func:`page_reduction` at ``budget_mb``) also carry that level (see
    :func:`_encode_sh`)."""
    if pm.model == "sh":
        info, L = layer_info(pm)
        T, S, P = pm.params.shape
        nc = P // 3
        # parameters are RGB-major (docs/reference/conventions.md), the layers coefficient-major
        perm = np.array([(i % 3) * nc + i // 3 for i in range(P)])
        return _encode_sh(pm.params, perm, gamma, tile, page_reduction(T, S, L, budget_mb))
    layers, info = viewer_layers(pm)
    entry, payloads = encode_layers(layers, info, gamma, tile)
    if info["model"] != "best" and len(entry["tiles"]) > 1:
        entry["mips"] = []
        for f, level in mip_levels(layers, info, tile):
            mip, more = encode_layers(level, info, gamma, tile)
            entry["mips"].append({**mip, "f": f, "T": level.shape[1], "S": level.shape[2],
                                  "first": len(payloads)})
            payloads += more
    return entry, payloads


def mip_levels(layers: np.ndarray, info: dict[str, Any], tile: int = TILE
               ) -> Iterator[tuple[int, np.ndarray]]:
    """The mip levels of a map's texture layers, for the page to show zoomed out.

    Each level halves the last (area-weighted box average, sizes rounded up, so every
    level covers the surface exactly), until one tile holds it; MH lobe directions are
    renormalised. A level averages parameters, not radiance: what a texel renders at a
    level is the look of the averaged material, enough where a screen pixel covers
    ``f`` x ``f`` texels and the level's texels are the page's pixels.

    Parameters
    ----------
    layers : (L, T, S, 4) float32 texture layers (:func:`parammap.viewer.viewer_layers`).
    info : their model description.
    tile : the payload tile size.

    Yields
    ------
    (f, (L, ceil(T / f), ceil(S / f), 4) float32) for f = 2, 4, ...
    """
    f, cur = 1, np.asarray(layers, np.float32)
    while max(cur.shape[1:3]) > tile:
        f *= 2
        T, S = -(-layers.shape[1] // f), -(-layers.shape[2] // f)
        cur = np.stack([cv2.resize(x, (S, T), interpolation=cv2.INTER_AREA)
                        .reshape(T, S, 4) for x in cur])
        if info["model"] == "mh":
            for layer in range(cur.shape[0]):
                if _mh_role(layer, 0) == "dir":
                    d = cur[layer, ..., :3]
                    n = np.linalg.norm(d, axis=-1, keepdims=True)
                    cur[layer, ..., :3] = np.where(n > 0, d / np.maximum(n, 1e-30), d)
        yield f, cur


def encode_layers(layers: np.ndarray, info: dict[str, Any], gamma: float = 1.0,
                  tile: int = TILE) -> tuple[dict, list[bytes]]:
    """Quantise a map's texture layers.

    Parameters
    ----------
    layers : (L, T, S, 4) float32, :func:`parammap.viewer.viewer_layers` (NaN-free).
    info : its model description (``model``: mh, sh or diffuse).
    gamma : the report's tone-mapping gamma (SH: sets the error budget in radiance).
    tile : maps wider or taller than this travel in tiles of ``tile`` x ``tile`` texels
        (:func:`tile_grid`), one payload each, quantised alike.

    Returns
    -------
    (manifest entry, payloads): the entry lists the planes in payload order (``layer``,
    ``channel``, ``transfer``, ``lo``, ``hi``; or ``const``; or ``derived``) and, for
    SH, the PCA's ``components`` (kept) and ``values``, each kept component's plane
    with its ``bits`` (8 or 16), ``lo`` and ``step`` (weight = lo + level x step), and
    its ``tiles`` (``r``, ``c``, ``T``, ``S`` and the per-plane ``filters``). A tile's
    payload is its deflated 8-bit planes (a 16-bit weight as its high-byte plane, then
    its low-byte plane), each filtered by its code (:func:`_filter`); the first tile's
    then carries (SH) at the next multiple of 4 bytes the PCA mean (``values``
    little-endian float32), each kept component's scale (float32) and its basis row
    as int16 multiples of that scale (``components`` x ``values``).
    """
    L, T, S, _ = layers.shape
    if info["model"] == "sh":
        A = layers[..., :3].transpose(1, 2, 0, 3).reshape(T, S, L * 3)
        return _encode_sh(A, np.arange(L * 3), gamma, tile)
    planes, data = [], []
    x = np.asarray(layers, np.float64)
    mh = info["model"] == "mh"
    sv = info["model"] == "svbrdf"
    for layer in range(L):
        if mh and _mh_role(layer, 0) == "dir":
            x[layer, ..., :2] = _hemioct(x[layer, ..., :3])
        for ch in range(4):
            y = x[layer, ..., ch]
            role = _mh_role(layer, ch) if mh else \
                ("m" if sv and (layer, ch) == (0, 3) else "kd")
            spec: dict[str, Any] = {"layer": layer, "channel": ch}
            if mh and role == "dir" and ch == 2:
                planes.append({**spec, "derived": "hemioct"})
                continue
            if (y == y.flat[0]).all():
                planes.append({**spec, "const": float(y.flat[0])})
                continue
            transfer = {"m": "log", "dir": "linear"}.get(role, "sqrt")
            if transfer == "sqrt" and ((y < 0).any() or info["model"] == "best"):
                transfer = "linear"
            q, lo, hi = _quantise(_forward(y, transfer))
            data.append(q)
            planes.append({**spec, "transfer": transfer, "lo": lo, "hi": hi})
    entry: dict[str, Any] = {"encoding": "u8-planes+deflate", "planes": planes, "tiles": []}
    payloads = [_tile_payload(entry, [a[r:r + h, c:c + w] for a in data], (r, c, h, w))
                for r, c, h, w in tile_grid(T, S, tile)]
    return entry, payloads


def _tile_payload(entry: dict, planes: list[np.ndarray], rect: tuple[int, int, int, int],
                  tail: bytes = b"") -> bytes:
    """Filter a tile's (rows, cols) uint8 planes, deflate them (and ``tail`` at the next
    multiple of 4 bytes), and record the tile in ``entry``."""
    r, c, h, w = rect
    filters = [_best_filter(a) for a in planes]
    z = zlib.compressobj(9)
    out = [z.compress(_filter(a, f).tobytes()) for a, f in zip(planes, filters, strict=True)]
    if tail:
        out.append(z.compress(bytes(-sum(a.size for a in planes) % 4) + tail))
    out.append(z.flush())
    entry["tiles"].append({"r": r, "c": c, "T": h, "S": w, "filters": filters})
    return b"".join(out)


def _encode_sh(A: np.ndarray, perm: np.ndarray, gamma: float, tile: int,
               level: int = 1) -> tuple[dict, list[bytes]]:
    """The SH payload of coefficients ``A`` (T, S, 3 c), whose column ``perm[i]`` is
    the layers' value i (coefficient-major, RGB inside); float32 row blocks with
    float64 sums, so that memory stays near the size of ``A``.

    ``level`` > 1 (a power of two dividing ``tile``): the map is also stored at that
    reduction, each f x f block's mean weights quantised with the same steps, as
    ``entry["level"]`` (``f``, ``T``, ``S``, ``tiles``; its payloads after the map's,
    its first tile carrying the PCA too), so that a page that shows the map reduced
    loads only that (the remainder rows and columns left out, as the page's reduction
    does)."""
    T, S, P = A.shape
    n = T * S
    rows = max(1, PCA_CHUNK // max(S, 1))

    def block(r0: int, r1: int, c0: int = 0, c1: int = S) -> np.ndarray:
        b = np.asarray(A[r0:r1, c0:c1], np.float32).reshape(-1, P)
        fin = np.isfinite(b)
        return b if fin.all() else np.where(fin, b, np.float32(0))

    # one pass for the covariance: second moments about a shift (the first block's
    # mean), in float64 (float32 sums blur the weak components' directions)
    shift = block(0, min(rows, T)).mean(0, dtype=np.float64)
    s1, s2 = np.zeros(P), np.zeros((P, P))
    for r0 in range(0, T, rows):
        b = block(r0, r0 + rows) - shift
        s1 += b.sum(0)
        s2 += b.T @ b
    d = s1 / max(n, 1)
    mean = shift + d
    V = np.linalg.eigh(s2 - n * np.outer(d, d))[1][:, ::-1]
    V32, mean32 = V.astype(np.float32), mean.astype(np.float32)
    lo, hi = np.full(P, np.inf), np.full(P, -np.inf)
    for r0 in range(0, T, rows):
        Wb = (block(r0, r0 + rows) - mean32) @ V32
        lo, hi = np.minimum(lo, Wb.min(0)), np.maximum(hi, Wb.max(0))
    take = np.unique(np.linspace(0, n - 1, min(n, PCA_SAMPLE)).astype(int))
    Xs = np.nan_to_num(np.asarray(A.reshape(n, P)[take], np.float64))
    step = _weight_steps(Xs[:, perm], V[perm], (Xs - mean) @ V, hi - lo, gamma)
    keep = np.flatnonzero(np.isfinite(step))
    planes = []
    for j in keep:
        top = int(np.round((hi[j] - lo[j]) / step[j]))
        planes.append({"component": int(j), "bits": 8 if top <= 255 else 16,
                       "lo": float(lo[j]), "step": float(step[j])})
    entry: dict[str, Any] = {"encoding": "u8-planes+deflate", "planes": planes,
                             "pca": {"components": len(keep), "values": P}, "tiles": []}
    Vk = V[perm][:, keep]  # (values, components), coefficient-major rows
    scale = np.maximum(np.abs(Vk).max(0), 1e-30) / 32767
    tail = (mean[perm].astype("<f4").tobytes() + scale.astype("<f4").tobytes()
            + np.round(Vk / scale).T.astype("<i2").tobytes())
    VkT = np.ascontiguousarray(V32[:, keep].T)  # (components, values) in A's order
    lo_k = lo[keep].astype(np.float32)[:, None]
    inv_k = (1 / step[keep]).astype(np.float32)[:, None]
    top_k = np.array([255 if p["bits"] == 8 else 65535 for p in planes], np.float32)[:, None]
    f = level if level > 1 and tile % level == 0 else 1
    T2, S2 = T // f, S // f
    wsum = np.zeros((len(keep), T2, S2), np.float32) if f > 1 else None
    payloads = []
    for r, c, h, w in tile_grid(T, S, tile):
        Q = np.empty((len(keep), h * w), np.uint16)  # levels, component-major
        sub = max(f, PCA_CHUNK // max(w, 1) // f * f)  # whole blocks of the level
        for r0 in range(r, r + h, sub):
            r1 = min(r0 + sub, r + h)
            Wt = VkT @ (block(r0, r1, c, c + w) - mean32).T
            Q[:, (r0 - r) * w:(r1 - r) * w] = np.clip(np.rint((Wt - lo_k) * inv_k), 0, top_k)
            if wsum is not None:  # this chunk's whole f x f blocks, summed
                nr, nc = min(r1, T2 * f) - r0, min(c + w, S2 * f) - c
                if nr > 0 and nc > 0:
                    Wb = Wt.reshape(len(keep), r1 - r0, w)[:, :nr, :nc]
                    wsum[:, r0 // f:r0 // f + nr // f, c // f:c // f + nc // f] += \
                        Wb.reshape(len(keep), nr // f, f, nc // f, f).sum((2, 4))
        payloads.append(_tile_payload(entry, _level_planes(Q, planes, h, w), (r, c, h, w),
                                      tail if not payloads else b""))
    if wsum is not None:
        lvl = {"f": f, "T": T2, "S": S2, "tiles": []}
        Ql = np.clip(np.rint((wsum.reshape(len(keep), -1) / (f * f) - lo_k) * inv_k), 0, top_k)
        for i, (r, c, h, w) in enumerate(tile_grid(T2, S2, tile)):
            q = Ql.reshape(len(keep), T2, S2)[:, r:r + h, c:c + w].reshape(len(keep), -1)
            payloads.append(_tile_payload(lvl, _level_planes(q, planes, h, w), (r, c, h, w),
                                          b"" if i else tail))
        entry["level"] = lvl
    return entry, payloads


def _level_planes(Q: np.ndarray, planes: list[dict], h: int, w: int) -> list[np.ndarray]:
    """(h, w) byte planes of weight levels Q (components, h w): a 16-bit weight as its
    high-byte plane, then its low-byte plane (the high bytes of a smooth map deflate
    well)."""
    data = []
    for q, p in zip(Q.astype(np.uint16), planes, strict=True):
        q = q.reshape(h, w)
        data += [(q >> 8).astype(np.uint8), (q & 255).astype(np.uint8)] \
            if p["bits"] == 16 else [q.astype(np.uint8)]
    return data


def _pca_tail(entry: dict, raw: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The PCA mean (values,) and basis (components, values) from the first tile's raw
    bytes (``n`` texels)."""
    k, nv = entry["pca"]["components"], entry["pca"]["values"]
    pos = sum(n * p.get("bits", 8) // 8 for p in entry["planes"])
    pos += -pos % 4
    f = raw[pos:pos + 4 * (nv + k)].view("<f4").astype(np.float64)
    b = raw[pos + 4 * (nv + k):pos + 4 * (nv + k) + 2 * k * nv].view("<i2")
    return f[:nv], b.reshape(k, nv) * f[nv:, None]


def decode_layers(entry: dict, payloads: list[bytes], shape: tuple[int, int, int],
                  every: int = 1, level: bool = False) -> np.ndarray:
    """The float layers (L, T, S, 4) of a manifest entry and its tiles' payloads
    (``shape`` = L, T, S); what the page does, in numpy. ``every`` > 1 keeps only the
    texels of every ``every``-th row and column (L, ceil(T / every), ceil(S / every), 4),
    decoding tile by tile, so that a map larger than memory can still be checked.
    ``level``: the stored reduced level instead (L, level T, level S, 4)."""
    L, T, S = shape
    n = len(entry["tiles"])
    tiles, payloads = (entry["level"]["tiles"], payloads[n:]) if level else \
        (entry["tiles"], payloads[:n])
    if level:
        T, S = entry["level"]["T"], entry["level"]["S"]
    out = np.zeros((L, -(-T // every), -(-S // every), 4), np.float32)
    pca = None
    for t, payload in zip(tiles, payloads, strict=True):
        h, w = t["T"], t["S"]
        n = h * w
        raw = np.frombuffer(zlib.decompress(payload), np.uint8).copy()
        for i, code in enumerate(t["filters"]):
            raw[i * n:(i + 1) * n] = _unfilter(raw[i * n:(i + 1) * n].reshape(h, w),
                                               code).ravel()
        if "pca" in entry and pca is None:
            pca = _pca_tail(entry, raw, n)
        r0, c0 = -t["r"] % every, -t["c"] % every  # the tile's first kept row, column
        # in blocks of rows (of whole strides): a tile's float64 values at once would be
        # over a GB for an SH-36 tile
        step = max(1, DECODE_BLOCK_VALUES // (w * L * 4) // every) * every
        for a in range(r0, h, step):
            x = _decode_tile(entry, raw, (L, h, w), pca, (a, min(h, a + step)))
            x = x[:, ::every, c0::every]
            R, C = (t["r"] + a) // every, (t["c"] + c0) // every
            out[:, R:R + x.shape[1], C:C + x.shape[2]] = x
    return out


def _decode_tile(entry: dict, raw: np.ndarray, shape: tuple[int, int, int],
                 pca: tuple[np.ndarray, np.ndarray] | None, rows: tuple[int, int] | None = None,
                 ) -> np.ndarray:
    """(L, rows, S, 4) float32 layers of a tile's unfiltered planes ``raw`` (shape: L,
    the tile's T and S), of its rows ``rows`` = (first, end) only where given."""
    L, T, S = shape
    a, b = rows or (0, T)
    h = b - a
    out = np.zeros((L, h, S, 4), np.float32)
    n, m, pos = T * S, h * S, 0

    def plane(at: int) -> np.ndarray:  # the rows' part of the plane at byte ``at``
        return raw[at + a * S:at + b * S]

    if pca is not None:
        W = np.empty((m, len(entry["planes"])))
        for j, p in enumerate(entry["planes"]):
            bits = p.get("bits", 8)
            q = plane(pos).astype(np.int64)
            if bits == 16:
                q = q * 256 + plane(pos + n)
            W[:, j] = p["lo"] + q * p["step"]
            pos += n * bits // 8
        X = pca[0] + W @ pca[1]
        out[..., :3] = X.reshape(h, S, L, 3).transpose(2, 0, 1, 3)
        return out
    derived = []
    for p in entry["planes"]:
        if "derived" in p:
            derived.append(p)
        elif "const" in p:
            out[p["layer"], ..., p["channel"]] = p["const"]
        else:
            y = _dequantise(plane(pos), p["lo"], p["hi"]).reshape(h, S)
            out[p["layer"], ..., p["channel"]] = _inverse(y, p["transfer"])
            pos += n
    for p in derived:  # lobe directions from their hemi-octahedral coordinates
        out[p["layer"], ..., :3] = _from_hemioct(out[p["layer"], ..., :2])
    return out


def _scaled_camera(intr, pixels: int):
    """``intr`` with its image scaled to at most ``pixels`` (pixel centres kept: a pixel
    at u maps to (u + 0.5) / s - 0.5); as it is where it has no more."""
    W, H = intr.image_size
    s = math.sqrt(W * H / pixels)
    if s <= 1:
        return intr
    size = (max(1, math.floor(W / s)), max(1, math.floor(H / s)))
    scale = np.array([W / size[0], H / size[1]])  # the image's edges kept exactly
    K = np.array(intr.K, float)
    K[:2] /= scale[:, None]
    K[:2, 2] += 0.5 / scale - 0.5
    return replace(intr, K=K, image_size=size)


def layers_to_params(layers: np.ndarray, info: dict[str, Any]) -> np.ndarray:
    """Parameters (T, S, P) in the docs/reference/conventions.md layout from texture layers (the
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
    if info["model"] == "best":  # candidate indices
        return np.rint(layers[0, ..., :2])
    if info["model"] == "svbrdf":  # (Kd, alpha), (Ks, coat)
        return np.concatenate([layers[0, ..., :3], layers[1, ..., :3], layers[0, ..., 3:],
                               layers[1, ..., 3:]], -1)
    return layers[0, ..., :3].copy()


def quantisation_error(pm, entry: dict, payloads: list[bytes], intr, poses,
                       gamma: float) -> float:
    """Mean 8-bit difference, at the report's tone mapping ``gamma``, of renders of the
    map from its compact payload (:func:`encode_map`) against renders of the float map,
    over ``poses`` (R, t) pairs and the surface pixels of each. Bounded for a lab's map
    and camera: a map above :data:`ERROR_TEXELS` texels or :data:`ERROR_LAYER_BYTES` of
    decoded layers is judged on both maps' every s-th texel (s the smallest that fits),
    and a camera above :data:`ERROR_PIXELS` renders at the largest scale that fits."""
    info, L = layer_info(pm)
    T, S = pm.shape
    # a 4096 x 4096 SH-64 map decoded whole would be a second 13 GB
    most = min(ERROR_TEXELS, ERROR_LAYER_BYTES / (16 * L))
    every = max(1, math.ceil(math.sqrt(T * S / most)))
    intr = _scaled_camera(intr, ERROR_PIXELS)
    back = decode_layers(entry, payloads, (L, T, S), every)
    pm = replace(pm, params=pm.params[::every, ::every])
    q = replace(pm, params=layers_to_params(back, info))
    diffs = []
    for R, t in poses:
        a, inside = render(pm, intr, R, t)
        b, _ = render(q, intr, R, t)
        diffs.append(np.abs(tone_map(a, gamma).astype(int) - tone_map(b, gamma).astype(int))
                     [inside])
    return float(np.concatenate(diffs).mean()) if diffs else float("nan")
