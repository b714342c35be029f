"""The observation map (``observation.zarr``): every texel's radiance, view direction,
validity and noise in every kept view, chunked in texel tiles with all views.

Arrays (T rows, S columns, N views): ``radiance`` (T, S, N, 3) float32, ``direction``
(T, S, N, 3) float32 unit vectors in the surface frame, ``valid`` (T, S, N) bool,
``noise`` (T, S, N) float32 relative sd (absent from stores written before the merge
recorded noise). Attributes: the grid (``S``, ``T``, ``tile``, ``width_mm``,
``height_mm``), ``view_ids``, ``held_out_view_ids`` and the build's figures.

The build writes views into a scratch store (one view per chunk row band), then
transposes bands of tile rows into the final store (:func:`create_scratch`,
:func:`write_view_rows`, :func:`read_scratch_band`, :func:`write_band`).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from ..config import default
from ..errors import InputError
from ..models.display import tone_gamma
from ..models.weights import noise_weights
from .common import (
    COMPLETE_ATTR,
    HEIGHT_ATTR,
    S_ATTR,
    SOFTWARE_ATTR,
    T_ATTR,
    TILE_ATTR,
    UNITS_ATTR,
    WIDTH_ATTR,
    MapStore,
    open_complete,
    software,
)
from .hdr import NOISE_CHANNEL

__all__ = ["OBS_DIMS", "OBS_UNITS", "ObservationError", "ObservationMap",
           "create_observation_map", "create_scratch", "finish_observation_map",
           "open_observation_map", "read_scratch_band", "sample_texel_observations",
           "set_build_attrs", "tile_observations", "write_band", "write_observation_arrays",
           "write_view_rows"]

# the observations' noise is the merged frames' (one name for both)
RADIANCE, DIRECTION, VALID, NOISE = "radiance", "direction", "valid", NOISE_CHANNEL
_REQUIRED = (RADIANCE, DIRECTION, VALID)


class ObservationError(InputError):
    """Missing or inconsistent inputs to the observation map, or an incomplete store."""


# dimension names of the observation arrays (xarray.open_zarr labels them)
OBS_DIMS = {RADIANCE: ("row", "col", "view", "channel"),
            DIRECTION: ("row", "col", "view", "xyz"),
            VALID: ("row", "col", "view"), NOISE: ("row", "col", "view")}

OBS_UNITS = {RADIANCE: "relative linear radiance (one global scale)",
             DIRECTION: "1 (unit vector toward the camera, surface frame)",
             VALID: "1 (true: observed, unsaturated, unoccluded)",
             NOISE: "1 (relative sd of the radiance; NaN: not recorded)"}


def _compressor():
    return zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")


class ObservationMap(MapStore):
    """A finished observation map opened for reading.

    ``radiance``, ``direction``, ``valid`` (zarr arrays, read lazily) and ``noise``
    (None for a store written before the merge recorded noise); the grid and the views
    as properties; :meth:`tile` gives a tile's observations cleaned for a model.
    """

    @property
    def radiance(self) -> zarr.Array:
        """(T, S, N, 3) relative linear radiance."""
        return self.group[RADIANCE]

    @property
    def direction(self) -> zarr.Array:
        """(T, S, N, 3) unit vectors toward the camera, surface frame."""
        return self.group[DIRECTION]

    @property
    def valid(self) -> zarr.Array:
        """(T, S, N) bool: observed, unsaturated, unoccluded."""
        return self.group[VALID]

    @property
    def noise(self) -> zarr.Array | None:
        """(T, S, N) relative sd per observation; None in stores from before it was
        recorded."""
        return self.group[NOISE] if NOISE in self.group else None

    @property
    def shape(self) -> tuple[int, int, int]:
        """(T, S, N): texel rows, columns and views."""
        return tuple(self.valid.shape)

    @property
    def N(self) -> int:
        return self.valid.shape[2]

    @property
    def view_ids(self) -> list[str]:
        return list(self.group.attrs["view_ids"])

    def tiles(self) -> list[tuple[slice, slice]]:
        """(rows, cols) of every chunk tile, row by row."""
        t = self.tile
        return [(slice(r0, min(r0 + t, self.T)), slice(c0, min(c0 + t, self.S)))
                for r0 in range(0, self.T, t) for c0 in range(0, self.S, t)]

    def sample_tiles(self, samples: int = 64, seed: int = 0) -> list[tuple[slice, slice]]:
        """Up to ``samples`` tiles (rows, cols) of the map, at random (all of them on a
        map of fewer)."""
        tiles = self.tiles()
        rng = np.random.default_rng(seed)
        return [tiles[i] for i in sorted(rng.permutation(len(tiles))[:samples])]

    def display_gamma(self, samples: int = 64, seed: int = 0) -> float:
        """The tone map's gamma for this map's radiance as the held-out views are shown
        (:func:`parammap.models.display.tone_gamma`), from the valid radiance of up to
        ``samples`` tiles at random."""
        vals = []
        for rows, cols in self.sample_tiles(samples, seed):
            _, L, W, _ = tile_observations(self, rows, cols)
            vals.append(L[W].ravel())
        return tone_gamma(np.concatenate(vals) if vals else np.ones(1))

    def valid_count(self) -> np.ndarray:
        """(T, S) valid observations per texel, read tile row by tile row."""
        count = np.zeros((self.T, self.S), np.int32)
        for r0 in range(0, self.T, self.tile):
            count[r0:r0 + self.tile] = self.valid[r0:r0 + self.tile].sum(-1)
        return count

    def mean_radiance(self) -> np.ndarray:
        """(T, S, 3) float32 mean radiance of each texel's valid observations (the
        diffuse-only baseline)."""
        kd = np.full((self.T, self.S, 3), np.nan, np.float32)
        for sl in self.tiles():
            v = self.valid[sl][..., None]
            L = np.nan_to_num(self.radiance[sl])
            kd[sl] = (L * v).sum(2) / np.maximum(v.sum(2), 1)
        return kd

    def texel(self, row: int, col: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One texel's valid observations: direction (n, 3), radiance (n, 3), and its
        (N,) valid mask."""
        v = self.valid[row, col]
        return self.direction[row, col][v], self.radiance[row, col][v], v


