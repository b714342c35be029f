"""Relighting on a physically based capture (issue 48 item 4): the held-out views
rendered under lights the capture never had (the first light moved, a second added:
:func:`parammap.synth.pbr.novel_lights`), against each model's render. The svbrdf map
is drawn under the new lights; MH, SH and diffuse cannot move theirs.

    python benchmarks/relight.py --root data/bench --preset pbr-tiny [--models ...]
        [--sampler multijitter --spp 8]

With ``--sampler``/``--spp`` both truths (the capture's clean renders and the relit
ones) are rendered afresh at that noise level into ``<root>/<preset>.truth-<sampler><spp>``
(the preset's own clean renders carry Monte Carlo noise that counts toward every
figure); the highlight speckle is reported against the truth used.

Needs ``<root>/<preset>`` processed into ``<root>/<preset>.proc`` with the models'
EXRs (``benchmarks/pbr_capture.py``, then ``parammap lights --capture <root>/<preset>``,
which passes on the sky's share the generator states, and ``fit-svbrdf``);
renders ``<root>/<preset>.truth/relit`` when missing; prints both tables and writes
``<root>/<preset>.relight.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from parammap.synth import testsupport as ev
from parammap.synth.pbr import PBR_PRESETS, render_relit


def run(root: Path, preset: str, models: list[str], sampler: str | None = None,
        spp: int | None = None) -> dict:
    cap, truth, out = root / preset, root / f"{preset}.truth", root / f"{preset}.proc"
    if sampler or spp:
        src, truth = truth, root / f"{preset}.truth-{sampler or 'preset'}{spp or ''}"
        if not (truth / "relit" / "lights.json").is_file():
            shutil.rmtree(truth, ignore_errors=True)
            shutil.copytree(src, truth, ignore=shutil.ignore_patterns("clean", "relit"))
            render_relit(truth, PBR_PRESETS[preset].lights, spp, sampler, folder="clean")
            render_relit(truth, None, spp, sampler)
    elif not (truth / "relit" / "lights.json").is_file():
        render_relit(truth)
    captured = ev.holdout_against_truth(cap, truth, out, models)
    relit = ev.relit_against_truth(cap, truth, out, models)
    mean = {k: {m: float(np.mean([r[m] for r in tab.values()])) for m in models}
            for k, tab in (("captured", captured), ("relit", relit))}
    return {"preset": preset, "truth": truth.name, "captured": captured, "relit": relit,
            "mean": mean, "ratio": {m: mean["relit"][m] / mean["captured"][m] for m in models},
            "speckle": ev.highlight_speckle(cap, truth, out, models)}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="data/bench")
    ap.add_argument("--preset", default="pbr-tiny")
    ap.add_argument("--models", nargs="*", default=["svbrdf-ggx", "mh-1", "mh-auto",
                                                     "sh-rlsop-36", "diffuse"])
    ap.add_argument("--sampler", help="Mitsuba sampler of fresh truths (e.g. multijitter)")
    ap.add_argument("--spp", type=int, help="their samples per render pixel")
    a = ap.parse_args()
    res = run(Path(a.root), a.preset, a.models, a.sampler, a.spp)
    for k in ("captured", "relit"):
        for vid, row in res[k].items():
            print(f"{a.preset} {k} {vid}: " + ", ".join(f"{m} {v:.2f}" for m, v in row.items()))
    print("mean under the capture's light: " + ", ".join(
        f"{m} {v:.2f}" for m, v in res["mean"]["captured"].items()))
    print("mean under the novel lights:    " + ", ".join(
        f"{m} {v:.2f}" for m, v in res["mean"]["relit"].items()))
    print("novel / captured: " + ", ".join(f"{m} {v:.2f}" for m, v in res["ratio"].items()))
    print("highlight speckle (truth = 1): " + ", ".join(
        f"{m} {v['ratio']:.2f}" for m, v in res["speckle"].items() if isinstance(v, dict)))
    (Path(a.root) / f"{res['truth'].replace('.truth', '.relight')}.json").write_text(
        json.dumps(res, indent=1))
