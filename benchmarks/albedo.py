"""The relightable map's albedo and roughness against a physically based capture's truth
(issue 48): white-card views of stated reflectance rendered into a copy of the capture,
the flat-field, the observation map, mh and the svbrdf map refitted with them, and each
material patch's base colour and alpha against its truth
(:func:`parammap.synth.testsupport.albedo_against_truth`), with the card's scale and
with the dielectrics' F0 = 0.04 one.

    python benchmarks/albedo.py --root data/bench --preset pbr-mirror [--lobes 2]

Needs ``<root>/<preset>`` processed into ``<root>/<preset>.proc`` (camera and hdr from
``benchmarks/pbr_capture.py``); works in ``<root>/<preset>.card`` and
``<root>/<preset>.card.proc``; prints a table and writes ``<root>/<preset>.albedo.json``.
``--lobes``: the MH fit the lights are found from (2 where the preset has two lights).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import yaml

from parammap.cli import main
from parammap.models.svbrdf import metallic_roughness
from parammap.stores.capture import load_capture
from parammap.stores.params import read_param_map
from parammap.synth.pbr import PBR_PRESETS, render_white_card, sky_share
from parammap.synth.testsupport import albedo_against_truth


def run(root: Path, preset: str, lobes: int = 1, views: int = 6) -> dict:
    cap0, truth, out0 = root / preset, root / f"{preset}.truth", root / f"{preset}.proc"
    cap, out = root / f"{preset}.card", root / f"{preset}.card.proc"
    if not (cap / "radiometry").is_dir():
        shutil.rmtree(cap, ignore_errors=True)
        shutil.copytree(cap0, cap)
        render_white_card(cap, truth, views=views)
        doc = yaml.safe_load((cap / "capture.yaml").read_text())
        if "ambient" not in doc and PBR_PRESETS[preset].environment > 0:
            # a capture generated before the generator stated its sky (session 43)
            doc["ambient"] = {"share": sky_share(PBR_PRESETS[preset])}
            (cap / "capture.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    for sub in ("camera", "hdr"):
        shutil.copytree(out0 / sub, out / sub)
    for v in load_capture(cap).flatfield:
        assert main(["-q", "hdr", str(cap), "--out", str(out), "--view", v.id]) == 0
    for stage in (["radiometry"], ["observe"]):
        assert main(["-q", stage[0], str(cap), "--out", str(out)]) == 0
    assert main(["-q", "fit-mh", "--out", str(out), "--lobes", str(lobes)]) == 0
    assert main(["-q", "lights", "--capture", str(cap), "--out", str(out),
                 "--set", f"lights.source=mh-{lobes}"]) == 0
    for stage in (["fit-svbrdf"], ["export", "--model", "svbrdf-ggx"], ["material"]):
        assert main(["-q", stage[0], "--out", str(out), *stage[1:]]) == 0
    card = albedo_against_truth(truth, out)
    pm = read_param_map(out / "params" / "svbrdf-ggx.exr")
    k0 = metallic_roughness(pm.params, pm.sd)["scale"]
    f0 = albedo_against_truth(truth, out, scale=k0)
    rec = json.loads((out / "metrics" / "material-svbrdf-ggx.json").read_text())
    return {"preset": preset, "scale_card": rec["albedo_scale"], "scale_f0": k0,
            "patches": {k: {**card[k], "albedo_f0": f0[k]["albedo"]} for k in card}}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="data/bench")
    ap.add_argument("--preset", default="pbr-tiny")
    ap.add_argument("--lobes", type=int, default=1)
    a = ap.parse_args()
    res = run(Path(a.root), a.preset, a.lobes)
    print(f"{a.preset}: k from the card {res['scale_card']:.4g}, from F0 = 0.04 "
          f"{res['scale_f0']:.4g}")
    print("| patch | albedo (card) | albedo (F0 = 0.04) | alpha fitted / true |")
    print("|---|---|---|---|")
    for k, r in res["patches"].items():
        al = "-" if r["alpha"] is None else f"{r['alpha'][0]:.3f} / {r['alpha'][1]:.3f}"
        print(f"| {k} {r['kind']} | {r['albedo']:.3f} | {r['albedo_f0']:.3f} | {al} |")
    ratios = [r["albedo"] for r in res["patches"].values()]
    print(f"median |albedo - 1| {np.median(np.abs(np.array(ratios) - 1)):.3f}")
    (Path(a.root) / f"{a.preset}.albedo.json").write_text(json.dumps(res, indent=1))
