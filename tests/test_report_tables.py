"""docs/results.md's Markdown tables (analysis/report/tables.py)."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pandas as pd

from pseudotwin.analysis.report.tables import calibration_by_day_md, md_table


def _cells(line: str) -> list[str]:
    """A GFM table row's cells: split at the pipes not escaped with a backslash."""
    return [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]


def test_a_pair_criterion_with_a_pipe_in_its_key_stays_one_cell() -> None:
    table = md_table(["criterion", "days"], [["`disagreement:A1/temp|A3/temp`", "4"]])
    header, _, row = table.splitlines()
    assert len(_cells(row)) == len(_cells(header)) == 2
    assert _cells(row)[0].replace("\\|", "|") == "`disagreement:A1/temp|A3/temp`"


def test_calibration_by_day_counts_each_models_days_by_their_coverage() -> None:
    """Per model, its days' ±2σ coverage: in, below and above 90–98 %, from daily.csv's
    columns; a raw reference (no σ) gets no row."""
    daily = pd.DataFrame({
        "day": ["2024-03-04", "2024-03-05", "2024-03-06"] * 2 + ["2024-03-04"],
        "model": ["estimate"] * 3 + ["triv"] * 3 + ["ref:r1"],
        "cover2_pct": [100.0, 95.0, 80.0, 90.0, 98.0, 97.0, np.nan],
        "crps": [0.1, 0.2, 0.6, 0.3, 0.3, 0.3, 0.5],
    })
    res = SimpleNamespace(daily=daily, ev=SimpleNamespace(artifact=SimpleNamespace(unit="°C")))
    lines = calibration_by_day_md(res).split("\n\n")[0].splitlines()  # type: ignore[arg-type]
    header, rows = _cells(lines[0]), {(c := _cells(line))[0]: c for line in lines[2:]}
    assert set(rows) == {"estimate", "triv"}
    est = dict(zip(header, rows["estimate"], strict=True))
    assert est["days"] == "3" and est["median daily ±2σ cover %"] == "95.0"
    assert est["lowest %"] == "80.0"
    assert (est["days < 90 %"], est["days 90–98 %"], est["days > 98 %"]) == ("1", "1", "1")
    assert est["mean daily CRPS [°C]"] == "0.300"
    triv = dict(zip(header, rows["triv"], strict=True))
    assert (triv["days < 90 %"], triv["days 90–98 %"], triv["days > 98 %"]) == ("0", "3", "0")
