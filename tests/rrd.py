"""Reading rerun recordings back in tests, with rerun's own reader."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from rerun.chunk import RrdReader


class Recording:
    """A recording's chunks by entity path: rows (timed) and static rows."""

    def __init__(self, path: Path) -> None:
        reader = RrdReader(path)
        self.blueprints = reader.blueprints()
        self.timed: dict[str, list] = defaultdict(list)
        self.static: dict[str, list] = defaultdict(list)
        for chunk in reader.stream():
            target = self.static if chunk.is_static else self.timed
            target[chunk.entity_path].append(chunk.to_record_batch())

    @property
    def entities(self) -> set[str]:
        return set(self.timed) | set(self.static)

    def rows(self, entity: str, static: bool = False) -> int:
        return sum(b.num_rows for b in (self.static if static else self.timed)[entity])

    def values(self, entity: str, column: str, static: bool = False, index: str | None = None):
        """The column's values row by row (Python lists), sorted by ``index`` if given."""
        rows = []
        for b in (self.static if static else self.timed)[entity]:
            if column not in b.schema.names:
                continue
            keys = b.column(index).to_pylist() if index else [0] * b.num_rows
            rows += list(zip(keys, b.column(column).to_pylist(), strict=True))
        if index:
            rows.sort(key=lambda kv: kv[0])
        return [v for _, v in rows]
