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
- within the day an AR(1) error of variance s_w² that decorrelates in ``--tau-h`` hours, at
  the scenario's readings per operating day (08:00–19:00);
- the estimate is TRIV with a flat profile: the reference plus the mean training offset, so
  a held-out training day's error is mean(o of the other days) − o_d + w and a test day's is
  mean(o of all training days) − o_test + w;

fits :class:`SigmaCalibration` to the training days' held-out errors, with the spread of the
training offsets as its floor (as validation does), and scores the ±2σ coverage of σ on the
test days. It prints the share of draws whose coverage lands in 90–98 %, below, above, and
the median coverage. There is nothing the twin could learn better here: any real data adds
drift, odd days and a model that is not the truth.

Scenarios: a grid of the day-level share s_b² / (s_b² + s_w²) × test days, and, when
``scripts/results.py`` has written ``out/results/<run>/``, the report's runs with their own
share (from the primary's calibration), test days and readings per day. The last column,
over the runs, is the chance that all of them land in 90–98 % at once.

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
from pseudotwin.live.calibration import Z2, SigmaCalibration
from tables import print_table

FIRST_H, LAST_H = 8.0, 19.0  # operating hours of the simulated days [h]
COVER = (90.0, 98.0)  # the band docs/results.md holds the ±2σ coverage to [%]
GRID_SHARES = (0.1, 0.5, 0.9)
GRID_TEST_DAYS = (10, 40, 130)
GRID_READINGS = 66  # readings per operating day of the grid (10-minute data)


def _within(rng: np.random.Generator, days: int, readings: int, tau_h: float) -> np.ndarray:
    """AR(1) errors of unit variance: [days, readings], decorrelating in ``tau_h`` hours."""
    phi = math.exp(-(LAST_H - FIRST_H) / readings / tau_h)
    e = rng.standard_normal((days, readings))
    w = np.empty_like(e)
    w[:, 0] = e[:, 0]
    scale = math.sqrt(1.0 - phi * phi)
    for j in range(1, readings):
        w[:, j] = phi * w[:, j - 1] + scale * e[:, j]
    return w


def coverage_draws(share: float, train_days: int, test_days: int, readings: int,
                   reps: int, tau_h: float, rng: np.random.Generator) -> np.ndarray:
    """±2σ coverage [%] of the test days in each of ``reps`` draws: [reps]."""
    s_b, s_w = math.sqrt(share), math.sqrt(1.0 - share)
    hours = np.linspace(FIRST_H, LAST_H, readings, endpoint=False)
    train_label = np.repeat(np.arange(train_days), readings)
    train_hours = np.tile(hours, train_days)
    out = np.empty(reps)
    for r in range(reps):
        o = s_b * rng.standard_normal(train_days)
        others = (o.sum() - o) / (train_days - 1)
        held = (others - o)[:, None] + s_w * _within(rng, train_days, readings, tau_h)
        cal = SigmaCalibration.fit(train_label, train_hours, held.ravel(),
                                   np.zeros(held.size), float(np.var(o, ddof=1)))
        sigma = np.array([cal.sigma(h, 0.0) for h in hours])
        o_test = s_b * rng.standard_normal(test_days)
        err = (o.mean() - o_test)[:, None] + s_w * _within(rng, test_days, readings, tau_h)
        out[r] = 100.0 * float(np.mean(np.abs(err) <= Z2 * sigma[None, :]))
    return out


def run_scenarios(results: Path) -> list[dict[str, Any]]:
    """The report's runs as scenarios, from what scripts/results.py wrote: the primary's
    day-level share of σ², the test days, the median readings per test day."""
    found = []
    for run in RUN_NAMES:
        folder = results / run
        if not (folder / "artifact.json").is_file() or not (folder / "daily.csv").is_file():
            continue
        art = json.loads((folder / "artifact.json").read_text())
        cal = art["calibration"][art["validation"]["primary"]]
        daily = pd.read_csv(folder / "daily.csv")
        est = daily[daily["model"] == "estimate"]
        found.append({
            "scenario": f"{run} (`{art['validation']['primary']}`)",
            "share": cal["day_var"] / (cal["day_var"] + cal["within_var"]),
            "test_days": len(est),
            "readings": int(est["n"].median()),
        })
    return found


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=1000, help="draws per scenario (default 1000)")
    ap.add_argument("--train-days", default="5,10,20",
                    help="training days to compare, comma-separated (default 5,10,20)")
    ap.add_argument("--tau-h", type=float, default=1.0,
                    help="decorrelation time of the within-day error [h] (default 1)")
    ap.add_argument("--results", type=Path, default=Path("out/results"),
                    help="where scripts/results.py wrote its runs (default out/results)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    train_days = [int(x) for x in args.train_days.split(",")]
    if args.reps < 1 or any(n < 2 for n in train_days):
        ap.error("--reps must be ≥ 1 and every --train-days ≥ 2")
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    scenarios = [{"scenario": f"grid: share {s:.1f}, {d} test days", "share": s,
                  "test_days": d, "readings": GRID_READINGS}
                 for s in GRID_SHARES for d in GRID_TEST_DAYS]
    runs = run_scenarios(args.results)
    if not runs:
        print(f"(no runs under {args.results}: `.venv/bin/python scripts/results.py` writes "
              "them; the grid alone follows)")
    rows: list[dict[str, Any]] = []
    run_rows: list[dict[str, Any]] = []
    for sc, is_run in [(sc, False) for sc in scenarios] + [(sc, True) for sc in runs]:
        for n in train_days:
            cover = coverage_draws(sc["share"], n, sc["test_days"], sc["readings"],
                                   args.reps, args.tau_h, rng)
            row = {**sc, "train_days": n,
                   "in_band_pct": 100.0 * float(np.mean((cover >= COVER[0])
                                                         & (cover <= COVER[1]))),
                   "below_pct": 100.0 * float(np.mean(cover < COVER[0])),
                   "above_pct": 100.0 * float(np.mean(cover > COVER[1])),
                   "median_cover_pct": float(np.median(cover)),
                   "mean_cover_pct": float(np.mean(cover))}
            rows.append(row)
            if is_run:
                run_rows.append(row)
    if runs:
        for n in train_days:
            odds = math.prod(r["in_band_pct"] / 100.0 for r in run_rows if r["train_days"] == n)
            rows.append({"scenario": f"all {len(runs)} runs in band at once", "share": math.nan,
                         "test_days": "—", "readings": "—", "train_days": n,
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
