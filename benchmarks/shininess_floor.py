"""How uniform can an MH shininess map of a uniform patch be (issue 15)?

On a processed capture of the analytic generator (the demo), the observation map's
radiance is replaced by the generator's noise-free radiance in the same views, the same
valid observations and the true directions, and ``fit-mh`` is run on it with the
workflow's defaults (repair and pooling included). The coefficient of variation of m
over each true material patch (its texels one in from the patch's edge, where a lobe is
fitted) is then what the model and the views allow, without noise, pose or read
errors; the processed capture's own fit is printed beside it.

    python benchmarks/shininess_floor.py --capture data/captures/demo \
        --processed data/processed/demo --lobes auto

Writes ``<processed>/../<id>.shininess_floor.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

from parammap.cli import main
from parammap.conventions import MH_M, mh_ks, mh_lobes
from parammap.stores.fit import open_fit
from parammap.stores.observation import open_observation_map, write_observation_arrays
from parammap.synth.generate import true_observations


def patch_cv(params: np.ndarray, kind: np.ndarray, m: np.ndarray, names: list[str],
             ) -> dict[str, dict[str, float]]:
    """CV of m per true patch (``kind`` and ``m`` (T, S) of the truth scene), over the
    patch's texels one in from its edge whose fit has a lobe."""
    K = mh_lobes(params.shape[-1])
    ks = sum(np.nan_to_num(params[..., mh_ks(k)]).sum(-1) for k in range(K))
    out = {}
    for kk in np.unique(kind):
        for mm in np.unique(m[kind == kk]):
            inner = binary_erosion((kind == kk) & (m == mm), iterations=1) & (ks > 0) \
                & np.isfinite(params[..., MH_M])
            v = params[..., MH_M][inner].astype(float)
            out[f"{names[kk]}{mm:g}"] = {
                "texels": int(inner.sum()),
                "cv": float(v.std() / v.mean()) if inner.sum() >= 5 else float("nan")}
    return out


def run(capture: Path, processed: Path, lobes: str) -> dict:
    truth = capture.with_name(capture.name + ".truth")
    scene = np.load(truth / "scene.npz")
    g = open_observation_map(processed / "observation.zarr")
    ids = list(g.attrs["view_ids"])
    T, S, N = g["valid"].shape
    rows, cols = (a.ravel() for a in np.mgrid[0:T, 0:S])
    d, rad = true_observations(truth, ids, rows, cols)
    valid = g["valid"][:]
    L = g["radiance"][:].reshape(T * S, N, 3)
    ok = valid.reshape(T * S, N)[..., None] & (rad > 0) & (L > 0)
    scale = float(np.median(L[ok] / rad[ok]))  # the capture's radiance scale
    attrs = {k: g.attrs[k] for k in g.attrs.keys() if k != "parammap_complete"}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        shutil.copytree(processed / "camera", work / "camera")
        noise = g["noise"][:] if "noise" in g else None
        write_observation_arrays(work / "observation.zarr",
                                 (scale * rad).reshape(T, S, N, 3).astype(np.float32),
                                 d.reshape(T, S, N, 3).astype(np.float32), valid,
                                 g.attrs["width_mm"], g.attrs["height_mm"],
                                 int(g.attrs["tile"]), ids, attrs=attrs, noise=noise)
        assert main(["fit-mh", "--out", str(work), "--lobes", lobes]) == 0
        ideal = open_fit(work / "fit" / f"mh-{lobes}.zarr")["params"][:]
    names = [str(n) for n in scene["kind_names"]]
    own = open_fit(processed / "fit" / f"mh-{lobes}.zarr")["params"][:]
    return {"model": f"mh-{lobes}",
            "noise_free": patch_cv(ideal, scene["kind"], scene["m"], names),
            "capture": patch_cv(own, scene["kind"], scene["m"], names)}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", default="data/captures/demo")
    ap.add_argument("--processed", default="data/processed/demo")
    ap.add_argument("--lobes", default="auto")
    a = ap.parse_args()
    res = run(Path(a.capture), Path(a.processed), a.lobes)
    dest = Path(a.processed).parent / f"{Path(a.capture).name}.shininess_floor.json"
    dest.write_text(json.dumps(res, indent=1))
    print(f"{res['model']}: CV of m per patch, noise-free data / the capture")
    for k, v in res["noise_free"].items():
        c = res["capture"][k]
        print(f"  {k:12s} {v['cv']:.3f} ({v['texels']}) / {c['cv']:.3f} ({c['texels']})")
