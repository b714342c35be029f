"""Benchmark: what a lab's full-resolution capture costs (issue 47), from measured rates.

Three measurements, each in its own processes, and a cost table built from them:

``hdr``
    Peak resident memory and time of merging one 24 MP bracket (6000 x 4000, three
    exposures through a recovered-looking response) in strips of rows, as the HDR stage
    does, and, for comparison, in one piece.
``scaling``
    The MH fit's throughput (texels per second) on an observation map with a dask
    ``LocalCluster`` of 1 and of 2 single-threaded worker processes.
``store``
    Bytes on disk per texel and view of an observation map and its encoding error
    against the photos' recorded noise.

The cost table extrapolates the measured per-texel-view rates of the observation build
and the fits to a 4096 x 4096 map seen from 300 views on N workers (node-hours, one
worker a core). Needs a processed capture with an observation map, e.g. the demo after
``make demo``::

    python benchmarks/lab_scale.py data/processed/demo --workdir data/bench/lab

Writes ``<workdir>/lab_scale.json`` and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _scratch import scratch_processed
from big_map import _watch

HDR_CHILD = r"""
import json, resource, sys, time
import numpy as np
import parammap.stages.hdr as hdr
H, W, strips = 4000, 6000, sys.argv[1] == "strips"
if not strips:
    hdr.MERGE_STRIP_PIXELS = H * W
rng = np.random.default_rng(0)
lev = np.arange(256)
g = np.log(np.clip(((lev + 0.5) / 256) ** 2.2, 1e-6, None))  # a gamma-like response
g = np.repeat((g - g[128])[:, None], 3, 1)
t = np.array([4.0, 1.0, 0.25])
stack = np.empty((3, H, W, 3), np.uint8)
for r0 in range(0, H, 250):  # the photos made a strip at a time: only they stay
    y, x = np.mgrid[r0:r0 + 250, 0:W].astype(np.float32)
    X = np.exp(np.sin(x / 97.0) + np.cos(y / 61.0) + 0.3 * np.sin((x + y) / 13.0))
    X = np.stack([X, 0.8 * X, 0.6 * X], -1) * np.float32(0.05)
    for p, ti in enumerate(t):
        z = np.interp(np.log(X * ti), g[:, 0], lev) + rng.normal(0, 0.5, X.shape)
        stack[p, r0:r0 + 250] = np.clip(z, 0, 255)
del X, x, y, z
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
rad, sat, dark, noise, rex = hdr._merge_in_strips(stack, t, g, 5, 250)
print(json.dumps({"seconds": time.perf_counter() - t0, "peak_rss_mb":
                  resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "rss_before_merge_mb": base / 1024, "pixels": H * W,
                  "reexposure_mean_levels": rex["mean_levels"]}))
