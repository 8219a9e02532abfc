"""recon.threads: calls spread over the cores come back in order, as the serial calls would."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from recon.threads import map_on_cores, prefetched


def test_results_come_back_in_the_items_order_and_equal_the_serial_calls():
    rng = np.random.default_rng(0)
    images = [rng.random((64, 64)) for _ in range(9)]
    blur = lambda image: np.cumsum(np.cumsum(image, 0), 1)  # noqa: E731
    got = map_on_cores(blur, images)
    assert len(got) == len(images)
    for image, result in zip(images, got):
        assert np.array_equal(result, blur(image))


def test_the_calls_run_on_more_than_one_thread_where_the_machine_has_cores(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    barrier = threading.Barrier(2, timeout=10)
    # Each call waits for the other: only two threads at once get past the barrier.
    assert map_on_cores(lambda k: barrier.wait() * 0 + k, [1, 2]) == [1, 2]
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    assert map_on_cores(lambda k: threading.current_thread() is threading.main_thread(), [1, 2]) == [True, True]


def test_an_error_in_a_call_reaches_the_caller():
    def fail(k):
        if k == 3:
            raise ValueError("item 3")
        return k

    with pytest.raises(ValueError, match="item 3"):
        map_on_cores(fail, range(5))


def test_prefetched_items_come_in_order_and_are_made_on_another_thread():
    made_on = []

    def frames():
        for k in range(20):
            made_on.append(threading.current_thread().name)
            yield k

    assert list(prefetched(frames(), ahead=3)) == list(range(20))
    assert set(made_on) == {"recon-prefetch"}


def test_an_error_while_prefetching_is_raised_at_its_item():
    def frames():
        yield 0
        yield 1
        raise ValueError("frame 2 is corrupt")

    got = []
    with pytest.raises(ValueError, match="frame 2 is corrupt"):
        for item in prefetched(frames()):
            got.append(item)
    assert got == [0, 1]


def test_leaving_a_prefetched_loop_early_stops_the_thread_and_closes_the_source():
    closed = threading.Event()

    def frames():
        try:
            k = 0
            while True:
                yield k
                k += 1
        finally:
            closed.set()

    before = threading.active_count()
    for item in prefetched(frames(), ahead=2):
        if item == 5:
            break
    # The generator is closed once the loop lets go of it (CPython: at once).
    assert closed.wait(timeout=5), "the source was not closed"
    assert threading.active_count() == before
