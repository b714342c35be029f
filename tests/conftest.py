"""Shared fixtures: one tiny synthetic capture per test session."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from parammap.synth.generate import generate

SHARED = Path(__file__).resolve().parents[2] / "shared"
REAL = SHARED / "data" / "real"


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> tuple[Path, Path]:
    """(capture dir, truth dir) of the ``tiny`` preset, seed 0. Read-only for tests."""
    root = tmp_path_factory.mktemp("tiny")
    cap = generate(root / "cap", root / "truth", preset="tiny", seed=0, workers=2,
                   log=lambda *_: None)
    return cap, root / "truth"


@pytest.fixture()
def tiny_copy(tiny_capture, tmp_path) -> Path:
    """A writable copy of the tiny capture, for tests that break it."""
    dst = tmp_path / "cap"
    shutil.copytree(tiny_capture[0], dst)
    return dst
