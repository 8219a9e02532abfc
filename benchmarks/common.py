"""Helpers shared by the benchmark scripts: machine description, progress lines, tables, JSON output."""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict:
    """What the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": sys.version.split()[0],
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }
    return info


def say(text: str) -> None:
    """A progress line with the time of day (long benchmark runs are read as they go)."""
    print(f"[{time.strftime('%H:%M:%S')}] {text}", flush=True)


def table(headers: list[str], rows: list[list]) -> str:
    """A markdown table."""
    cells = [[str(c) for c in row] for row in rows]
    widths = [max([len(h), *(len(r[k]) for r in cells)]) for k, h in enumerate(headers)]
    fmt = lambda row: "| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |"  # noqa: E731
    return "\n".join([fmt(headers), "|" + "|".join("-" * (w + 2) for w in widths) + "|", *map(fmt, cells)])


def parse_variant(text: str) -> tuple[str, list[str]]:
    """A command-line variant "LABEL=RECON RUN ARGS" as (label, argument list)."""
    import argparse
    import shlex

    label, _, args = text.partition("=")
    if not label:
        raise argparse.ArgumentTypeError(f"expected LABEL=ARGS, got {text!r}")
    return label, shlex.split(args)


def write_json(name: str, payload: dict) -> Path:
    """benchmarks/results/<name>.json, or `name` itself where it is a path to a .json file
    (a path given for a name once cost a whole validation run: its folder did not exist)."""
    path = Path(name) if name.endswith(".json") or "/" in name else RESULTS / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=float))
    tmp.replace(path)
    return path


def ping_pong(count: int, length: int):
    """Indices (length,) of `count` frames played forwards, backwards, forwards, ... (a camera
    walking the same room again), the turning frames not repeated."""
    import numpy as np

    return np.resize(np.concatenate([np.arange(count), np.arange(count - 2, 0, -1)]), length)


def best_ms_per_item(run, count: int, rounds: int = 3) -> float:
    """Milliseconds per item of ``run()`` (which handles ``count`` items): one warm-up call,
    then the best of ``rounds`` timed calls (on a shared machine the minimum is the least
    disturbed run)."""
    import time

    run()
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return 1000 * min(times) / count
