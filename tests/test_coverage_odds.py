"""scripts/coverage_odds.py: the world it draws is the calibration's own model."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from daemon_support import script_module


@pytest.fixture(scope="module")
def coverage_odds() -> Iterator[ModuleType]:
    with script_module("coverage_odds") as module:
        yield module


def test_sigma_from_five_days_covers_95_percent_on_average_but_spreads_widely(
        coverage_odds: ModuleType) -> None:
    rng = np.random.default_rng(1)
    five = coverage_odds.coverage_draws(0.8, 5, 30, 22, 400, 1.0, rng)
    twenty = coverage_odds.coverage_draws(0.8, 20, 30, 22, 400, 1.0, rng)
    # Honest on average: a ±2σ band of a calibrated Gaussian covers 95.4 %.
    assert abs(float(np.mean(five)) - 95.45) < 1.5
    assert abs(float(np.mean(twenty)) - 95.45) < 1.5
    # From five day means the band lands outside 90–98 % far more often than from twenty.
    def outside(c: np.ndarray) -> float:
        return float(np.mean((c < 90.0) | (c > 98.0)))
    assert outside(five) > 0.5
    assert outside(five) > outside(twenty) + 0.15


def test_the_report_runs_are_read_from_what_results_py_wrote(
        coverage_odds: ModuleType, tmp_path: Path) -> None:
    assert coverage_odds.run_scenarios(tmp_path) == []
    run = tmp_path / "appliances"
    run.mkdir()
    run.joinpath("artifact.json").write_text(
        '{"validation": {"primary": "triv"}, '
        '"calibration": {"triv": {"day_var": 3.0, "within_var": 1.0}}}')
    run.joinpath("daily.csv").write_text(
        "day,model,n\n2016-01-17,triv,60\n2016-01-17,estimate,60\n"
        "2016-01-18,estimate,70\n2016-01-19,estimate,80\n")
    assert coverage_odds.run_scenarios(tmp_path) == [
        {"scenario": "appliances (`triv`)", "share": 0.75, "test_days": 3, "readings": 70}]
