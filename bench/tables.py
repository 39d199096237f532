"""A table as data (the ground layer of :mod:`bench`): a title, columns (name, alignment),
rows of cell texts and notes, rendered alike to Markdown (the reports), CSV and HTML; the
console renders the same object with rich (:func:`bench.console.tables.rich_table`).
What a table shows comes from the typed read of ``metrics.json``
(:mod:`bench.summaries`); the paper's Tables I–III keep their own model,
:class:`calib.evaluation.cross_validation.PaperTable`, which :meth:`Table.from_paper`
takes over for the console.

The renderings leave the title to the document around the table (a heading, a sentence
before it): Markdown and CSV write the columns and rows, HTML adds the title as the
table's caption; the console shows it above the table.
"""

from __future__ import annotations

import csv
import html
import io
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from calib.evaluation.cross_validation import PaperTable

__all__ = ["Column", "Table", "left", "right"]

Align = Literal["left", "right"]


@dataclass(frozen=True)
class Column:
    """A column: its name, how its cells align, whether the console keeps them on one
    line (``no_wrap``: labels) and whether they are identifiers (``code``: in backticks
    in Markdown, ``<code>`` in HTML, plain elsewhere)."""

    name: str
    align: Align = "left"
    no_wrap: bool = False
    code: bool = False


def left(*names: str) -> tuple[Column, ...]:
    """Left-aligned columns (labels)."""
    return tuple(Column(n, "left") for n in names)


def right(*names: str) -> tuple[Column, ...]:
    """Right-aligned columns (figures)."""
    return tuple(Column(n, "right") for n in names)


def _md_cell(text: str) -> str:
    # An empty cell is one space wide: ``| | |`` (an unnamed column's header).
    return f" {text} " if text else " "


@dataclass(frozen=True)
class Table:
    """Columns, rows of cell texts (one per column), an optional title and notes (the
    paragraphs that follow the table: units, what a column means)."""

    columns: tuple[Column, ...]
    rows: tuple[tuple[str, ...], ...] = ()
    title: str | None = None
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for row in self.rows:
            if len(row) != len(self.columns):
                raise ValueError(f"a row of {len(row)} cells in a table of {len(self.columns)}")

    @classmethod
    def from_paper(cls, t: PaperTable, columns: Sequence[str] | None = None) -> Table:
        """One of the paper's tables (:class:`calib.evaluation.cross_validation.PaperTable`):
        its two label columns left and unwrapped, the figures right; ``columns`` replaces its column
        names (shorter ones for a narrow terminal)."""
        names = tuple(columns or t.columns)
        cols = tuple(
            Column(n, "left" if i < 2 else "right", no_wrap=i < 2) for i, n in enumerate(names)
        )
        return cls(cols, t.rows, t.title)

    def cells(self, row: Sequence[str]) -> list[str]:
        """A row's cells as Markdown writes them (identifiers in backticks)."""
        return [f"`{c}`" if col.code and c else c for col, c in zip(self.columns, row, strict=True)]

    def markdown(self) -> str:
        """The table (GitHub / CommonMark tables), then each note as a paragraph; no
        trailing newline."""
        lines = ["|" + "|".join(_md_cell(c.name) for c in self.columns) + "|"]
        lines.append("|" + "".join("---:|" if c.align == "right" else "---|" for c in self.columns))
        lines += ["|" + "|".join(_md_cell(c) for c in self.cells(r)) + "|" for r in self.rows]
        return "\n\n".join(["\n".join(lines), *self.notes])

    def csv(self) -> str:
        """The column names, then the rows (notes and title left out)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow([c.name for c in self.columns])
        w.writerows(self.rows)
        return buf.getvalue()

    def html(self) -> str:
        """A ``<table>`` (the title as its caption), then each note as a paragraph."""

        def cell(tag: str, col: Column, text: str) -> str:
            style = ' style="text-align: right"' if col.align == "right" else ""
            body = html.escape(text, quote=False)
            return f"<{tag}{style}>{f'<code>{body}</code>' if col.code and text else body}</{tag}>"

        lines = ["<table>"]
        if self.title:
            lines.append(f"<caption>{html.escape(self.title, quote=False)}</caption>")
        lines += ["<thead>", "<tr>"]
        lines += [cell("th", Column(c.name, c.align), c.name) for c in self.columns]
        lines += ["</tr>", "</thead>", "<tbody>"]
        for row in self.rows:
            lines.append("<tr>")
            lines += [cell("td", col, c) for col, c in zip(self.columns, row, strict=True)]
            lines.append("</tr>")
        lines += ["</tbody>", "</table>"]
        lines += [f"<p>{html.escape(n, quote=False)}</p>" for n in self.notes]
        return "\n".join(lines) + "\n"
