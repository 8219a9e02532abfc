"""What an earlier `recon run` wrote into an output folder, by its own report.json, so that a
run with ``--overwrite`` can remove the earlier run's results it did not write again (a
run written as segments after a single one, fewer segments than before, frames that no
longer get depth) and never a file recon did not write.

A report lists its files (``files``: names in the folder; a run written as segments lists
its ``segment_NN`` folders, each with a report of its own) and the frames whose depth maps
it wrote (``frames.depth_names``, else ``frames.names``).
"""

from __future__ import annotations

import json
from pathlib import Path

from recon.io.output_folder import DEPTH_DIR, DEPTH_NPY, DEPTH_PNG, REPORT_JSON, UNFINISHED, depth_name


def earlier_run_files(folder) -> list[Path]:
    """The files the run whose report.json is in `folder` wrote there (its report, each
    file it lists, the depth maps of the frames it names, and the same for each segment
    folder it lists), those that exist; [] when the folder has no readable report."""
    folder = Path(folder)
    try:
        report = json.loads((folder / REPORT_JSON).read_text())
    except (OSError, ValueError):
        return []
    if not isinstance(report, dict):
        return []
    found = [folder / REPORT_JSON]
    for name in (report.get("files") or {}).values():
        path = (folder / str(name)).resolve()
        if folder.resolve() not in path.parents:
            continue  # a file the report names outside the folder (a recording saved elsewhere)
        if path.is_dir() and path.name == DEPTH_DIR:
            frames = report.get("frames") or {}
            names = frames.get("depth_names") or frames.get("names") or []
            found += [folder / depth_name(str(n), suffix) for n in names for suffix in (DEPTH_PNG, DEPTH_NPY)]
        elif path.is_dir():
            found += earlier_run_files(path)
        else:
            found.append(path)
    return [p for p in dict.fromkeys(found) if p.is_file()]


def remove_earlier_run(folder, files: list[Path], since: float) -> list[Path]:
    """Delete those of an earlier run's `files` in `folder` (earlier_run_files) that were not
    written again since `since` (seconds since the epoch, the new run's start: a file
    written again is the new run's), then the folders inside `folder` that this leaves
    empty; returns the files removed."""
    folder = Path(folder).resolve()
    removed = []
    for path in files:
        try:
            if path.stat().st_mtime < since and path.name != UNFINISHED:
                path.unlink()
                removed.append(path)
        except FileNotFoundError:
            continue
    emptied = {p.resolve().parent for p in removed}
    for sub in sorted(emptied, key=lambda p: len(p.parts), reverse=True):
        while folder in sub.parents:
            try:
                sub.rmdir()  # only when empty
            except OSError:
                break
            sub = sub.parent
    return removed


__all__ = ["earlier_run_files", "remove_earlier_run"]
