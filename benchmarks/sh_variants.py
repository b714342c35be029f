"""One SH model, with config overrides, refitted on a processed capture and compared on
its held-out views (issue 49): the quick loop for trying an SH projection's settings
without rerunning the workflow.

The processed folder's camera, HDR frames and observation map are reused (linked into a
scratch folder); the model is fitted (``fit-sh --set ...``), exported beside the diffuse
texture and compared with the held-out photos (``holdout``), or with the generator's
clean renders when ``--truth`` names its truth folder (the physically based presets).

    python benchmarks/sh_variants.py --capture data/captures/demo \
        --processed data/processed/demo --model sh-rlsop-36 [--set fit.sh.robust=false]

Prints the mean 8-bit difference per held-out view, the model's and the diffuse
texture's, and the fit's seconds.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from _scratch import scratch_processed

from parammap.cli import main


def compare(capture: Path, processed: Path, model: str, sets: list[str],
            truth: Path | None, scratch: Path) -> dict:
    """Fit ``model`` with ``sets`` in ``scratch`` and compare it with the diffuse texture
    on the held-out views; returns the per-view means and the fit's seconds."""
    out = scratch_processed(processed, scratch, ("hdr", "observation.zarr", "capture.ok"))
    (out / "metrics").mkdir()
    (out / "fit").mkdir()
    for f in (processed / "fit").glob("mh-*.zarr"):  # the MH fits sh-mh-<n^2> bakes
        (out / "fit" / f.name).symlink_to(f.resolve())
    for f in (processed / "metrics").glob("*.json"):  # the stages' records they read
        (out / "metrics" / f.name).write_bytes(f.read_bytes())
    t0 = time.perf_counter()
    assert main(["fit-sh", "--out", str(out), "--model", model,
                 *[x for kv in sets for x in ("--set", kv)]]) == 0
    seconds = time.perf_counter() - t0
    models = [x for m in (model, "diffuse") for x in ("--model", m)]
    assert main(["export", "--out", str(out), *models]) == 0
    if truth is not None:
        from parammap.synth import testsupport as ev

        views = ev.holdout_against_truth(capture, truth, out, [model, "diffuse"])
    else:
        assert main(["holdout", str(capture), "--out", str(out), *models]) == 0
        h = json.loads((out / "metrics" / "holdout.json").read_text())["views"]
        views = {v: {m: r["models"][m]["mean_diff_8bit"] for m in (model, "diffuse")}
                 for v, r in h.items()}
    return {"views": views, "fit_seconds": seconds}


def cli(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", type=Path, required=True)
    ap.add_argument("--processed", type=Path, required=True)
    ap.add_argument("--model", default="sh-rlsop-36")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--truth", type=Path, help="the generator's truth folder: compare "
                                               "with its clean renders, not the photos")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        r = compare(a.capture, a.processed, a.model, a.set, a.truth, Path(tmp) / "proc")
    for m in (a.model, "diffuse"):
        per = [row[m] for row in r["views"].values()]
        print(f"{m}: mean {np.mean(per):.3f}; " + ", ".join(
            f"{v} {row[m]:.2f}" for v, row in r["views"].items()))
    print(f"fit {r['fit_seconds']:.0f} s")


if __name__ == "__main__":
    cli()
