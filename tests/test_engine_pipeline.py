"""The bounded capture → process → store pipeline."""

from __future__ import annotations

import threading
import tracemalloc

import numpy as np
import pytest

from m2s2hil.engine.pipeline import Pipeline, PipelineClosed


def test_items_flow_in_order_and_results_carry_no_pixels() -> None:
    seen: list[int] = []
    p = Pipeline(lambda k, x: x * 2, lambda k, x: seen.append(k) or (k, int(x.sum())), process_depth=2,
                 store_depth=2).start()
    for i in range(20):
        p.submit(i, np.full(4, i))
    assert p.drain(timeout=10)
    p.stop()
    out = p.results()
    assert [o.key for o in out] == list(range(20)) == seen
    assert all(o.ok and o.result == (o.key, 8 * o.key) for o in out)
    st = p.stats()
    assert (st.submitted, st.processed, st.stored, st.failed, st.in_flight) == (20, 20, 20, 0, 0)


def test_slow_sink_blocks_the_producer_instead_of_growing() -> None:
    """A disk that stalls: the queues never exceed their bounds, submit() waits."""
    gate = threading.Event()
    stored: list[int] = []

    def slow_store(key: int, payload: np.ndarray) -> int:
        gate.wait(timeout=10)
        stored.append(key)
        return key

    p = Pipeline(lambda k, x: x, slow_store, process_depth=3, store_depth=2).start()
    n = 40
    producer = threading.Thread(
        target=lambda: [p.submit(i, np.zeros(256 * 1024, np.uint8)) for i in range(n)]
    )
    producer.start()
    producer.join(timeout=0.5)
    assert producer.is_alive(), "submit() should block while the sink is stalled"
    st = p.stats()
    assert st.in_flight <= st.bound
    assert st.max_process_depth <= 3 and st.max_store_depth <= 2
    gate.set()
    producer.join(timeout=10)
    assert p.drain(timeout=10)
    p.stop()
    st = p.stats()
    assert stored == list(range(n))
    assert st.max_in_flight <= st.bound and st.blocked_count > 0


def test_memory_stays_bounded_with_a_slow_sink() -> None:
    """Peak traced memory stays near bound × frame size, not n × frame size."""
    frame_bytes = 1 << 20
    gate = threading.Semaphore(0)

    def store(key: int, payload: np.ndarray) -> None:
        gate.acquire(timeout=10)

    p = Pipeline(lambda k, x: x.copy(), store, process_depth=2, store_depth=2).start()
    tracemalloc.start()
    try:
        n = 60

        def produce() -> None:
            for i in range(n):
                p.submit(i, np.ones(frame_bytes, np.uint8))

        t = threading.Thread(target=produce)
        t.start()
        for _ in range(n):
            gate.release()
        t.join(timeout=20)
        assert p.drain(timeout=20)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
        p.stop()
    bound = p.stats().bound
    # each item exists at most twice (raw + processed copy) while in flight
    assert peak < (2 * bound + 4) * frame_bytes
    assert peak < n * frame_bytes / 3


def test_failures_are_reported_per_item_with_their_stage() -> None:
    def process(k: int, x: int) -> int:
        if k == 1:
            raise ValueError("bad frame")
        return x

    def store(k: int, x: int) -> int:
        if k == 2:
            raise OSError(28, "No space left on device")
        return x

    p = Pipeline(process, store).start()
    for i in range(4):
        p.submit(i, i)
    assert p.drain(timeout=10)
    p.stop()
    by_key = {o.key: o for o in p.results()}
    assert by_key[0].ok and by_key[3].ok
    assert not by_key[1].ok and by_key[1].stage == "process" and isinstance(by_key[1].error, ValueError)
    assert not by_key[2].ok and by_key[2].stage == "store" and isinstance(by_key[2].error, OSError)
    with pytest.raises(PipelineClosed):
        p.submit(9, 9)


def test_depths_must_be_positive() -> None:
    with pytest.raises(ValueError):
        Pipeline(lambda k, x: x, lambda k, x: x, process_depth=0)
    with pytest.raises(ValueError):
        Pipeline(lambda k, x: x, lambda k, x: x, store_workers=0)


def test_store_workers_write_in_parallel_and_each_item_once() -> None:
    both_in = threading.Barrier(2, timeout=10)  # passes only if two writes overlap
    seen: list[int] = []
    lock = threading.Lock()

    def store(k: int, x: int) -> int:
        if k < 2:
            both_in.wait()
        with lock:
            seen.append(k)
        return k

    p = Pipeline(lambda k, x: x, store, process_depth=2, store_depth=2, store_workers=2).start()
    for i in range(30):
        p.submit(i, i)
    assert p.drain(timeout=10)
    p.stop()
    assert sorted(seen) == list(range(30))
    assert sorted(o.key for o in p.results() if o.ok) == list(range(30))
    st = p.stats()
    assert st.bound == 2 + 2 + 2 + 2 and st.max_in_flight <= st.bound
