"""The relightable map under its lights as points and as the area lights they are
(issue 48 item 2): the svbrdf map refitted from a processed physically based capture,
once with the lights stage's lights as found and once with the preset's lights stated
as a lab would measure them (shape and size, ``synth.pbr.stated_lights``); each held out
against the clean renders, its highlights' speckle and each glossy patch's median alpha
against the truth.

    python benchmarks/area_lights.py --root data/bench --preset pbr-tiny pbr-mirror

Needs ``<root>/<preset>`` processed into ``<root>/<preset>.proc`` through the lights
stage (``benchmarks/pbr_capture.py``, then ``parammap lights``); works in
``<root>/<preset>.points`` and ``<root>/<preset>.area``; prints a table and writes
``<root>/<preset>.area.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

from parammap.cli import main
from parammap.conventions import SV_ALPHA
from parammap.stages.lights import match_measured
from parammap.stores.params import read_param_map
from parammap.synth.pbr import PBR_PRESETS, patch_labels, stated_lights
from parammap.synth.testsupport import highlight_speckle, holdout_against_truth

MODEL = "svbrdf-ggx"


def _copy(proc: Path, work: Path) -> None:
    shutil.rmtree(work, ignore_errors=True)
    (work / "fit").mkdir(parents=True)
    for name in ("camera", "observation.zarr", "metrics"):
        shutil.copytree(proc / name, work / name)
    (work / "hdr").symlink_to((proc / "hdr").resolve())


def _alphas(truth: Path, work: Path) -> dict[str, list[float]]:
    pm = read_param_map(work / "params" / f"{MODEL}.exr")
    T, S = pm.params.shape[:2]
    lab = patch_labels(truth, S, T, pm.width_mm, pm.height_mm)
    patches = json.loads((truth / "scene.json").read_text())["patches"]
    return {f"p{k}": [p["alpha"], float(np.median(pm.params[..., SV_ALPHA][lab == k]))]
            for k, p in enumerate(patches) if "alpha" in p}


def run(root: Path, preset: str) -> dict:
    cap, truth, proc = root / preset, root / f"{preset}.truth", root / f"{preset}.proc"
    out = {}
    for kind in ("points", "area"):
        work = root / f"{preset}.{kind}"
        _copy(proc, work)
        if kind == "area":
            doc = yaml.safe_load((work / "camera" / "lights.yaml").read_text())
            match_measured(doc["lights"], stated_lights(PBR_PRESETS[preset]))
            (work / "camera" / "lights.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        t0 = time.perf_counter()
        assert main(["fit-svbrdf", "--out", str(work), "-q"]) == 0
        seconds = time.perf_counter() - t0
        assert main(["export", "--out", str(work), "--model", MODEL, "-q"]) == 0
        held = holdout_against_truth(cap, truth, work, [MODEL])
        out[kind] = {"held_out": [r[MODEL] for r in held.values()],
                     "speckle": highlight_speckle(cap, truth, work, [MODEL])[MODEL]["ratio"],
                     "alpha": _alphas(truth, work), "fit_seconds": seconds}
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="data/bench")
    ap.add_argument("--preset", nargs="+", default=["pbr-tiny", "pbr-mirror", "pbr-two-lights"])
    a = ap.parse_args()
    for preset in a.preset:
        r = run(Path(a.root), preset)
        (Path(a.root) / f"{preset}.area.json").write_text(json.dumps(r, indent=1))
        for kind, m in r.items():
            alphas = " ".join(f"{k} {t:.3f}->{f:.3f}" for k, (t, f) in m["alpha"].items())
            print(f"{preset} {kind:6s} held out {np.mean(m['held_out']):.3f} "
                  f"speckle {m['speckle']:.3f} fit {m['fit_seconds']:.0f} s  alpha {alphas}")
