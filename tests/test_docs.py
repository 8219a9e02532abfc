"""The documentation against the code: the README stays short, every long option of every
`recon` sub-command is documented in the README or a page of docs/, and every relative link
of those files points to a file that exists. Reads text and builds the argparse parser;
runs nothing."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from recon.commands.cli_args import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
MAX_README_LINES = 200

# [text](target) and ![alt](target), with an optional "title"; targets without spaces.
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
EXTERNAL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")  # http:, https:, mailto:, ...


def doc_files() -> list[Path]:
    return [README, *sorted(DOCS.glob("*.md"))]


def documented_text() -> str:
    return "\n".join(path.read_text(encoding="utf-8") for path in doc_files())


def long_options(parser: argparse.ArgumentParser) -> dict[str, set[str]]:
    """{sub-command: its long options} for every sub-command of the parser (and theirs,
    should one have sub-commands of its own), without --help."""
    found: dict[str, set[str]] = {}

    def walk(p: argparse.ArgumentParser, name: str) -> None:
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    walk(sub, f"{name} {sub_name}".strip())
            elif name:
                options = {o for o in action.option_strings if o.startswith("--") and o != "--help"}
                found.setdefault(name, set()).update(options)

    walk(parser, "")
    return found


def mentioned(option: str, text: str) -> bool:
    """`option` as a whole word: --polish does not count inside --polish-option or --no-polish."""
    return re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text) is not None


def relative_links(path: Path) -> list[str]:
    """The relative link targets of a markdown file, fenced code blocks left out."""
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.DOTALL)
    return [t for t in LINK.findall(text) if not EXTERNAL.match(t) and not t.startswith("#")]


def test_readme_is_short():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) < MAX_README_LINES, f"README.md has {len(lines)} lines; move detail to docs/"


def test_parser_walk_finds_the_subcommands():
    options = long_options(build_parser())
    assert {"run", "batch", "demo", "view", "eval"} <= set(options)
    assert {"--stride", "--on-break", "--max-triangles", "--set"} <= options["run"]
    assert "--help" not in options["run"]


def test_every_long_option_is_documented():
    text = documented_text()
    missing = sorted(f"recon {command} {option}" for command, options in long_options(build_parser()).items()
                     for option in options if not mentioned(option, text))
    assert not missing, "options documented neither in README.md nor docs/*.md: " + ", ".join(missing)


def test_option_match_is_whole_word():
    assert mentioned("--polish", "give `--polish` to polish")
    assert not mentioned("--polish", "--polish-option calibrate_lens=true and --no-polish")
    assert not mentioned("--no-medea", "--no-medea-gate")


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    broken = []
    for target in relative_links(path):
        file = target.split("#", 1)[0].split("?", 1)[0]
        if file and not (path.parent / file).exists():
            broken.append(target)
    assert not broken, f"{path.relative_to(ROOT)}: links to missing files: {', '.join(broken)}"


def test_link_check_sees_links():
    readme_links = relative_links(README)
    assert "docs/images/rerun_layout.png" in readme_links
    assert any(link.startswith("docs/") and link.endswith(".md") for link in readme_links)
