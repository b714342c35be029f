"""Small helpers shared by the stages that write zarr stores and run process pools."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import zarr

__all__ = ["COMPLETE_ATTR", "die_with_parent", "executor", "open_complete", "store_bytes",
           "worker_initializer"]

# Set on a store's group only after every chunk is written and just before the rename
# from its temporary name: a store without it is never accepted.
COMPLETE_ATTR = "parammap_complete"


class _Serial:
    """Stand-in for an executor that runs jobs in this process."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    @staticmethod
    def map(fn, jobs):
        return map(fn, jobs)


def die_with_parent(parent: int) -> None:
    """Worker-process initializer: end this worker when ``parent`` (the process that
    started it) dies, even by SIGKILL (a pre-empting scheduler, the out-of-memory
    killer), which gives the pool no chance to stop its workers. Linux (prctl);
    elsewhere only the check that the parent is still there."""
    import ctypes
    import os
    import signal
    import sys

    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PDEATHSIG
        except OSError:
            pass
    if os.getppid() != parent:  # it died before the line above took effect
        os._exit(1)


def worker_initializer():
    """:func:`die_with_parent` bound to this process, for a pool's ``initializer``."""
    import os
    from functools import partial

    return partial(die_with_parent, os.getpid())


def executor(workers: int):
    """A process pool of ``workers`` (ended with their parent, :func:`die_with_parent`),
    or in-process execution for one worker."""
    return ProcessPoolExecutor(workers, initializer=worker_initializer()) if workers > 1 \
        else _Serial()


def mtime_ns(path: str | Path) -> int:
    """A file's modification time (ns), 0 when it is missing: part of the keys that say
    whether a partial store may be resumed."""
    try:
        return Path(path).stat().st_mtime_ns
    except OSError:
        return 0


def store_bytes(path: str | Path) -> int:
    """Bytes on disk of a file or a directory store."""
    path = Path(path)
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def open_complete(path: str | Path, error: type[Exception], what: str) -> zarr.Group:
    """Open a finished zarr group; ``error`` names a missing or incomplete one."""
    path = Path(path)
    try:
        g = zarr.open_group(path, mode="r")
    except (FileNotFoundError, zarr.errors.GroupNotFoundError) as exc:
        raise error(f"{path}: no {what} ({exc})") from None
    if not g.attrs.get(COMPLETE_ATTR):
        raise error(f"{path}: incomplete {what} (interrupted run?)")
    return g
