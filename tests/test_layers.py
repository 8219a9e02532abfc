"""The layering the code keeps: the method packages (medea_core, mvs_core) and the viewer
never import recon or open3d, and recon's geometry modules never import its drivers.
Read from the source (every import statement, also those inside functions), not from
what happens to be loaded."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(package: str) -> dict[str, set[str]]:
    """{file: top-level-qualified names it imports} for every .py file of `package`."""
    found = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        names = set()
        here = list(path.relative_to(ROOT).with_suffix("").parts)  # recon/poses/ba -> [recon, poses, ba]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                # A relative import is resolved against the file's package (level 1: its own).
                base = here[: len(here) - node.level] if node.level else []
                module = ".".join(base + ([node.module] if node.module else []))
                names.add(module)
                names.update(f"{module}.{alias.name}" for alias in node.names)
        found[str(path.relative_to(ROOT))] = names
    return found


@pytest.mark.parametrize("package", ["medea_core", "mvs_core", "viewer"])
def test_pure_packages_import_neither_recon_nor_open3d(package):
    files = imported_modules(package)
    assert files, package
    offenders = {f: sorted(n for n in names if n.split(".")[0] in ("recon", "open3d"))
                 for f, names in files.items()}
    assert not {f: n for f, n in offenders.items() if n}


def test_geometry_and_io_do_not_import_the_drivers():
    """recon/poses, recon/io, recon/fusion and recon/camera.py are below the pipeline: none
    of them imports recon.pipeline, recon.stream* or recon.cli*."""
    drivers = ("recon.pipeline", "recon.stream", "recon.stream_track", "recon.stream_depth", "recon.stream_plan",
               "recon.cli", "recon.cli_args")
    offenders = {}
    for package in ("recon/poses", "recon/io", "recon/fusion"):
        for f, names in imported_modules(package).items():
            bad = sorted(n for n in names if n in drivers)
            if bad:
                offenders[f] = bad
    assert not offenders
