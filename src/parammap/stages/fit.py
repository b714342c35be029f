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
under a temporary name (``.<model>.zarr.partial``) and renamed when every tile is done;
a marker per finished tile (``.<model>.zarr.tiles/``) lets a killed fit resume: run
again with the same observation map and config, it fits only the tiles left, and the
finished store is identical to an uninterrupted run's.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import math
import multiprocessing
import os
import shutil
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import dask
import dask.array as da
import numpy as np
from dask.callbacks import Callback

from .. import __version__
from ..config import default
from ..conventions import SH_BAKED, SH_CAP_AWARE, SV_ALPHA, SVBRDF_MODEL, FitArray, FitStatus
from ..errors import InputError
from ..geometry import texel_centres
from ..models.lights import expand_lights
from ..models.mh import (
    ALGORITHMS,
    K_MAX_AUTO,
    REPAIR_FACTOR,
    REPAIR_RADIUS,
    REPAIR_STARTS,
    MhFitConfig,
    fit_mh_tile,
    mh_outputs,
    parse_lobes,
    repair_mh_tile,
    stains,
)
from ..models.radiometry import IrradianceGrid
from ..models.sh import fit_sh_tile, parse_sh_model, sh_outputs
from ..models.sh.bake import bake_outputs, bake_tile
from ..models.sh.cap import guard_steps
from ..models.svbrdf import MIN_OBS as SVBRDF_MIN_OBS
from ..models.svbrdf import (
    POOL_RADIUS,
    REFERENCE_MM,
    ambient_irradiance,
    fit_svbrdf_batch,
    fit_svbrdf_tile,
    pool_svbrdf_tile,
    refine_lights,
    svbrdf_outputs,
)
from ..models.svbrdf import light_weights as svbrdf_weights
from ..parallel import worker_initializer
from ..stores.common import mtime_ns
from ..stores.fit import (
    FitError,
    create_partial,
    finish,
    grid_attrs,
    mh_attrs,
    open_fit,
    partial_key,
    sh_attrs,
    svbrdf_attrs,
    tile_arrays,
)
from ..stores.lights import read_lights
from ..stores.metrics import digest, write_metrics
from ..stores.observation import open_observation_map, tile_observations, tile_reader
from ..stores.paths import Processed
from ..stores.radiometry import read_radiometry

logger = logging.getLogger(__name__)

__all__ = ["RepairFn", "fit_map", "fit_mh_map", "fit_sh_map", "fit_summary",
           "fit_svbrdf_map", "run_fit", "svbrdf_lights"]


# (radiance, direction, valid of a tile; keyword noise: its relative sd per observation)
TileFn = Callable[..., dict[str, np.ndarray]]
# (fit arrays of the tile and its halo, radiance, direction, valid of the tile, offset of
# the tile in the halo arrays; keyword noise as for TileFn; keyword halo_obs, where the
# function takes it: the radiance, direction, valid and noise of the tile and its halo)
# -> the tile's new arrays plus "changed", or None
RepairFn = Callable[..., dict[str, np.ndarray] | None]


def _marker(done_dir: str, name: str, block_info) -> Path:
    bi, bj, _ = block_info[0]["chunk-location"]
    return Path(done_dir) / f"{name}-{bi}-{bj}"


def _fit_block(valid: np.ndarray, block_info=None, *, obs_path: str, out_path: str,
               tile_fn: TileFn, done_dir: str, key: str = "", snapshot: bool = False,
               ) -> np.ndarray:
    (r0, r1), (c0, c1), _ = block_info[0]["array-location"]
    marker = _marker(done_dir, "fit", block_info)
    out = tile_arrays(out_path, key or done_dir)
    if marker.is_file():  # finished by an earlier, interrupted run
        return np.asarray(out[FitArray.STATUS][r0:r1, c0:c1], np.int8)
    g = tile_reader(obs_path)
    rad = g.radiance[r0:r1, c0:c1]
    dirs = g.direction[r0:r1, c0:c1]
    # observation maps built before the merge recorded noise have none
    kw = {"noise": g.noise[r0:r1, c0:c1]} if g.noise is not None else {}
    if _wants(tile_fn, "origin"):  # a model that needs its texels' positions
        kw["origin"] = (r0, c0)
    res = tile_fn(rad, dirs, np.asarray(valid), **kw)
    for name, arr in res.items():
        out[name][r0:r1, c0:c1] = arr
    if snapshot:
        # the tile pass's result as the repair pass reads it (its halo, and where the
        # tile starts from), untouched by the repairs written into the store meanwhile
        snap = _marker(done_dir, "snap", block_info).with_suffix(".npz")
        tmp = snap.with_name(snap.name + ".tmp")
        with tmp.open("wb") as f:
            np.savez(f, **res)
        tmp.replace(snap)
    marker.touch()  # only once every array of the tile is written
    return np.asarray(res[FitArray.STATUS], np.int8)