def open_observation_map(path: str | Path) -> ObservationMap:
    """Open a finished observation map; refuses a missing or incomplete store."""
    g = open_complete(path, ObservationError, "observation map")
    for name in _REQUIRED:
        if name not in g:
            raise ObservationError(f"{path}: observation map lacks array {name!r}")
    return ObservationMap(g, path)


def tile_observations(g: ObservationMap, rows: slice, cols: slice) -> tuple[np.ndarray, ...]:
    """Observations of the texels of a tile, flattened, for a model: V, L (n, N, 3)
    (invalid ones: +z and 0), W (n, N) valid, and the noise weights (n, N)
    (:func:`parammap.models.weights.noise_weights`)."""
    N = g.N
    L = np.asarray(g.radiance[rows, cols], float).reshape(-1, N, 3)
    V = np.asarray(g.direction[rows, cols], float).reshape(-1, N, 3)
    W = np.asarray(g.valid[rows, cols], bool).reshape(-1, N) & np.isfinite(L).all(-1) \
        & np.isfinite(V).all(-1)
    L = np.where(W[..., None], L, 0.0)
    V = np.where(W[..., None], V, [0.0, 0.0, 1.0])
    noise = g.noise[rows, cols].reshape(-1, N) if g.noise is not None else None
    return V, L, W, noise_weights(noise, W)


