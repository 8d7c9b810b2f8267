"""Process pools for simulated drives: parallel across processes, one math thread inside each.

Every worker drives one placement on the simulated clock, so the parallelism belongs to the
processes. Left alone, numpy's OpenBLAS (and any OpenMP library) starts one thread per core in
every worker, and on a many-core machine the workers' thread pools fight (research/LOG.md: two
placements at `--jobs 2` on a 16-core machine had not finished after 40 s, and took 3.0 s with
one BLAS thread per worker). The
initializer limits each worker to one such thread: threadpoolctl for the libraries a worker has
already loaded (a spawned worker imports its parent's main module first), the variables those
libraries read at load time for the ones it loads later.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor

# read by OpenBLAS, OpenMP and MKL when they load
ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def limit_worker_threads() -> None:
    """In a pool worker: BLAS and OpenMP thread pools to one thread for the worker's life."""
    from threadpoolctl import threadpool_limits

    os.environ.update(ONE_THREAD)
    threadpool_limits(limits=1)


def _worker_ignoring_interrupts() -> None:
    """In a pool worker whose caller handles Ctrl-C: SIGINT to the process group must not
    print a traceback per worker; the caller ends the workers itself."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_worker_threads()


def worker_pool(
    jobs: int, start_method: str, ignore_interrupts: bool = False
) -> ProcessPoolExecutor:
    """`jobs` processes started by `start_method`, each limited to one math thread.

    An executor, not multiprocessing.Pool: a worker that dies mid-run (a crash in a native
    library) breaks it with an error (BrokenProcessPool) instead of leaving the caller waiting
    forever."""
    context = multiprocessing.get_context(start_method)
    init = _worker_ignoring_interrupts if ignore_interrupts else limit_worker_threads
    return ProcessPoolExecutor(jobs, mp_context=context, initializer=init)
