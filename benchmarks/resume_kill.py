"""Benchmark: a fit killed with SIGKILL after half its tiles resumes, fits only the rest,
and its store is byte for byte that of an uninterrupted run.

Needs a processed capture with an observation map, e.g. the paper preset::

    parammap synth --preset paper --out data/captures/paper --workers 2
    snakemake --cores 2 --config 'captures={"paper": "data/captures/paper"}' \
        -- data/processed/paper/observation.zarr
    python benchmarks/resume_kill.py data/captures/paper data/processed/paper --lobes 1

Three runs of ``parammap fit-mh`` into scratch folders beside the observation map: one
uninterrupted, one killed (its whole process group, as a pre-empting scheduler does)
once half of the tile markers exist, and the same command again. Prints the times,
the tiles the resumed run found done, whether any process of the killed run survived,
and whether the two stores are identical file by file.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
from _scratch import scratch_processed


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("processed", help="processed folder with camera/ and observation.zarr")
    ap.add_argument("--lobes", default="1")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--kill-at", type=float, default=0.5, help="fraction of tiles done")
    ap.add_argument("--workdir", default="data/bench/resume")
    a = ap.parse_args()
    src, work = Path(a.processed), Path(a.workdir)
    name = f"mh-{a.lobes}"
    obs = json.loads((src / "observation.zarr" / "zarr.json").read_text())["attributes"]
    S, T, tile = obs["S"], obs["T"], obs["tile"]
    ntiles = -(-S // tile) * -(-T // tile)

    def cmd(out: Path) -> list[str]:
        return [sys.executable, "-m", "parammap", "fit-mh", "--out", str(out),
                "--lobes", a.lobes, "--set", f"workers={a.workers}"]

    res: dict = {"map": [S, T], "tiles": ntiles, "model": name}
    ref, run = work / "uninterrupted", work / "killed"
    scratch_processed(src, ref, ("observation.zarr",))
    t0 = time.perf_counter()
    subprocess.run(cmd(ref), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    res["uninterrupted_s"] = time.perf_counter() - t0
    print(f"uninterrupted: {res['uninterrupted_s']:.1f} s for {ntiles} tiles", flush=True)

    scratch_processed(src, run, ("observation.zarr",))
    marks = run / "fit" / f".{name}.zarr.tiles"
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd(run), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)
    tree: set[int] = set()
    while p.poll() is None:
        try:
            tree |= {c.pid for c in psutil.Process(p.pid).children(recursive=True)}
        except psutil.Error:
            pass
        n = len(list(marks.glob("fit-*"))) if marks.is_dir() else 0
        if n >= a.kill_at * ntiles:
            os.killpg(p.pid, signal.SIGKILL)
            break
        time.sleep(0.1)
    p.wait()
    res["killed_after_s"] = time.perf_counter() - t0
    res["tiles_done_when_killed"] = len(list(marks.glob("fit-*")))
    time.sleep(3)
    res["processes_left"] = sum(psutil.pid_exists(pid) and psutil.Process(pid).status()
                                != psutil.STATUS_ZOMBIE for pid in tree)
    print(f"killed after {res['killed_after_s']:.1f} s with {res['tiles_done_when_killed']} "
          f"of {ntiles} tiles done; {res['processes_left']} of its {len(tree)} worker "
          f"processes left 3 s later", flush=True)
    t0 = time.perf_counter()
    out = subprocess.run(cmd(run), check=True, capture_output=True, text=True)
    res["resumed_s"] = time.perf_counter() - t0
    said = [ln for ln in (out.stdout + out.stderr).splitlines() if "resuming" in ln]
    res["resume_log"] = said[0].strip() if said else None
    a_files = _files(ref / "fit" / f"{name}.zarr")
    b_files = _files(run / "fit" / f"{name}.zarr")
    res["files"] = len(a_files)
    res["identical"] = a_files == b_files
    print(f"resumed: {res['resumed_s']:.1f} s ({res['resume_log']}); stores identical: "
          f"{res['identical']} ({len(a_files)} files)")
    (work / "resume_kill.json").write_text(json.dumps(res, indent=1))
    return 0 if res["identical"] and res["processes_left"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
