"""A :class:`bench.tables.Table` on the console: rich's table (title above, columns
aligned and, for labels, unwrapped), then its notes."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table as RichTable

from ..tables import Table

__all__ = ["print_table", "rich_table"]


def rich_table(t: Table) -> RichTable:
    """The table for rich (without its notes)."""
    table = RichTable(title=t.title)
    for col in t.columns:
        table.add_column(col.name, justify=col.align, no_wrap=col.no_wrap)
    for row in t.rows:
        table.add_row(*row)
    return table


def print_table(t: Table, console: Console) -> None:
    """The table, then each of its notes as a line of its own."""
    console.print(rich_table(t))
    for note in t.notes:
        console.print(note)
