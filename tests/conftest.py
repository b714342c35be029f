"""Shared fixtures: one tiny synthetic capture per test session (per worker), and the
physically based ``pbr-tiny`` capture, rendered once for all workers."""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from parammap.cli import main
from parammap.stages.calibration import Intrinsics
from parammap.stores.camera import save_intrinsics
from parammap.synth.generate import generate

SHARED = Path(__file__).resolve().parents[2] / "shared"
REAL = SHARED / "data" / "real"


# The longest modules (rendering or a whole workflow in a module fixture), longest first:
# `make test` runs the modules on parallel workers in collection order
# (``--dist loadfile --no-loadscope-reorder``), so these start at once rather than
# leaving one worker alone with a long tail. The relighting tests come after the
# viewer's and svbrdf's, by when the other worker has rendered pbr-tiny: a worker that
# waits for it leaves a core idle through that fixture's single-threaded stages.
LONGEST_FIRST = ("test_pbr_capture.py", "test_demo_accuracy.py", "test_viewer.py",
                 "test_svbrdf.py", "test_pbr_relight.py", "test_cluster.py", "test_paper.py")


def pytest_collection_modifyitems(items: list) -> None:
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(Path(str(item.fspath)).name, len(rank)))


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> tuple[Path, Path]:
    """(capture dir, truth dir) of the ``tiny`` preset, seed 0. Read-only for tests."""
    root = tmp_path_factory.mktemp("tiny")
    cap = generate(root / "cap", root / "truth", preset="tiny", seed=0, workers=2)
    return cap, root / "truth"


@pytest.fixture()
def tiny_copy(tiny_capture, tmp_path) -> Path:
    """A writable copy of the tiny capture, for tests that break it."""
    dst = tmp_path / "cap"
    shutil.copytree(tiny_capture[0], dst)
    return dst


def poses_with_true_intrinsics(cap: Path, truth: Path, out: Path) -> None:
    """Response, HDR and poses of a capture, with the generator's true intrinsics (the
    tiny preset's 320x240 board photos are too small to calibrate)."""
    assert main(["response", str(cap), "--out", str(out)]) == 0
    assert main(["hdr", str(cap), "--out", str(out)]) == 0
    cam = yaml.safe_load((truth / "camera.yaml").read_text())
    save_intrinsics(out / "camera" / "intrinsics.yaml",
                    Intrinsics(np.array(cam["K"]), np.array(cam["dist"]),
                               tuple(cam["image_size"]), 0.0))
    assert main(["poses", str(cap), "--out", str(out)]) == 0


@pytest.fixture(scope="session")
def tiny_processed(tiny_capture, tmp_path_factory):
    """The tiny capture through response, HDR, poses (true intrinsics: the tiny preset's
    320x240 board photos are too small to calibrate) and the observation map."""
    cap, truth = tiny_capture
    out = tmp_path_factory.mktemp("proc")
    poses_with_true_intrinsics(cap, truth, out)
    assert main(["observe", str(cap), "--out", str(out), "--set", "observation.texels_x=24",
                 "--set", "observation.tile=8", "--figures", str(out / "fig")]) == 0
    return cap, truth, out


@pytest.fixture()
def tiny_work(tiny_processed, tmp_path) -> tuple[Path, Path, Path]:
    """(capture, truth, processed) with a writable copy of ``tiny_processed``'s folder,
    for tests that fit or export into it: the session's folder is shared, and what one
    test wrote there another would find (or miss) depending on the order they ran in."""
    cap, truth, out = tiny_processed
    work = tmp_path / "proc"
    shutil.copytree(out, work)
    return cap, truth, work


PBR_MODELS = ["--model", "mh-1", "--model", "sh-rlsop-36", "--model", "diffuse"]


@contextlib.contextmanager
def _exclusive(path: Path):
    """An exclusive lock on ``path`` (created), held for the block: one process builds
    what the parallel test workers share, the others wait for it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def pbr_tiny(tmp_path_factory) -> tuple[Path, Path, Path]:
    """(capture, truth, processed) of the ``pbr-tiny`` preset, seed 0, through every
    stage up to the held-out comparison of mh-1, sh-rlsop-36 and diffuse. Read-only for
    tests. Rendered once per run: under pytest-xdist the first worker to ask builds it
    in the run's common temporary folder while the others wait on a lock."""
    pytest.importorskip("mitsuba", reason="the pbr presets need parammap[pbr] (Mitsuba 3)")
    from parammap.synth.pbr import generate_pbr

    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "pbr-tiny"
    cap, truth, out = root / "cap", root / "truth", root / "proc"
    with _exclusive(root.with_name("pbr-tiny.lock")):
        if not (root / "done").is_file():  # a worker whose build failed left no mark
            shutil.rmtree(root, ignore_errors=True)
            generate_pbr(cap, truth, preset="pbr-tiny", seed=0)
            for stage in (["response"], ["hdr"], ["calibrate"], ["poses"], ["observe"],
                          ["fit-mh", "--lobes", "1"], ["fit-sh", "--model", "sh-rlsop-36"],
                          ["export", *PBR_MODELS], ["holdout", *PBR_MODELS]):
                assert main([stage[0], str(cap), "--out", str(out), *stage[1:]]) == 0, stage
            (root / "done").write_text(str(os.getpid()))
    return cap, truth, out
