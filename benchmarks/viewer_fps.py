"""Benchmark: frame rate of the viewer page in headless Chromium with software rendering
(SwiftShader), as the page itself reports it, for each model's map resampled (nearest)
to size x size texels, and as a ratio to the diffuse map (a flat texture through the
same page) in the same run; also the page's load time and payload size per model.

    python benchmarks/viewer_fps.py data/processed/demo [--model mh-2 ...] [--size 512 ...]

``--repeat`` lays copies of each map side by side instead (a fitted 1024 x 1024 map four
times across is a 4096 x 4096 map with a fitted map's detail in every texel, which
nearest resampling would not give: its payload would compress to nothing); the time to
the first frame of the model is then that of a map of the lab's size.

Measured in the free orbit view and in the first held-out view; then a mouse drag
orbits the camera and the benchmark reports whether the image changed.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import yaml

from parammap.stores.camera import load_intrinsics
from parammap.stores.params import ParamMap, read_param_map
from parammap.viewer import write_viewer

ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("processed")
    ap.add_argument("--model", nargs="+", default=["mh-1", "mh-2", "sh-rlsop-36"])
    ap.add_argument("--size", type=int, nargs="+", default=[512],
                    help="texels across (0: each map at its own size, not resampled)")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    ap.add_argument("--repeat", action="store_true",
                    help="copies of each map side by side, not nearest resampling")
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright

    proc = Path(a.processed)
    intr = load_intrinsics(proc / "camera" / "intrinsics.yaml")
    views = [v for v in yaml.safe_load((proc / "camera" / "poses.yaml").read_text())["views"]
             if v["kept"]]
    held = next(v["id"] for v in views if v["holdout"])
    names = ["diffuse"] + [m for m in a.model if m != "diffuse"]
    for size in a.size:
        maps = _Resampled(proc, names, size, a.repeat)
        with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
            t0 = time.perf_counter()
            write_viewer(tmp, "bench", maps, intr, views, 1.0)
            written = time.perf_counter() - t0
            man = json.loads((Path(tmp) / "manifest.json").read_text())
            T, S = maps[names[0]].shape
            label = f"{S}x{T}"
            print(f"{label} payload bytes per texel (the page loads): " + ", ".join(
                f"{m['name']} {m['bytes_per_texel']:.2f} ({m['bytes_loaded'] / (S * T):.2f})"
                for m in man["models"]))
            browser = p.chromium.launch(executable_path=a.chromium, args=ARGS)
            page = browser.new_page()
            t0 = time.perf_counter()
            page.goto((Path(tmp) / "index.html").as_uri(), wait_until="domcontentloaded")
            opened = time.perf_counter() - t0
            page.wait_for_function("window.viewer && window.viewer.ready", timeout=60000)
            ready = time.perf_counter() - t0
            print(f"{label} texels: payloads written in {written:.1f} s, page open in "
                  f"{opened:.2f} s, controls ready in {ready:.2f} s (float-linear filtering: "
                  f"{page.evaluate('viewer.floatLinear')})")
            base = {}
            for name in names:
                t0 = time.perf_counter()
                page.evaluate(f"viewer.setModel('{name}')")
                loaded = time.perf_counter() - t0
                heap = page.evaluate("performance.memory ? performance.memory.usedJSHeapSize"
                                     " : null")
                print(f"  {name}: first frame {ready + loaded:.2f} s after the page was "
                      f"opened ({man_bytes(man, name) / 1e6:.1f} MB of payload; JS heap "
                      f"{heap / 1e6 if heap else float('nan'):.0f} MB)")
                _streaming(page, man, name, ready + loaded)
                note = page.inner_text("#msg").strip()
                if note:
                    print(f"  {name}: {note}")
                for label, js in (("orbit 640x480", "viewer.setView('')"),
                                  (f"view {held}", f"viewer.setView('{held}')")):
                    page.evaluate(js)
                    fps = _fps(page)
                    base.setdefault(label, fps)
                    print(f"  {name}: loaded in {loaded:.2f} s; {label}: {fps:.1f} fps, "
                          f"{fps / base[label]:.2f} x diffuse")
                print(f"  {name}: orbit by dragging changes the image: {_orbits(page)}")
            browser.close()


def _streaming(page, man: dict, name: str, first: float) -> None:
    """A streamed map (tiles and mip levels): the time from the page's opening to the
    full detail of the default orbit view (every tile on screen of the level it asks
    for), then to that of a view zoomed in on the surface's centre, the tiles each
    loaded and the JS heap."""
    m = next(x for x in man["models"] if x["name"] == name)
    if "mips" not in m["compact"]:
        return
    top = m["compact"]["mips"][-1]
    print(f"  {name}: streamed; its first frame from the 1/{top['f']} level "
          f"({top['S']}x{top['T']})")
    for label, js in (("default orbit", "viewer.orbit(0.6, 0.9, 2.2)"),
                      ("zoomed in (0.15 sizes away)", "viewer.orbit(0.6, 1.4, 0.15)")):
        t0 = time.perf_counter()
        st = page.evaluate(f"(async () => {{ {js}; return viewer.settle(); }})()")
        took = time.perf_counter() - t0
        first += took
        heap = page.evaluate("performance.memory ? performance.memory.usedJSHeapSize : null")
        tiles = ", ".join(f"1/{lv['f']}: {len(lv['have'])} of {lv['tiles']}"
                          for lv in st["levels"])
        print(f"  {name}: {label}: level 1/{st['wanted']} in full {took:.2f} s later "
              f"({first:.2f} s after opening); tiles loaded {tiles}; JS heap "
              f"{heap / 1e6 if heap else float('nan'):.0f} MB")
    page.evaluate("viewer.orbit(0.6, 0.9, 2.2)")


def first_frames(page_dir: Path, models: list[str], chromium: str = "/usr/bin/chromium"
                 ) -> dict:
    """A viewer page as written: per model, the seconds from opening the page to its
    first frame (a model shown first: the default orbit view), to the full detail of that
    view and of one zoomed in on the surface's centre (streamed maps), and the JS heap."""
    from playwright.sync_api import sync_playwright

    man = json.loads((Path(page_dir) / "manifest.json").read_text())
    out = {}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=ARGS)
        for name in models:
            page = browser.new_page()
            t0 = time.perf_counter()
            page.goto((Path(page_dir) / "index.html").as_uri() + f"#model={name}")
            page.wait_for_function("window.viewer && window.viewer.ready", timeout=60000)
            page.evaluate(f"(async () => {{ await viewer.setModel('{name}'); viewer.draw(); }})()")
            loaded = time.perf_counter() - t0
            # drawn by the page's own frame loop as soon as it could (a best map: before
            # its candidates have all arrived), on its clock from navigation
            first = page.evaluate(f"viewer.firstDrawn('{name}')") / 1e3
            row = {"first_frame_s": first, "loaded_s": loaded,
                   "payload_mb": man_bytes(man, name) / 1e6}
            m = next(x for x in man["models"] if x["name"] == name)
            for label, js in (("orbit", "viewer.orbit(0.6, 0.9, 2.2)"),
                              ("zoomed", "viewer.orbit(0.6, 1.4, 0.15)")):
                st = page.evaluate(f"(async () => {{ {js}; return viewer.settle(); }})()")
                row[f"{label}_full_s"] = time.perf_counter() - t0
                row[f"{label}_level"] = st["wanted"]
                row[f"{label}_tiles"] = [len(lv["have"]) for lv in st["levels"]]
            row["js_heap_mb"] = page.evaluate(
                "performance.memory ? performance.memory.usedJSHeapSize / 1e6 : null")
            row["streamed"] = "mips" in m["compact"]
            page.close()
            out[name] = row
            print(f"viewer {name}: first frame {first:.2f} s, loaded {loaded:.2f} s, full detail "
                  f"{row['orbit_full_s']:.2f}"
                  f" s (level 1/{row['orbit_level']}), zoomed in {row['zoomed_full_s']:.2f} s "
                  f"(tiles {row['zoomed_tiles']}), JS heap {row['js_heap_mb']:.0f} MB", flush=True)
        browser.close()
    return out


