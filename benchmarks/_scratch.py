"""Scratch processed folders for benchmarks: a copy of a processed capture's camera/
with links to the (large, read-only) stage outputs it reuses."""

from __future__ import annotations

import shutil
from pathlib import Path


def scratch_processed(src: Path, dst: Path, links: tuple[str, ...]) -> Path:
    """``dst`` afresh: ``src/camera`` copied (stages may rewrite it), ``links`` (names
    under ``src``, e.g. ``hdr``, ``observation.zarr``) linked."""
    if dst.exists():
        shutil.rmtree(dst)
    (dst / "camera").mkdir(parents=True)
    for f in (src / "camera").iterdir():
        shutil.copy(f, dst / "camera" / f.name)
    for name in links:
        (dst / name).symlink_to((src / name).resolve())
    return dst
