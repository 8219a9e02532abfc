"""Independent calls spread over the machine's cores by threads: for calls that release the
GIL (OpenCV, most of numpy), whose results do not depend on the thread they ran on."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
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