def _wants(fn: Callable, name: str) -> bool:
    try:
        return name in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def _snapshot(done_dir: str, rows: tuple[int, int], cols: tuple[int, int], tile: int,
              ) -> dict[str, np.ndarray]:
    """The tile pass's results over rows x cols of the map, from the snapshots its
    tiles left (:func:`_fit_block`)."""
    (R0, R1), (C0, C1) = rows, cols
    out: dict[str, np.ndarray] = {}
    for bi in range(R0 // tile, (R1 - 1) // tile + 1):
        for bj in range(C0 // tile, (C1 - 1) // tile + 1):
            y0, x0 = bi * tile, bj * tile
            with np.load(Path(done_dir) / f"snap-{bi}-{bj}.npz") as held:
                for name in held.files:
                    a = held[name]
                    if name not in out:
                        out[name] = np.empty((R1 - R0, C1 - C0) + a.shape[2:], a.dtype)
                    ys = slice(max(R0, y0), min(R1, y0 + a.shape[0]))
                    xs = slice(max(C0, x0), min(C1, x0 + a.shape[1]))
                    out[name][ys.start - R0:ys.stop - R0, xs.start - C0:xs.stop - C0] = \
                        a[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]
    return out


def _repair_block(valid: np.ndarray, block_info=None, *, obs_path: str, out_path: str,
                  repair_fn: RepairFn, halo: int, tile: int, done_dir: str, key: str = "",
                  ) -> np.ndarray:
    """One tile of the repair pass. It starts from the tile pass's results and reads
    its halo from them (the snapshots of :func:`_fit_block`), never from the repairs
    its neighbours write meanwhile: the tiles run at once, the result does not depend
    on their order, and a tile repaired again after an interruption gets the same."""
    (r0, r1), (c0, c1), _ = block_info[0]["array-location"]
    marker = _marker(done_dir, "repair", block_info)
    if marker.is_file():  # the texels it changed, as recorded when it finished
        return np.load(marker, allow_pickle=False)
    T, S = block_info[None]["shape"][:2]
    R0, R1, C0, C1 = max(r0 - halo, 0), min(r1 + halo, T), max(c0 - halo, 0), min(c1 + halo, S)
    fields = _snapshot(done_dir, (R0, R1), (C0, C1), tile)
    g = tile_reader(obs_path)
    kw = {"noise": g.noise[r0:r1, c0:c1]} if g.noise is not None else {}
    if _wants(repair_fn, "origin"):
        kw["origin"] = (r0, c0)
    if _wants(repair_fn, "halo_obs"):  # the halo's observations too
        kw["halo_obs"] = (g.radiance[R0:R1, C0:C1], g.direction[R0:R1, C0:C1],
                          np.asarray(g.valid[R0:R1, C0:C1]),
                          None if g.noise is None else g.noise[R0:R1, C0:C1])
    res = repair_fn(fields, g.radiance[r0:r1, c0:c1], g.direction[r0:r1, c0:c1],
                    np.asarray(valid), (r0 - R0, c0 - C0), **kw)
    changed = np.zeros((r1 - r0, c1 - c0), np.int8)
    if res is not None and np.any(res[FitArray.CHANGED]):
        out = tile_arrays(out_path, key or done_dir)
        for name, arr in res.items():
            if name != FitArray.CHANGED:
                out[name][r0:r1, c0:c1] = arr
        changed = np.asarray(res[FitArray.CHANGED], np.int8)
    with marker.open("wb") as f:
        np.save(f, changed)
    return changed


def _show_progress() -> bool:
    """A progress bar only where a person watches: stderr a terminal, not ``-q``."""
    return sys.stderr.isatty() and logger.isEnabledFor(logging.INFO)


class _LogProgress(Callback):
    """A log line at every tenth of a pass's tasks done, where no terminal shows a bar
    (a batch job's log: a lab map's SH fit runs for half an hour)."""

    def __init__(self, after_s: float = 10.0):
        super().__init__()
        self.after_s = after_s  # a shorter pass says nothing

    def _start(self, dsk):
        self._t0, self._shown = time.perf_counter(), 0

    def _posttask(self, key, result, dsk, state, worker_id):
        done = len(state["finished"])
        total = done + sum(len(state[k]) for k in ("ready", "waiting", "running"))
        tenth = 10 * done // max(total, 1)
        elapsed = time.perf_counter() - self._t0
        if tenth > self._shown and elapsed >= self.after_s:
            self._shown = tenth
            logger.info(f"fit: {10 * tenth} % of the pass ({done}/{total} tasks, "
                        f"{elapsed:.0f} s)")


START_METHODS = ("auto", "fork", "forkserver", "spawn")


def _mp_context(start_method: str = default("fit.start_method")):
    """The multiprocessing context of a fit's worker pool. ``auto``: ``fork`` on Linux,
    where a forked worker starts with the driver's imports and compiled kernels (a
    spawned one imports them again: about a second per fit on the demo, a sixth of its
    mh-auto time); elsewhere dask's configured context (``spawn``: fork is unsafe on
    macOS)."""
    if start_method not in START_METHODS:
        raise FitError(f"fit.start_method: unknown {start_method!r} "
                       f"(one of {', '.join(START_METHODS)})")
    if start_method == "auto":
        if sys.platform.startswith("linux"):
            return multiprocessing.get_context("fork")
        from dask.multiprocessing import get_context

        return get_context()
    return multiprocessing.get_context(start_method)


@contextlib.contextmanager
def _process_pool(scheduler: str, workers: int, start_method: str = default("fit.start_method")):
    """One process pool for every pass of a fit (tiles, then the repair passes): each new
    pool would start its workers again. None for the other schedulers."""
    if scheduler != "processes":
        yield None
        return

    from dask.multiprocessing import initialize_worker_process

    os.environ.setdefault("PYTHONHASHSEED", "6640")  # as dask's own pools (dask#6640)
    pool = ProcessPoolExecutor(workers, mp_context=_mp_context(start_method),
                               initializer=partial(initialize_worker_process,
                                                   user_initializer=worker_initializer()))
    try:
        yield pool
    finally:
        pool.shutdown(cancel_futures=True)


def _compute(x, scheduler: str, workers: int, pool=None):
    if scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://")):
        from dask.distributed import Client, progress

        with Client(scheduler) as client:
            fut = client.compute(x)
            if _show_progress():
                progress(fut)
            return fut.result()
    # chunksize 1: a tile is seconds of work, and dask's default (6 tasks a dispatch)
    # hands a map of a few tiles to one worker
    kw = {"processes": {"pool": pool, "chunksize": 1} if pool is not None else
          {"num_workers": workers, "initializer": worker_initializer(), "chunksize": 1},
          "threads": {"num_workers": workers}, "synchronous": {}}
    if scheduler not in kw:
        raise FitError(f"fit.scheduler: unknown scheduler {scheduler!r} (processes, threads, "
                       "synchronous or a tcp:// address)")
    bar = _LogProgress() if logger.isEnabledFor(logging.INFO) else contextlib.nullcontext()
    if _show_progress():
        from dask.diagnostics import ProgressBar

        bar = ProgressBar(minimum=2.0, out=sys.stderr)
    with bar:
        return x.compute(scheduler=scheduler, **kw[scheduler])


def fit_map(
    obs_path: str | Path,
    out_path: str | Path,
    tile_fn: TileFn,
    outputs: dict[str, tuple[tuple[int, ...], str, Any]],
    attrs: dict[str, Any],
    scheduler: str = default("fit.scheduler"),
    workers: int = default("workers"),
    repair_fn: RepairFn | None = None,
    halo: int = 4,
    start_method: str = default("fit.start_method"),
) -> dict[str, Any]:
    """Apply ``tile_fn`` to every texel tile of an observation map into a zarr store.

    With ``repair_fn`` a second pass follows once every tile is fitted: each tile sees
    its neighbours' results (``halo`` texels around it) and may refit texels that stand
    out from them (e.g. stuck in a poor local minimum). Every tile reads its halo from
    the tile pass's results (snapshots beside the store), so all tiles are repaired at
    once and the result does not depend on their order.

    Parameters
    ----------
    obs_path : the observation map (``observation.zarr``).
    out_path : the fit store to write (``fit/<model>.zarr``), replaced atomically.
    tile_fn : (radiance (t, u, N, 3), direction (t, u, N, 3), valid (t, u, N)) ->
        dict of (t, u, ...) arrays, one per entry of ``outputs`` (``status`` included).
    outputs : name -> (trailing shape, dtype, fill value).
    attrs : model description stored as group attributes.
    start_method : how the ``processes`` scheduler starts its workers
        (:func:`_mp_context`).

    Returns
    -------
    dict with ``texels``, ``seconds``, ``texels_per_second`` and ``status`` (the (T, S)
    int8 map of status codes).
    """
    obs = open_observation_map(obs_path)
    T, S, N = obs.shape
    tile = fit_tile_size(T, S, obs.tile, workers)
    out_path = Path(out_path)
    # A partial store under a fixed name, with a marker per finished tile beside it: a
    # killed run resumes where it stopped when the same fit of the same observation map
    # runs again; anything else starts afresh.
    tmp = out_path.with_name(f".{out_path.name}.partial")
    done = out_path.with_name(f".{out_path.name}.tiles")
    key = digest({"attrs": attrs, "outputs": {k: [list(v[0]), v[1], v[2]]
                                              for k, v in outputs.items()},
                  "observation": obs.metadata, "shape": [T, S, N],
                  "observation_mtime_ns": mtime_ns(Path(obs_path) / "zarr.json"),
                  # a partial store of the four-phase repair (no snapshots) starts afresh
                  "repair": "snapshot halo" if repair_fn is not None else False,
                  "tile": tile, "software": __version__})
    valid = da.from_zarr(obs.valid, chunks=(tile, tile, N))
    ntiles = len(valid.chunks[0]) * len(valid.chunks[1])
    _resume_or_create(tmp, done, key, ntiles, outputs, (T, S, tile),
                      {**attrs, **grid_attrs(obs, tile)})
    logger.info(f"fit: {T}x{S} texels, {N} views, {ntiles} tiles, scheduler {scheduler}, "
                f"{workers} workers")
    status = valid.map_blocks(
        _fit_block, obs_path=str(obs_path), out_path=str(tmp), tile_fn=tile_fn,
        done_dir=str(done), key=key, snapshot=repair_fn is not None, drop_axis=2,
        dtype=np.int8, meta=np.array((), np.int8), chunks=valid.chunks[:2])
    t0 = time.perf_counter()
    with dask.config.set({"optimization.fuse.active": False}), \
            _process_pool(scheduler, workers, start_method) as pool:
        status = np.asarray(_compute(status, scheduler, workers, pool))
        repaired = 0
        if repair_fn is not None:
            ch = valid.map_blocks(
                _repair_block, obs_path=str(obs_path), out_path=str(tmp),
                repair_fn=repair_fn, halo=halo, tile=tile, done_dir=str(done), key=key,
                drop_axis=2, dtype=np.int8, meta=np.array((), np.int8),
                chunks=valid.chunks[:2])
            repaired = int(np.asarray(_compute(ch, scheduler, workers, pool)).sum())
            status = tile_arrays(str(tmp), key)[FitArray.STATUS][:]
            logger.info(f"fit: repair pass refitted {repaired} texels from their neighbours")
    seconds = time.perf_counter() - t0
    finish(tmp, out_path)
    shutil.rmtree(done, ignore_errors=True)
    logger.info(f"fit: {T * S} texels in {seconds:.1f} s ({T * S / seconds:.1f} texels/s)")
    return {"texels": T * S, "seconds": seconds, "texels_per_second": T * S / seconds,
            "status": status, "repaired": repaired}


def fit_tile_size(T: int, S: int, tile: int, workers: int, smallest: int = 8) -> int:
    """Texels across a fit task: the observation map's tile, halved (down to
    ``smallest``) while the map has fewer than four tasks per worker. A map of a few
    tiles otherwise leaves workers idle behind the slowest tile (the demo's 64 x 64 map:
    four tiles of 32, 16 of 16)."""
    b = tile
    while (b // 2 >= smallest and b % 2 == 0
           and math.ceil(T / b) * math.ceil(S / b) < 4 * max(workers, 1)):
        b //= 2
    return b


def _resume_or_create(tmp: Path, done: Path, key: str, ntiles: int,
                      outputs: dict[str, tuple[tuple[int, ...], str, Any]],
                      grid: tuple[int, int, int], attrs: dict[str, Any]) -> None:
    """Keep the partial store of an interrupted run of this very fit (``key``), or start
    a new one."""
    if tmp.is_dir() and done.is_dir():
        if partial_key(tmp) == key:
            n = len(list(done.glob("fit-*")))
            logger.info(f"fit: resuming an interrupted run, {n} of {ntiles} tiles done")
            return
        logger.info("fit: a partial store of another input or config is there; starting "
                    "afresh")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.rmtree(done, ignore_errors=True)
    done.mkdir(parents=True)
    create_partial(tmp, key, outputs, grid, attrs)


def fit_summary(out_path: str | Path, res: dict[str, Any], name: str,
                **extra: Any) -> dict[str, Any]:
    """Figures of a finished fit for its metrics file: texels fitted, too few
    observations (status 2) and failed (3), speed, the mean / median of the per-texel
    mean percentage residual and RMSE per channel, and the median reduced chi-square
    (residuals against the expected noise; about 1 where the model explains all but
    the noise)."""
    g = open_fit(out_path)
    status = g[FitArray.STATUS][:]
    ok = status == FitStatus.OK
    mpr, rmse = g[FitArray.MPR][:][ok], g[FitArray.RMSE][:][ok]
    return {
        "model": name, "texels": res["texels"], "fitted": int(ok.sum()),
        "too_few_observations": int((status == FitStatus.TOO_FEW).sum()),
        "failed": int((status == FitStatus.FAILED).sum()),
        "seconds": res["seconds"], "texels_per_second": res["texels_per_second"],
        "mean_percentage_residual": np.nanmean(mpr, 0).tolist() if ok.any() else None,
        "median_percentage_residual": np.nanmedian(mpr, 0).tolist() if ok.any() else None,
        FitArray.RMSE: np.nanmean(rmse, 0).tolist() if ok.any() else None,
        "chi2_median": _nanmedian(g[FitArray.CHI2][:][ok]) if FitArray.CHI2 in g else None,
        **extra,
    }


def _nanmedian(x: np.ndarray) -> float | None:
    """Median of the finite values (None when there are none: e.g. no noise recorded)."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else None


# ---------------------------------------------------------------------------------
# Map drivers of the models (numerics in parammap.models)


def fit_mh_map(obs_path: str | Path, out_path: str | Path, K: int | str, cfg: dict,
               scheduler: str = default("fit.scheduler"), workers: int = default("workers"),
               start_method: str = default("fit.start_method")) -> dict:
    """Fit the MH model with K lobes (or ``auto``) to every texel of an observation map
    into ``fit/mh-<K>.zarr``; returns the figures for ``metrics/fit-mh-<K>.json``."""
    K = parse_lobes(K)
    fcfg = MhFitConfig(**{k: cfg[k] for k in MhFitConfig.__dataclass_fields__ if k in cfg})
    if fcfg.algorithm not in ALGORITHMS:
        raise InputError(f"fit.mh.algorithm: unknown {fcfg.algorithm!r} "
                         f"(one of {', '.join(ALGORITHMS)})")
    K_max = cfg.get("K_max", K_MAX_AUTO) if K == "auto" else K
    pool = bool(cfg.get("pool_shininess", default("fit.mh.pool_shininess")))
    lobes = bool(cfg.get("pool_lobes", default("fit.mh.pool_lobes")))
    repair = partial(repair_mh_tile, K=K, cfg=fcfg, pool=pool, lobes=lobes) \
        if cfg.get("repair", default("fit.mh.repair")) else None
    res = fit_map(obs_path, out_path, partial(fit_mh_tile, K=K, cfg=fcfg, K_max=K_max),
                  mh_outputs(K_max),
                  mh_attrs(K, K_max,
                           fit={k: getattr(fcfg, k) for k in MhFitConfig.__dataclass_fields__},
                           repair={"factor": REPAIR_FACTOR, "radius": REPAIR_RADIUS,
                                   "starts": REPAIR_STARTS, "pool_shininess": pool,
                                   "pool_lobes": lobes}
                           if repair else None),
                  scheduler, workers, repair_fn=repair, halo=REPAIR_RADIUS,
                  start_method=start_method)
    g = open_fit(out_path)
    ok = g[FitArray.STATUS][:] == FitStatus.OK
    kused = g[FitArray.K_USED][:][ok]
    if K == "auto" and len(kused):
        # BIC may have wanted more where the cap bound: say so, and where to raise it
        logger.info(f"fit: {100 * np.mean(kused == K_max):.1f} % of the texels use all "
                    f"{K_max} lobes auto may (fit.mh.K_max)")
    return fit_summary(
        out_path, res, f"mh-{K}", scheduler=scheduler, workers=workers,
        lobes_used={str(k): int((kused == k).sum()) for k in np.unique(kused)},
        repaired_texels=int(res.get("repaired", 0)),
        largest_stain_texels=int(next(iter(stains(g[FitArray.RMSE][:],
                                                  g[FitArray.STATUS][:])), 0)),
        mean_evals=float(g[FitArray.EVALS][:][ok].mean()) if ok.any() else None)


def fit_sh_map(obs_path: str | Path, out_path: str | Path, hemisphere: str, n: int,
               cfg: dict, scheduler: str = default("fit.scheduler"),
               workers: int = default("workers"),
               start_method: str = default("fit.start_method")) -> dict:
    """Project every texel of an observation map onto n SH bands into
    ``fit/sh-<hemisphere>-<n^2>.zarr``; returns the figures for its metrics file."""
    reg = cfg.get("regularisation", default("fit.sh.regularisation"))
    reg = reg if reg == "auto" else float(reg)
    cap = bool(cfg.get("sampled_cap", default("fit.sh.sampled_cap"))) \
        and hemisphere in SH_CAP_AWARE
    areas = cfg.get("solid_angles", default("fit.sh.solid_angles"))
    shrink = cap and bool(cfg.get("shrink", default("fit.sh.shrink")))
    robust = cap and bool(cfg.get("robust", default("fit.sh.robust")))
    gamma = open_observation_map(obs_path).display_gamma() \
        if cap and cfg.get("display_weights", default("fit.sh.display_weights")) else None
    res = fit_map(obs_path, out_path,
                  partial(fit_sh_tile, n=n, hemisphere=hemisphere, reg=reg,
                          sampled_cap=cap, areas=areas, shrink=shrink, robust=robust,
                          display_gamma=gamma),
                  sh_outputs(n),
                  sh_attrs(hemisphere, n, cap, areas,
                           reg if hemisphere in ("rlsop", "wls") else None, shrink, robust,
                           gamma),
                  scheduler, workers, start_method=start_method)
    extra = {}
    if cap:
        g = open_fit(out_path)
        ok = g[FitArray.STATUS][:] == FitStatus.OK
        lam, esc = g[FitArray.REG][:][ok], g[FitArray.GUARD][:][ok]
        extra = {"sampled_cap": True,
                 "regularisation_median": float(np.median(lam)) if ok.any() else None,
                 "guarded_texels": int((esc > 0).sum()),
                 "guard_unresolved_texels": int((esc > guard_steps(hemisphere)).sum()),
                 "bands_median": float(np.median(g[FitArray.BANDS][:][ok]))
                 if ok.any() else None}
        if robust and ok.any():
            extra |= {"robust_share_median": float(np.median(g[FitArray.ROBUST][:][ok]))}
        if shrink and ok.any():
            a = g[FitArray.SHRINK][:][ok]
            extra |= {"shrink_median": float(np.median(a)),
                      "shrunk_to_mean_texels": int((a < 0.5).sum())}
    return fit_summary(out_path, res, f"sh-{hemisphere}-{n * n}", scheduler=scheduler,
                       workers=workers, **extra)


def _bake_block(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray, *,
                origin: tuple[int, int], source: str, n: int, gamma: float,
                noise: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """:func:`parammap.models.sh.bake.bake_tile` of one tile, its MH parameters read
    from the ``source`` fit store."""
    (r0, c0), (t, u) = origin, radiance.shape[:2]
    src = open_fit(source)
    P = np.asarray(src[FitArray.PARAMS][r0:r0 + t, c0:c0 + u])
    ok = np.asarray(src[FitArray.STATUS][r0:r0 + t, c0:c0 + u]) == FitStatus.OK
    return bake_tile(radiance, direction, valid, P, ok, n, gamma)


def bake_sh_map(obs_path: str | Path, out_path: str | Path, source_path: str | Path,
                n: int, scheduler: str = default("fit.scheduler"),
                workers: int = default("workers"),
                start_method: str = default("fit.start_method")) -> dict:
    """Bake every texel's MH fit (the store at ``source_path``) onto n SH bands over its
    sampled cap, in the values shown (:mod:`parammap.models.sh.bake`), into
    ``fit/sh-mh-<n^2>.zarr``; returns the figures for its metrics file."""
    src = open_fit(source_path)
    if src.model != "mh":
        raise InputError(f"fit.sh.source: {Path(source_path).name} is not an MH fit")
    gamma = open_observation_map(obs_path).display_gamma()
    res = fit_map(obs_path, out_path,
                  partial(_bake_block, source=str(source_path), n=n, gamma=gamma),
                  bake_outputs(n),
                  sh_attrs("mh", n, True, "spherical", None, display_gamma=gamma)
                  | {"source": Path(source_path).stem},
                  scheduler, workers, start_method=start_method)
    return fit_summary(out_path, res, f"sh-mh-{n * n}", scheduler=scheduler,
                       workers=workers, source=Path(source_path).stem)


REFINE_TEXELS = 1024  # of the pilot's, drawn at random: the texels that place the lights
REFINE_OBSERVATIONS = 50_000  # and at most this many texel views (the refinement's cost)
PILOT_TILES = 128  # tiles the pilot's texels come from


def svbrdf_lights(obs_path: str | Path, lights_mm: np.ndarray,
                  texels: int = default("fit.svbrdf.pilot_texels"), refine: bool = True,
                  seed: int = 0, irradiance: IrradianceGrid | None = None,
                  extents: list | None = None, measured_mm: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The lights an svbrdf fit is made under, from a pilot of up to ``texels`` texels
    from tiles across the map: their positions refined from the found ones
    (:func:`parammap.models.svbrdf.refine_lights`, with ``refine``) and their (J, 3)
    relative intensities (the first's 1), each texel given a specular amplitude per
    light and their ratios pooled (:func:`parammap.models.svbrdf.light_weights`).
    ``irradiance``: the flat-field's, put back into the observations (the lights'
    fall-off is the model's). ``extents``: per light None or its shape, an area light
    (:func:`parammap.models.lights.expand_lights`, facing the surface's centre unless it
    states its normal). ``measured_mm``: (J, 3) the lab's measured centres (the found
    ones where none was), a second start for the refinement. Returns positions (J, 3)
    mm (the area lights' centres),
    intensities and a record for the metrics."""
    obs = open_observation_map(obs_path)
    target = np.array([obs.width_mm / 2, obs.height_mm / 2, 0.0])
    rng = np.random.default_rng(seed)
    # texels from many tiles, a few from each: the highlights' positions over the whole
    # map place the lights
    tiles = obs.sample_tiles(PILOT_TILES, seed)
    each = max(1, math.ceil(texels / len(tiles)))
    parts = []
    for rows, cols in tiles:
        V, L, W, w = tile_observations(obs, rows, cols)
        pts = texel_centres(obs.S, obs.T, obs.width_mm, obs.height_mm,
                            np.arange(rows.start, rows.stop),
                            np.arange(cols.start, cols.stop)).reshape(-1, 3)
        keep = np.flatnonzero(W.sum(1) >= SVBRDF_MIN_OBS)
        keep = rng.permutation(keep)[:each]
        if irradiance is not None:
            L = L * irradiance(pts)[:, None, None]
        parts.append((V[keep], L[keep], w[keep], pts[keep]))
    V, L, w, pts = (np.concatenate(a)[:texels] for a in zip(*parts, strict=True))
    record: dict[str, Any] = {"found_mm": np.round(lights_mm, 3).tolist(), "pilot_texels": len(V)}
    if refine:
        t0 = time.perf_counter()
        views = float((w > 0).sum(1).mean())
        top = rng.permutation(len(L))[:max(64, min(REFINE_TEXELS,
                                                   int(REFINE_OBSERVATIONS / views)))]
        lights_mm, rec = refine_lights(L[top], V[top], w[top], pts[top], lights_mm,
                                       extents=extents, target_mm=target,
                                       also_from=measured_mm)
        record |= {"refined_mm": np.round(lights_mm, 3).tolist(), **rec,
                   "refine_texels": len(top), "views_per_texel": views,
                   "seconds": time.perf_counter() - t0}
        logger.info(f"fit: lights refined to {np.round(lights_mm, 1).tolist()} mm "
                    f"(pilot residual {rec['start']:.4g} -> {rec['final']:.4g}, "
                    f"{rec['evaluations']} evaluations)")
    weights = np.ones((len(lights_mm), 3))
    if len(lights_mm) > 1:
        points, group = expand_lights(lights_mm, extents, target)
        r = fit_svbrdf_batch(L, V, w, pts, points, None, group=group)
        weights = svbrdf_weights(r["ks"], r["stdev_ks"])
    return lights_mm, weights, record


def fit_svbrdf_map(obs_path: str | Path, out_path: str | Path, lights_path: str | Path,
                   radiometry_path: str | Path | None,
                   cfg: dict, scheduler: str = default("fit.scheduler"),
                   workers: int = default("workers"),
                   start_method: str = default("fit.start_method")) -> dict:
    """Fit the microfacet SVBRDF (:mod:`parammap.models.svbrdf`) to every texel of an
    observation map under the lights of ``lights_path`` (``camera/lights.yaml``) into
    ``fit/svbrdf-ggx.zarr``; returns the figures for its metrics file. Where the
    capture's flat-field (``radiometry_path``, ``camera/radiometry.json``; None or
    missing: none) divided the lights' fall-off out of the observations, it is put back:
    the model's lights fall off themselves."""
    doc = read_lights(lights_path)
    rad = read_radiometry(radiometry_path if radiometry_path and Path(radiometry_path).is_file()
                          else None)
    obs = open_observation_map(obs_path)
    refine = cfg.get("refine_lights", default("fit.svbrdf.refine_lights"))
    extents = [lt.get("extent") for lt in doc["lights"]]
    measured = None
    if any("measured_mm" in lt for lt in doc["lights"]):
        measured = np.array([lt.get("measured_mm", lt["position_mm"]) for lt in doc["lights"]],
                            float)
    if doc["lights"]:
        lights_mm = np.array([lt["position_mm"] for lt in doc["lights"]], float)
    else:  # a matte surface, or lobes that meet nowhere: the run goes on
        lights_mm = np.array([[obs.width_mm / 2, obs.height_mm / 2, REFERENCE_MM]])
        refine = False
        logger.warning(f"fit: {lights_path} lists no light (see metrics/lights.json); "
                       f"{SVBRDF_MODEL} is fitted under a nominal light {REFERENCE_MM:g} mm "
                       "above the surface's centre, where it is not relightable")
    irradiance = None if rad.irradiance is None else IrradianceGrid(
        rad.irradiance, obs.width_mm, obs.height_mm)
    lights_mm, weights, record = svbrdf_lights(
        obs_path, lights_mm, cfg.get("pilot_texels", default("fit.svbrdf.pilot_texels")),
        refine, irradiance=irradiance, extents=extents, measured_mm=measured)
    record["nominal"] = not doc["lights"]
    lamps = None
    if any(extents):  # from here on the models see each area light as its points
        points, group = expand_lights(lights_mm, extents,
                                      np.array([obs.width_mm / 2, obs.height_mm / 2, 0.0]))
        lamps = (lights_mm, weights, extents)
        record["area_points"] = group.astype(bool).sum(0).tolist()
        logger.info(f"fit: area lights drawn as {record['area_points']} points")
        lights_mm, weights = points, group @ weights
    ambient = None
    if doc.get("ambient"):  # the room's light, measured against the lamps' at one point
        amb = doc["ambient"]
        ambient = ambient_irradiance(amb["share"], np.r_[amb["at_mm"], 0.0], lights_mm,
                                     weights)
        record["ambient"] = np.round(ambient, 6).tolist()
    shown = lamps[:2] if lamps else (lights_mm, weights)
    logger.info(f"fit: {SVBRDF_MODEL} under {len(shown[0])} light(s) at "
                f"{np.round(shown[0], 1).tolist()} mm, relative intensities "
                f"{np.round(shown[1], 3).tolist()}"
                + ("" if ambient is None else
                   f", the room's ambient irradiance {np.round(ambient, 4).tolist()}"))
    geom = {"grid": (obs.S, obs.T, obs.width_mm, obs.height_mm), "lights_mm": lights_mm,
            "weights": weights, "irradiance": irradiance, "ambient": ambient}
    pool = bool(cfg.get("pool_neighbours", default("fit.svbrdf.pool_neighbours")))
    res = fit_map(obs_path, out_path, partial(fit_svbrdf_tile, **geom), svbrdf_outputs(),
                  svbrdf_attrs(lights_mm, weights, irradiance, ambient, lamps,
                               lights_source=doc.get("source"),
                               pool_radius=POOL_RADIUS if pool else 0),
                  scheduler, workers, start_method=start_method,
                  repair_fn=partial(pool_svbrdf_tile, **geom) if pool else None,
                  halo=POOL_RADIUS)
    g = open_fit(out_path)
    ok = g[FitArray.STATUS][:] == FitStatus.OK
    alpha = g[FitArray.PARAMS][:][ok][:, SV_ALPHA]
    return fit_summary(out_path, res, SVBRDF_MODEL, scheduler=scheduler, workers=workers,
                       lights=len(shown[0]), light_weights=np.round(shown[1], 4).tolist(),
                       light_positions=record, pooled_texels=int(res.get("repaired", 0)),
                       alpha_median=float(np.median(alpha)) if alpha.size else None)


def run_fit(source: str | Path, processed: str | Path, config: dict[str, Any], *,
            model: str, workers: int | None = None) -> dict[str, Any]:
    """The fit stage of one model (``mh-<K>``, ``mh-auto``, ``sh-<hemisphere>-<n^2>`` or
    ``svbrdf-ggx``, which needs the lights stage's ``camera/lights.yaml``):
    ``fit/<model>.zarr`` from the observation map with the whole (validated) ``config``
    (section ``fit``) and ``metrics/fit-<model>.json``. Returns the metrics; its
    figures come from :mod:`parammap.stages.figures`."""
    src, proc = Processed(source), Processed(processed)
    cfg = config["fit"]
    workers = workers or cfg["workers"] or config["workers"]
    if model.startswith("mh-"):
        K = parse_lobes(model[3:])
        name, fit, args, family = f"mh-{K}", fit_mh_map, (K,), "mh"
    elif model == SVBRDF_MODEL:
        name, fit, args, family = (model, fit_svbrdf_map, (proc.lights, proc.radiometry),
                                   "svbrdf")
    else:
        hemi, n = parse_sh_model(model)
        name, fit, args, family = f"sh-{hemi}-{n * n}", fit_sh_map, (hemi, n), "sh"
    if model.startswith("sh-") and hemi in SH_BAKED:
        m = bake_sh_map(src.observation, proc.fit(name), proc.fit(cfg["sh"]["source"]), n,
                        cfg["scheduler"], workers, cfg["start_method"])
    else:
        m = fit(src.observation, proc.fit(name), *args, cfg[family], cfg["scheduler"],
                workers, cfg["start_method"])
    write_metrics(proc.metrics(f"fit-{name}"), m)
    logger.info(f"fit: {name} mean % residual {m['mean_percentage_residual']}, "
                f"{m['failed']} failed, {m['texels_per_second']:.1f} texels/s")
    return m
