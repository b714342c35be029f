"""Process pools whose workers end with their parent, in-process execution for one
worker, and progress output: what the stages that run jobs in parallel share."""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
from collections.abc import Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from typing import TextIO, TypeVar

__all__ = ["die_with_parent", "executor", "progress", "worker_initializer"]

T = TypeVar("T")


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


def progress(items: Iterable[T], total: int, label: str, log: logging.Logger,
             done: int = 0, of: int | None = None, stream: TextIO | None = None,
             ) -> Iterator[T]:
    """Yield ``items`` (results of a long step, ``total`` of them) and say how far it got:
    a bar redrawn on ``stream`` (stderr) where a person watches it (a terminal, the log
    at INFO), else a log line ``<label> k/n`` at every tenth and at the end. ``done``
    items finished before (a resumed step) count towards ``of`` (default ``done +
    total``)."""
    stream = sys.stderr if stream is None else stream
    n = done + total if of is None else of
    bar = stream.isatty() and log.isEnabledFor(logging.INFO)
    step = max(1, total // 10)
    for k, item in enumerate(items, 1):
        yield item
        if bar:
            filled = int(30 * (done + k) / max(n, 1))
            stream.write(f"\r{label} [{'#' * filled}{'.' * (30 - filled)}] {done + k}/{n}")
            if k == total:
                stream.write("\n")
            stream.flush()
        elif k % step == 0 or k == total:
            log.info(f"{label} {done + k}/{n}")
