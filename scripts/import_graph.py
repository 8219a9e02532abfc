"""The import graph of a checkout, read from its source: which file imports which (every
import statement, those inside functions too, relative ones resolved), drawn as floors of
rooms (a room: a module directly in ``recon/``, a package under it, or a top-level package
beside it; a room stands one floor above the highest room it imports), with the loops between
files and the imports that run against the layers of ``LAYERS``.

The same reading backs ``tests/test_layers.py``. Run it on another checkout to compare
layouts: ``python scripts/import_graph.py [--root CHECKOUT]``.
"""

from __future__ import annotations

import argparse
import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("recon", "medea_core", "mvs_core", "viewer")

# The layers, lowest first: a module may import its own layer and those below, never one above
# (recon/pipeline.py chooses a driver; the drivers run the stages of recon/core; the stages call
# the methods and readers, which share recon/geometry). A module falls to the layer of its
# longest named prefix.
LAYERS = (
    ("ground", ("recon.errors", "recon.choices", "recon.options", "recon.memory", "recon.threads", "recon",
                "medea_core", "mvs_core", "viewer")),
    ("geometry", ("recon.geometry",)),
    ("methods and readers", ("recon.poses", "recon.io", "recon.fusion", "recon.priors", "recon.eval",
                             "recon.synthetic")),
    ("stages", ("recon.core",)),
    ("export", ("recon.export",)),
    ("drivers", ("recon.drivers",)),
    ("pipeline", ("recon.pipeline",)),
    ("commands", ("recon.commands", "recon.__main__")),
)

# Inside recon.poses its packages keep the same rule, lowest first (recon/poses/__init__.py):
# what an estimate is, the solver and the matching it fits, the checks on an estimate, the
# front end's settings, the camera and given poses, the front end, SfM, the entry point.
POSES_LAYERS = (
    ("result", ("recon.poses.result",)),
    ("solver and matching", ("recon.poses.ba", "recon.poses.matching")),
    ("checks", ("recon.poses.checks",)),
    ("front-end settings", ("recon.poses.config",)),
    ("camera and given poses", ("recon.poses.intrinsics", "recon.poses.given")),
    ("front end", ("recon.poses.frontend",)),
    ("SfM", ("recon.poses.sfm",)),
    ("entry point", ("recon.poses",)),
)
MOST_MODULES = 12  # modules (besides __init__.py) one folder may hold


