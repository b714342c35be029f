"""The observation map (``observation.zarr``): every texel's radiance, view direction,
validity and noise in every kept view, chunked in texel tiles with all views.

Arrays (T rows, S columns, N views): ``radiance`` (T, S, N, 3) float32, ``direction``
(T, S, N, 3) float32 unit vectors in the surface frame, ``valid`` (T, S, N) bool,
``noise`` (T, S, N) float32 relative sd (absent from stores written before the merge
recorded noise). Attributes: the grid (``S``, ``T``, ``tile``, ``width_mm``,
``height_mm``), ``view_ids``, ``held_out_view_ids`` and the build's figures.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from .. import __version__
from ..config import default
from ..errors import InputError
from ..models.weights import noise_weights
from .common import COMPLETE_ATTR, open_complete

__all__ = ["OBS_DIMS", "OBS_UNITS", "ObservationError", "open_observation_map",
           "sample_texel_observations", "tile_observations", "write_observation_arrays"]


class ObservationError(InputError):
    """Missing or inconsistent inputs to the observation map, or an incomplete store."""


# dimension names of the observation arrays (xarray.open_zarr labels them)
OBS_DIMS = {"radiance": ("row", "col", "view", "channel"),
            "direction": ("row", "col", "view", "xyz"),
            "valid": ("row", "col", "view"), "noise": ("row", "col", "view")}


OBS_UNITS = {"radiance": "relative linear radiance (one global scale)",
             "direction": "1 (unit vector toward the camera, surface frame)",
             "valid": "1 (true: observed, unsaturated, unoccluded)",
             "noise": "1 (relative sd of the radiance; NaN: not recorded)"}


def _compressor():
    return zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")


def create_observation_map(final: Path, S: int, T: int, N: int, tile: int) -> zarr.Group:
    """The observation map's arrays, chunked by texel tiles with all views."""
    g = zarr.open_group(final, mode="w")
    comp = _compressor()
    for name in ("radiance", "direction", "valid", "noise"):
        trail = (3,) if name in ("radiance", "direction") else ()
        dtype = "bool" if name == "valid" else "float32"
        g.create_array(name, shape=(T, S, N) + trail, dimension_names=OBS_DIMS[name],
                       attributes={"units": OBS_UNITS[name]}, chunks=(tile, tile, N) + trail,
                       dtype=dtype, compressors=comp,
                       fill_value=False if name == "valid" else np.nan)
    return g


def open_observation_map(path: str | Path) -> zarr.Group:
    """Open a finished observation map; refuses a missing or incomplete store."""
    g = open_complete(path, ObservationError, "observation map")
    for name in ("radiance", "direction", "valid"):
        if name not in g:
            raise ObservationError(f"{path}: observation map lacks array {name!r}")
    return g


def write_observation_arrays(
    path: str | Path, radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray,
    width_mm: float, height_mm: float, tile: int = default("observation.tile"),
    view_ids: list[str] | None = None,
    attrs: dict[str, Any] | None = None, noise: np.ndarray | None = None,
) -> Path:
    """Write in-memory observations (T, S, N, ...) as a complete observation map, e.g.
    for the 004 test set-ups of :mod:`parammap.synth.cases` (small maps only); ``noise``
    (T, S, N) relative sd per observation (NaN when not given)."""
    path = Path(path)
    T, S, N = valid.shape
    tile = int(min(tile, S, T))
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    g = zarr.open_group(tmp, mode="w")
    comp = _compressor()
    if noise is None:
        noise = np.full(valid.shape, np.nan, np.float32)
    for name, arr, fill in (("radiance", radiance, np.nan), ("direction", direction, np.nan),
                            ("valid", valid, False), ("noise", noise, np.nan)):
        a = g.create_array(name, shape=arr.shape, chunks=(tile, tile) + arr.shape[2:],
                           dtype="bool" if name == "valid" else "float32", compressors=comp,
                           fill_value=fill, dimension_names=OBS_DIMS[name],
                           attributes={"units": OBS_UNITS[name]})
        a[...] = arr
    g.attrs.update({"width_mm": width_mm, "height_mm": height_mm, "S": S, "T": T,
                    "tile": tile, "view_ids": view_ids or [f"v{n:03d}" for n in range(N)],
                    "held_out_view_ids": [], "software": f"parammap {__version__}",
                    **(attrs or {}), COMPLETE_ATTR: True})
    if path.exists():
        shutil.rmtree(path)
    tmp.rename(path)
    return path


def tile_observations(g: zarr.Group, rows: slice, cols: slice) -> tuple[np.ndarray, ...]:
    """Observations of the texels of a tile, flattened, for a model: V, L (n, N, 3)
    (invalid ones: +z and 0), W (n, N) valid, and the noise weights (n, N)
    (:func:`parammap.models.weights.noise_weights`)."""
    N = g["valid"].shape[2]
    L = np.asarray(g["radiance"][rows, cols], float).reshape(-1, N, 3)
    V = np.asarray(g["direction"][rows, cols], float).reshape(-1, N, 3)
    W = np.asarray(g["valid"][rows, cols], bool).reshape(-1, N) & np.isfinite(L).all(-1) \
        & np.isfinite(V).all(-1)
    L = np.where(W[..., None], L, 0.0)
    V = np.where(W[..., None], V, [0.0, 0.0, 1.0])
    noise = g["noise"][rows, cols].reshape(-1, N) if "noise" in g else None
    return V, L, W, noise_weights(noise, W)


def sample_texel_observations(g: zarr.Group, members: np.ndarray, S: int, tile: int,
                         size: int, rng: np.random.Generator):
    """Texel indices and observations (V, L, W, weights) of up to ``size`` of the flat
    texel indices ``members``: whole tiles in random order, every member of a tile
    read, until the sample is full (reads a few tiles, not the map)."""
    T_tiles = -(-S // tile)
    key = (members // S // tile) * T_tiles + (members % S) // tile
    picked, parts = [], []
    for kt in rng.permutation(np.unique(key)):
        r0, c0 = (kt // T_tiles) * tile, (kt % T_tiles) * tile
        rows, cols = slice(r0, r0 + tile), slice(c0, c0 + tile)
        here = members[key == kt]
        obs = tile_observations(g, rows, cols)
        width = min(c0 + tile, S) - c0
        local = (here // S - r0) * width + (here % S - c0)
        parts.append([a[local] for a in obs])
        picked.append(here)
        if sum(len(p) for p in picked) >= size:
            break
    return np.concatenate(picked), *(np.concatenate(a) for a in zip(*parts, strict=True))
