"""How file names are ordered: the one natural sort rule of every folder recon reads.

Image folders, dataset frame lists, depth folders, per-frame pose files, COLMAP image
names and output depth maps are all listed with :func:`natural_key`, so the same folder
gives the same frame order wherever it is read.
"""

from __future__ import annotations

import re

_DIGIT_RUNS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple[tuple, str]:
    """Sort key of a file name: digit runs compare as numbers, text case-insensitively.

    'frame2' sorts before 'frame10' and 'B1.png' after 'a1.png'; the whole name is part of
    the key (extension included), and names equal under that rule ('f01' and 'f1', 'A1'
    and 'a1') are ordered by their exact text, so the order never depends on listing order.
    """
    parts = _DIGIT_RUNS.split(name)
    # re.split with one group alternates text (even positions) and digit runs (odd ones).
    return tuple(int(p) if i % 2 else p.lower() for i, p in enumerate(parts)), name
