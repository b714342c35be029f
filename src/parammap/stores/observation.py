"""The observation map (``observation.zarr``): every texel's radiance, view direction,
validity and noise in every kept view, chunked in texel tiles with all views.

Arrays on disk (T rows, S columns, N views): ``radiance`` (T, S, N, 3) uint16, the
log2 of the relative linear radiance in :data:`RADIANCE_CODES` steps over the range the
array's ``log2_range`` attribute gives (code 0: no observation; :func:`encode_radiance`),
``valid`` (T, S, N) bool, ``noise`` (T, S, N) float16 relative sd. The view directions
are not stored: each is the unit vector from the texel's centre to its view's camera
centre (attribute ``camera_centres_mm``), computed when read (:class:`Directions`).
Attributes: the grid (``S``, ``T``, ``tile``, ``width_mm``, ``height_mm``),
``view_ids``, ``held_out_view_ids`` and the build's figures.

Readers (:class:`ObservationMap`, :func:`tile_reader`) hand out float32 radiance, noise
and directions whatever the store holds: stores written before this encoding (float32
``radiance``, a stored float32 ``direction``, no ``noise``) read as they did, and a
store written from in-memory arrays whose directions come from no camera centre keeps
them (:func:`write_observation_arrays`).

The build writes views into a scratch store (one view per chunk row band), then
transposes bands of tile rows into the final store (:func:`create_scratch`,
:func:`write_view_rows`, :func:`read_scratch_band`, :func:`write_band`).
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from ..config import default
from ..errors import InputError
from ..geometry import texel_centres, unit
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

__all__ = ["BYTES_PER_OBSERVATION", "Directions", "LOG2_RANGE", "OBS_DIMS", "OBS_UNITS",
           "ObservationError", "ObservationMap", "RADIANCE_CODES", "create_observation_map",
           "create_scratch", "decode_radiance", "encode_radiance", "finish_observation_map",
           "open_observation_map", "read_scratch_band", "sample_texel_observations",
           "set_build_attrs", "tile_observations", "write_band", "write_observation_arrays",
           "write_view_rows"]

logger = logging.getLogger(__name__)

# the observations' noise is the merged frames' (one name for both)
RADIANCE, DIRECTION, VALID, NOISE = "radiance", "direction", "valid", NOISE_CHANNEL
_REQUIRED = (RADIANCE, DIRECTION, VALID)
#: the attribute recording the flat-field and colour correction of the map's radiance
RADIOMETRY_ATTR = "radiometry"


class ObservationError(InputError):
    """Missing or inconsistent inputs to the observation map, or an incomplete store."""


# dimension names of the observation arrays (xarray.open_zarr labels them)
OBS_DIMS = {RADIANCE: ("row", "col", "view", "channel"),
            DIRECTION: ("row", "col", "view", "xyz"),
            VALID: ("row", "col", "view"), NOISE: ("row", "col", "view")}

# Radiance as log2 codes over a fixed range: 48 stops hold any exposure time and
# response (radiance is exp(g(z)) / t with g(128) = 0), and a step of 2**(48 / 65534)
# is 5.1e-4 relative: at most 2.5e-4 off (rms 1.5e-4), a tenth of the 0.25 % sd of an
# 8-bit level at its best and far below a merged frame's noise (docs: outputs).
LOG2_RANGE = (-24.0, 24.0)
RADIANCE_CODES = 65534
LOG2_RANGE_ATTR, ENCODING_ATTR = "log2_range", "encoding"
RADIANCE_ENCODING = "log2 uint16, code 0: none"
RADIANCE_DTYPE, NOISE_DTYPE = "uint16", "float16"
# bytes per texel per view before compression: radiance codes, noise, valid
BYTES_PER_OBSERVATION = 3 * 2 + 2 + 1

OBS_UNITS = {RADIANCE: "relative linear radiance (one global scale); on disk log2 codes "
                       "(attributes encoding, log2_range)",
             DIRECTION: "1 (unit vector toward the camera, surface frame)",
             VALID: "1 (true: observed, unsaturated, unoccluded)",
             NOISE: "1 (relative sd of the radiance; NaN: not recorded)"}


def _compressor():
    # zstd with byte shuffle: the smallest of zstd/lz4 x shuffle/bitshuffle measured
    # on the demo's codes (docs: outputs)
    return zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")


def encode_radiance(L: np.ndarray, log2_range: tuple[float, float] = LOG2_RANGE,
                    ) -> np.ndarray:
    """Relative linear radiance (any shape) as uint16 log2 codes: 1..65535 over
    ``log2_range``, 0 where the value is NaN or not positive. Values outside the range
    are clipped to it (a warning says how many)."""
    lo, hi = log2_range
    L = np.asarray(L, np.float64)
    ok = np.isfinite(L) & (L > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.log2(np.where(ok, L, 1.0))
    out = ok & ((x < lo) | (x > hi))
    if out.any():
        logger.warning(f"observation: {int(out.sum())} radiance values outside 2**{lo:g} .. "
                       f"2**{hi:g} clipped to the encoding's range")
    code = np.rint((np.clip(x, lo, hi) - lo) * (RADIANCE_CODES / (hi - lo))) + 1
    return np.where(ok, code, 0).astype(np.uint16)


def decode_radiance(code: np.ndarray, log2_range: tuple[float, float] = LOG2_RANGE,
                    ) -> np.ndarray:
    """float32 relative linear radiance of uint16 log2 codes (:func:`encode_radiance`);
    NaN for code 0."""
    lo, hi = log2_range
    code = np.asarray(code)
    x = (code.astype(np.float64) - 1) * ((hi - lo) / RADIANCE_CODES) + lo
    return np.where(code > 0, np.exp2(x), np.nan).astype(np.float32)


class _Decoded:
    """A stored array read as float32: radiance codes decoded, float16 noise widened,
    float32 arrays of older stores as they are. Indexing reads from the zarr array."""

    def __init__(self, array: zarr.Array) -> None:
        self.array = array
        self.shape, self.chunks = tuple(array.shape), array.chunks
        self.ndim, self.dtype = len(self.shape), np.dtype(np.float32)
        enc = array.attrs.get(ENCODING_ATTR)
        rng = array.attrs.get(LOG2_RANGE_ATTR, LOG2_RANGE)
        self._decode = (lambda a: decode_radiance(a, tuple(rng))) if enc \
            else (lambda a: np.asarray(a, np.float32))

    def __getitem__(self, key) -> np.ndarray:
        return self._decode(self.array[key])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return self[...] if dtype is None else self[...].astype(dtype)

    @property
    def oindex(self) -> _Outer:
        """Orthogonal indexing (index arrays per axis), as zarr's ``oindex``."""
        return _Outer(lambda key: self._decode(self.array.oindex[key]))


