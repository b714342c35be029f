"""One table and figure over every surface of a run (issue 19): a lab processing many
surfaces sees the outliers at a glance."""

from __future__ import annotations

import csv

import numpy as np

from parammap.cli import main
from parammap.stages.figures import _robust_outliers
from parammap.stores.metrics import write_metrics


def test_outliers_are_robust():
    v = np.array([1.0, 1.1, 0.9, 1.05, 0.95, 5.0, np.nan])
    assert _robust_outliers(v).tolist() == [False] * 5 + [True, False]
    assert not _robust_outliers(np.array([1.0, 2.0])).any()  # too few to judge


def test_summary_over_surfaces(tmp_path):
    for k, sid in enumerate(["s1", "s2", "s3", "s4"]):
        m = tmp_path / "proc" / sid / "metrics"
        write_metrics(m / "poses.json", {"views": 100, "kept_fraction": 0.99 - 0.3 * (k == 3),
                                         "median_rms_px": 0.05})
        write_metrics(m / "calibration.json", {"rms_px": 0.2})
        write_metrics(m / "observation.json", {"texels": 4096, "valid_fraction": 0.9})
        write_metrics(m / "fit-mh-1.json", {"mean_percentage_residual": [5.0, 6.0, 7.0],
                                            "seconds": 10.0})
        write_metrics(m / "holdout.json", {"views": {"v1": {"models": {
            "mh-1": {"mean_diff_8bit": 8.0 + k}}}}})
    assert main(["batch-summary", "--processed", str(tmp_path / "proc"), "--surface", "s1",
                 "--surface", "s2", "--surface", "s3", "--surface", "s4", "--model", "mh-1",
                 "--out", str(tmp_path / "reports")]) == 0
    with (tmp_path / "reports" / "summary.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["surface"] for r in rows] == ["s1", "s2", "s3", "s4"]
    assert float(rows[2]["mh-1 residual %"]) == 6.0
    assert float(rows[3]["mh-1 held-out 8-bit"]) == 11.0
    assert (tmp_path / "reports" / "summary.png").stat().st_size > 5000