def module_name(path: Path, root: Path = ROOT) -> str:
    """recon/poses/ba/bundle.py -> recon.poses.ba.bundle; recon/poses/__init__.py -> recon.poses."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(root: Path, dotted: str) -> bool:
    where = root.joinpath(*dotted.split("."))
    return where.with_suffix(".py").is_file() or (where / "__init__.py").is_file()


def imported_modules(package: str, root: Path = ROOT) -> dict[str, set[str]]:
    """{file (relative path): the dotted names it imports} for every .py file of ``package``;
    ``from a.b import c`` counts as a.b.c, and as a.b unless every name it takes is a module
    of a.b (``from recon.poses import lie`` depends on lie, not on what poses/__init__.py
    defines)."""
    found = {}
    for path in sorted((root / package).rglob("*.py")):
        names = set()
        here = list(path.relative_to(root).with_suffix("").parts)  # recon/poses/ba -> [recon, poses, ba]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                # A relative import is resolved against the file's package (level 1: its own).
                base = here[: len(here) - node.level] if node.level else []
                module = ".".join(base + ([node.module] if node.module else []))
                taken = [f"{module}.{alias.name}" for alias in node.names]
                names.update(taken)
                if not all(_is_module(root, name) for name in taken):
                    names.add(module)
        found[path.relative_to(root).as_posix()] = names
    return found


def file_edges(root: Path = ROOT) -> dict[str, set[str]]:
    """{file: the files of the checkout it imports} (an import of a package: its __init__.py;
    ``from pkg import mod``: pkg/mod.py as well)."""
    files = {f: names for package in PACKAGES if (root / package).is_dir()
             for f, names in imported_modules(package, root).items()}
    file_of = {module_name(root / f, root): f for f in files}
    return {f: {file_of[n] for n in names if n in file_of and file_of[n] != f} for f, names in files.items()}


def loops(edges: dict[str, set[str]]) -> list[list[str]]:
    """The cycles a depth-first walk meets (each as [a, b, ..., a]); none in a layered graph."""
    state, found = {}, []

    def visit(f, path):
        state[f] = "open"
        for g in sorted(edges.get(f, ())):
            if state.get(g) == "open":
                found.append(path[path.index(g):] + [g])
            elif g not in state:
                visit(g, path + [g])
        state[f] = "done"

    for f in sorted(edges):
        if f not in state:
            visit(f, [f])
    return found


def layer_of(module: str, layers=LAYERS) -> int | None:
    """The index in `layers` of the longest prefix naming `module` (None: no layer names it)."""
    best, depth = None, -1
    for k, (_, prefixes) in enumerate(layers):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and prefix.count(".") > depth:
                best, depth = k, prefix.count(".")
    return best


def upward_imports(root: Path = ROOT, layers=LAYERS, packages=PACKAGES) -> dict[str, list[str]]:
    """{file: the modules it imports from a layer above its own}, for the files of `packages`
    (dotted names) under the order `layers`; modules no layer names are left out."""
    found = {}
    for package in packages:
        for f, names in imported_modules(package.replace(".", "/"), root).items():
            mine = layer_of(module_name(root / f, root), layers)
            if mine is None:
                continue
            above = sorted(n for n in names if (layer_of(n, layers) or 0) > mine)
            if above:
                found[f] = [f"{n} ({layers[layer_of(n, layers)][0]})" for n in above]
    return found


def crowded_folders(root: Path = ROOT, most: int = MOST_MODULES) -> dict[str, int]:
    """{folder: its module count} for the package folders holding more than `most` modules
    (.py files besides __init__.py directly in the folder)."""
    found = {}
    for package in PACKAGES:
        for folder in [root / package, *sorted(p.parent for p in (root / package).rglob("*/__init__.py"))]:
            count = sum(1 for p in folder.glob("*.py") if p.name != "__init__.py")
            if count > most:
                found[folder.relative_to(root).as_posix()] = count
    return found


def room_of(path: str) -> str:
    """recon/poses/ba/bundle.py -> recon/poses/; recon/pipeline.py -> itself; viewer/x.py -> viewer/."""
    parts = path.split("/")
    if parts[0] != "recon":
        return parts[0] + "/"
    return path if len(parts) == 2 else "/".join(parts[:2]) + "/"


def floors(edges: dict[str, set[str]]) -> dict[str, int]:
    """{room: floor}: 1 for a room that imports no other, else one above the highest it
    imports (rooms in a loop share the floor the walk reaches first)."""
    rooms = defaultdict(set)
    for f, to in edges.items():
        rooms[room_of(f)].update(room_of(g) for g in to if room_of(g) != room_of(f))
    floor: dict[str, int] = {}

    def height(room, seen=()):
        if room not in floor:
            below = [height(r, seen + (room,)) for r in rooms[room] if r not in seen]
            floor[room] = 1 + max(below, default=0)
        return floor[room]

    for room in sorted(rooms):
        height(room)
    return floor


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="the checkout to read (default: this one)")
    root = parser.parse_args().root.resolve()
    edges = file_edges(root)
    floor = floors(edges)
    size = defaultdict(int)
    for f in edges:
        size[room_of(f)] += 1
    print(f"{root}: {len(edges)} files, {sum(map(len, edges.values()))} imports between them, "
          f"{sum(1 for f in edges if f.count('/') == 1 and f.startswith('recon/'))} modules directly in recon/")
    for k in sorted(set(floor.values()), reverse=True):
        rooms = sorted(r for r in floor if floor[r] == k)
        print(f"floor {k:2d}  " + ", ".join(f"{r}" + (f" ({size[r]} files)" if r.endswith('/') else "")
                                            for r in rooms))
    cycles = loops(edges)
    print(f"import loops between files: {len(cycles)}" + "".join(f"\n  {' -> '.join(c)}" for c in cycles))
    where = [root / name.replace(".", "/") for _, names in LAYERS[1:] for name in names]
    if not all(p.is_dir() or p.with_suffix(".py").is_file() for p in where):
        print("(the layers of LAYERS name packages this checkout does not have: no layer check)")
        return
    up = upward_imports(root)
    print(f"files importing a layer above their own (LAYERS): {len(up)}"
          + "".join(f"\n  {f}: {', '.join(n)}" for f, n in sorted(up.items())))
    if (root / "recon" / "poses" / "ba").is_dir():
        up = upward_imports(root, POSES_LAYERS, ("recon.poses",))
        print(f"files in recon/poses importing a package above their own (POSES_LAYERS): {len(up)}"
              + "".join(f"\n  {f}: {', '.join(n)}" for f, n in sorted(up.items())))
    crowded = crowded_folders(root)
    print(f"folders holding more than {MOST_MODULES} modules: {len(crowded)}"
          + "".join(f"\n  {f}: {n}" for f, n in sorted(crowded.items())))


if __name__ == "__main__":
    main()
