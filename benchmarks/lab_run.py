"""Benchmark: the ``lab`` preset end to end, stage by stage (issue 47).

Generates the preset once (12 MP JPEG brackets, 121 views and 6 held out; cached under
``--root``), then runs each stage as its own ``python -m parammap`` process and records
its wall time, CPU seconds (the process and every worker it waited for), the peak
resident memory of the stage's main process and of its largest worker, and the bytes
its outputs take on disk. A stage whose outputs are there from an earlier run is not run
again (its figures are kept from that run), so the benchmark resumes where it stopped::

    python benchmarks/lab_run.py --root data/bench/lab-run --models mh-1

``--texels N`` builds the observation map N texels across instead of the photos' own
resolution (the auto default), in its own folder, which starts from the auto-resolution
run's response, HDR frames and camera when that run is there (they do not depend on the
map's size). Writes ``<root>/lab_run.json`` after every stage and
prints the per-stage table; ``--first-frame`` then opens the viewer page the ``viewer``
stage wrote in headless Chromium (each model's first frame and full detail).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

from big_map import _watch

#: stage -> (reads the capture, outputs under the processed folder)
STAGES = {
    "response": (True, ["camera/response.csv"]),
    "hdr": (True, ["hdr"]),
    "calibrate": (True, ["camera/intrinsics.yaml"]),
    "poses": (True, ["camera/poses.yaml"]),
    "observe": (True, ["observation.zarr"]),
}


def _bytes(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else 0


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


#: the default config's models, fitted in this order (each after what it reads)
DEFAULT_MODELS = ["mh-1", "mh-2", "mh-auto", "mh-materials", "sh-lsop-16", "sh-rlsop-36",
                  "sh-wls-36", "svbrdf-ggx"]


def _model_stage(model: str) -> tuple[list[str], list[str]]:
    """The fit command of a model and its outputs."""
    if model == "mh-materials":
        return (["materials", "--set", "materials.source=mh-auto"],
                ["fit/mh-materials.zarr"])
    if model == "svbrdf-ggx":
        return ["fit-svbrdf"], ["fit/svbrdf-ggx.zarr"]
    if model.startswith("mh-"):
        return ["fit-mh", "--lobes", model.split("-", 1)[1]], [f"fit/{model}.zarr"]
    if model.startswith("sh-"):
        return ["fit-sh", "--model", model], [f"fit/{model}.zarr"]
    raise SystemExit(f"--models: {model!r} is not an mh-K or sh-<hemisphere>-<n> model")


def _link_photo_stages(full: Path, proc: Path) -> None:
    """A smaller map's folder starts from the auto-resolution run's response, HDR frames
    and camera (hard links): they do not depend on the map's size."""
    import os

    for f in full.rglob("*"):
        rel = f.relative_to(full)
        if f.is_file() and rel.parts[0] in ("hdr", "camera") and rel.name != "lights.yaml":
            (proc / rel).parent.mkdir(parents=True, exist_ok=True)
            os.link(f, proc / rel)


