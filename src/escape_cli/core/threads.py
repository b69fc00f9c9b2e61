"""Worker threads shared by the numeric stages that split their work (numpy and the kernels release the interpreter lock).

A completion runs the solver's batches and the neighbour queries on a few threads; a
new pool per call would start its threads every time (3 ms a thread on a busy
machine), so one pool per worker count lives as long as the process.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

_POOLS: dict[int, ThreadPoolExecutor] = {}
_LOCK = threading.Lock()


def thread_map(func, items, workers: int) -> list:
    """``[func(item) for item in items]``, on up to `workers` threads, results in order.

    `func` must not call `thread_map` itself (a task waiting for the pool it runs on
    could wait forever).
    """
    items = list(items)
    workers = min(int(workers), len(items))
    if workers <= 1:
        return [func(item) for item in items]
    with _LOCK:
        pool = _POOLS.get(workers)
        if pool is None:
            pool = _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix="escape-worker")
    return list(pool.map(func, items))
