#!/usr/bin/env python3
"""The odds of the ±2σ band: how often a σ calibrated on a few training days covers 90–98 %
of a test span, when the errors follow exactly the model the calibration assumes.

docs/results.md asks the published estimate's ±2σ band to cover 90–98 % of the true readings
on every run. The twin sizes σ from leave-one-day-out errors of five training days
(``pseudotwin.live.calibration``): the day-level part of the error is then estimated from
five day means, four degrees of freedom. This script measures what that allows at best. Per
scenario it draws, ``--reps`` times, a world that is the calibration's own model and
stationary:

- each day's reference–target offset o_d ~ N(0, s_b²), the same on training and test days;
- within the day an AR(1) error w of variance s_w² that decorrelates in ``--tau-h`` hours, at
  the scenario's readings per operating day (08:00–19:00); its day mean w̄_d adds to the
  day's level, as it does in the calibration's split;
- the estimate is TRIV with a flat profile: the reference plus the mean training offset
  x_d = o_d + w̄_d, so a held-out training day's error is mean(x of the other days) − o_d − w
  and a test day's is mean(x of all training days) − o_test − w;

fits :class:`SigmaCalibration` to the training days' held-out errors, with var(x, ddof=1) as
its floor (validation's ``offset_variance``), and scores the pooled ±2σ coverage of σ on the
test days. It prints the share of draws whose coverage lands in 90–98 %, below, above, and
the median and mean coverage. There is nothing the twin could learn better here: real data
add drift, odd days and a model that is not the truth.

Scenarios: a grid of the world's day share s_b² / (s_b² + s_w²) × test days, and, when
``scripts/results.py`` has written ``out/results/<run>/``, the report's runs. A run's day
share is read back from its primary's calibration: day_var against the within-day variance
with the slope term at the test days' mean |ṙ| (σ² = C·(day_var + a + k·|ṙ|)), less what
the within-day day means and the leave-one-day-out centring put into day_var. The last rows
give the chance that all the runs land in 90–98 % at once (the product of theirs).

Prints the table and, last, one JSON line.

    .venv/bin/python scripts/coverage_odds.py [--reps 1000] [--train-days 5,10,20]
                                              [--results out/results] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pseudotwin.analysis.report.runs import RUN_NAMES
from pseudotwin.analysis.report.verdicts import COVER2_RANGE
from pseudotwin.analysis.validation import MIN_DAYS
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.live.calibration import Z2, SigmaCalibration
from tables import print_table

REPO = Path(__file__).resolve().parents[1]
HOURS = OperatingHours()  # the simulated days' operating hours (08:00–19:00)
GRID_SHARES = (0.1, 0.5, 0.9)
GRID_TEST_DAYS = (10, 40, 130)
GRID_READINGS = 66  # readings per operating day of the grid (10-minute data)
RUN_TRAIN_DAYS = 5  # the report's runs train on five days


def _phi(readings: int, tau_h: float) -> float:
    """Lag-one correlation of the within-day error at ``readings`` per operating day."""
    return math.exp(-(HOURS.day_end - HOURS.day_start) / readings / tau_h)


def within_day(rng: np.random.Generator, days: int, readings: int, tau_h: float) -> np.ndarray:
    """AR(1) errors of unit variance: [days, readings], decorrelating in ``tau_h`` hours."""
    phi = _phi(readings, tau_h)
    e = rng.standard_normal((days, readings))
    w = np.empty_like(e)
    w[:, 0] = e[:, 0]
    scale = math.sqrt(1.0 - phi * phi)
    for j in range(1, readings):
        w[:, j] = phi * w[:, j - 1] + scale * e[:, j]
    return w


def day_mean_variance(readings: int, tau_h: float) -> float:
    """Variance of the day mean of :func:`within_day`'s unit-variance errors."""
    lag = np.arange(1, readings)
    phi = _phi(readings, tau_h)
    return float((readings + 2.0 * np.sum((readings - lag) * phi**lag)) / readings**2)


def training_calibration(rng: np.random.Generator, share: float, train_days: int,
                         readings: int, tau_h: float) -> tuple[SigmaCalibration, np.ndarray]:
    """One draw of the training days: σ calibrated on their held-out errors, and each day's
    mean offset x: [train_days]. share: the world's day share s_b² / (s_b² + s_w²)."""
    s_b, s_w = math.sqrt(share), math.sqrt(1.0 - share)
    hours = np.linspace(HOURS.day_start, HOURS.day_end, readings, endpoint=False)
    o = s_b * rng.standard_normal(train_days)
    w = s_w * within_day(rng, train_days, readings, tau_h)
    x = o + w.mean(axis=1)  # each training day's mean offset, as validation sees it
    others = (x.sum() - x) / (train_days - 1)
    held = (others - o)[:, None] - w
    cal = SigmaCalibration.fit(np.repeat(np.arange(train_days), readings),
                               np.tile(hours, train_days), held.ravel(), np.zeros(held.size),
                               float(np.var(x, ddof=1)))
    return cal, x


def coverage_draws(share: float, train_days: int, test_days: int, readings: int,
                   reps: int, tau_h: float, rng: np.random.Generator) -> np.ndarray:
    """±2σ coverage [%] of the test days in each of ``reps`` draws: [reps]. share: the
    world's day share s_b² / (s_b² + s_w²)."""
    s_b, s_w = math.sqrt(share), math.sqrt(1.0 - share)
    hours = np.linspace(HOURS.day_start, HOURS.day_end, readings, endpoint=False)
    out = np.empty(reps)
    for r in range(reps):
        cal, x = training_calibration(rng, share, train_days, readings, tau_h)
        sigma = np.array([cal.sigma(h, 0.0) for h in hours])
        o_test = s_b * rng.standard_normal(test_days)
        err = (x.mean() - o_test)[:, None] - s_w * within_day(rng, test_days, readings, tau_h)
        out[r] = 100.0 * float(np.mean(np.abs(err) <= Z2 * sigma[None, :]))
    return out