def sample_texel_observations(g: ObservationMap, members: np.ndarray, S: int, tile: int,
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


class TileReader:
    """An observation map's arrays for the tasks of a fit, opened once per process
    (:func:`tile_reader`); ``noise`` None in stores without it."""

    def __init__(self, path: str) -> None:
        g = zarr.open_group(path, mode="r")
        self.radiance, self.direction = g[RADIANCE], g[DIRECTION]
        self.noise = g[NOISE] if NOISE in g else None


_READERS: dict[str, TileReader] = {}


def tile_reader(path: str) -> TileReader:
    """The observation map at ``path`` opened for reading tiles, once per process."""
    if path not in _READERS:
        if len(_READERS) > 8:
            _READERS.clear()
        _READERS[path] = TileReader(path)
    return _READERS[path]


# ---------------------------------------------------------------------------------
# Writing


def create_observation_map(final: Path, S: int, T: int, N: int, tile: int) -> zarr.Group:
    """The observation map's arrays, chunked by texel tiles with all views."""
    g = zarr.open_group(final, mode="w")
    comp = _compressor()
    for name in (RADIANCE, DIRECTION, VALID, NOISE):
        trail = (3,) if name in (RADIANCE, DIRECTION) else ()
        dtype = "bool" if name == VALID else "float32"
        g.create_array(name, shape=(T, S, N) + trail, dimension_names=OBS_DIMS[name],
                       attributes={UNITS_ATTR: OBS_UNITS[name]}, chunks=(tile, tile, N) + trail,
                       dtype=dtype, compressors=comp,
                       fill_value=False if name == VALID else np.nan)
    return g


def create_scratch(scratch: Path, N: int, T: int, S: int, band: int) -> None:
    """The build's scratch store: one view per chunk row band, fast compression."""
    sg = zarr.open_group(scratch, mode="w")
    fast = zarr.codecs.BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")
    sg.create_array(RADIANCE, shape=(N, T, S, 3), chunks=(1, band, S, 3),
                    dtype="float32", compressors=fast, fill_value=np.nan)
    sg.create_array(VALID, shape=(N, T, S), chunks=(1, band, S), dtype="bool",
                    compressors=fast, fill_value=False)
    sg.create_array(NOISE, shape=(N, T, S), chunks=(1, band, S), dtype="float32",
                    compressors=fast, fill_value=np.nan)


def write_view_rows(scratch: zarr.Group | str, n: int, rows: slice, radiance: np.ndarray,
                    valid: np.ndarray, noise: np.ndarray | None) -> None:
    """View ``n``'s samples of the texel rows ``rows`` into the scratch store."""
    g = zarr.open_group(scratch, mode="r+") if isinstance(scratch, str | Path) else scratch
    g[RADIANCE][n, rows] = radiance
    g[VALID][n, rows] = valid
    if noise is not None:
        g[NOISE][n, rows] = noise


def open_scratch(scratch: str | Path) -> zarr.Group:
    """The scratch store, open for writing views."""
    return zarr.open_group(scratch, mode="r+")


def read_scratch_band(scratch: str | Path, r0: int, r1: int,
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texel rows r0:r1 of every view from the scratch store, views moved last:
    radiance (r, S, N, 3), valid (r, S, N), noise (r, S, N)."""
    src = zarr.open_group(scratch, mode="r")
    return (np.moveaxis(src[RADIANCE][:, r0:r1], 0, 2),
            np.moveaxis(src[VALID][:, r0:r1], 0, 2),
            np.moveaxis(src[NOISE][:, r0:r1], 0, 2))


def write_band(final: str | Path, r0: int, r1: int, radiance: np.ndarray,
               direction: np.ndarray, valid: np.ndarray, noise: np.ndarray) -> None:
    """Texel rows r0:r1 of every array of the final store."""
    dst = zarr.open_group(final, mode="r+")
    dst[RADIANCE][r0:r1] = radiance
    dst[DIRECTION][r0:r1] = direction
    dst[VALID][r0:r1] = valid
    dst[NOISE][r0:r1] = noise


def set_build_attrs(final: str | Path, *, width_mm: float, height_mm: float, S: int, T: int,
                    tile: int, view_ids: list[str], held_out_view_ids: list[str],
                    camera_centres_mm: list, calibration: dict, sampling: dict,
                    marker_texels: int, surface_id: str, config: dict) -> None:
    """The attributes of a map being built: its grid, views, camera, sampling settings
    and figures, the units of its arrays and the software that built it."""
    zarr.open_group(final, mode="r+").attrs.update({
        WIDTH_ATTR: width_mm, HEIGHT_ATTR: height_mm, S_ATTR: S, T_ATTR: T, TILE_ATTR: tile,
        "view_ids": view_ids, "held_out_view_ids": held_out_view_ids,
        "camera_centres_mm": camera_centres_mm, "calibration": calibration,
        UNITS_ATTR: {RADIANCE: "relative linear radiance (one global scale)",
                  NOISE: "relative sd of each observation (NaN: not recorded)",
                  DIRECTION: "unit vector toward the camera, surface frame",
                  "lengths": "mm"},
        "sampling": sampling, "marker_texels": marker_texels, "surface_id": surface_id,
        SOFTWARE_ATTR: software(), "config": config,
    })


def finish_observation_map(final: Path, out: Path) -> None:
    """Mark a built map complete and move it to ``out`` (replacing it)."""
    zarr.open_group(final, mode="r+").attrs[COMPLETE_ATTR] = True
    if out.exists():
        shutil.rmtree(out)
    final.rename(out)


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
    for name, arr, fill in ((RADIANCE, radiance, np.nan), (DIRECTION, direction, np.nan),
                            (VALID, valid, False), (NOISE, noise, np.nan)):
        a = g.create_array(name, shape=arr.shape, chunks=(tile, tile) + arr.shape[2:],
                           dtype="bool" if name == VALID else "float32", compressors=comp,
                           fill_value=fill, dimension_names=OBS_DIMS[name],
                           attributes={UNITS_ATTR: OBS_UNITS[name]})
        a[...] = arr
    g.attrs.update({WIDTH_ATTR: width_mm, HEIGHT_ATTR: height_mm, S_ATTR: S, T_ATTR: T,
                    TILE_ATTR: tile, "view_ids": view_ids or [f"v{n:03d}" for n in range(N)],
                    "held_out_view_ids": [], SOFTWARE_ATTR: software(),
                    **(attrs or {}), COMPLETE_ATTR: True})
    if path.exists():
        shutil.rmtree(path)
    tmp.rename(path)
    return path
