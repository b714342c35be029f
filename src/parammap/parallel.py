"""Process pools whose workers end with their parent, and in-process execution for one
worker: what the stages that run jobs in parallel share."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor
from functools import partial

__all__ = ["die_with_parent", "executor", "worker_initializer"]


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
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PDEATHSIG
        except OSError:
            pass
    if os.getppid() != parent:  # it died before the line above took effect
        os._exit(1)


def worker_initializer():
    """:func:`die_with_parent` bound to this process, for a pool's ``initializer``."""
    return partial(die_with_parent, os.getpid())


def executor(workers: int):
    """A process pool of ``workers`` (ended with their parent, :func:`die_with_parent`),
    or in-process execution for one worker."""
    return ProcessPoolExecutor(workers, initializer=worker_initializer()) if workers > 1 \
        else _Serial()
