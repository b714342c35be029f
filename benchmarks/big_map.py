"""Benchmark: time and peak memory of the observation map and the fits against map size.

Builds the observation map of one processed capture (its HDR frames and poses) at
several map sizes (256 ... 2048 texels across; beyond the photos' own resolution the
map oversamples them, which changes nothing of the work per texel and view), then fits
each map, every stage in its own process tree. While a stage runs, the resident memory
of its driver and of every worker process is sampled (psutil, every 0.2 s): the
question is whether a worker's peak is bounded by the tile, not by the map.

Needs a processed capture, e.g. the demo after ``make demo``::

    python benchmarks/big_map.py data/captures/demo data/processed/demo \
        --sizes 256 512 1024 2048 --model sh-lsop-16 --model mh-1 --mh-max 512

Writes ``<workdir>/big_map.json`` (one row per size and stage) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import psutil
import yaml
from _scratch import scratch_processed


def _watch(cmd: list[str], log: Path) -> dict:
    """Run ``cmd``; its wall time, exit code and peak RSS (MB) of the driver and of the
    largest worker (any descendant process)."""
    t0 = time.perf_counter()
    with log.open("w") as fh:
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
        proc = psutil.Process(p.pid)
        main_peak = worker_peak = 0.0
        workers: set[int] = set()
        while p.poll() is None:
            try:
                main_peak = max(main_peak, proc.memory_info().rss / 2**20)
                for c in proc.children(recursive=True):
                    try:
                        worker_peak = max(worker_peak, c.memory_info().rss / 2**20)
                        workers.add(c.pid)
                    except psutil.Error:
                        pass
            except psutil.Error:
                pass
            time.sleep(0.2)
    return {"seconds": time.perf_counter() - t0, "rc": p.returncode,
            "driver_peak_mb": main_peak, "worker_peak_mb": worker_peak,
            "worker_processes": len(workers)}


def _thin_views(poses: Path, every: int) -> None:
    """Keep every ``every``-th kept view that is not held out (the benchmark's subset)."""
    doc = yaml.safe_load(poses.read_text())
    fitted = [v for v in doc["views"] if v["kept"] and not v.get("holdout")]
    for k, v in enumerate(fitted):
        if k % every:
            v.update(kept=False, reason="left out of the benchmark's subset")
    poses.write_text(yaml.safe_dump(doc, sort_keys=False))


def _store_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("processed", help="processed folder with camera/ and hdr/ of the capture")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    ap.add_argument("--model", action="append", help="sh-... or mh-K (repeatable; "
                    "default sh-lsop-16)")
    ap.add_argument("--mh-max", type=int, default=512, help="largest map fitted with MH")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--workdir", default="data/bench/big")
    ap.add_argument("--views-every", type=int, default=1,
                    help="keep every n-th fitted view only (a smaller map on disk)")
    ap.add_argument("--keep", action="store_true", help="keep each size's stores")
    a = ap.parse_args()
    models = a.model or ["sh-lsop-16"]
    src = Path(a.processed)
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    py = [sys.executable, "-m", "parammap"]
    for S in a.sizes:
        proc = scratch_processed(src, work / f"S{S}", ("hdr",))
        if a.views_every > 1:
            _thin_views(proc / "camera" / "poses.yaml", a.views_every)
        common = ["--out", str(proc), "--set", f"workers={a.workers}"]
        stages = [("observe", [*py, "observe", a.capture, *common,
                               "--set", f"observation.texels_x={S}"])]
        for m in models:
            if m.startswith("mh-"):
                if S <= a.mh_max:
                    stages.append((m, [*py, "fit-mh", *common, "--lobes", m[3:]]))
            else:
                stages.append((m, [*py, "fit-sh", *common, "--model", m]))
        for name, cmd in stages:
            print(f"S={S} {name} ...", flush=True)
            r = _watch(cmd, proc / f"{name}.log")
            if r["rc"] != 0:
                print((proc / f"{name}.log").read_text()[-3000:])
                raise SystemExit(f"{name} at {S} failed (log {proc / f'{name}.log'})")
            store = proc / ("observation.zarr" if name == "observe" else f"fit/{name}.zarr")
            r.update(size=S, stage=name, store_mb=_store_bytes(store) / 1e6)
            if name == "observe":
                g = json.loads((proc / "metrics" / "observation.json").read_text())
                T = int(g["T"])
                r["views"] = g.get("views")
            r["T"] = T
            r["texels_per_s"] = S * T / r["seconds"]
            rows.append(r)
            print(f"  {r['seconds']:8.1f} s  driver {r['driver_peak_mb']:7.0f} MB  largest "
                  f"worker {r['worker_peak_mb']:7.0f} MB  store {r['store_mb']:9.1f} MB",
                  flush=True)
            (work / "big_map.json").write_text(json.dumps(rows, indent=1))
        if not a.keep:
            shutil.rmtree(proc / "observation.zarr", ignore_errors=True)
            shutil.rmtree(proc / "fit", ignore_errors=True)
    print(f"{'size':>6} {'stage':>12} {'s':>8} {'texels/s':>9} {'driver MB':>10} "
          f"{'worker MB':>10} {'store MB':>9}")
    for r in rows:
        print(f"{r['size']:>6} {r['stage']:>12} {r['seconds']:8.1f} {r['texels_per_s']:9.0f} "
              f"{r['driver_peak_mb']:10.0f} {r['worker_peak_mb']:10.0f} {r['store_mb']:9.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
