"""Benchmark: frame rate of the viewer page for a 512 x 512 MH map in headless Chromium
with software rendering (SwiftShader), as the page itself reports it.

    python benchmarks/viewer_fps.py data/processed/demo [--model mh-2] [--size 512]

The map is the given model's map resampled (nearest) to size x size texels; the page is
measured in the free orbit view and in the first held-out view.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from parammap.calibration import load_intrinsics
from parammap.params import ParamMap, read_param_map
from parammap.viewer import write_viewer

ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("processed")
    ap.add_argument("--model", default="mh-2")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright

    proc = Path(a.processed)
    pm = read_param_map(proc / "params" / f"{a.model}.exr")
    T, S = pm.shape
    r = (np.arange(a.size) * T // a.size)[:, None]
    c = (np.arange(a.size) * S // a.size)[None, :]
    big = ParamMap(pm.model, pm.params[r, c], pm.width_mm, pm.height_mm, pm.hemisphere)
    intr = load_intrinsics(proc / "camera" / "intrinsics.yaml")
    views = [v for v in yaml.safe_load((proc / "camera" / "poses.yaml").read_text())["views"]
             if v["kept"]]
    held = next(v["id"] for v in views if v["holdout"])
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
        write_viewer(tmp, "bench", {a.model: big}, intr, views, 1.0)
        browser = p.chromium.launch(executable_path=a.chromium, args=ARGS)
        page = browser.new_page()
        page.goto((Path(tmp) / "index.html").as_uri())
        page.wait_for_function("window.viewer && window.viewer.ready", timeout=60000)
        for label, js in (("orbit 640x480", ""), (f"held-out view {held}",
                                                  f"viewer.setView('{held}')")):
            page.evaluate(js or "0")
            time.sleep(4.0)
            fps = page.evaluate("viewer.fps()")
            print(f"{a.model} {a.size}x{a.size} texels, {label}: {fps:.1f} fps "
                  f"(float-linear filtering: {page.evaluate('viewer.floatLinear')})")
        browser.close()


if __name__ == "__main__":
    main()
