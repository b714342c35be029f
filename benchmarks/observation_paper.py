"""Benchmark: build the observation map of the ``paper`` preset (512 x 512 texels).

Needs a processed paper capture (poses and HDR frames), e.g.::

    parammap synth --preset paper --out data/captures/paper --workers 2
    snakemake --cores 2 --config 'captures={"paper": "data/captures/paper"}' \
        'observation={"texels_x": 512}' -- data/processed/paper/camera/poses.yaml

then ``python benchmarks/observation_paper.py data/captures/paper data/processed/paper``.
Prints build time, peak RSS (this process and its workers) and MB/s of HDR read.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

from parammap.stages.observation import build_observation_map
from parammap.stores.capture import load_capture


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("processed")
    ap.add_argument("--texels", type=int, default=512)
    ap.add_argument("--tile", type=int, default=32)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", help="store path (default <processed>/observation-bench.zarr)")
    a = ap.parse_args()
    out = Path(a.out or Path(a.processed) / "observation-bench.zarr")
    t0 = time.perf_counter()
    m = build_observation_map(load_capture(a.capture), a.processed, out, a.texels, None,
                              a.tile, workers=a.workers)
    wall = time.perf_counter() - t0
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print(f"texels {m['S']}x{m['T']}  views {m['views']}  workers {a.workers}")
    print(f"build time      {wall:8.1f} s  (sampling {m['sample_seconds']:.1f} s)")
    print(f"peak RSS        {self_kb / 1024:8.0f} MB main, {child_kb / 1024:.0f} MB largest worker")
    print(f"HDR read        {m['read_mb_per_s']:8.1f} MB/s ({m['hdr_bytes_read'] / 1e9:.2f} GB)")
    print(f"store           {m['bytes_on_disk'] / 1e6:8.1f} MB on disk, "
          f"{m['bytes_uncompressed'] / 1e6:.1f} MB uncompressed "
          f"(ratio {m['compression_ratio']:.2f})")
    print(f"valid fraction  {m['valid_fraction']:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
