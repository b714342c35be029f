"""Shared fixtures: one tiny synthetic capture per test session."""

from __future__ import annotations

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
