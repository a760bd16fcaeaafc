"""A process-wide pool of helper threads for compiled kernels that release the GIL.

The store's reader decodes tiles on several threads (terrain.heightcodec), and the
clipmap's draw plan measures a moved level's blocks in parts (client.render.clipmap_layer):
both hand :func:`map_shared` a list of independent jobs whose work is in ``nogil`` numba
kernels (or zstd), so the threads run at once. One pool per thread count serves every
caller of the process; the calling thread works too.
"""

from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor


def cpu_count() -> int:
    """The CPUs this process may run on (its affinity), at least 1."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


_pools: dict[int, ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()


def _reset_pools_after_fork() -> None:
    """A forked child has none of its parent's threads (and maybe a lock held by one):
    it starts with no pools and a fresh lock."""
    global _pools, _pools_lock
    _pools = {}
    _pools_lock = threading.Lock()


os.register_at_fork(after_in_child=_reset_pools_after_fork)


def map_shared(fn, items: list, threads: int) -> list:
    """[fn(x) for x in items], on up to ``threads`` threads: the caller's and helpers
    from a process-wide pool, each taking the next item until none is left. The caller
    works too, so a helper that starts late costs nothing; the first exception raised
    stops the hand-out and is re-raised once every thread has stopped."""
    n = len(items)
    helpers = min(threads, n) - 1
    if helpers <= 0:
        return [fn(x) for x in items]
    results = [None] * n
    counter = itertools.count()  # next() on it is atomic under the GIL
    failed: list[BaseException] = []

    def work():
        while not failed:
            i = next(counter)
            if i >= n:
                return
            try:
                results[i] = fn(items[i])
            except BaseException as e:  # re-raised in the caller below
                failed.append(e)

    futures = [_pool(threads).submit(work) for _ in range(helpers)]
    work()
    for f in futures:
        if not f.cancel():  # a helper that has not started (the pool is busy) is not waited for
            f.result()
    if failed:
        raise failed[0]
    return results


def _pool(threads: int) -> ThreadPoolExecutor:
    """The process-wide pool of ``threads`` - 1 helper threads (the caller is the last)."""
    with _pools_lock:
        pool = _pools.get(threads)
        if pool is None:
            pool = _pools[threads] = ThreadPoolExecutor(threads - 1, thread_name_prefix="sortie-helper")
        return pool


__all__ = ["cpu_count", "map_shared"]
