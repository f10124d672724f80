"""A process pool that stops at once on Ctrl-C (record, ingest, replay's scenes and rollouts).

multiprocessing's Pool, not concurrent.futures: an interrupted executor cancels only the jobs it has not yet handed
to its workers and waits for the rest (those running and those queued behind them), so `record --world kitchen`
went on recording for up to a minute after Ctrl-C and wrote bags after it; cancelling its futures trips its
management thread (InvalidStateError, a hang). Here the workers ignore SIGINT (Ctrl-C reaches the whole process
group; a worker dying mid-result would hang the pool) and the parent terminates them. Ctrl-C is held back while the
workers fork, so it never meets a half-built pool. What a terminated worker was writing is the caller's to remove
(a writer's temp file: see record).
"""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from multiprocessing.pool import Pool


def _worker_init(then: Callable[[], None] | None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if then is not None:
        then()


@contextmanager
def stoppable_pool(workers: int, initializer: Callable[[], None] | None = None,
                   context: str = "fork") -> Iterator[Pool]:
    """A pool of `workers` processes (forked; "spawn" where the parent used CUDA); on any exception (Ctrl-C
    included) inside the block the workers are terminated before it propagates, else they finish their jobs."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        pool = multiprocessing.get_context(context).Pool(workers, initializer=_worker_init, initargs=(initializer,))
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
    try:
        yield pool
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()
