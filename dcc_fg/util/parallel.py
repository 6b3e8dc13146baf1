"""Ordered, bounded parallel map over a stream: the process pool behind ``--jobs``.

:func:`ordered_map` applies a picklable top-level function to a stream of items in ``jobs`` worker
processes and yields the results **in input order**, with at most ``window`` items in flight (submitted
and not yet yielded), so a long stream (a 2,000-frame bag) is processed in bounded memory while the
caller keeps reading. ``jobs = 1`` is a plain lazy ``map`` in this process (no pool at all).

Workers come from a ``forkserver`` context: no fork of a process that may hold OpenCV or GTSAM worker
threads, and module imports paid once by the server. Like every ``spawn``/``forkserver`` pool, a
script that calls this with ``jobs > 1`` must guard its entry point with
``if __name__ == "__main__":`` (the ``dcc-fg`` command and pytest do); the Python API therefore
defaults to ``jobs = 1`` and the command line to every usable core.

An exception raised by ``func`` in a worker is re-raised here, at the position of its item (the
results before it have been yielded); the remaining work is cancelled.
"""

from __future__ import annotations

import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: In-flight items per worker by default: enough to hide the caller's reading between results.
WINDOW_PER_JOB = 3


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, e.g. a container's cpuset), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def resolve_jobs(jobs: int | None) -> int:
    """``jobs`` as a worker count: None or 0 means every usable core; negative is an error."""
    if jobs is None or jobs == 0:
        return usable_cores()
    if jobs < 0:
        raise ValueError(f"--jobs must be >= 0 (0: every usable core), got {jobs}")
    return int(jobs)


def run_chunk(task: tuple[Callable[[T], R], list[T]]) -> tuple[list[R], BaseException | None]:
    """Worker: ``func`` over a chunk of items, in order; stops at the first exception and returns the
    results before it with the exception (so the caller can yield those, then raise it in place)."""
    func, chunk = task
    out: list[R] = []
    for item in chunk:
        try:
            out.append(func(item))
        except Exception as exc:  # noqa: BLE001 - handed back to the caller, raised there at its item
            return out, exc
    return out, None


def _chunks(items: Iterable[T], size: int) -> Iterator[list[T]]:
    """``items`` in lists of ``size`` (the last one shorter), read lazily."""
    chunk: list[T] = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _take(fut: Future[tuple[list[R], BaseException | None]]) -> Iterator[R]:
    """The results of a finished chunk, then its exception (if an item raised one)."""
    done, exc = fut.result()
    yield from done
    if exc is not None:
        raise exc


def ordered_map(
    func: Callable[[T], R],
    items: Iterable[T],
    jobs: int = 1,
    window: int | None = None,
    preload: tuple[str, ...] = (),
    initializer: Callable[[], None] | None = None,
    chunk: int = 1,
) -> Iterator[R]:
    """``func`` over ``items`` in ``jobs`` processes, results in input order (module docstring).

    Args:
        func: a module-level function (pickled by reference); its argument and result are pickled.
        items: read lazily, at most ``window`` tasks ahead of the results yielded.
        jobs: worker processes; 1 runs ``func`` here, without a pool.
        window: tasks in flight (default ``WINDOW_PER_JOB * jobs``).
        preload: modules the fork server imports once for all workers (e.g. ``("dcc_fg.detection",)``).
        initializer: a module-level function each worker runs once before its first item.
        chunk: items per task (a worker gets ``chunk`` consecutive items at once): fewer round trips
            through the pool when each item is quick; at most ``window * chunk`` items are in flight. An
            exception is still raised at its own item, after the results before it.
    """
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    if jobs == 1:
        yield from map(func, items)
        return
    limit = window if window is not None else WINDOW_PER_JOB * jobs
    if limit < 1:
        raise ValueError(f"window must be >= 1, got {limit}")
    ctx = multiprocessing.get_context("forkserver")
    if preload:
        ctx.set_forkserver_preload(list(preload))
    pending: deque[Future[tuple[list[R], BaseException | None]]] = deque()

    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=initializer) as pool:
        try:
            for part in _chunks(items, chunk):
                pending.append(pool.submit(run_chunk, (func, part)))
                if len(pending) >= limit:
                    yield from _take(pending.popleft())
            while pending:
                yield from _take(pending.popleft())
        finally:
            for fut in pending:
                fut.cancel()
