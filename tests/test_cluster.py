"""The cluster path (issue 19): the workflow through `profiles/sbatch` (Snakemake's
cluster-generic executor submitting with sbatch) against a fake sbatch that runs each
job script at once, proving the profile's resources and its grouping of the per-view
HDR merges into one submission."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytest.importorskip("snakemake_executor_plugin_cluster_generic",
                    reason="snakemake-executor-plugin-cluster-generic not installed")

FAKE_SBATCH = """#!/bin/sh
# fake sbatch: record the options, run the job script now, print a job id
echo "$@" >> "{log}"
for last; do :; done
sh "$last" > /dev/null 2>&1
echo $$
"""


def test_workflow_through_a_fake_sbatch(tiny_capture, tmp_path):
    cap, _ = tiny_capture
    (tmp_path / "bin").mkdir()
    sbatch = tmp_path / "bin" / "sbatch"
    log = tmp_path / "sbatch.log"
    sbatch.write_text(FAKE_SBATCH.format(log=log))
    sbatch.chmod(0o755)
    work = tmp_path / "work"
    (work / "config").mkdir(parents=True)
    shutil.copy(ROOT / "config" / "config.yaml", work / "config" / "config.yaml")
    (work / "run.yaml").write_text(
        f"captures: {{tiny: {cap}}}\nsynth: {{}}\noverrides: {{}}\n"
        f"processed_dir: {work / 'proc'}\nreports_dir: {work / 'rep'}\n")
    targets = [str(work / "proc" / "tiny" / "hdr" / f"v00{k}.exr") for k in range(3)]
    env = {"PATH": f"{tmp_path / 'bin'}:{Path(sys.executable).parent}:/usr/bin:/bin",
           "HOME": str(tmp_path)}
    r = subprocess.run([sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"),
                        "--directory", str(work), "--profile", str(ROOT / "profiles" / "sbatch"),
                        "--configfile", str(work / "run.yaml"), "--", *targets],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    for t in targets:
        assert Path(t).stat().st_size > 0
    calls = log.read_text().splitlines()
    by_name = {c.split("--job-name=")[1].split()[0]: c for c in calls}
    assert set(by_name) == {"smk-validate_capture", "smk-response", "smk-GROUP"}, calls
    assert "--mem=4000" in by_name["smk-response"] and "--time=60" in by_name["smk-response"]
    assert "snakejob.hdr_hdr_view" in by_name["smk-GROUP"]  # three merges, one submission
