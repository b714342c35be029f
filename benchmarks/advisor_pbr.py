"""Capture advisor on a physically based capture (issue 20): do the views it advises
cut the held-out error more than as many random views?

From a processed physically based capture (``benchmarks/pbr_capture.py`` first), a
``--pool`` of its fitted views is set aside (seeded at random) and the rest are fitted
(``--model``, an MH fit). The advisor ranks the pool's directions (as seen from the
region's centre) by the greedy design of the ``advise`` stage on that fit (its default,
D-optimal, and the I-optimal one for comparison); its ``--count`` best are added back and the
map refitted, and so are the pool views that fill the largest gaps between the fitted
ones (the advisor's fallback) and ``--random`` draws of as many pool views at random.
Each map is compared with the clean renders of the capture's held-out views (mean 8-bit
difference, as ``pbr_capture.py``), or, on a capture of the analytic generator (its
truth folder holds ``scene.npz``: the demo), with the truth itself in 256 directions up
to 75 deg at every texel (:func:`parammap.synth.testsupport.directions_against_truth`),
which three or four held-out views are too few and too noisy to replace. The pool's
views are real photos of the capture, so no view is rendered anew.

    python benchmarks/advisor_pbr.py --preset pbr-tiny --pool 8 --count 3 --random 3
    python benchmarks/advisor_pbr.py --preset demo --root data/captures \
        --processed data/processed/demo --model mh-auto --pool 8 --count 3 --random 6

Writes ``<root>/<preset>.advise.json`` and prints the figures.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

from parammap.cli import ON_PROCESSED, main
from parammap.config import validate_config
from parammap.geometry import unit
from parammap.models.advisor import advise_directions
from parammap.stores.capture import load_capture
from parammap.stores.fit import open_mh_source
from parammap.stores.observation import sample_texel_observations
from parammap.synth import testsupport as ev
from parammap.synth.sampling import stratified

#: directions the analytic generator's truth is compared in: 256, stratified over the
#: cap up to 75 deg (beyond the demo's 72 deg views, as far as real captures reach)
DIRECTIONS = stratified(16, 75.0, seed=1)


def _workdir(proc: Path, work: Path) -> None:
    """A processed folder sharing ``proc``'s camera files and HDR frames (linked)."""
    shutil.rmtree(work, ignore_errors=True)
    (work / "camera").mkdir(parents=True)
    for f in (proc / "camera").iterdir():
        shutil.copy(f, work / "camera" / f.name)
    (work / "hdr").symlink_to((proc / "hdr").resolve())


def _errors(cap: Path, truth: Path, work: Path, model: str) -> dict[str, dict[str, float]]:
    """Held-out errors of the map in ``work``: against the clean renders of the held-out
    views (a physically based capture), or, for the analytic generator (``scene.npz``),
    against its truth in :data:`DIRECTIONS` at every texel (``{"directions": {model:
    error}}``: hundreds of directions instead of a few held-out views)."""
    if (truth / "scene.npz").is_file():
        return {"directions": ev.directions_against_truth(truth, work, [model], DIRECTIONS)}
    return ev.holdout_against_truth(cap, truth, work, [model])


def _fit(cap: Path, truth: Path, work: Path, poses: dict, kept: set[str],
         model: str) -> dict[str, float]:
    """Observation map and fit from the fitted views in ``kept``; held-out errors."""
    recs = json.loads(json.dumps(poses))
    for r in recs["views"]:
        if not r.get("holdout") and r.get("kept"):
            r["kept"] = r["id"] in kept
    (work / "camera" / "poses.yaml").write_text(yaml.safe_dump(recs, sort_keys=False))
    for d in ("observation.zarr", "fit", "params"):
        shutil.rmtree(work / d, ignore_errors=True)
    lobes = model.split("-")[1]
    for stage in (["observe"], ["fit-mh", "--lobes", lobes], ["export", "--model", model]):
        reads = [] if stage[0] in ON_PROCESSED else [str(cap)]
        assert main(["-q", stage[0], *reads, "--out", str(work), *stage[1:]]) == 0, stage
    return _errors(cap, truth, work, model)


def _advise(work: Path, model: str, pool_dirs: np.ndarray, count: int,
            seed: int, criterion: str | None = None) -> list[int]:
    """Indices into the pool of the ``count`` directions the advisor ranks first (by
    ``criterion``, default the stage's)."""
    cfg = validate_config({"captures": {"x": "."}})["advisor"]
    criterion = criterion or cfg["criterion"]
    _, obs, P, fitted = open_mh_source(work, model, "advisor.source")
    T, S, _ = obs["valid"].shape
    rng = np.random.default_rng(seed)
    idx, V, L, W, w = sample_texel_observations(obs, np.flatnonzero(fitted), S,
                                                int(obs.attrs["tile"]), int(cfg["sample"]),
                                                rng)
    order, _, _ = advise_directions(P[idx], V, L, W, w, pool_dirs, count, criterion)
    return [int(i) for i in order]


