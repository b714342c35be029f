"""Gather the per-view HDR figures into metrics/hdr.json (Snakemake script)."""

import json
from pathlib import Path

from parammap.metrics import write_metrics

snakemake = globals()["snakemake"]
views = {Path(p).stem: json.loads(Path(p).read_text()) for p in snakemake.input.stats}
write_metrics(snakemake.output[0], {
    "views": len(views),
    "saturated_fraction_max": max(v["saturated_fraction"] for v in views.values()),
    "per_view": views,
})
