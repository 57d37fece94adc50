"""The Dask client of a scale-out run: a local cluster started and closed here, or a
remote scheduler, and the client's accounting of its waits on the workers.

``scheduler`` is ``"local"`` (a :class:`distributed.LocalCluster` of ``n_workers``
single-threaded processes, started and closed here) or the address of an existing
scheduler (``tcp://host:8786``), or a ready :class:`distributed.Client`.
"""

from __future__ import annotations

import contextlib
import os
import time

from mems_stereo.errors import OptionError
from mems_stereo.util.environ import saved_environ

#: seconds a remote scheduler's handshake may take
SCHEDULER_CONNECT_TIMEOUT = 10.0

#: Dask settings of the LocalCluster that :func:`dask_client` starts: the housekeeping
#: of a local cluster shares the cores with the work, so no statistical profiler on
#: the workers (it samples the running task's stack every 10 ms) and the event loops'
#: tick and the memory and system monitors less often
LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False,
                        "distributed.admin.tick.interval": "200ms",
                        "distributed.worker.memory.monitor-interval": "1s",
                        "distributed.admin.system-monitor.interval": "2s"}

#: glibc settings of the LocalCluster's worker processes (workers of a remote cluster
#: are best started with them too): one malloc arena per worker.  A worker runs its
#: tasks in a thread of its own, whose glibc arena would hand the heaps of freed
#: temporaries back to the OS and page-fault them in again on every task
WORKER_MALLOC_ENV = {"MALLOC_ARENA_MAX": "1"}

#: environment of the LocalCluster's workers: numba's OpenMP threading layer with one
#: thread (each worker is one single-threaded process)
WORKER_ENV = {"NUMBA_THREADING_LAYER": "omp", "OMP_NUM_THREADS": "1"}


@contextlib.contextmanager
def dask_client(scheduler="local", n_workers: int = 2):
    """A Dask client for ``scheduler`` (see module docstring); closes what it started."""
    from distributed import Client

    if isinstance(scheduler, Client):
        yield scheduler
    elif scheduler in (None, "local"):
        with _local_client(n_workers) as client:
            yield client
    else:
        with _remote_client(scheduler) as client:
            yield client


@contextlib.contextmanager
def _local_client(n_workers: int):
    """A client of a LocalCluster of ``n_workers`` single-threaded processes.

    Dask's nannies set ``MALLOC_TRIM_THRESHOLD_=65536`` by default: glibc then returns
    every large temporary to the OS and page-faults it back, which makes this
    pipeline's NumPy stages slower; glibc's default is kept.  The workers' glibc
    settings (:data:`WORKER_MALLOC_ENV`) are read when a process starts, so they go
    into Dask's pre-spawn environment, which also lands in this process's
    ``os.environ``; that, and the threading layer the workers inherit, is put back
    once the workers have started.
    """
    import dask
    from distributed import Client, LocalCluster

    config = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
              **{f"distributed.nanny.pre-spawn-environ.{k}": v
                 for k, v in WORKER_MALLOC_ENV.items()},
              **LOCAL_CLUSTER_CONFIG}
    with saved_environ([*WORKER_MALLOC_ENV, "NUMBA_THREADING_LAYER"]) as restore:
        os.environ.setdefault("NUMBA_THREADING_LAYER", WORKER_ENV["NUMBA_THREADING_LAYER"])
        with dask.config.set(config), \
                LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                             dashboard_address=None, env=WORKER_ENV) as cluster:
            restore()
            with Client(cluster) as client:
                yield client


@contextlib.contextmanager
def _remote_client(address: str):
    """A client of the scheduler at ``address``; an :class:`OptionError` where none
    answers."""
    from distributed import Client

    try:
        client = Client(address, timeout=SCHEDULER_CONNECT_TIMEOUT)
    except Exception as e:  # noqa: BLE001 - the handshake's faults vary with what answered
        # e.g. an HTTP server on that port: Dask reads its bytes as a frame length
        # and asks for exabytes (MemoryError), or times out, or is refused
        why = "it answered, but not as a Dask scheduler" if isinstance(
            e, (MemoryError, ValueError, TypeError)) else (str(e) or type(e).__name__)
        raise OptionError(f"cannot connect to a Dask scheduler at {address}: {why}",
                          field="--scheduler") from None
    with client:
        yield client


def n_workers_of(client) -> int:
    """The cluster's workers (at least 1)."""
    return max(1, len(client.scheduler_info().get("workers", {})))


def worker_addresses(client) -> list:
    """The cluster's worker addresses, sorted (empty where the scheduler lists none)."""
    return sorted(client.scheduler_info().get("workers", {}))


def on_worker(addresses: list, i: int) -> dict:
    """``client.submit`` keywords that place task ``i`` on worker ``i`` mod the workers
    (any worker where that one is busy or gone; anywhere without addresses)."""
    if not addresses:  # Dask refuses allow_other_workers without workers
        return {}
    return {"workers": [addresses[i % len(addresses)]], "allow_other_workers": True}


def scatter_one(client, obj):
    """One future of ``obj`` on every worker (a dict scattered directly becomes one
    future per value, keyed by the dict's keys: two dicts of the same fields would
    share their keys)."""
    return client.scatter([obj], broadcast=True)[0]


class ClientWaits:
    """Seconds the client spends blocked on its workers' results, and how many times:
    ``waits(client.gather, futures)`` gathers and counts."""

    __slots__ = ("seconds", "count")

    def __init__(self):
        self.seconds = 0.0
        self.count = 0

    def __call__(self, fn, *args):
        self.count += 1
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.seconds += time.perf_counter() - t
