"""A field's shards on every core: one pool of threads for per-shard work.

A field's shards (an atlas field's charts; a one-chart field is one shard) are
independent triangulations, so their inserts, queries, snapshots and restores
can run at once. The extension releases the GIL for its long calls (insert,
locate, interpolate, serialise) and NumPy for its large array operations, so
threads use the cores. :meth:`ShardPool.map` gives the results in the order of
the work: a field's answers are bit for bit those of the one-after-the-other
loop whatever the number of threads (each shard makes the same calls on the
same data; only when they run changes). Work started from inside the pool's
own threads runs inline, so a shard's work never waits for the pool it runs in.

The process has one pool, :func:`shard_pool`, of :func:`default_threads`
threads (``FLATSERVE_SHARD_THREADS``, else the cores this process may run on);
:func:`set_shard_threads` resizes it (1: no threads, the sequential loop).

Examples
--------
>>> from flatserve.parallel import ShardPool
>>> list(ShardPool(2).map(lambda x: x * x, range(5)))
[0, 1, 4, 9, 16]
"""
from __future__ import annotations

import collections
import itertools
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Any, Callable, Iterable, Iterator

from .errors import InvalidInputError

__all__ = ["ShardPool", "default_threads", "set_shard_threads", "shard_pool"]

#: Environment variable that sets the default number of shard threads.
THREADS_ENV = "FLATSERVE_SHARD_THREADS"

_worker = threading.local()  # .active: this thread runs a pool's work


def _check_threads(threads, where: str) -> int:
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise InvalidInputError(f"{where}: expected a whole number >= 1, got {threads!r}", where)
    return threads


def default_threads() -> int:
    """Threads of the process's shard pool unless set: ``FLATSERVE_SHARD_THREADS``,
    else the number of cores this process may run on."""
    raw = os.environ.get(THREADS_ENV, "").strip()
    if raw:
        try:
            value = int(raw)
        except ValueError:
            value = raw
        return _check_threads(value, THREADS_ENV)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class ShardPool:
    """Threads that run per-shard work, results in the order of the work.

    Parameters
    ----------
    threads : int, optional
        At most this many shards at once (default :func:`default_threads`);
        1 runs the work one item after the other in the calling thread.
    window : int, optional
        Items started ahead of the one the caller is reading (default twice
        ``threads``): bounds what waits in memory when each result is large
        (a shard's snapshot bytes).
    """

    def __init__(self, threads: int | None = None, *, window: int | None = None) -> None:
        self.threads = default_threads() if threads is None else _check_threads(threads, "threads")
        self.window = 2 * self.threads if window is None else _check_threads(window, "window")
        self._executor: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        """``fn(item)`` for each item, yielded in order (lazily).

        Inline (the caller's thread, one after the other) with one thread, one
        item, or when called from a thread of a pool. Otherwise up to
        ``window`` items run ahead on the pool; an exception is raised in its
        item's place, after the items already running have finished (none
        runs on once the caller has its answer, so a lock the caller holds
        covers them all) and with the rest not started.
        """
        items = list(items)
        if self.threads == 1 or len(items) < 2 or getattr(_worker, "active", False):
            return (fn(x) for x in items)
        return self._ordered(fn, items)

    def _ordered(self, fn, items: list) -> Iterator[Any]:
        executor = self._start()
        todo = iter(items)
        running: collections.deque[Future] = collections.deque(
            executor.submit(_run, fn, x) for x in itertools.islice(todo, self.window))
        try:
            while running:
                result = running.popleft().result()
                for x in itertools.islice(todo, 1):
                    running.append(executor.submit(_run, fn, x))
                yield result
        finally:
            for fut in running:
                fut.cancel()
            wait(running)

    def _start(self) -> ThreadPoolExecutor:
        with self._lock:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(self.threads,
                                                    thread_name_prefix="flatserve-shard")
            return self._executor

    def close(self) -> None:
        """Stop the threads once their work is done (a later :meth:`map` starts new ones)."""
        with self._lock:
            executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=True)

    def __repr__(self) -> str:
        return f"ShardPool(threads={self.threads})"


def _run(fn, x):
    _worker.active = True
    try:
        return fn(x)
    finally:
        _worker.active = False


_pool: ShardPool | None = None
_pool_lock = threading.Lock()


def shard_pool() -> ShardPool:
    """The process's shard pool (made on first use)."""
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ShardPool()
        return _pool


def set_shard_threads(threads: int | None) -> ShardPool:
    """Resize the process's shard pool (None: :func:`default_threads`).

    Work already running on the former pool finishes there; its idle threads
    end with it.

    Returns
    -------
    ShardPool
        The new pool.
    """
    global _pool
    new = ShardPool(threads)
    with _pool_lock:
        _pool = new
    return new
