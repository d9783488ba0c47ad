"""docs/results.md's Markdown tables (analysis/report/tables.py)."""

from __future__ import annotations

import re

from pseudotwin.analysis.report.tables import md_table


def _cells(line: str) -> list[str]:
    """A GFM table row's cells: split at the pipes not escaped with a backslash."""
    return [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]


def test_a_pair_criterion_with_a_pipe_in_its_key_stays_one_cell() -> None:
    table = md_table(["criterion", "days"], [["`disagreement:A1/temp|A3/temp`", "4"]])
    header, _, row = table.splitlines()
    assert len(_cells(row)) == len(_cells(header)) == 2
    assert _cells(row)[0].replace("\\|", "|") == "`disagreement:A1/temp|A3/temp`"
