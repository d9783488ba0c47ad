"""scripts/coverage_odds.py: the world it draws is the calibration's own model."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from scripts_support import script_module


@pytest.fixture(scope="module")
def coverage_odds() -> Iterator[ModuleType]:
    with script_module("coverage_odds") as module:
        yield module


def test_the_within_day_error_has_unit_variance_and_decorrelates_in_tau(
        coverage_odds: ModuleType) -> None:
    w = coverage_odds.within_day(np.random.default_rng(2), 4000, 44, 1.0)
    assert abs(float(np.var(w)) - 1.0) < 0.03
    lag1 = float(np.mean(w[:, 1:] * w[:, :-1]))
    assert abs(lag1 - np.exp(-0.25)) < 0.02  # 44 readings in 11 h: 15 min apart, τ = 1 h
    assert abs(float(np.var(w.mean(axis=1))) / coverage_odds.day_mean_variance(44, 1.0)
               - 1.0) < 0.08


def test_the_day_share_read_back_from_calibrations_is_the_worlds(
        coverage_odds: ModuleType) -> None:
    """What run_scenarios does to a run's calibration recovers the share of the world that
    calibration was fitted in."""
    rng = np.random.default_rng(3)
    cals = [coverage_odds.training_calibration(rng, 0.6, 5, 30, 1.0)[0] for _ in range(600)]
    day_var = float(np.mean([c.day_var for c in cals]))
    within = float(np.mean([c.within_var for c in cals]))
    assert abs(coverage_odds.world_share(day_var, within, 30, 1.0) - 0.6) < 0.04


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
    """A run folder without all three files is left out; the slope term of σ counts as
    within-day variance, so a run whose σ grows with |ṙ| has a smaller day share."""
    assert coverage_odds.run_scenarios(tmp_path) == []
    run = tmp_path / "appliances"
    run.mkdir()
    calibration = {"day_var": 3.0, "within_var": 1.0, "slope_coef": 0.0}
    artifact = {"created": "2026-11-27T07:00:00+00:00", "validation": {"primary": "triv"},
                "calibration": {"triv": calibration}}
    run.joinpath("artifact.json").write_text(json.dumps(artifact))
    run.joinpath("daily.csv").write_text(
        "day,model,n\n2016-01-17,triv,60\n2016-01-17,estimate,60\n"
        "2016-01-18,estimate,70\n2016-01-19,estimate,80\n")
    assert coverage_odds.run_scenarios(tmp_path) == []
    run.joinpath("estimates.csv").write_text(
        "ts,model,value,std,truth,quality,slope\n"
        "2016-01-17T08:00:00+00:00,estimate,20,1,20,ok,-2\n"
        "2016-01-17T08:10:00+00:00,estimate,20,1,20,ok,2\n"
        "2016-01-17T08:10:00+00:00,triv,20,1,20,ok,50\n")
    (flat,) = coverage_odds.run_scenarios(tmp_path)
    assert (flat["scenario"], flat["test_days"], flat["readings"]) == (
        "appliances (`triv`)", 3, 70)
    calibration["slope_coef"] = 0.5  # k·mean|ṙ| = 1: the within-day variance doubles
    run.joinpath("artifact.json").write_text(json.dumps(artifact))
    (sloped,) = coverage_odds.run_scenarios(tmp_path)
    assert sloped["share"] < flat["share"]
    assert sloped["share"] == pytest.approx(coverage_odds.world_share(3.0, 2.0, 70, 1.0))
