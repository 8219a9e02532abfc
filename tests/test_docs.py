"""The documentation against the code: the README stays short, every long option of every
`recon` sub-command is documented in the README or a page of docs/, every relative link of
those files points to a file (and heading) that exists, every doc heading cited from code
exists, and no heading outside docs/history/ names an issue or a stop. Reads text and
builds the argparse parser; runs nothing."""

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


HISTORY = DOCS / "history"
# Where code cites doc headings: the packages, the benchmarks, the scripts, the presets.
CITING = [ROOT / "recon", ROOT / "medea_core", ROOT / "mvs_core", ROOT / "benchmarks", ROOT / "scripts"]
CITING_SUFFIXES = {".py", ".yaml", ".yml", ".sh"}
# docs/X.md, "Heading" or 'Heading' (the quotes may wrap over lines, through comment marks);
# docs/X.md#anchor; a bare docs/X.md.
CITED_HEADING = re.compile(r"(docs/[\w/.-]+?\.md)`{0,2},\s*(?:#\s*)?([\"'])(.+?)\2", re.DOTALL)
CITED_ANCHOR = re.compile(r"(docs/[\w/.-]+?\.md)#([\w-]+)")
CITED_FILE = re.compile(r"(docs/[\w/.-]+?\.md)")
ISSUE_OR_STOP = re.compile(r"\b(issue|stop)s? \d", re.IGNORECASE)


def doc_files() -> list[Path]:
    return [README, *sorted(DOCS.glob("*.md"))]


def history_files() -> list[Path]:
    return sorted(HISTORY.glob("*.md"))


def headings(path: Path) -> list[str]:
    """The markdown headings of a file (ATX style), fenced code blocks left out."""
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.DOTALL)
    return [m.group(1).strip() for m in re.finditer(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, flags=re.MULTILINE)]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor of a markdown file, GitHub style (a repeated heading gets -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    for heading in headings(path):
        base = slug(heading)
        n = seen.get(base, 0)
        out.add(base if n == 0 else f"{base}-{n}")
        seen[base] = n + 1
    return out


def flatten(quoted: str) -> str:
    """A quoted heading as written in code, joined over its line breaks and comment marks."""
    return re.sub(r"\s*\n\s*(?:#\s*)?", " ", quoted).strip()


def cited(text: str) -> list[tuple[str, str, str]]:
    """The doc citations in a text: (file, "heading" or "#anchor" or "", the citation)."""
    out = [(m.group(1), m.group(3) and flatten(m.group(3)), m.group(0)) for m in CITED_HEADING.finditer(text)]
    out += [(m.group(1), "#" + m.group(2), m.group(0)) for m in CITED_ANCHOR.finditer(text)]
    out += [(m.group(1), "", m.group(0)) for m in CITED_FILE.finditer(text)]
    return out


def bad_citations(text: str) -> list[str]:
    """The citations in `text` whose file, heading or anchor does not exist."""
    bad = []
    for file, target, citation in cited(text):
        path = ROOT / file
        if not path.is_file():
            bad.append(f"{citation!r}: no such file")
        elif target.startswith("#"):
            if target[1:] not in anchors(path):
                bad.append(f"{citation!r}: no such anchor")
        elif target and target not in headings(path):
            bad.append(f"{citation!r}: no such heading")
    return bad


def citing_files() -> list[Path]:
    return sorted(p for root in CITING for p in root.rglob("*")
                  if p.suffix in CITING_SUFFIXES and p.is_file() and "results" not in p.relative_to(ROOT).parts)


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


@pytest.mark.parametrize("path", doc_files() + history_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    broken = []
    for target in relative_links(path):
        file, _, anchor = target.split("?", 1)[0].partition("#")
        linked = (path.parent / file) if file else path
        if not linked.exists():
            broken.append(target)
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            broken.append(target)
    assert not broken, f"{path.relative_to(ROOT)}: links to missing files or headings: {', '.join(broken)}"


def test_slugs_are_githubs():
    assert slug("Settings: `--pose-option`") == "settings---pose-option"
    assert slug("MEDeA (`medea_core/`)") == "medea-medea_core"
    assert slug("The prior's input size") == "the-priors-input-size"


def test_history_is_linked_from_the_index():
    index = (DOCS / "README.md").read_text(encoding="utf-8")
    for path in history_files():
        assert f"history/{path.name}" in index, f"docs/README.md does not link {path.relative_to(ROOT)}"


def test_no_heading_names_an_issue_or_a_stop():
    found = [f"{path.relative_to(ROOT)}: {h}" for path in doc_files()
             for h in headings(path) if ISSUE_OR_STOP.search(h)]
    assert not found, "headings outside docs/history/ name an issue or a stop: " + "; ".join(found)


def test_benchmarks_page_is_short():
    lines = (DOCS / "benchmarks.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) < 600, f"docs/benchmarks.md has {len(lines)} lines; move history to docs/history/"


def test_every_cited_doc_heading_exists():
    files = citing_files()
    assert any(p.name == "fast.yaml" for p in files) and any(p.parts[-2:] == ("core", "report.py") for p in files)
    bad = [f"{p.relative_to(ROOT)}: {b}" for p in files for b in bad_citations(p.read_text(encoding="utf-8"))]
    assert not bad, "code cites doc headings that do not exist:\n" + "\n".join(bad)


def test_citation_check_finds_bad_citations():
    good = 'docs/decisions.md, "The fast preset" and docs/decisions.md#the-fast-preset'
    assert cited(good)[0][1] == "The fast preset"
    assert not bad_citations(good)
    wrapped = '# (docs/decisions.md, "MEDeA on CPU\n    # and CUDA").'
    assert not bad_citations(wrapped)
    assert len(cited(wrapped)) == 2  # the heading and the file
    assert bad_citations('see docs/decisions.md, "A heading nobody wrote"')
    assert bad_citations("see docs/decisions.md#no-such-anchor")
    assert bad_citations('see docs/nowhere.md, "The fast preset"')
    assert bad_citations("see docs/nowhere.md")
    assert bad_citations('``docs/benchmarks.md``, "The gate on given poses"')


def test_link_check_sees_links():
    readme_links = relative_links(README)
    assert "docs/images/rerun_layout.png" in readme_links
    assert any(link.startswith("docs/") and link.endswith(".md") for link in readme_links)
