"""The cluster path (issue 19): the workflow through `profiles/sbatch` (Snakemake's
cluster-generic executor submitting with sbatch) against a fake sbatch that runs each
job script at once, proving the profile's resources and its grouping of the per-view
HDR merges into one submission."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
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
                        "--configfile", str(work / "run.yaml"),
                        # the fake sbatch has finished each job when it returns: no need
                        # to wait the default 10 s a round to see it
                        "--seconds-between-status-checks", "1", "--", *targets],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    for t in targets:
        assert Path(t).stat().st_size > 0
    calls = log.read_text().splitlines()
    by_name = {c.split("--job-name=")[1].split()[0]: c for c in calls}
    assert set(by_name) == {"smk-validate_capture", "smk-response", "smk-GROUP"}, calls
    assert "--mem=4000" in by_name["smk-response"] and "--time=60" in by_name["smk-response"]
    assert "snakejob.hdr_hdr_view" in by_name["smk-GROUP"]  # three merges, one submission


# fake SLURM for dask-jobqueue: sbatch keeps a copy of the job script (dask-jobqueue
# deletes its own once submitted), starts it in its own session and prints a job id;
# scancel ends that session
FAKE_JQ_SBATCH = """#!/bin/sh
for last; do :; done
id=$(date +%s%N | cut -c10-18)
cp "$last" "{jobs}/$id.sh"
setsid sh "{jobs}/$id.sh" > "{jobs}/$id.log" 2>&1 &
echo $! > "{jobs}/$id.pid"
echo "Submitted batch job $id"
"""
FAKE_JQ_SCANCEL = """#!/bin/sh
for id; do
  [ -f "{jobs}/$id.pid" ] && kill -TERM -- -"$(cat "{jobs}/$id.pid")" 2>/dev/null
done
exit 0
"""


def test_fit_through_dask_jobqueue_on_a_fake_slurm(tiny_processed, tmp_path, monkeypatch):
    """The README's SLURM + dask-jobqueue recipe: a SLURMCluster whose workers are
    sbatch jobs (here a fake sbatch that runs them on this machine), its scheduler's
    address given to ``fit-mh`` as ``fit.scheduler``: the maps equal a local fit's, and
    no worker outlives the cluster."""
    import os
    import signal
    import time

    import zarr

    jq = pytest.importorskip("dask_jobqueue", reason="dask-jobqueue not installed")
    from parammap.cli import main

    cap, _, proc = tiny_processed
    work = tmp_path / "proc"
    work.mkdir()
    for name in ("camera", "observation.zarr", "metrics"):
        shutil.copytree(proc / name, work / name)
    jobs = tmp_path / "jobs"
    jobs.mkdir()
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    for cmd, text in (("sbatch", FAKE_JQ_SBATCH), ("scancel", FAKE_JQ_SCANCEL)):
        (bin_ / cmd).write_text(text.format(jobs=jobs))
        (bin_ / cmd).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_}:{os.environ['PATH']}")
    assert main(["fit-mh", str(cap), "--out", str(work), "--workers", "1",
                 "--set", "fit.scheduler=synchronous"]) == 0
    shutil.move(work / "fit" / "mh-1.zarr", tmp_path / "local.zarr")
    with jq.SLURMCluster(cores=1, processes=1, memory="2GB", walltime="00:10:00",
                         scheduler_options={"dashboard_address": None}) as cluster:
        cluster.scale(jobs=2)
        assert main(["fit-mh", str(cap), "--out", str(work),
                     "--set", f"fit.scheduler={cluster.scheduler_address}"]) == 0
        submitted = sorted(jobs.glob("*.sh"))
    assert len(submitted) == 2 and "#SBATCH" in submitted[0].read_text()
    a, b = zarr.open_group(tmp_path / "local.zarr"), zarr.open_group(work / "fit" / "mh-1.zarr")
    for name in ("params", "rmse", "status"):
        np.testing.assert_array_equal(a[name][:], b[name][:])
    deadline = time.time() + 30
    pids = [int(p.read_text()) for p in jobs.glob("*.pid")]

    def alive(pid):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True

    while time.time() < deadline and any(alive(p) for p in pids):
        time.sleep(0.5)
    left = [p for p in pids if alive(p)]
    for p in left:
        os.killpg(p, signal.SIGKILL)
    assert not left