class _Outer:
    def __init__(self, get) -> None:
        self._get = get

    def __getitem__(self, key) -> np.ndarray:
        return self._get(key)


def _grid_index(key, T: int, S: int, outer: bool = False,
                ) -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    """Split an index of a (T, S, ...) array into row and column indices (arrays), the
    axes to drop for integer indices and the index of the trailing axes; index arrays
    for rows and columns only with ``outer`` (orthogonal indexing)."""
    if key is Ellipsis:
        key = ()
    key = key if isinstance(key, tuple) else (key,)
    if any(k is Ellipsis for k in key):
        raise IndexError("derived directions take rows, cols[, views, xyz], not ...")
    key = key + (slice(None),) * max(0, 2 - len(key))
    if not outer and any(not isinstance(k, int | np.integer | slice) for k in key[:2]):
        raise IndexError("derived directions: index arrays only through .oindex")
    rows, cols = np.arange(T)[key[0]], np.arange(S)[key[1]]
    drop = tuple(0 if np.ndim(a) == 0 else slice(None) for a in (rows, cols))
    return np.atleast_1d(rows), np.atleast_1d(cols), drop, key[2:]


class Directions:
    """The (T, S, N, 3) float32 view directions of a map, computed when indexed: the
    unit vector from each texel's centre (:func:`parammap.geometry.texel_centres`) to
    each view's camera centre (surface frame, mm). Index it like the array it stands
    for (rows and columns by integer, slice or index array, then views and xyz)."""

    def __init__(self, centres_mm: np.ndarray, S: int, T: int, width_mm: float,
                 height_mm: float) -> None:
        self.centres = np.asarray(centres_mm, np.float64).reshape(-1, 3)
        self.S, self.T, self.width_mm, self.height_mm = S, T, width_mm, height_mm
        self.shape = (T, S, len(self.centres), 3)
        self.ndim, self.dtype = 4, np.dtype(np.float32)

    def __getitem__(self, key) -> np.ndarray:
        return self._get(key, outer=False)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return self[...] if dtype is None else self[...].astype(dtype)

    @property
    def oindex(self) -> _Outer:
        """Orthogonal indexing (index arrays of rows and columns), as zarr's."""
        return _Outer(lambda key: self._get(key, outer=True))

    def _get(self, key, outer: bool) -> np.ndarray:
        rows, cols, drop, rest = _grid_index(key, self.T, self.S, outer)
        p = texel_centres(self.S, self.T, self.width_mm, self.height_mm, rows, cols)
        d = unit(self.centres[None, None] - p[:, :, None]).astype(np.float32)
        return d[drop][(slice(None),) * (2 - drop.count(0)) + rest] if rest else d[drop]


