"""The layering the code keeps: the method packages (medea_core, mvs_core) and the viewer
never import recon or open3d, no module imports a layer above its own, no files import
each other in a loop. Read from the source (every import statement, also those inside
functions), not from what happens to be loaded (scripts/import_graph.py prints the same
reading as floors)."""

import ast
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

from import_graph import (  # noqa: E402
    LAYERS,
    MOST_MODULES,
    POSES_LAYERS,
    crowded_folders,
    file_edges,
    imported_modules,
    layer_of,
    loops,
    upward_imports,
)


@pytest.mark.parametrize("package", ["medea_core", "mvs_core", "viewer"])
def test_pure_packages_import_neither_recon_nor_open3d(package):
    files = imported_modules(package)
    assert files, package
    offenders = {f: sorted(n for n in names if n.split(".")[0] in ("recon", "open3d"))
                 for f, names in files.items()}
    assert not {f: n for f, n in offenders.items() if n}


def test_no_module_imports_a_higher_layer():
    assert not upward_imports()


def test_the_layers_are_real_and_the_top_level_is_small():
    """Every layer holds code (a renamed package cannot leave the rule above checking nothing),
    and recon/ itself holds only the ground modules, the pipeline and `python -m recon`."""
    modules = {p.relative_to(ROOT).with_suffix("").as_posix().replace("/", ".")
               for p in (ROOT / "recon").rglob("*.py")}
    for k, (name, _) in enumerate(LAYERS):
        assert any(layer_of(m) == k for m in modules), name
    top = sorted(p.name for p in (ROOT / "recon").glob("*.py"))
    assert top == ["__init__.py", "__main__.py", "choices.py", "errors.py", "memory.py", "options.py", "pipeline.py",
                   "threads.py"]


def test_the_pose_packages_import_only_their_own_level_and_below():
    """recon/poses/__init__.py's order: result < ba, matching < checks < config < intrinsics,
    given < frontend < sfm < the entry point; every level holds code."""
    assert not upward_imports(ROOT, POSES_LAYERS, ("recon.poses",))
    modules = {p.relative_to(ROOT).with_suffix("").as_posix().replace("/", ".")
               for p in (ROOT / "recon" / "poses").rglob("*.py")}
    for k, (name, _) in enumerate(POSES_LAYERS):
        assert any(layer_of(m, POSES_LAYERS) == k for m in modules), name
    assert layer_of("recon.poses.ba.bundle", POSES_LAYERS) < layer_of("recon.poses.frontend.tracker", POSES_LAYERS)
    assert layer_of("recon.poses.second_opinion", POSES_LAYERS) == len(POSES_LAYERS) - 1


def test_no_folder_holds_more_than_twelve_modules(tmp_path):
    """A folder past MOST_MODULES modules is split into packages by role; the check itself sees
    a made-up crowded package."""
    assert not crowded_folders()
    crowded = tmp_path / "recon" / "crowd"
    crowded.mkdir(parents=True)
    for k in range(MOST_MODULES + 1):
        (crowded / f"m{k}.py").write_text("")
    (crowded / "__init__.py").write_text("")
    assert crowded_folders(tmp_path) == {"recon/crowd": MOST_MODULES + 1}


def test_no_import_loop_between_files():
    assert not loops(file_edges())


def test_the_loop_and_layer_checks_can_fail():
    """The two readings above on a made-up graph and module: a loop is found, an upward import named."""
    assert loops({"a.py": {"b.py"}, "b.py": {"c.py"}, "c.py": {"a.py"}}) == [["a.py", "b.py", "c.py", "a.py"]]
    assert layer_of("recon.core.stages") > layer_of("recon.geometry.lie") > layer_of("recon.errors")
    assert layer_of("recon.commands.cli") == len(LAYERS) - 1


# Test files that cover the repository rather than one module (tests/README.md).
REPO_WIDE_TESTS = {"test_docs.py", "test_examples.py", "test_layers.py"}


def test_every_test_file_is_named_after_the_module_it_tests():
    """tests/README.md's rule: test_<package>_<module>[_<aspect>].py for recon/<package>/<module>.py
    (recon's own package name left out; medea_core, mvs_core and viewer keep theirs)."""
    modules = set()
    for package in ("recon", "medea_core", "mvs_core", "viewer"):
        for path in (ROOT / package).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            modules.add("_".join(parts[1:] if parts[0] == "recon" else parts))
    modules.discard("")
    misnamed = [p.name for p in sorted((ROOT / "tests").glob("test_*.py")) if p.name not in REPO_WIDE_TESTS
                and not any(p.stem[5:] == m or p.stem[5:].startswith(m + "_") for m in modules)]
    assert not misnamed


