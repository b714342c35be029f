"""Benchmark: the recovered response against an oracle over families of camera responses
(issue 45 item 4).

For each response family (a pure gamma, sRGB, a filmic curve with toe and shoulder, a
rational curve with a hard shoulder, the demo generator's own), bracket spacing (1 and 2
stops) and exposure count (3, 5, 7), three brackets of a finely printed exposure ramp
with shot and read noise are made, the response recovered from them
(:func:`parammap.stages.hdr.recover_response`) and one bracket merged with it and with
the true response (the oracle). Prints the merged radiance's relative error against the
truth, median and 95th percentile, and the ratio to the oracle's::

    python benchmarks/response_families.py [--out data/bench/response_families.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from parammap.synth.responses import FAMILIES, against_oracle


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="data/bench/response_families.json")
    a = ap.parse_args()
    rows = []
    print(f"{'family':>14} {'stops':>5} {'n':>2} {'median %':>9} {'oracle':>7} {'x':>5} "
          f"{'p95 %':>7} {'oracle':>7} {'x':>5}")
    for name, R in FAMILIES.items():
        for stops in (1.0, 2.0):
            for count in (3, 5, 7):
                r = against_oracle(name, R, stops, count)
                rows.append(r)
                print(f"{name:>14} {stops:5.0f} {count:2d} {100 * r['median']:9.2f} "
                      f"{100 * r['oracle_median']:7.2f} {r['ratio_median']:5.2f} "
                      f"{100 * r['p95']:7.2f} {100 * r['oracle_p95']:7.2f} "
                      f"{r['ratio_p95']:5.2f}", flush=True)
    worst = max(rows, key=lambda r: max(r["ratio_median"], r["ratio_p95"]))
    print(f"worst: {worst['family']} {worst['stops']:g} stops x {worst['exposures']}: "
          f"{worst['ratio_median']:.2f} / {worst['ratio_p95']:.2f} of the oracle")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
