"""Relighting on a physically based capture (issue 48 item 4): the held-out views
rendered under lights the capture never had (the first light moved, a second added:
:func:`parammap.synth.pbr.novel_lights`), against each model's render. The svbrdf map
is drawn under the new lights; MH, SH and diffuse cannot move theirs.

    python benchmarks/relight.py --root data/bench --preset pbr-tiny [--models ...]

Needs ``<root>/<preset>`` processed into ``<root>/<preset>.proc`` with the models'
EXRs (``benchmarks/pbr_capture.py``, then ``parammap lights`` and ``fit-svbrdf``);
renders ``<root>/<preset>.truth/relit`` when missing; prints both tables and writes
``<root>/<preset>.relight.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from parammap.synth import testsupport as ev
from parammap.synth.pbr import render_relit


def run(root: Path, preset: str, models: list[str]) -> dict:
    cap, truth, out = root / preset, root / f"{preset}.truth", root / f"{preset}.proc"
    if not (truth / "relit" / "lights.json").is_file():
        render_relit(truth)
    captured = ev.holdout_against_truth(cap, truth, out, models)
    relit = ev.relit_against_truth(cap, truth, out, models)
    mean = {k: {m: float(np.mean([r[m] for r in tab.values()])) for m in models}
            for k, tab in (("captured", captured), ("relit", relit))}
    return {"preset": preset, "captured": captured, "relit": relit, "mean": mean,
            "ratio": {m: mean["relit"][m] / mean["captured"][m] for m in models}}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="data/bench")
    ap.add_argument("--preset", default="pbr-tiny")
    ap.add_argument("--models", nargs="*", default=["svbrdf-ggx", "mh-1", "mh-auto",
                                                     "sh-rlsop-36", "diffuse"])
    a = ap.parse_args()
    res = run(Path(a.root), a.preset, a.models)
    for k in ("captured", "relit"):
        for vid, row in res[k].items():
            print(f"{a.preset} {k} {vid}: " + ", ".join(f"{m} {v:.2f}" for m, v in row.items()))
    print("mean under the capture's light: " + ", ".join(
        f"{m} {v:.2f}" for m, v in res["mean"]["captured"].items()))
    print("mean under the novel lights:    " + ", ".join(
        f"{m} {v:.2f}" for m, v in res["mean"]["relit"].items()))
    print("novel / captured: " + ", ".join(f"{m} {v:.2f}" for m, v in res["ratio"].items()))
    (Path(a.root) / f"{a.preset}.relight.json").write_text(json.dumps(res, indent=1))
