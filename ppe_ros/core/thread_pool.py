"""Independent tasks on the calling thread and a process-wide pool of helper threads.

The extractor's nogil kernels (the greedy on each tile, the consolidation's candidate pairs in row
blocks) run as tasks numbered 0..n-1: the calling thread and ``threads - 1`` pool threads each take
the next task in a given order until none is left, and the results come back in task order, so
they do not depend on which thread ran what.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

Result = TypeVar('Result')


class SharedThreadPool:
    """A process-wide ThreadPoolExecutor that grows to the largest number of workers asked for."""

    def __init__(self, thread_name_prefix: str) -> None:
        self._prefix = thread_name_prefix
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None

    def executor(self, workers: int) -> ThreadPoolExecutor:
        """The pool, with at least ``workers`` threads."""
        with self._lock:
            if self._pool is None or self._pool._max_workers < workers:
                # a smaller pool is replaced, not shut down: a caller may still submit to it; its idle
                # threads end when it is no longer referenced
                self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=self._prefix)
            return self._pool


def run_tasks(run: Callable[[int], Result], order: Sequence[int], threads: int, pool: SharedThreadPool) -> list[Result]:
    """``[run(i) for i in sorted(order)]``, with the tasks taken in ``order`` by the calling thread and
    ``threads - 1`` threads of ``pool`` (one thread: all in the calling thread). An exception of a
    task is raised here."""
    if threads <= 1:
        done = [(i, run(i)) for i in order]
    else:
        tickets = iter(list(order))  # next() on a list iterator is atomic under the GIL
        ticket_lock = threading.Lock()

        def drain() -> list:
            taken = []
            while True:
                with ticket_lock:
                    i = next(tickets, None)
                if i is None:
                    return taken
                taken.append((i, run(i)))

        executor = pool.executor(threads - 1)
        futures = [executor.submit(drain) for _ in range(threads - 1)]
        done = drain()
        for future in futures:
            done += future.result()
    return [result for _, result in sorted(done, key=lambda pair: pair[0])]