class ObservationMap(MapStore):
    """A finished observation map opened for reading.

    ``radiance``, ``direction``, ``valid`` (zarr arrays, read lazily) and ``noise``
    (None for a store written before the merge recorded noise); the grid and the views
    as properties; :meth:`tile` gives a tile's observations cleaned for a model.
    """

    def __getitem__(self, name: str):
        """An array by name; radiance, direction and noise as their float32 readers."""
        readers = {RADIANCE: lambda: self.radiance, DIRECTION: lambda: self.direction,
                   NOISE: lambda: self.noise}
        return readers[name]() if name in readers else self.group[name]

    def __contains__(self, name: str) -> bool:
        return name == DIRECTION or name in self.group

    @property
    def radiance(self) -> _Decoded:
        """(T, S, N, 3) float32 relative linear radiance (NaN: no observation)."""
        return _Decoded(self.group[RADIANCE])

    @property
    def direction(self) -> Directions | zarr.Array:
        """(T, S, N, 3) float32 unit vectors toward the camera, surface frame: computed
        from the camera centres (:class:`Directions`), or as stored in older maps."""
        return _directions(self.group)

    @property
    def valid(self) -> zarr.Array:
        """(T, S, N) bool: observed, unsaturated, unoccluded."""
        return self.group[VALID]

    @property
    def noise(self) -> _Decoded | None:
        """(T, S, N) float32 relative sd per observation; None in stores from before it
        was recorded."""
        return _Decoded(self.group[NOISE]) if NOISE in self.group else None

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

    @property
    def radiometry(self) -> dict[str, str]:
        """What the frames' flat-field and colour correction did to the radiance
        (:func:`parammap.models.radiometry.describe_radiometry`); empty for maps built
        before it was recorded."""
        return dict(self.group.attrs.get(RADIOMETRY_ATTR) or {})

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


def _directions(g: zarr.Group) -> Directions | zarr.Array:
    """A store's view directions: stored (older maps, in-memory set-ups) or computed
    from its camera centres."""
    if DIRECTION in g:
        return g[DIRECTION]
    a = g.attrs
    return Directions(a["camera_centres_mm"], a[S_ATTR], a[T_ATTR], a[WIDTH_ATTR],
                      a[HEIGHT_ATTR])


def open_observation_map(path: str | Path) -> ObservationMap:
    """Open a finished observation map; refuses a missing or incomplete store."""
    g = open_complete(path, ObservationError, "observation map")
    for name in _REQUIRED:
        if name not in g and not (name == DIRECTION and "camera_centres_mm" in g.attrs):
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
        self.radiance, self.direction = _Decoded(g[RADIANCE]), _directions(g)
        self.valid = g[VALID]
        self.noise = _Decoded(g[NOISE]) if NOISE in g else None


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