def run(preset: str, root: Path, pool: int, count: int, draws: int, model: str,
        seed: int, processed: Path | None = None) -> dict:
    cap, truth = root / preset, root / f"{preset}.truth"
    proc = processed or root / f"{preset}.proc"
    poses = yaml.safe_load((proc / "camera" / "poses.yaml").read_text())
    fitted = [r for r in poses["views"] if r.get("kept") and not r.get("holdout")]
    rng = np.random.default_rng(seed)
    pool_ids = [fitted[i]["id"] for i in rng.choice(len(fitted), pool, replace=False)]
    base = {r["id"] for r in fitted} - set(pool_ids)
    work = proc.parent / f"{preset}.advise"
    _workdir(proc, work)
    c = load_capture(cap)
    X0 = np.array([c.width_mm / 2, c.height_mm / 2, 0.0])
    centre = {r["id"]: np.asarray(r["centre_mm"], float) for r in fitted}
    pool_dirs = unit(np.array([centre[i] for i in pool_ids]) - X0)
    res: dict = {"preset": preset, "model": model, "pool": pool_ids, "fitted_before": len(base)}
    t0 = time.perf_counter()
    res["base"] = _fit(cap, truth, work, poses, base, model)
    picked = [pool_ids[i] for i in _advise(work, model, pool_dirs, count, seed)]
    # the stage's other design (I-optimal against the D-optimal default, or back)
    default = validate_config({"captures": {"x": "."}})["advisor"]["criterion"]
    res["other_criterion"] = other = "prediction" if default == "volume" else "volume"
    alt = [pool_ids[i] for i in _advise(work, model, pool_dirs, count, seed, other)]
    res["advised_views"] = picked
    res["advised"] = _fit(cap, truth, work, poses, base | set(picked), model)
    res["other_views"] = alt
    res["other"] = res["advised"] if set(alt) == set(picked) else \
        _fit(cap, truth, work, poses, base | set(alt), model)
    # the advisor's own fallback: fill the largest gaps between the views (greedy)
    have = unit(np.array([centre[i] for i in base]) - X0)
    gap = np.degrees(np.arccos(np.clip((pool_dirs @ have.T).max(1), -1, 1)))
    gaps = []
    for _ in range(count):
        b = int(np.argmax(gap))
        gaps.append(pool_ids[b])
        gap = np.minimum(gap, np.degrees(np.arccos(np.clip(pool_dirs @ pool_dirs[b], -1, 1))))
    res["gap_views"] = gaps
    res["gaps"] = _fit(cap, truth, work, poses, base | set(gaps), model)
    res["random"] = []
    for k in range(draws):
        ids = list(np.random.default_rng(seed + 1 + k).choice(pool_ids, count, replace=False))
        res["random"].append({"views": [str(i) for i in ids],
                              "errors": _fit(cap, truth, work, poses, base | set(ids), model)})
    res["seconds"] = time.perf_counter() - t0
    shutil.rmtree(work, ignore_errors=True)

    def mean(errs):
        return float(np.mean([row[model] for row in errs.values()]))

    res["mean"] = {"base": mean(res["base"]), "advised": mean(res["advised"]),
                   "other": mean(res["other"]),
                   "gaps": mean(res["gaps"]),
                   "random": [mean(r["errors"]) for r in res["random"]]}
    return res


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="pbr-tiny")
    ap.add_argument("--root", default="data/bench")
    ap.add_argument("--pool", type=int, default=8, help="fitted views set aside")
    ap.add_argument("--count", type=int, default=3, help="views added back")
    ap.add_argument("--random", type=int, default=3, help="random draws to compare")
    ap.add_argument("--model", default="mh-auto")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--processed", type=Path, default=None,
                    help="processed capture (default <root>/<preset>.proc)")
    a = ap.parse_args()
    r = run(a.preset, Path(a.root), a.pool, a.count, a.random, a.model, a.seed, a.processed)
    (Path(a.root) / f"{a.preset}.advise.json").write_text(json.dumps(r, indent=1))
    m = r["mean"]
    print(f"{a.preset} {a.model}: held-out mean 8-bit difference with {r['fitted_before']} "
          f"views {m['base']:.2f}; + {a.count} advised {r['advised_views']} "
          f"{m['advised']:.2f}; + {a.count} by {r['other_criterion']} {r['other_views']} "
          f"{m['other']:.2f}; "
          f"+ {a.count} filling gaps {r['gap_views']} {m['gaps']:.2f}; "
          f"+ {a.count} random " + ", ".join(f"{x:.2f}" for x in
                                                              m["random"])
          + f" (mean {np.mean(m['random']):.2f}); {r['seconds']:.0f} s")