def run_stage(name: str, cmd: list[str], outputs: list[Path], log: Path) -> dict:
    """One stage in its own process: wall, CPU, peak RSS, bytes of its outputs."""
    cpu0 = _cpu_children()
    r = _watch([sys.executable, "-m", "parammap", *cmd], log)
    r["cpu_seconds"] = _cpu_children() - cpu0
    if r["rc"]:
        raise SystemExit(f"{name} failed (exit {r['rc']}): {log.read_text()[-3000:]}")
    r["bytes_on_disk"] = sum(_bytes(p) for p in outputs)
    print(f"{name:>18}: {r['seconds']:8.1f} s wall, {r['cpu_seconds']:8.1f} s CPU, peak RSS "
          f"{r['driver_peak_mb']:6.0f} MB main, {r['worker_peak_mb']:6.0f} MB worker, "
          f"{r['bytes_on_disk'] / 2**30:7.2f} GiB", flush=True)
    return r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="data/bench/lab-run")
    ap.add_argument("--preset", default="lab")
    ap.add_argument("--models", nargs="*", default=["mh-1"],
                    help="models to fit, or 'default' for the default config's, with the "
                         "lights they need and the best map")
    ap.add_argument("--texels", type=int, help="observation map this many texels across "
                    "(default: the photos' own resolution)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--first-frame", action="store_true",
                    help="open the viewer page in headless Chromium: each model's first "
                         "frame, its full detail, the JS heap (benchmarks/viewer_fps.py)")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    a = ap.parse_args()
    with_best = a.models == ["default"]
    if with_best:
        a.models = DEFAULT_MODELS
    root = Path(a.root)
    cap, proc = root / a.preset, root / f"{a.preset}.proc"
    if a.texels:
        proc = root / f"{a.preset}.proc-{a.texels}"
    res_path = root / f"lab_run{'-' + str(a.texels) if a.texels else ''}.json"
    res = json.loads(res_path.read_text()) if res_path.is_file() else {"stages": {}}
    logs = root / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    common = ["--set", f"workers={a.workers}"]

    def save() -> None:
        tmp = res_path.with_name(f".{res_path.name}.tmp")
        tmp.write_text(json.dumps(res, indent=1))
        tmp.replace(res_path)

    plan: list[tuple[str, list[str], list[Path]]] = []
    if not (cap / "capture.yaml").is_file():
        plan.append(("synth", ["synth", "--preset", a.preset, "--out", str(cap), "--workers",
                               str(a.workers)], [cap]))
    full = root / f"{a.preset}.proc"
    if a.texels and (full / "camera" / "poses.yaml").is_file() and not proc.exists():
        _link_photo_stages(full, proc)
    for name, (on_capture, outs) in STAGES.items():
        if a.texels and name != "observe" and name not in res["stages"] \
                and all((proc / o).exists() for o in outs):
            res["stages"][name] = {"shared_with": str(full)}  # its figures: the full run's
        extra = (["--set", f"observation.texels_x={a.texels}"]
                 if name == "observe" and a.texels else [])
        plan.append((name, [name, *([str(cap)] if on_capture else []), "--out", str(proc),
                            *common, *extra], [proc / o for o in outs]))
    for m in a.models:
        if m == "svbrdf-ggx":
            plan.append(("lights", ["lights", "--out", str(proc), "--capture", str(cap),
                                    "--figures", str(root / "reports"), "--set",
                                    "lights.source=mh-auto", *common],
                         [proc / "camera" / "lights.yaml"]))
        cmd, outs = _model_stage(m)
        plan.append((m, [*cmd, "--out", str(proc), *common], [proc / o for o in outs]))
    maps = [*a.models, "diffuse"]
    named = [x for m in maps for x in ("--model", m)]
    plan.append(("export", ["export", "--out", str(proc), *named, *common],
                 [proc / "params" / f"{m}.exr" for m in maps]))
    if with_best:
        plan.append(("best", ["best", "--out", str(proc), *named, "--figures",
                              str(root / "reports"), *common], [proc / "params" / "best.exr"]))
        maps = [*maps, "best"]
        named = [x for m in maps for x in ("--model", m)]
    plan.append(("holdout", ["holdout", str(cap), "--out", str(proc), *named, *common],
                 [proc / "metrics" / "holdout.json"]))
    page = root / "reports" / f"{proc.name}-viewer"
    plan.append(("viewer", ["viewer", str(cap), "--out", str(proc), "--figures", str(page),
                            *named], [page]))
    for name, cmd, outs in plan:
        if name in res["stages"] and all(p.exists() for p in outs):
            was = res["stages"][name]
            print(f"{name:>18}: " + (f"done before ({was['seconds']:.1f} s)" if "seconds"
                                     in was else f"shared with {was['shared_with']}"))
            continue
        t = time.strftime("%H:%M:%S")
        print(f"{name:>18}: starting at {t}", flush=True)
        res["stages"][name] = run_stage(name, cmd, outs, logs / f"{proc.name}-{name}.log")
        save()
    obs = proc / "metrics" / "observation.json"
    if obs.is_file():
        m = json.loads(obs.read_text())
        res["map"] = {k: m.get(k) for k in ("texels", "views", "bytes_on_disk")}
        res["map"]["shape"] = [m.get("T"), m.get("S")]
        save()
        print(f"observation map: {m.get('S')} x {m.get('T')} texels, {m.get('views')} views, "
              f"{m['bytes_on_disk'] / (m['texels'] * m['views']):.2f} bytes per texel and view")
    if a.first_frame and (page / "index.html").is_file():
        from viewer_fps import first_frames

        res["viewer_page"] = first_frames(page, maps, a.chromium)
        save()
    held = proc / "metrics" / "holdout.json"
    if held.is_file():
        views = json.loads(held.read_text())["views"]
        res["held_out"] = {m: sum(v["models"][m]["mean_diff_8bit"] for v in views.values())
                           / len(views) for m in maps}
        save()
        print("held out, mean 8-bit difference: " + ", ".join(
            f"{m} {v:.3f}" for m, v in res["held_out"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
