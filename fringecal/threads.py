"""One thread policy for a run: how many step instances run at once, and how many
threads each gives numba's parallel loops and BLAS.

Three kinds of threads compete for a run's cores: the run's worker pool (step instances
side by side), numba's parallel loops inside an instance, and the BLAS library under
numpy and scipy. Left alone, each sizes itself to every core of the machine, so on two
cores two workers start four numba threads and four BLAS threads; on a machine that is
busy besides, a parallel loop or a BLAS call then waits for whichever of its threads
the operating system has descheduled, and spinning BLAS threads take cores from the
work itself (a 122 x 122 ``eigh``: 1.3 ms on one thread, up to 0.5 s with two beside
busy neighbours; ``docs/performance.md``). :class:`ThreadPolicy` sizes them together
from the cores the run may use (``runner.cores``, default: all the process may run on):

* ``workers`` step instances at once: ``runner.max_workers``, at most the cores;
* each of the instances of a step that run at once gets ``cores // instances`` numba
  threads (a step of one instance, such as the bundle adjustment, gets every core);
* BLAS gets one thread in every process of the run: the run's dense matrices are at
  most a few hundred rows (the adjustment's normal matrix), where BLAS threads never
  pay for their synchronisation.

:func:`step_threads` applies the policy around one step instance, in whichever thread
or process runs it (the flow's worker threads, Dask workers, ``fringecal step``).
"""

from __future__ import annotations

import os
import threading
from contextlib import contextmanager
from dataclasses import dataclass

__all__ = ["ThreadPolicy", "available_cores", "step_threads", "numba_threads", "granted", "limit_blas"]

#: BLAS threads per process of a run (see the module notes)
BLAS_THREADS = 1

_blas_lock = threading.Lock()
_blas_limited = False


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; all of the machine's if unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class ThreadPolicy:
    """Cores the run may use and the step instances that run at once on them."""

    cores: int
    workers: int

    @classmethod
    def of(cls, cores: int | None, workers: int) -> "ThreadPolicy":
        """The policy for ``cores`` (None: all available; more than available: the
        available ones) and ``workers`` requested step instances at once.

        >>> ThreadPolicy.of(2, 4)
        ThreadPolicy(cores=2, workers=2)
        """
        usable = available_cores() if cores is None else max(1, min(int(cores), available_cores()))
        return cls(usable, max(1, min(int(workers), usable)))

    def instance_threads(self, instances: int) -> int:
        """numba threads for each step instance when a step has ``instances`` of them.

        >>> ThreadPolicy(2, 2).instance_threads(24), ThreadPolicy(2, 2).instance_threads(1)
        (1, 2)
        """
        return max(1, self.cores // max(1, min(self.workers, int(instances))))

    def to_dict(self) -> dict:
        return {"cores": self.cores, "workers": self.workers, "blas_threads": BLAS_THREADS,
                "numba_threads_per_instance": {"one instance": self.instance_threads(1),
                                               "many instances": self.instance_threads(self.workers)}}


def limit_blas() -> None:
    """Limit every BLAS library of this process to ``BLAS_THREADS`` (once per process).

    numpy's and scipy's BLAS are loaded first: threadpoolctl reaches only libraries
    already loaded.
    """
    global _blas_limited
    with _blas_lock:
        if _blas_limited:
            return
        import numpy  # noqa: F401
        import scipy.linalg  # noqa: F401  (loads scipy's own BLAS)
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=BLAS_THREADS, user_api="blas")
        _blas_limited = True


@contextmanager
def numba_threads(threads: int):
    """Run the block with ``threads`` numba threads in this thread (numba's setting is
    per thread; at most its ``NUMBA_NUM_THREADS``)."""
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(before)


@contextmanager
def step_threads(threads: int):
    """Run the block with ``threads`` numba threads in this thread and BLAS limited
    for the process."""
    limit_blas()
    with numba_threads(threads):
        yield


def granted() -> int:
    """The numba threads the calling thread may use (what :func:`step_threads` set)."""
    import numba

    return int(numba.get_num_threads())
