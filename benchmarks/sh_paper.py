"""Benchmark: SH projection of a whole observation map (e.g. the ``paper`` preset's
512 x 512 texels) with dask over texel tiles.

    python benchmarks/sh_paper.py data/processed/paper/observation-bench.zarr \
        [--model sh-lsop-36] [--workers 2] [--scheduler processes]

Prints time and texels per second.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from parammap.models.sh import parse_sh_model
from parammap.stages.fit import fit_sh_map


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("observation")
    ap.add_argument("--model", default="sh-lsop-36")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scheduler", default="processes")
    a = ap.parse_args()
    hemi, n = parse_sh_model(a.model)
    with tempfile.TemporaryDirectory(dir=Path(a.observation).parent) as tmp:
        t0 = time.perf_counter()
        m = fit_sh_map(a.observation, Path(tmp) / f"{a.model}.zarr", hemi, n, {},
                       a.scheduler, a.workers)
        wall = time.perf_counter() - t0
    print(f"{a.model}: {m['texels']} texels, {m['fitted']} fitted, {m['failed']} failed")
    print(f"time {wall:.1f} s wall ({m['seconds']:.1f} s fitting), "
          f"{m['texels'] / wall:.0f} texels/s, {a.workers} {a.scheduler}")
    print(f"median percentage residual RGB {m['median_percentage_residual']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