"""


def bench_hdr() -> list[dict]:
    """The 24 MP merge in strips and whole, each in a fresh interpreter."""
    rows = []
    for mode in ("strips", "whole"):
        out = subprocess.run([sys.executable, "-c", HDR_CHILD, mode], capture_output=True,
                             text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append({"mode": mode, **r})
        print(f"hdr 24 MP {mode:>6}: {r['seconds']:6.1f} s, peak RSS {r['peak_rss_mb']:6.0f} MB "
              f"(photos and test image before the merge: {r['rss_before_merge_mb']:.0f} MB)",
              flush=True)
    return rows


def bench_scaling(processed: Path, work: Path, lobes: str, workers: list[int]) -> list[dict]:
    """The MH fit of ``processed``'s observation map on a LocalCluster of k workers."""
    from dask.distributed import LocalCluster

    rows = []
    for k in workers:
        proc = scratch_processed(processed, work / f"scaling-{k}", ("hdr", "observation.zarr"))
        with LocalCluster(n_workers=k, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster:
            cmd = [sys.executable, "-m", "parammap", "fit-mh", "--out", str(proc), "--lobes",
                   lobes, "--set", f"fit.scheduler={cluster.scheduler_address}",
                   "--set", f"workers={k}"]
            r = _watch(cmd, proc / "fit.log")
        if r["rc"]:
            log = (proc / "fit.log").read_text()[-2000:]
            raise SystemExit(f"fit with {k} workers failed: {log}")
        texels = _texels(processed)
        m = json.loads((proc / "metrics" / f"fit-mh-{lobes}.json").read_text())
        # the fit's own time (tiles and repairs), without the interpreter's start
        rows.append({"workers": k, "wall_seconds": r["seconds"], "texels": texels,
                     "fit_seconds": m["seconds"], "texels_per_s": texels / m["seconds"],
                     "driver_peak_mb": r["driver_peak_mb"]})
        print(f"mh-{lobes} on {k} worker(s): fit {m['seconds']:.1f} s ({r['seconds']:.1f} s "
              f"wall), {texels / m['seconds']:.0f} texels/s", flush=True)
    return rows


def _observe(capture: str, processed: Path, dst: Path, texels: int) -> Path:
    """A scratch processed folder whose observation map is ``texels`` across."""
    out = scratch_processed(processed, dst, ("hdr",))
    r = _watch([sys.executable, "-m", "parammap", "observe", capture, "--out", str(out),
                "--set", f"observation.texels_x={texels}"], out / "observe.log")
    if r["rc"]:
        raise SystemExit(f"observe failed: {(out / 'observe.log').read_text()[-2000:]}")
    print(f"observation map {texels} across: {r['seconds']:.1f} s, driver "
          f"{r['driver_peak_mb']:.0f} MB, largest worker {r['worker_peak_mb']:.0f} MB",
          flush=True)
    return out


def _texels(processed: Path) -> int:
    m = json.loads((processed / "metrics" / "observation.json").read_text())
    return int(m["texels"])


def bench_store(processed: Path) -> dict:
    """Bytes per observation on disk and the encoding's error against the noise."""
    from parammap.stores.observation import LOG2_RANGE, RADIANCE_CODES, open_observation_map

    m = json.loads((processed / "metrics" / "observation.json").read_text())
    g = open_observation_map(processed / "observation.zarr")
    noise = np.concatenate([g.noise[sl][g.valid[sl]] for sl in g.tiles()])
    half_step = 2 ** ((LOG2_RANGE[1] - LOG2_RANGE[0]) / RADIANCE_CODES / 2) - 1
    out = {"bytes_per_observation": m["bytes_on_disk"] / (m["texels"] * m["views"]),
           "encoding_max_rel_error": half_step,
           "noise_min": float(np.nanmin(noise)), "noise_median": float(np.nanmedian(noise)),
           "sample_seconds_per_texel_view": m["sample_seconds"] / (m["texels"] * m["views"])}
    out["encoding_error_over_min_noise"] = half_step / out["noise_min"]
    print(f"store: {out['bytes_per_observation']:.2f} bytes per texel and view; encoding "
          f"error at most {half_step:.2e}, {out['encoding_error_over_min_noise']:.3f} of the "
          f"smallest noise ({out['noise_min']:.4f})", flush=True)
    return out


def cost_table(store: dict, scaling: list[dict], views_measured: int, S: int = 4096,
               views: int = 300, nodes_workers: tuple[int, ...] = (1, 16, 64, 256)) -> list[dict]:
    """Node-hours (one worker a core) of the observation build and an MH fit of an
    S x S map from ``views`` views, from the measured per-texel-view rates."""
    one = min(scaling, key=lambda r: r["workers"])
    fit_s_per_tv = 1 / one["texels_per_s"] / views_measured
    obs_s_per_tv = store["sample_seconds_per_texel_view"]
    tv = S * S * views
    rows = []
    for n in nodes_workers:
        rows.append({"workers": n, "observation_hours": tv * obs_s_per_tv / n / 3600,
                     "mh_fit_hours": tv * fit_s_per_tv / n / 3600,
                     "core_hours": tv * (obs_s_per_tv + fit_s_per_tv) / 3600})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("processed", help="a processed capture with observation.zarr")
    ap.add_argument("--workdir", default="data/bench/lab")
    ap.add_argument("--lobes", default="1")
    ap.add_argument("--only", choices=["hdr", "scaling", "store"], action="append")
    ap.add_argument("--capture", help="the capture, to build the maps at --texels")
    ap.add_argument("--texels", type=int, help="build the observation map this many "
                    "texels across first (a scratch copy; default: the processed one's)")
    a = ap.parse_args()
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    proc = Path(a.processed)
    if a.texels:
        if not a.capture:
            raise SystemExit("--texels needs --capture")
        proc = _observe(a.capture, proc, work / f"obs-{a.texels}", a.texels)
    only = set(a.only or ["hdr", "scaling", "store"])
    res: dict = {"date": time.strftime("%Y-%m-%d %H:%M")}
    if "hdr" in only:
        res["hdr"] = bench_hdr()
    if "store" in only:
        res["store"] = bench_store(proc)
    if "scaling" in only:
        res["scaling"] = bench_scaling(proc, work, a.lobes, [1, 2])
        r1, r2 = res["scaling"]
        res["speedup_2_workers"] = r2["texels_per_s"] / r1["texels_per_s"]
        print(f"speed-up from 1 to 2 workers: {res['speedup_2_workers']:.2f}x")
    if "store" in only and "scaling" in only:
        views = json.loads((proc / "metrics" / "observation.json").read_text())["views"]
        res["cost"] = cost_table(res["store"], res["scaling"], views)
        print(f"{'workers':>8} {'observe h':>10} {'mh fit h':>9} {'core-hours':>11}"
              "   (4096 x 4096 texels, 300 views)")
        for r in res["cost"]:
            print(f"{r['workers']:>8} {r['observation_hours']:10.2f} {r['mh_fit_hours']:9.2f} "
                  f"{r['core_hours']:11.1f}")
    (work / "lab_scale.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
