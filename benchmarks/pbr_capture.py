"""The whole pipeline on a physically based capture (Mitsuba 3), measured against its
ground truth: HDR against an oracle merge, intrinsics, views kept and pose accuracy,
the map resolution chosen, observation directions, held-out errors of every model
against the clean renders and the speckle of their highlights
(:func:`parammap.synth.testsupport.highlight_speckle`); with ``--materials``, the basis
materials (their adjusted Rand index against the true patches) and the best-per-texel
map as well.

    python benchmarks/pbr_capture.py --preset pbr-bench --root data/bench [--models ...]

Generates ``<root>/<preset>`` (skipped when it exists) and processes it into
``<root>/<preset>.proc``; prints a summary and writes ``<root>/<preset>.json``. With
``--camera-noise`` the preset's photos are rendered with stratified samples (about a
camera's noise where its independent ones leave 18 %) and its held-out truths with 8
multijitter samples, as ``pbr-tiny-camera`` does for pbr-tiny.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from parammap.cli import ON_PROCESSED, main
from parammap.synth import testsupport as ev


def run(preset: str, root: Path, models: list[str], seed: int, reuse_hdr: bool = False,
        materials: bool = False, camera_noise: bool = False) -> dict:
    cap = root / preset
    truth = root / f"{preset}.truth"
    out = root / f"{preset}.proc"
    times = {}
    if not (cap / "capture.yaml").is_file():
        t0 = time.perf_counter()
        if camera_noise:
            from dataclasses import replace

            from parammap.synth.pbr import PBR_PRESETS, generate_pbr

            generate_pbr(cap, truth, replace(PBR_PRESETS[preset], sampler="multijitter",
                                             clean_spp=8, clean_sampler="multijitter"),
                         seed=seed)
        else:
            assert main(["synth", "--preset", preset, "--seed", str(seed), "--out", str(cap),
                         "--truth", str(truth)]) == 0
        times["synth"] = time.perf_counter() - t0
    baked = [m for m in models if m.startswith("sh-mh-")]  # after the MH fit they bake
    fits = [["fit-mh", "--lobes", m.split("-")[1]] if m.startswith("mh-") else
            ["fit-sh", "--model", m] for m in models if m not in baked]
    extra = ["mh-materials"] if materials else []
    named = [x for m in models + extra + ["diffuse"] for x in ("--model", m)]
    merged = reuse_hdr and any((out / "hdr").glob("*.exr"))
    stages = [] if merged else [["response"], ["hdr"]]
    source = "mh-auto" if "mh-auto" in models else next(m for m in models if m.startswith("mh-"))
    fits += [["materials", "--set", f"materials.source={source}"]] if materials else []
    fits += [["fit-sh", "--model", m, "--set",
              f"fit.sh.source={'mh-materials' if materials else source}"] for m in baked]
    best = [["best", *named]] if materials else []
    compared = named + (["--model", "best"] if materials else [])
    stages += [["calibrate"], ["poses"], ["observe"], *fits, ["export", *named], *best,
               ["holdout", *compared]]
    for stage in stages:
        t0 = time.perf_counter()
        reads = [] if stage[0] in ON_PROCESSED else [str(cap)]
        assert main([stage[0], *reads, "--out", str(out), *stage[1:]]) == 0, stage
        times[" ".join(stage[:3] if stage[0].startswith("fit") else stage[:1])] = \
            time.perf_counter() - t0
    import yaml

    from parammap.stores.capture import load_capture
    from parammap.stores.observation import open_observation_map

    c = load_capture(cap)
    sample = [v.id for v in c.views][:: max(1, len(c.views) // 6)]
    res: dict = {"preset": preset, "seconds": times}
    res["hdr"] = ev.hdr_errors(cap, truth, out, sample)
    res["intrinsics"] = ev.intrinsics_errors(truth, out)
    poses = json.loads((out / "metrics" / "poses.json").read_text())
    pe = ev.pose_errors(truth, out)
    kept = [v for v in pe.values() if v["kept"]]
    recs = yaml.safe_load((out / "camera" / "poses.yaml").read_text())["views"]
    res["poses"] = {
        "views": poses["views"], "kept": poses["kept"], "dropped": poses["dropped"],
        "held_out_kept": sum(r["kept"] for r in recs if r["holdout"]),
        "held_out": sum(r["holdout"] for r in recs),
        "centre_mm_median": float(np.median([v["centre_mm"] for v in kept])),
        "centre_mm_worst": float(max(v["centre_mm"] for v in kept)),
        "rotation_deg_median": float(np.median([v["rotation_deg"] for v in kept])),
        "rotation_deg_worst": float(max(v["rotation_deg"] for v in kept)),
        "map": poses["map"]}
    g = open_observation_map(out / "observation.zarr")
    T, S, _ = g["valid"].shape
    dt = ev.true_directions(truth, g.attrs["view_ids"], S, T, g.attrs["width_mm"],
                            g.attrs["height_mm"])
    ang = ev.angle_deg(g["direction"][:], dt)[g["valid"][:]]
    res["directions_deg"] = {"median": float(np.median(ang)), "max": float(ang.max())}
    compared_models = models + extra + (["best"] if materials else []) + ["diffuse"]
    res["holdout_vs_clean"] = ev.holdout_against_truth(cap, truth, out, compared_models)
    res["speckle"] = ev.highlight_speckle(cap, truth, out, compared_models)
    if materials:
        from parammap.models.materials import adjusted_rand_index
        from parammap.stores.fit import open_fit
        from parammap.synth.pbr import patch_labels

        lab = open_fit(out / "fit" / "mh-materials.zarr")["label"][:]
        true = patch_labels(truth, lab.shape[1], lab.shape[0], c.width_mm, c.height_mm)
        res["materials"] = {
            "count": int(lab.max()), "adjusted_rand_index": adjusted_rand_index(lab, true),
            "best": json.loads((out / "metrics" / "best.json").read_text())}
    return res


def _print(res: dict) -> None:
    h, i, p = res["hdr"], res["intrinsics"], res["poses"]
    if h["oracle_median"] is None:  # a linear (RAW) capture
        print(f"{res['preset']}: HDR median {100 * h['median']:.2f} %, p95 "
              f"{100 * h['p95']:.2f} % (linear capture)")
    else:
        print(f"{res['preset']}: HDR median {100 * h['median']:.2f} % (oracle "
              f"{100 * h['oracle_median']:.2f}), p95 {100 * h['p95']:.2f} % (oracle "
              f"{100 * h['oracle_p95']:.2f})")
    print(f"  intrinsics fx {100 * i['fx_rel']:+.3f} %, fy {100 * i['fy_rel']:+.3f} %, "
          f"principal point {i['principal_px']:.2f} px")
    print(f"  views kept {p['kept']}/{p['views']} (held out {p['held_out_kept']}/"
          f"{p['held_out']}); centre median {p['centre_mm_median']:.2f} mm worst "
          f"{p['centre_mm_worst']:.2f}; rotation median {p['rotation_deg_median']:.3f} deg "
          f"worst {p['rotation_deg_worst']:.3f}")
    print(f"  map {p['map']['S']}x{p['map']['T']} ({p['map']['source']}); directions median "
          f"{res['directions_deg']['median']:.4f} deg, max {res['directions_deg']['max']:.4f}")
    for vid, row in res["holdout_vs_clean"].items():
        print(f"  held out {vid}: " + ", ".join(f"{m} {v:.2f}" for m, v in row.items()))
    sp = dict(res["speckle"])
    print(f"  highlight speckle over {sp.pop('highlights')} (view, patch) highlights, "
          "neighbouring-pixel variation against the clean render's: "
          + ", ".join(f"{m} {v['ratio']:.2f} (worst {v['worst']:.2f})" for m, v in sp.items()))
    if "materials" in res:
        print(f"  basis materials: {res['materials']['count']}, adjusted Rand index against "
              f"the true patches {res['materials']['adjusted_rand_index']:.3f}")
    print("  seconds: " + ", ".join(f"{k} {v:.0f}" for k, v in res["seconds"].items()))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="pbr-bench")
    ap.add_argument("--root", default="data/bench")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--models", nargs="*", default=["mh-1", "mh-2"])
    ap.add_argument("--materials", action="store_true",
                    help="also the basis materials (ARI against the true patches) and best map")
    ap.add_argument("--reuse-hdr", action="store_true",
                    help="keep the HDR frames of an earlier run (the merge is the slow part)")
    ap.add_argument("--camera-noise", action="store_true",
                    help="render the photos with about a camera's noise (stratified samples)"
                         " and the held-out truths 5x cleaner")
    a = ap.parse_args()
    root = Path(a.root)
    root.mkdir(parents=True, exist_ok=True)
    r = run(a.preset, root, a.models, a.seed, a.reuse_hdr, a.materials, a.camera_noise)
    (root / f"{a.preset}.json").write_text(json.dumps(r, indent=1))
    _print(r)
