"""The front page and the reference docs: their size, the two commands up front, links that
resolve (files and section anchors), and no roadmap wording where a user reads."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = sorted([README, ROOT / "CHANGELOG.md", *(ROOT / "docs").glob("*.md")])
GENERATED = {ROOT / "docs" / "results.md"}  # written by `trafficweaving report`; checked once it exists


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _prose(path: Path) -> list[str]:
    """The lines of ``path`` outside fenced code blocks."""
    lines, fenced = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced:
            lines.append(line)
    return lines


def _anchors(path: Path) -> set[str]:
    return {_slug(m.group(1)) for line in _prose(path) if (m := re.match(r"#+\s+(.*)", line))}


def test_readme_is_a_front_page_with_both_commands_up_front():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250
    head = "\n".join(lines[:50])
    assert "make demo" in head and "make test" in head


@pytest.mark.parametrize("page", [p for p in PAGES if p.parent.name == "docs"], ids=lambda p: p.name)
def test_no_docs_page_over_500_lines(page):
    assert len(page.read_text(encoding="utf-8").splitlines()) <= 500


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_resolve_to_files_and_sections(page):
    broken = []
    for line in _prose(page):
        for target in re.findall(r"\]\(([^)\s]+)\)", line):
            if target.startswith(("http://", "https://")):
                continue
            path, _, anchor = target.partition("#")
            resolved = (page.parent / path).resolve() if path else page
            if resolved in GENERATED and not resolved.exists():
                continue
            if not resolved.exists():
                broken.append(target)
            elif anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
                broken.append(target)
    assert not broken, f"{page.name}: broken links {broken}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_roadmap_wording(page):
    text = page.read_text(encoding="utf-8")
    assert not re.search(r"\broadmap\b|\bstep-\d|\bstage \d of\b", text, re.IGNORECASE)
