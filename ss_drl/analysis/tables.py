"""Markdown tables: the one writer behind the results table (:mod:`.aggregate`) and the benchmark tables."""

from __future__ import annotations

from collections.abc import Sequence


def _cell(value: object) -> str:
    # A "|" would end the cell and a line break the row: escape the one, fold the other into a space.
    return " ".join(str(value).split("\n")).replace("|", "\\|")


def format_markdown_table(headers: Sequence[object], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured markdown table: header, separator, one line per row; no trailing newline.

    Cells are written with ``str`` (format numbers before), ``|`` is escaped and line breaks become spaces. Raises
    ``ValueError`` when there are no headers or a row has a different number of cells than the header.
    """
    if not headers:
        raise ValueError("a markdown table needs at least one header")
    for i, row in enumerate(rows):
        if len(row) != len(headers):
            raise ValueError(f"table row {i} has {len(row)} cells, expected {len(headers)} (one per header)")

    def line(cells: Sequence[object]) -> str:
        return "| " + " | ".join(_cell(c) for c in cells) + " |"

    return "\n".join([line(headers), "|" + "|".join("---" for _ in headers) + "|", *(line(r) for r in rows)])