def world_share(day_var: float, within_var: float, readings: int, tau_h: float,
                train_days: int = RUN_TRAIN_DAYS) -> float:
    """The world's day share behind a calibration's day_var and within-day variance (its
    ``within_var`` plus the slope term): day_var ≈ n/(n−1)·(s_b² + v·s_w²) (held-out day
    means centred on the other n − 1 days, the within-day error's day mean of variance v·s_w²
    included) and the within-day variance ≈ (1 − v)·s_w²."""
    v = day_mean_variance(readings, tau_h)
    s_w2 = within_var / (1.0 - v)
    s_b2 = max(day_var * (train_days - 1) / train_days - v * s_w2, 0.0)
    return s_b2 / (s_b2 + s_w2)


def run_scenarios(results: Path, tau_h: float = 1.0) -> list[dict[str, Any]]:
    """The report's runs as scenarios, from what scripts/results.py wrote: the world's day
    share behind the primary's calibration, the test days, the median readings per day."""
    found = []
    for run in RUN_NAMES:
        folder = results / run
        files = [folder / f for f in ("artifact.json", "daily.csv", "estimates.csv")]
        if not all(f.is_file() for f in files):
            continue
        art = json.loads(files[0].read_text())
        primary = art["validation"]["primary"]
        cal = art["calibration"][primary]
        est = pd.read_csv(files[1])
        est = est[est["model"] == "estimate"]
        rows = pd.read_csv(files[2], usecols=["model", "slope"])
        slope = float(rows.loc[rows["model"] == "estimate", "slope"].abs().mean())
        readings = int(est["n"].median())
        within = cal["within_var"] + cal["slope_coef"] * slope
        found.append({
            "scenario": f"{run} (`{primary}`)",
            "share": world_share(cal["day_var"], within, readings, tau_h),
            "test_days": len(est),
            "readings": readings,
            "created": str(art.get("created", "")),
        })
    return found


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=1000, help="draws per scenario (default 1000)")
    ap.add_argument("--train-days", default="5,10,20",
                    help="training days to compare, comma-separated (default 5,10,20)")
    ap.add_argument("--tau-h", type=float, default=1.0,
                    help="decorrelation time of the within-day error [h] (default 1)")
    ap.add_argument("--results", type=Path, default=REPO / "out" / "results",
                    help="where scripts/results.py wrote its runs (default out/results)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    train_days = [int(x) for x in args.train_days.split(",")]
    if args.reps < 1 or any(n < MIN_DAYS for n in train_days):
        ap.error(f"--reps must be ≥ 1 and every --train-days ≥ {MIN_DAYS} (validation's least)")
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    scenarios = [{"scenario": f"grid: share {s:.1f}, {d} test days", "share": s,
                  "test_days": d, "readings": GRID_READINGS}
                 for s in GRID_SHARES for d in GRID_TEST_DAYS]
    runs = run_scenarios(args.results, args.tau_h)
    if runs:
        where = (args.results.relative_to(REPO) if args.results.is_relative_to(REPO)
                 else args.results)
        print(f"runs: the primaries' calibrations in {where} (artifacts written "
              f"{', '.join(sorted({r['created'][:10] for r in runs}))})")
    else:
        print(f"(no runs under {args.results}: `.venv/bin/python scripts/results.py` writes "
              "them; the grid alone follows)")
    rows: list[dict[str, Any]] = []
    run_rows: list[dict[str, Any]] = []
    for sc, is_run in [(sc, False) for sc in scenarios] + [(sc, True) for sc in runs]:
        for n in train_days:
            cover = coverage_draws(sc["share"], n, sc["test_days"], sc["readings"],
                                   args.reps, args.tau_h, rng)
            row = {**{k: v for k, v in sc.items() if k != "created"}, "train_days": n,
                   "in_band_pct": 100.0 * float(np.mean((cover >= COVER2_RANGE[0])
                                                         & (cover <= COVER2_RANGE[1]))),
                   "below_pct": 100.0 * float(np.mean(cover < COVER2_RANGE[0])),
                   "above_pct": 100.0 * float(np.mean(cover > COVER2_RANGE[1])),
                   "median_cover_pct": float(np.median(cover)),
                   "mean_cover_pct": float(np.mean(cover))}
            rows.append(row)
            if is_run:
                run_rows.append(row)
    if runs:
        for n in train_days:
            odds = math.prod(r["in_band_pct"] / 100.0 for r in run_rows if r["train_days"] == n)
            rows.append({"scenario": f"all {len(runs)} runs in band at once", "share": math.nan,
                         "test_days": None, "readings": None, "train_days": n,
                         "in_band_pct": 100.0 * odds, "below_pct": math.nan,
                         "above_pct": math.nan, "median_cover_pct": math.nan,
                         "mean_cover_pct": math.nan})
    print(f"{args.reps} draws per scenario, within-day errors decorrelating in {args.tau_h} h, "
          f"{time.perf_counter() - t0:.0f} s")
    print_table("coverage_odds", rows, [
        ("scenario", "scenario", None), ("day share", "share", 2),
        ("test days", "test_days", None), ("readings / day", "readings", None),
        ("training days", "train_days", None), ("in 90–98 %", "in_band_pct", 1),
        ("< 90 %", "below_pct", 1), ("> 98 %", "above_pct", 1),
        ("median ±2σ cover %", "median_cover_pct", 1), ("mean ±2σ cover %", "mean_cover_pct", 1),
    ])


if __name__ == "__main__":
    main()
