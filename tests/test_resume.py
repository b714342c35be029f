"""A killed fit resumes where it stopped (issue 19): only the tiles left are fitted, and
the finished store is byte for byte the store of an uninterrupted run."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import pytest
import zarr

from parammap.models.mh import REPAIR_RADIUS, MhFitConfig, fit_mh_tile, mh_outputs, repair_mh_tile
from parammap.stages.fit import fit_map
from parammap.stores.observation import write_observation_arrays
from parammap.synth.cases import phong_case


class Killed(RuntimeError):
    pass


class Tiles:
    """A tile function that counts its calls and dies at call ``die_at``."""

    def __init__(self, die_at=None):
        self.calls, self.die_at = 0, die_at
        self.fn = partial(fit_mh_tile, K=1, cfg=MhFitConfig(), K_max=1)

    def __call__(self, *args, **kw):
        self.calls += 1
        if self.calls == self.die_at:
            raise Killed("pre-empted")
        return self.fn(*args, **kw)


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture()
def obs(tmp_path):
    case = phong_case(texels=8, level=2, noise=0.002)
    return write_observation_arrays(tmp_path / "obs.zarr", case.radiance, case.direction,
                                    case.valid, 1000.0, 1000.0, tile=2)


def _fit(obs, out, tiles):
    repair = partial(repair_mh_tile, K=1, cfg=MhFitConfig())
    return fit_map(obs, out, tiles, mh_outputs(1), {"model": "mh", "lobes": "1"},
                   "synchronous", 1, repair_fn=repair, halo=REPAIR_RADIUS)


def test_killed_fit_resumes_and_matches_an_uninterrupted_run(obs, tmp_path):
    ref = Tiles()
    _fit(obs, tmp_path / "ref" / "mh-1.zarr", ref)
    assert ref.calls == 16  # 8 x 8 texels in 2 x 2 tiles
    out = tmp_path / "run" / "mh-1.zarr"
    first = Tiles(die_at=9)
    with pytest.raises(Killed):
        _fit(obs, out, first)
    assert not out.exists() and (out.parent / ".mh-1.zarr.partial").is_dir()
    second = Tiles()
    m = _fit(obs, out, second)
    assert second.calls == 16 - 8  # only the tiles the killed run had not finished
    assert m["status"].shape == (8, 8)
    assert _files(out) == _files(tmp_path / "ref" / "mh-1.zarr")
    assert not (out.parent / ".mh-1.zarr.partial").exists()
    assert not (out.parent / ".mh-1.zarr.tiles").exists()


class Smooth:
    """A repair that replaces every texel's RMSE by the mean over its halo window (so a
    tile's result depends on what its neighbours hold), dying at call ``die_at``."""

    def __init__(self, die_at=None):
        self.calls, self.die_at = 0, die_at

    def __call__(self, fields, radiance, direction, valid, offset, noise=None):
        self.calls += 1
        if self.calls == self.die_at:
            raise Killed("pre-empted")
        (oy, ox), (t, u) = offset, valid.shape[:2]
        out = {k: np.array(fields[k][oy:oy + t, ox:ox + u]) for k in ("rmse", "status")}
        out["rmse"][:] = np.nanmean(fields["rmse"], (0, 1))
        out["changed"] = np.ones((t, u), np.int8)
        return out


def test_repair_reads_the_tile_pass_and_resumes_identically(obs, tmp_path):
    def fit(out, repair):
        return fit_map(obs, out, Tiles(), mh_outputs(1), {"model": "mh", "lobes": "1"},
                       "synchronous", 1, repair_fn=repair, halo=1)

    ref = tmp_path / "ref" / "mh-1.zarr"
    fit(ref, Smooth())
    plain = tmp_path / "plain" / "mh-1.zarr"
    res = fit_map(obs, plain, Tiles(), mh_outputs(1), {"model": "mh"},
                  "synchronous", 1)
    assert res["status"].shape == (8, 8)
    # every tile's halo is the tile pass's RMSE, not a neighbour's repaired one
    before = zarr.open_group(plain)["rmse"][:]
    got = zarr.open_group(ref)["rmse"][:]
    for i in range(0, 8, 2):
        for j in range(0, 8, 2):
            win = before[max(i - 1, 0):i + 3, max(j - 1, 0):j + 3]
            np.testing.assert_allclose(got[i, j], np.nanmean(win, (0, 1)), rtol=1e-6)
    out = tmp_path / "run" / "mh-1.zarr"
    with pytest.raises(Killed):
        fit(out, Smooth(die_at=7))
    again = Smooth()
    fit(out, again)
    assert again.calls == 16 - 6  # the repairs finished before the kill are kept
    assert _files(out) == _files(ref)