def _array_spec(name: str) -> dict[str, Any]:
    """dtype, fill value and attributes of an observation array as stored."""
    if name == RADIANCE:
        return {"dtype": RADIANCE_DTYPE, "fill_value": 0,
                "attributes": {ENCODING_ATTR: RADIANCE_ENCODING,
                               LOG2_RANGE_ATTR: list(LOG2_RANGE)}}
    if name == VALID:
        return {"dtype": "bool", "fill_value": False, "attributes": {}}
    return {"dtype": NOISE_DTYPE if name == NOISE else "float32", "fill_value": np.nan,
            "attributes": {}}


def _create(g: zarr.Group, name: str, shape: tuple, chunks: tuple, compressors) -> zarr.Array:
    spec = _array_spec(name)
    return g.create_array(name, shape=shape, chunks=chunks, dtype=spec["dtype"],
                          fill_value=spec["fill_value"], compressors=compressors,
                          dimension_names=OBS_DIMS[name],
                          attributes={UNITS_ATTR: OBS_UNITS[name], **spec["attributes"]})


def create_observation_map(final: Path, S: int, T: int, N: int, tile: int) -> zarr.Group:
    """The observation map's arrays (radiance codes, valid, noise), chunked by texel
    tiles with all views; directions follow from the camera centres."""
    g = zarr.open_group(final, mode="w")
    for name in (RADIANCE, VALID, NOISE):
        trail = (3,) if name == RADIANCE else ()
        _create(g, name, (T, S, N) + trail, (tile, tile, N) + trail, _compressor())
    return g


def create_scratch(scratch: Path, N: int, T: int, S: int, band: int) -> None:
    """The build's scratch store: one view per chunk row band, fast compression, the
    final store's encoding (the transpose copies codes)."""
    sg = zarr.open_group(scratch, mode="w")
    fast = zarr.codecs.BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")
    for name in (RADIANCE, VALID, NOISE):
        trail = (3,) if name == RADIANCE else ()
        spec = _array_spec(name)
        sg.create_array(name, shape=(N, T, S) + trail, chunks=(1, band, S) + trail,
                        dtype=spec["dtype"], compressors=fast, fill_value=spec["fill_value"])


def write_view_rows(scratch: zarr.Group | str, n: int, rows: slice, radiance: np.ndarray,
                    valid: np.ndarray, noise: np.ndarray | None) -> None:
    """View ``n``'s samples of the texel rows ``rows`` (linear radiance, valid, relative
    noise sd) into the scratch store."""
    g = zarr.open_group(scratch, mode="r+") if isinstance(scratch, str | Path) else scratch
    g[RADIANCE][n, rows] = encode_radiance(radiance)
    g[VALID][n, rows] = valid
    if noise is not None:
        g[NOISE][n, rows] = noise


def open_scratch(scratch: str | Path) -> zarr.Group:
    """The scratch store, open for writing views."""
    return zarr.open_group(scratch, mode="r+")


