"""Gather the per-view HDR figures into metrics/hdr.json (Snakemake script)."""

from parammap.stages.hdr import gather_hdr_metrics

snakemake = globals()["snakemake"]
gather_hdr_metrics(snakemake.input.stats, snakemake.output.metrics)
