"""Fit a per-texel model over the whole observation map, in parallel over texel tiles.

One dask ``map_blocks`` over the observation map's ``valid`` array (chunks = texel tiles
with all views): each task reads its tile's radiance and directions from the zarr
store, fits, and writes its region of every output array itself, so every write covers
whole zarr chunks of the output (created up front with the same tiles) and no two tasks
touch one chunk (pitfalls.md). The task returns the tile's status codes, which the
driver gathers for the metrics.

The scheduler comes from config: ``processes`` (default; nlopt callbacks hold the GIL),
``threads``, ``synchronous``, or the address of a dask.distributed scheduler
(``tcp://host:8786``) for a cluster, with no code change. The whole store is written
under a temporary name and renamed when every tile is done.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import dask
import dask.array as da
import numpy as np
import zarr

from . import __version__
from .conventions import FitStatus
from .errors import InputError
from .observation import open_observation_map
from .stores import COMPLETE_ATTR, open_complete

__all__ = ["COMPLETE_ATTR", "FitError", "RepairFn", "fit_map", "fit_summary", "open_fit"]

# (radiance, direction, valid of a tile; keyword noise: its relative sd per observation)
TileFn = Callable[..., dict[str, np.ndarray]]
# (fit arrays of the tile and its halo, radiance, direction, valid of the tile, offset of
# the tile in the halo arrays) -> the tile's new arrays plus "changed", or None
RepairFn = Callable[..., dict[str, np.ndarray] | None]


class FitError(InputError):
    """A missing, incomplete or mismatched fit store, or a bad fit setting."""


def _fit_block(valid: np.ndarray, block_info=None, *, obs_path: str, out_path: str,
               tile_fn: TileFn) -> np.ndarray:
    (r0, r1), (c0, c1), _ = block_info[0]["array-location"]
    g = zarr.open_group(obs_path, mode="r")
    rad = g["radiance"][r0:r1, c0:c1]
    dirs = g["direction"][r0:r1, c0:c1]
    # observation maps built before the merge recorded noise have no "noise" array
    kw = {"noise": g["noise"][r0:r1, c0:c1]} if "noise" in g else {}
    res = tile_fn(rad, dirs, np.asarray(valid), **kw)
    out = zarr.open_group(out_path, mode="r+")
    for name, arr in res.items():
        out[name][r0:r1, c0:c1] = arr
    return np.asarray(res["status"], np.int8)


def _repair_block(valid: np.ndarray, block_info=None, *, obs_path: str, out_path: str,
                  repair_fn: RepairFn, halo: int, phase: tuple[int, int]) -> np.ndarray:
    """One tile of the repair pass: only tiles of this checkerboard ``phase`` work, so
    no tile rewrites what a neighbour is reading as its halo."""
    (r0, r1), (c0, c1), _ = block_info[0]["array-location"]
    bi, bj, _ = block_info[0]["chunk-location"]
    changed = np.zeros((r1 - r0, c1 - c0), np.int8)
    if (bi % 2, bj % 2) != phase:
        return changed
    out = zarr.open_group(out_path, mode="r+")
    T, S = out["status"].shape
    R0, R1, C0, C1 = max(r0 - halo, 0), min(r1 + halo, T), max(c0 - halo, 0), min(c1 + halo, S)
    fields = {name: out[name][R0:R1, C0:C1] for name in out.array_keys()}
    g = zarr.open_group(obs_path, mode="r")
    res = repair_fn(fields, g["radiance"][r0:r1, c0:c1], g["direction"][r0:r1, c0:c1],
                    np.asarray(valid), (r0 - R0, c0 - C0))
    if res is None:
        return changed
    for name, arr in res.items():
        if name != "changed":
            out[name][r0:r1, c0:c1] = arr
    return np.asarray(res["changed"], np.int8)


def _compute(x, scheduler: str, workers: int):
    if scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://")):
        from dask.distributed import Client

        with Client(scheduler):
            return x.compute()
    if scheduler == "processes":
        return x.compute(scheduler="processes", num_workers=workers)
    if scheduler == "threads":
        return x.compute(scheduler="threads", num_workers=workers)
    if scheduler == "synchronous":
        return x.compute(scheduler="synchronous")
    raise FitError(f"fit.scheduler: unknown scheduler {scheduler!r} (processes, threads, "
                   "synchronous or a tcp:// address)")


def fit_map(
    obs_path: str | Path,
    out_path: str | Path,
    tile_fn: TileFn,
    outputs: dict[str, tuple[tuple[int, ...], str, Any]],
    attrs: dict[str, Any],
    scheduler: str = "processes",
    workers: int = 2,
    log=print,
    repair_fn: RepairFn | None = None,
    halo: int = 4,
) -> dict[str, Any]:
    """Apply ``tile_fn`` to every texel tile of an observation map into a zarr store.

    With ``repair_fn`` a second pass follows once every tile is fitted: each tile sees
    its neighbours' results (``halo`` texels around it) and may refit texels that stand
    out from them (e.g. stuck in a poor local minimum). Tiles run in four checkerboard
    phases, so no tile is rewritten while a neighbour reads it.

    Parameters
    ----------
    obs_path : the observation map (``observation.zarr``).
    out_path : the fit store to write (``fit/<model>.zarr``), replaced atomically.
    tile_fn : (radiance (t, u, N, 3), direction (t, u, N, 3), valid (t, u, N)) ->
        dict of (t, u, ...) arrays, one per entry of ``outputs`` (``status`` included).
    outputs : name -> (trailing shape, dtype, fill value).
    attrs : model description stored as group attributes.

    Returns
    -------
    dict with ``texels``, ``seconds``, ``texels_per_second`` and ``status`` (the (T, S)
    int8 map of status codes).
    """
    obs = open_observation_map(obs_path)
    T, S, N = obs["valid"].shape
    tile = obs.attrs["tile"]
    out_path = Path(out_path)
    tmp = out_path.with_name(f".{out_path.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    g = zarr.open_group(tmp, mode="w")
    comp = zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")
    for name, (shape, dtype, fill) in outputs.items():
        # dimension names let xarray.open_zarr label the maps
        dims = ("row", "col") + tuple(f"{name}_{k}" for k in range(len(shape)))
        g.create_array(name, shape=(T, S) + tuple(shape), chunks=(tile, tile) + tuple(shape),
                       dtype=dtype, compressors=comp, fill_value=fill, dimension_names=dims)
    g.attrs.update({**attrs, "S": S, "T": T, "tile": tile,
                    "width_mm": obs.attrs["width_mm"], "height_mm": obs.attrs["height_mm"],
                    "observation_views": len(obs.attrs["view_ids"]),
                    "software": f"parammap {__version__}"})
    valid = da.from_zarr(obs["valid"])
    ntiles = len(valid.chunks[0]) * len(valid.chunks[1])
    log(f"fit: {T}x{S} texels, {N} views, {ntiles} tiles, scheduler {scheduler}, "
        f"{workers} workers")
    status = valid.map_blocks(
        _fit_block, obs_path=str(obs_path), out_path=str(tmp), tile_fn=tile_fn,
        drop_axis=2, dtype=np.int8, meta=np.array((), np.int8),
        chunks=valid.chunks[:2])
    t0 = time.perf_counter()
    try:
        with dask.config.set({"optimization.fuse.active": False}):
            status = np.asarray(_compute(status, scheduler, workers))
            repaired = 0
            if repair_fn is not None:
                for phase in ((0, 0), (0, 1), (1, 0), (1, 1)):
                    ch = valid.map_blocks(
                        _repair_block, obs_path=str(obs_path), out_path=str(tmp),
                        repair_fn=repair_fn, halo=halo, phase=phase, drop_axis=2,
                        dtype=np.int8, meta=np.array((), np.int8), chunks=valid.chunks[:2])
                    repaired += int(np.asarray(_compute(ch, scheduler, workers)).sum())
                status = g["status"][:]
                log(f"fit: repair pass refitted {repaired} texels from their neighbours")
        seconds = time.perf_counter() - t0
        g.attrs[COMPLETE_ATTR] = True
        if out_path.exists():
            shutil.rmtree(out_path)
        out_path.parent.mkdir(parents=True, exist_ok=True)
        tmp.rename(out_path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log(f"fit: {T * S} texels in {seconds:.1f} s ({T * S / seconds:.1f} texels/s)")
    return {"texels": T * S, "seconds": seconds, "texels_per_second": T * S / seconds,
            "status": status, "repaired": repaired}


def open_fit(path: str | Path) -> zarr.Group:
    """Open a finished fit store; refuses a missing or incomplete one."""
    return open_complete(path, FitError, "fit store")


def fit_summary(out_path: str | Path, res: dict[str, Any], name: str,
                **extra: Any) -> dict[str, Any]:
    """Figures of a finished fit for its metrics file: texels fitted, too few
    observations (status 2) and failed (3), speed, the mean / median of the per-texel
    mean percentage residual and RMSE per channel, and the median reduced chi-square
    (residuals against the expected noise; about 1 where the model explains all but
    the noise)."""
    g = open_fit(out_path)
    status = g["status"][:]
    ok = status == FitStatus.OK
    mpr, rmse = g["mpr"][:][ok], g["rmse"][:][ok]
    return {
        "model": name, "texels": res["texels"], "fitted": int(ok.sum()),
        "too_few_observations": int((status == FitStatus.TOO_FEW).sum()),
        "failed": int((status == FitStatus.FAILED).sum()),
        "seconds": res["seconds"], "texels_per_second": res["texels_per_second"],
        "mean_percentage_residual": np.nanmean(mpr, 0).tolist() if ok.any() else None,
        "median_percentage_residual": np.nanmedian(mpr, 0).tolist() if ok.any() else None,
        "rmse": np.nanmean(rmse, 0).tolist() if ok.any() else None,
        "chi2_median": _nanmedian(g["chi2"][:][ok]) if "chi2" in g else None, **extra,
    }


def _nanmedian(x: np.ndarray) -> float | None:
    """Median of the finite values (None when there are none: e.g. no noise recorded)."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else None
