"""Work on threads beside the caller's: independent calls spread over the machine's cores,
and an iterable's items made ahead of their use. For calls that release the GIL (OpenCV, a
video's decoding, most of numpy), whose results do not depend on the thread they ran on."""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

Item = TypeVar("Item")
Result = TypeVar("Result")


def map_on_cores(function: Callable[[Item], Result], items: Iterable[Item]) -> list[Result]:
    """``[function(item) for item in items]``, a thread per core (at most one per item).

    Args:
        function: called once per item; it must not share mutable state between calls
            (an OpenCV algorithm object, a random generator).
        items: the arguments.

    Returns:
        The results, in the items' order.
    """
    items = list(items)
    workers = max(1, min(os.cpu_count() or 1, len(items)))
    if workers == 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(function, items))


_END = object()


def prefetched(items: Iterable[Item], ahead: int = 1) -> Iterator[Item]:
    """The items of an iterable in order, each made on a background thread while the caller
    works on the ones before (at most `ahead` waiting): a video's decoding overlaps the work
    on its frames.

    The iterable is advanced on that thread alone; an exception it raises is raised here, at
    the item where it happened. Leaving the loop early stops the thread (and closes the
    iterable) before this generator finishes closing.

    Args:
        items: the iterable (e.g. a frame source); advanced by the background thread only.
        ahead: items made in advance at most, >= 1.

    Returns:
        An iterator over the same items.
    """
    waiting: queue.Queue = queue.Queue(maxsize=max(1, int(ahead)))
    stop = threading.Event()

    def hand_over(entry) -> bool:
        while not stop.is_set():
            try:
                waiting.put(entry, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        iterator = iter(items)
        try:
            for item in iterator:
                if not hand_over((item, None)):
                    return
            hand_over((_END, None))
        except BaseException as error:  # raised again on the caller's thread
            hand_over((_END, error))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()

    thread = threading.Thread(target=produce, name="recon-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            item, error = waiting.get()
            if item is _END:
                if error is not None:
                    raise error
                return
            yield item
    finally:
        stop.set()
        thread.join()
