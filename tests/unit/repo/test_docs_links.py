"""Every relative link and image in README.md, CONTRIBUTING.md and docs/**/*.md points at a file
that exists, and every #anchor at a heading of that page (GitHub's slug rule)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
PAGES = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md", *(ROOT / "docs").rglob("*.md")])
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def links(page: Path) -> list[str]:
    text = FENCE.sub("", page.read_text())
    return [m.group(1) for m in LINK.finditer(text)]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but ``-`` and ``_`` dropped, spaces to
    hyphens (of the rendered text: code and emphasis marks go first)."""
    text = re.sub(r"[`*]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.+)$", text, re.M)}


def test_the_pages_and_the_link_pattern():
    assert ROOT / "README.md" in PAGES and ROOT / "docs" / "results.md" in PAGES
    found = links(ROOT / "README.md")
    assert "docs/results.md" in found and "docs/lego_test_r_9.png" in found
    assert slug("Speed: fine-tuning, memory, process settings, HTTP") == (
        "speed-fine-tuning-memory-process-settings-http")
    assert slug("gsplat `simple_trainer`") == "gsplat-simple_trainer"
    assert slug("Numerical rules (one definition each, used by every entry point)") == (
        "numerical-rules-one-definition-each-used-by-every-entry-point")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path):
    broken = []
    for target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target}: no file {file}")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{target}: no heading #{anchor} in {file.name}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_readme_is_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250
