"""The threads the compiled kernels' shares of regions run on (perception.depthmap's cut,
perception.surface's fit): one pool a process, kept, with the calling thread taking a share.

Why kept: a pass of a planner's request is a few regions, and a pool made a call started its
threads every pass. A thread's start waits until the new thread has run, which in a busy node
waits for Python's lock, held by the threads drawing the prior up to its switch interval: in the
inference node's profile serving 64-region requests, 4.6 % of the samples were threads starting.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _forget_pool() -> None:
    """In a forked child the pool's threads are gone: it makes its own."""
    global _pool
    _pool = None


os.register_at_fork(after_in_child=_forget_pool)


def _kept_pool() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(os.cpu_count() or 1, thread_name_prefix="dtx-kernel")
        return _pool


def run_shares(work: Callable[[int, int], None], shares: Sequence[tuple[int, int]]) -> None:
    """``work(first, stop)`` for every share, side by side: the first on the calling thread, the
    others on the process's kept pool (the kernels release Python's lock). Returns when every
    share is done; an error of any share is raised (the first share's before the others')."""
    if not shares:
        return
    others = [_kept_pool().submit(work, first, stop) for first, stop in shares[1:]]
    try:
        work(*shares[0])
    finally:
        wait(others)
    for future in others:
        future.result()
