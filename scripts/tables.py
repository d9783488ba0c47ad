"""The measurement scripts' output: a Markdown table of their rows, then the rows as one
JSON line (non-finite numbers as null), as every script under scripts/ ends."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

#: (heading, row key, decimals of a number column; None: a left-aligned text column)
Column = tuple[str, str, int | None]


def cell(x: Any, digits: int = 2) -> str:
    """A float with ``digits`` decimals; "—" for nothing (None, "", NaN, ±inf)."""
    if x is None or x == "" or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    return f"{x:.{digits}f}" if isinstance(x, float) else str(x)


def print_markdown(rows: Sequence[Mapping[str, Any]], columns: Sequence[Column]) -> None:
    """The rows as a Markdown table."""
    print("| " + " | ".join(h for h, _, _ in columns) + " |")
    print("|" + "|".join("---" if d is None else "---:" for _, _, d in columns) + "|")
    for r in rows:
        print("| " + " | ".join(cell(r[k], 2 if d is None else d) for _, k, d in columns)
              + " |")


def print_table(key: str, rows: Sequence[Mapping[str, Any]], columns: Sequence[Column]) -> None:
    """The table, then ``{key: rows}`` as the last line."""
    print_markdown(rows, columns)
    print(json.dumps({key: [{k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                             for k, v in r.items()} for r in rows]}))
