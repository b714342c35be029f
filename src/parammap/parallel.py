"""Process pools whose workers end with their parent, in-process execution for one
worker, and progress output: what the stages that run jobs in parallel share."""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from typing import Any, TextIO, TypeVar

__all__ = ["die_with_parent", "executor", "map_shared", "progress", "worker_initializer"]

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


_SHARED: Any = None  # a worker's copy of what map_shared hands every job


def _init_shared(parent: int, shared: Any) -> None:
    global _SHARED
    die_with_parent(parent)
    _SHARED = shared


def _call_shared(fn: Callable, job: Any) -> Any:
    return fn(_SHARED, job)


def map_shared(fn: Callable[[Any, Any], T], jobs: Iterable, workers: int, shared: Any,
               ) -> Iterator[T]:
    """Yield ``fn(shared, job)`` for each job, in order, over ``workers`` processes.

    ``shared`` (large read-only inputs: a stage's parameter maps) reaches each worker
    once, not with every job: on Linux the workers are forked and inherit it without a
    copy (pages are shared until written); elsewhere it is pickled once per worker.
    ``fn`` must be a module-level function. One worker: in this process."""
    if workers <= 1:
        for job in jobs:
            yield fn(shared, job)
        return
    ctx = multiprocessing.get_context("fork") if sys.platform.startswith("linux") else None
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_shared,
                             initargs=(os.getpid(), shared)) as pool:
        yield from pool.map(partial(_call_shared, fn), jobs)


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