def man_bytes(man: dict, name: str) -> float:
    """The bytes of a model's payload the page loads (from the manifest)."""
    return float(next(m["bytes_loaded"] for m in man["models"] if m["name"] == name))


class _Resampled(Mapping):
    """Each model's map resampled (nearest) to size x size texels, made when it is
    asked for and not kept: a 4096 x 4096 SH-64 map is 12.9 GB of float32, so the
    page's maps are encoded one at a time."""

    def __init__(self, proc: Path, names: list[str], size: int, repeat: bool = False):
        self.proc, self.names, self.size, self.repeat = proc, names, size, repeat

    def __getitem__(self, name: str) -> ParamMap:
        pm = read_param_map(self.proc / "params" / f"{name}.exr")
        T, S = pm.shape
        if not self.size:
            return ParamMap(pm.model, pm.params.astype(np.float32), pm.width_mm,
                            pm.height_mm, pm.hemisphere)
        if self.repeat:
            r = (np.arange(self.size) % T)[:, None]
            c = (np.arange(self.size) % S)[None, :]
        else:
            r = (np.arange(self.size) * T // self.size)[:, None]
            c = (np.arange(self.size) * S // self.size)[None, :]
        return ParamMap(pm.model, pm.params.astype(np.float32)[r, c], pm.width_mm,
                        pm.height_mm, pm.hemisphere)

    def __iter__(self):
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)


def _fps(page, samples: int = 5) -> float:
    """The page's frame rate (frames per second over its last second), the median of
    ``samples`` readings 1.5 s apart after 3 s to settle: software rendering at a few
    frames per second makes a single reading noisy."""
    page.evaluate("viewer.setContinuous(true)")  # the page draws only on a change
    time.sleep(3.0)
    got = []
    for _ in range(samples):
        time.sleep(1.5)
        got.append(page.evaluate("viewer.fps()"))
    page.evaluate("viewer.setContinuous(false)")
    return float(np.median(got))


def _orbits(page) -> bool:
    """Drag across the canvas in the free view; True when the rendered image changed."""
    shot = "document.getElementById('gl').toDataURL('image/png')"
    page.evaluate("viewer.setView('')")
    time.sleep(1.0)
    before = page.evaluate(shot)
    box = page.locator("#gl").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 120, y + 30, steps=6)
    page.mouse.up()
    time.sleep(1.5)
    return page.evaluate(shot) != before


if __name__ == "__main__":
    main()
