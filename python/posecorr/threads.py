"""How many threads training may use, applied to torch and to the BLAS / OpenMP pools alike.

The default is what the machine can give without oversubscription: the cores this
process may run on (its CPU affinity) less the cores other processes keep busy (the
one-minute load average, rounded), shared out between the worker processes, at least one
thread each. Why not torch's default (every core): with one busy neighbour on two cores,
torch's threads wait on each other and a training epoch ran 10x slower (3.14 s against
0.30 s with one thread, issue 11).

``set_threads`` limits the libraries already loaded (threadpoolctl, and torch when it is
imported) and sets OMP_NUM_THREADS / OPENBLAS_NUM_THREADS / MKL_NUM_THREADS for the ones
loaded later (torch reads them when it is first imported) and for child processes.
"""
from __future__ import annotations

import os
import sys

_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def available_cores() -> int:
    """Cores this process may use that no other process keeps busy (at least 1)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    try:
        busy = os.getloadavg()[0]
    except (AttributeError, OSError):
        busy = 0.0
    return max(1, min(cores, int(round(cores - busy))))


def default_threads(workers: int = 1) -> int:
    """Threads per worker process: the idle cores shared between ``workers`` processes."""
    return max(1, available_cores() // max(1, int(workers)))


def set_threads(threads: int | None = None, workers: int = 1) -> int:
    """Limit torch and BLAS to ``threads`` (None: ``default_threads(workers)``); returns the count."""
    n = default_threads(workers) if threads is None else int(threads)
    if n < 1:
        raise ValueError(f"--threads must be at least 1, got {threads}")
    for name in _ENV:
        os.environ[name] = str(n)
    import numpy  # noqa: F401  (loads numpy's BLAS so that the limit below reaches it)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=n)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)
    return n


def threads_in_use() -> dict[str, int]:
    """{library: threads} of the loaded BLAS / OpenMP pools and torch (for tests and reports)."""
    from threadpoolctl import threadpool_info

    out = {f"{info['internal_api']}:{os.path.basename(info['filepath'])}": int(info["num_threads"])
           for info in threadpool_info()}
    if "torch" in sys.modules:
        out["torch"] = int(sys.modules["torch"].get_num_threads())
    return out
