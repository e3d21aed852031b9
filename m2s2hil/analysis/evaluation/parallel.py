"""Running per-image work on Dask: a local cluster on every core, or an existing cluster.

- Default: ``dask.distributed.LocalCluster(n_workers=<all cores>, threads_per_worker=1,
  processes=True)``. One single-threaded process per core: the per-image work (Gaussian
  mixtures, SLIC, scikit-learn metrics) holds the GIL for long stretches, so processes
  scale where threads would not, and the segmenters already limit BLAS to one thread.
- ``scheduler="tcp://host:8786"``: connect a ``dask.distributed.Client`` to a running
  scheduler. Its workers must import ``m2s2hil`` and see the same file paths (a shared
  file system): jobs carry paths, not pixels.
- ``workers=0``: no Dask at all, a plain loop in this process (debugging, profiling).

Scheduling, retries and load balancing are Dask's; this module only opens the client and
collects results in submission order.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from m2s2hil.errors import UsageError

log = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")
SCHEMES = ("tcp://", "tls://", "inproc://", "ucx://", "ws://", "wss://")


class SchedulerUnavailable(UsageError):
    """A ``--scheduler`` address that is malformed or does not answer."""


def default_workers() -> int:
    """One worker per core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def check_scheduler_address(address: str) -> str:
    addr = address.strip()
    if not addr.startswith(SCHEMES) or len(addr.split("://", 1)[1]) == 0:
        raise SchedulerUnavailable(
            f"--scheduler {address!r}: expected a Dask scheduler address such as tcp://host:8786"
        )
    return addr


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None,
    *,
    workers: int | None = None,
    processes: bool = True,
    timeout_s: float = 10.0,
) -> Iterator[Any]:
    """A ``distributed.Client``: connected to ``scheduler``, or to a fresh LocalCluster.

    The LocalCluster (and only it) is closed on exit; an existing cluster is left running.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:  # a capture-only install
        raise SchedulerUnavailable(
            "evaluation runs on Dask, which is not installed: pip install 'm2s2hil[analysis]'"
        ) from None

    if scheduler:
        addr = check_scheduler_address(scheduler)
        try:
            client = Client(addr, timeout=f"{timeout_s}s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise SchedulerUnavailable(f"cannot reach the Dask scheduler at {addr}: {exc}") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise UsageError(f"--workers must be ≥ 1 for a local cluster, got {n}")
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=processes,
        dashboard_address=None,
        silence_logs=logging.ERROR,  # worker start/stop chatter would drown the progress bar
    )
    try:
        client = Client(cluster, set_as_default=False)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def describe(client: Any) -> dict[str, Any]:
    """Scheduler address and worker count (for the report's provenance)."""
    if client is None:
        return {"scheduler": "in-process", "workers": 1}
    info = client.scheduler_info()
    return {"scheduler": str(client.scheduler.address), "workers": len(info.get("workers", {}))}


def map_ordered(
    fn: Callable[..., R],
    items: Sequence[T],
    *,
    client: Any = None,
    on_result: Callable[[int, R], None] | None = None,
    **kwargs: Any,
) -> list[R]:
    """``[fn(item, **kwargs) for item in items]`` on the client's workers (or in-process when
    ``client`` is None), results in the order of ``items``; ``on_result(done, result)``
    is called as each one arrives (progress). ``fn`` must be importable by the workers and
    ``kwargs`` small (they travel with every task)."""
    if client is None:
        out = []
        for i, item in enumerate(items):
            out.append(fn(item, **kwargs))
            if on_result is not None:
                on_result(i + 1, out[-1])
        return out
    from distributed import as_completed  # Dask is the optional `analysis` extra

    if not items:
        return []
    futures = client.map(fn, list(items), pure=False, **kwargs)
    index = {f.key: i for i, f in enumerate(futures)}
    results: list[Any] = [None] * len(futures)
    for done, (fut, res) in enumerate(as_completed(futures, with_results=True, loop=client.loop), start=1):
        results[index[fut.key]] = res
        if on_result is not None:
            on_result(done, res)
    return results