def read_scratch_band(scratch: str | Path, r0: int, r1: int, c0: int = 0,
                      c1: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texel rows r0:r1 (columns c0:c1) of every view from the scratch store, views
    moved last, as stored: radiance codes (r, c, N, 3), valid (r, c, N), noise (r, c,
    N)."""
    src = zarr.open_group(scratch, mode="r")
    cols = slice(c0, c1)
    return (np.moveaxis(src[RADIANCE][:, r0:r1, cols], 0, 2),
            np.moveaxis(src[VALID][:, r0:r1, cols], 0, 2),
            np.moveaxis(src[NOISE][:, r0:r1, cols], 0, 2))


def write_band(final: str | Path, r0: int, r1: int, radiance: np.ndarray,
               valid: np.ndarray, noise: np.ndarray, c0: int = 0,
               c1: int | None = None) -> None:
    """Texel rows r0:r1 (columns c0:c1) of every array of the final store, as
    :func:`read_scratch_band` hands them out (radiance codes)."""
    dst = zarr.open_group(final, mode="r+")
    cols = slice(c0, c1)
    dst[RADIANCE][r0:r1, cols] = radiance
    dst[VALID][r0:r1, cols] = valid
    dst[NOISE][r0:r1, cols] = noise


def set_build_attrs(final: str | Path, *, width_mm: float, height_mm: float, S: int, T: int,
                    tile: int, view_ids: list[str], held_out_view_ids: list[str],
                    camera_centres_mm: list, calibration: dict, sampling: dict,
                    marker_texels: int, surface_id: str, config: dict,
                    radiometry: dict[str, str] | None = None) -> None:
    """The attributes of a map being built: its grid, views, camera, sampling settings
    and figures, the flat-field and colour its radiance carries (``radiometry``,
    :func:`parammap.models.radiometry.describe_radiometry`), the units of its arrays
    and the software that built it."""
    zarr.open_group(final, mode="r+").attrs.update({
        WIDTH_ATTR: width_mm, HEIGHT_ATTR: height_mm, S_ATTR: S, T_ATTR: T, TILE_ATTR: tile,
        "view_ids": view_ids, "held_out_view_ids": held_out_view_ids,
        "camera_centres_mm": camera_centres_mm, "calibration": calibration,
        UNITS_ATTR: {RADIANCE: "relative linear radiance (one global scale)",
                  NOISE: "relative sd of each observation (NaN: not recorded)",
                  DIRECTION: "unit vector toward the camera, surface frame",
                  "lengths": "mm"},
        "sampling": sampling, "marker_texels": marker_texels, "surface_id": surface_id,
        SOFTWARE_ATTR: software(), "config": config, RADIOMETRY_ATTR: radiometry or {},
    })


def finish_observation_map(final: Path, out: Path) -> None:
    """Mark a built map complete and move it to ``out`` (replacing it)."""
    zarr.open_group(final, mode="r+").attrs[COMPLETE_ATTR] = True
    if out.exists():
        shutil.rmtree(out)
    final.rename(out)


def write_observation_arrays(
    path: str | Path, radiance: np.ndarray, direction: np.ndarray | None, valid: np.ndarray,
    width_mm: float, height_mm: float, tile: int = default("observation.tile"),
    view_ids: list[str] | None = None,
    attrs: dict[str, Any] | None = None, noise: np.ndarray | None = None,
) -> Path:
    """Write in-memory observations (T, S, N, ...) as a complete observation map, e.g.
    for the 004 test set-ups of :mod:`parammap.synth.cases` (small maps only); ``noise``
    (T, S, N) relative sd per observation (NaN when not given). ``direction`` (T, S, N,
    3) is stored as given (set-ups whose directions come from no camera centre); None
    leaves it to the camera centres, which ``attrs`` must then hold
    (``camera_centres_mm``, (N, 3) mm)."""
    path = Path(path)
    T, S, N = valid.shape
    if direction is None and "camera_centres_mm" not in (attrs or {}):
        raise ObservationError(f"{path}: directions not given and no camera_centres_mm "
                               "to compute them from")
    tile = int(min(tile, S, T))
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    g = zarr.open_group(tmp, mode="w")
    comp = _compressor()
    if noise is None:
        noise = np.full(valid.shape, np.nan, np.float32)
    arrays = ((RADIANCE, encode_radiance(radiance)), (DIRECTION, direction),
              (VALID, valid), (NOISE, noise))
    for name, arr in arrays:
        if arr is not None:
            _create(g, name, arr.shape, (tile, tile) + arr.shape[2:], comp)[...] = arr
    g.attrs.update({WIDTH_ATTR: width_mm, HEIGHT_ATTR: height_mm, S_ATTR: S, T_ATTR: T,
                    TILE_ATTR: tile, "view_ids": view_ids or [f"v{n:03d}" for n in range(N)],
                    "held_out_view_ids": [], SOFTWARE_ATTR: software(),
                    **(attrs or {}), COMPLETE_ATTR: True})
    if path.exists():
        shutil.rmtree(path)
    tmp.rename(path)
    return path