# Public functions of these packages state their contract as kornia does (issue 65).
DOCUMENTED_PACKAGES = ("medea_core", "mvs_core", "recon/geometry", "recon/fusion")
# Methods whose docstrings are another change's: the config dataclasses' fields and methods.
DOCUMENTED_ELSEWHERE: set[str] = set()


def _public_functions(tree: ast.Module):
    """(qualified name, node) of the module's public functions and public classes' public methods."""
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            yield node.name, node
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for member in node.body:
                if isinstance(member, (ast.FunctionDef, ast.AsyncFunctionDef)) and not member.name.startswith("_"):
                    yield f"{node.name}.{member.name}", member


def _returns_value(fn) -> bool:
    """A return annotation other than None, or a `return <value>` outside nested functions."""
    if fn.returns is not None and not (isinstance(fn.returns, ast.Constant) and fn.returns.value is None):
        return True
    stack = list(fn.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            continue
        if isinstance(node, ast.Return) and node.value is not None:
            return True
        stack.extend(ast.iter_child_nodes(node))
    return False


def contract_problems(fn) -> list[str]:
    """What a function's docstring lacks: a summary line followed by a blank line, an `Args:` section
    naming every parameter but self/cls, a `Returns:` section when it returns a value."""
    doc = ast.get_docstring(fn) or ""
    lines = doc.splitlines()
    problems = []
    if not lines or not lines[0].strip() or (len(lines) > 1 and lines[1].strip()):
        problems.append("summary line")
    args = fn.args
    params = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs + [args.vararg, args.kwarg] if a]
    params = [p for p in params if p not in ("self", "cls")]
    if params:
        section = re.search(r"^Args:\n((?:[ \t]+\S.*\n?|\n)*)", doc, re.M)
        named = set(re.findall(r"^[ \t]+\**(\w+)[ \t]*[(:]", section.group(1), re.M)) if section else set()
        problems += [f"Args: {p}" for p in params if p not in named]
    if _returns_value(fn) and not re.search(r"^Returns:\n[ \t]+\S", doc, re.M):
        problems.append("Returns")
    return problems


def test_public_functions_document_their_contract():
    """Every public function and method of the method and geometry packages has a summary line,
    Args naming each parameter and Returns when it returns something."""
    found, undocumented = 0, {}
    for package in DOCUMENTED_PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = path.relative_to(ROOT).as_posix()
            if name in DOCUMENTED_ELSEWHERE:
                continue
            for qualname, fn in _public_functions(ast.parse(path.read_text(encoding="utf-8"))):
                found += 1
                if problems := contract_problems(fn):
                    undocumented[f"{name}:{fn.lineno} {qualname}"] = problems
    assert found > 100
    assert not undocumented


def test_the_contract_check_can_fail():
    """The check above on made-up functions: a missing parameter, Returns and summary line are found."""
    source = '''
def good(x, *, y=1):
    """Add.

    Args:
        x: (N,) values.
        y: offset.

    Returns:
        (N,) x + y.
    """
    return x + y

def bad(x, y):
    """Add
    two numbers.

    Args:
        x: (N,) values.
    """
    return x + y

def nothing(self):
    """Do nothing."""
'''
    funcs = {fn.name: fn for fn in ast.parse(source).body}
    assert contract_problems(funcs["good"]) == []
    assert contract_problems(funcs["bad"]) == ["summary line", "Args: y", "Returns"]
    assert contract_problems(funcs["nothing"]) == []


MODULE_DOCSTRING_PACKAGES = ["recon", "medea_core", "mvs_core", "viewer"]
MAX_MODULE_DOCSTRING_LINES = 10


def module_docstring_lines(source: str) -> int:
    """The number of lines of a module's docstring (0 without one), as written."""
    doc = ast.get_docstring(ast.parse(source), clean=False)
    return len(doc.splitlines()) if doc else 0


def test_module_docstrings_are_short():
    """Every module docstring says the module's contract in at most ten lines; the design,
    measurements and file formats live in docs/, to which the docstring points."""
    found, long = 0, {}
    for package in MODULE_DOCSTRING_PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            found += 1
            if (n := module_docstring_lines(path.read_text(encoding="utf-8"))) > MAX_MODULE_DOCSTRING_LINES:
                long[path.relative_to(ROOT).as_posix()] = n
    assert found > 100
    assert not long


def test_the_module_docstring_check_can_fail():
    """The count above on made-up modules: lines as written, none without a docstring."""
    assert module_docstring_lines('"""One line."""\nx = 1\n') == 1
    assert module_docstring_lines('"""Summary.\n\nMore: docs/x.md#y\n"""\n') == 3
    assert module_docstring_lines("x = 1\n") == 0
    assert module_docstring_lines('"""' + "line\n" * 11 + '"""\n') == 11