def test_a_changed_config_starts_afresh(obs, tmp_path):
    out = tmp_path / "mh-1.zarr"
    with pytest.raises(Killed):
        _fit(obs, out, Tiles(die_at=5))
    again = Tiles()
    repair = partial(repair_mh_tile, K=1, cfg=MhFitConfig())
    fit_map(obs, out, again, mh_outputs(1), {"model": "mh", "lobes": "1", "other": 1},
            "synchronous", 1, repair_fn=repair, halo=REPAIR_RADIUS)
    assert again.calls == 16
    assert np.isfinite(zarr.open_group(out)["params"][:]).all()


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_no_worker_outlives_a_killed_fit(tmp_path):
    """kill -9 of the driver (a pre-empting scheduler, the OOM killer): its worker
    processes end with it."""
    import os
    import signal
    import subprocess
    import sys
    import time

    case = phong_case(texels=24, level=3, noise=0.002)
    obs = write_observation_arrays(tmp_path / "obs.zarr", case.radiance, case.direction,
                                   case.valid, 1000.0, 1000.0, tile=4)
    code = ("from parammap.stages.fit import fit_mh_map\n"
            "if __name__ == '__main__':\n"
            f"    fit_mh_map({str(obs)!r}, {str(tmp_path / 'mh.zarr')!r}, 'auto', {{}}, "
            "'processes', 2)\n")
    script = tmp_path / "drive.py"
    script.write_text(code)
    driver = subprocess.Popen([sys.executable, str(script)], stderr=subprocess.DEVNULL)
    workers: list[int] = []
    deadline = time.time() + 60
    while time.time() < deadline and len(workers) < 2 and driver.poll() is None:
        time.sleep(0.2)
        workers = [c for c in _children(driver.pid) if _alive(c)]
    assert driver.poll() is None and workers, "the fit ended before its workers were seen"
    os.kill(driver.pid, signal.SIGKILL)
    driver.wait()
    # a worker still starting (importing) when its parent died ends once it gets to
    # its initializer; on a loaded machine that takes a few seconds
    deadline = time.time() + 30
    while time.time() < deadline and [w for w in workers if _alive(w)]:
        time.sleep(0.5)
    assert not [w for w in workers if _alive(w)]


def test_fit_through_a_dask_distributed_cluster_address(tmp_path):
    """fit.scheduler set to a dask.distributed scheduler's address (a cluster) gives the
    maps of the in-process scheduler."""
    distributed = pytest.importorskip("distributed")

    from parammap.stages.fit import fit_mh_map

    case = phong_case(texels=8, level=2, noise=0.002)
    obs = write_observation_arrays(tmp_path / "obs.zarr", case.radiance, case.direction,
                                   case.valid, 1000.0, 1000.0, tile=4)
    fit_mh_map(obs, tmp_path / "local.zarr", 1, {}, "synchronous", 1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  protocol="tcp", dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://")
        m = fit_mh_map(obs, tmp_path / "cluster.zarr", 1, {}, cluster.scheduler_address, 2)
    assert m["fitted"] == 64
    a, b = zarr.open_group(tmp_path / "local.zarr"), zarr.open_group(tmp_path / "cluster.zarr")
    for name in ("params", "rmse", "status"):
        np.testing.assert_array_equal(a[name][:], b[name][:])


def test_killed_observation_build_resumes(tiny_processed, tmp_path, monkeypatch):
    """The observation map's views: a build killed part way samples only the views
    left when run again, and writes the same store as an uninterrupted build."""
    import parammap.stages.observation as obsmod
    from parammap.stores.capture import load_capture

    cap, _, proc = tiny_processed
    capture = load_capture(cap)
    ref = tmp_path / "ref" / "observation.zarr"
    obsmod.build_observation_map(capture, proc, ref, 16, None, 8, workers=1)
    calls = []
    real = obsmod._pass1_view

    def dying(job):
        calls.append(job[1])
        if len(calls) == 5:
            raise Killed("pre-empted")
        return real(job)

    out = tmp_path / "run" / "observation.zarr"
    monkeypatch.setattr(obsmod, "_pass1_view", dying)
    with pytest.raises(Killed):
        obsmod.build_observation_map(capture, proc, out, 16, None, 8, workers=1)
    calls.clear()
    monkeypatch.setattr(obsmod, "_pass1_view", lambda job: (calls.append(job[1]), real(job))[1])
    m = obsmod.build_observation_map(capture, proc, out, 16, None, 8, workers=1)
    assert len(calls) == m["views"] - 4
    assert _files(out) == _files(ref)
    assert not list(out.parent.glob(".*"))


def test_only_a_fit_with_a_repair_keeps_tile_snapshots(obs, tmp_path):
    # the snapshots are the repair's halo; a fit without one (SH) must not spend the
    # disk on them
    for repair, want in ((None, 0), (partial(repair_mh_tile, K=1, cfg=MhFitConfig()), 4)):
        out = tmp_path / f"{want}" / "mh-1.zarr"
        with pytest.raises(Killed):
            fit_map(obs, out, Tiles(die_at=5), mh_outputs(1), {"model": "mh"},
                    "synchronous", 1, repair_fn=repair, halo=REPAIR_RADIUS)
        assert len(list((out.parent / ".mh-1.zarr.tiles").glob("snap-*.npz"))) == want
