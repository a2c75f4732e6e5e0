"""The README's and docs' relative links point at files that exist (a bug, fixed: docs/architecture.md linked
docs/benchmarks.md relative to docs/, that is docs/docs/benchmarks.md)."""

from __future__ import annotations

import re

from helpers import ROOT

#: A Markdown inline link or image: [text](target) or ![alt](target), the target up to a space or ")".
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s[^)]*)?\)")


def relative_links(text: str) -> list[str]:
    """The file parts of the relative link targets in ``text`` (no URL scheme, no pure #anchor), code spans aside."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    targets = (m.group(1) for m in LINK.finditer(text))
    return [t.split("#", 1)[0] for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:", t) and not t.startswith("#")]


def test_relative_links_finds_file_parts_only():
    text = '[a](docs/x.md#part) ![b](fig.png) [c](https://example.org) [d](#top) `[e](in/code.md)` [f](y.md "title")'
    assert relative_links(text) == ["docs/x.md", "fig.png", "y.md"]


def test_every_relative_link_in_the_readme_and_docs_resolves():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    broken = [
        f"{page.relative_to(ROOT)}: {target}"
        for page in pages
        for target in relative_links(page.read_text())
        if not (page.parent / target).exists()
    ]
    assert len(pages) > 5 and not broken, broken


def test_the_architecture_page_names_every_module():
    """docs/architecture.md's module table names each module of the package by its file (it had left out
    smart_start/frontier.py and agents/tables.py)."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    modules = sorted(p for p in (ROOT / "ss_drl").rglob("*.py") if p.name != "__init__.py")
    missing = [str(p.relative_to(ROOT)) for p in modules if f"{p.name}`" not in page]
    assert modules and not missing, f"not in docs/architecture.md: {missing}"
