#!/usr/bin/env python3
"""Unseen pairs: every other sensor pair of a shared dataset, trained once, scored after.

docs/results.md evaluates one twin per dataset, and every choice in the code was made while
looking at those runs. ``--house appliances`` (default): the Appliances house's eight indoor
rooms (its ninth sensor, T6 ``outside``, hangs outside the building) make 56 ordered pairs;
the 55 other than the report's ironing → parents are twins no choice in the code was made on,
scored for months. ``--house room-climate-a`` / ``room-climate-b``: the nodes of one FAU
office (4 and 3, at different heights and walls of the same room) make 12 and 6 ordered
pairs; those whose target is the report's target and whose reference is one of its
references are left out (10 and 4 remain), scored for the one to two weeks of scripted
episodes the data holds. The pairs are not independent of the report: the same building,
weather and weeks, and a pair and its mirror (kitchen → office, office → kitchen) share one
offset up to its sign, so they behave much alike: read the Appliances shares as coming from
about 28 room pairs of one house. Each pair is trained as the report's runs are (the quick
candidates by default, the first ``--train-days`` days from ``--start`` on, validation picks
the primary and calibrates σ on those days only) and scored on every later day.
``--every N`` keeps the desk sensor's readings only on every N-th day of
the training span: the same number of training days, spread over weeks (the days between are
not scored either); ``--score-from DAY`` scores no earlier day, so that twins trained on
different days are compared on the same test days.

Per pair: the report's figures (the estimate against TRIV and the floor, ±2σ coverage, mean
σ / RMSE, CRPS / RMSE) and the coverage in the first ``--early-days`` days after training
against the days after: whether σ holds up as the training days age. Then the share of pairs
that meets each figure, as scripts/origins.py does for the rolling origins (its summary and
oracle), and how often ``train`` calls one training day unlike the others
(analysis/commissioning/oddday.py) with the median coverage of those pairs and of the rest.
Prints the pairs' table, the summary and, last, one JSON line.

    .venv/bin/python scripts/pairs.py [--house appliances] [--start DAY] [--train-days 5]
                                      [--every 1] [--score-from DAY] [--early-days 14]
                                      [--models MODEL,...] [--jobs 2]
"""

from __future__ import annotations

import argparse
import datetime as dt
import itertools
import logging
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy does any work)
from origins import QUICK, oracle, score_span, summary
from pseudotwin.analysis.report.runs import RUNS, RunSpec
from pseudotwin.analysis.validation import MIN_DAYS
from pseudotwin.history.convert import load
from tables import print_markdown, print_table


@dataclass(frozen=True)
class House:
    """A shared dataset whose sensors pair up: the report's run on it (its pairs are not
    unseen), the temperature sensors that pair up, the default first candidate day."""

    report: RunSpec
    sensors: tuple[str, ...]
    start: dt.date

    def pairs(self) -> list[tuple[str, str]]:
        """Every ordered (reference, target) pair no choice in the code was made on."""
        seen = {(r, self.report.target) for r in self.report.references}
        return [p for p in itertools.permutations(self.sensors, 2) if p not in seen]


def _report(name: str) -> RunSpec:
    return next(r for r in RUNS if r.name == name)


ROOMS = ("kitchen", "living", "laundry", "office", "bathroom", "ironing", "teen", "parents")
HOUSES = {
    "appliances": House(_report("appliances"), tuple(f"{r}/temp" for r in ROOMS),
                        dt.date(2016, 2, 1)),
    "room-climate-a": House(_report("room-climate-a"), ("A1/temp", "A2/temp", "A3/temp",
                                                        "A4/temp"),
                            _report("room-climate-a").train_start),
    "room-climate-b": House(_report("room-climate-b"), ("B1/temp", "B2/temp", "B3/temp"),
                            _report("room-climate-b").train_start),
}
ALL_DAYS = 400  # the longest history, Appliances', is 138 days: every day after training


def pair_spec(house: str, reference: str, target: str, start: dt.date,
              train_days: int) -> RunSpec:
    """The twin that pseudo-measures ``target`` from ``reference`` alone."""
    report = HOUSES[house].report
    name = f"{reference.removesuffix('/temp')} → {target.removesuffix('/temp')}"
    return RunSpec(name, name, report.dataset, (reference,), target, "temperature",
                   report.timezone, start, f"an unseen pair of {report.title}",
                   train_days=train_days, long_term=report.long_term)


def spread(history: pd.DataFrame, spec: RunSpec, every: int) -> pd.DataFrame:
    """``history`` with the target's readings kept only on every ``every``-th day of the
    training span: the desk sensor visits on days weeks apart instead of five in a row."""
    target = history["sensor"] == spec.target
    days, _ = spec.twin.hours.day_and_hours(history.loc[target, "ts"])
    since = (days - np.datetime64(spec.train_start, "D")).astype(int)
    span = every * (spec.train_days - 1)
    drop = (since >= 0) & (since <= span) & (since % every != 0)
    return history.drop(history.index[target][drop])


def one(house: str, pair: tuple[str, str], start: dt.date, train_days: int, early: int,
        models: tuple[str, ...], every: int = 1,
        score_from: dt.date | None = None) -> dict[str, Any]:
    """The (reference, target) twin's row: the report's figures over every day after its
    training days (from ``score_from`` on), and ±2σ coverage in the ``early`` days after the
    last training day and in the days after them."""
    spec = pair_spec(house, *pair, start, train_days)
    history = load(spec.dataset)
    if every > 1:
        history = spread(history, spec, every)
    row = score_span(spec, start, ALL_DAYS, models, history=history, score_from=score_from)
    if "_age" in row:
        inside = row["_abs_err"] <= 2.0 * row["_std"]
        young = row["_age"] <= early
        row["cover2_early_pct"] = 100.0 * float(np.mean(inside[young])) if young.any() else math.nan
        row["cover2_late_pct"] = (100.0 * float(np.mean(inside[~young])) if (~young).any()
                                  else math.nan)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--house", choices=tuple(HOUSES), default="appliances",
                    help="the dataset whose sensors pair up (%(default)s)")
    ap.add_argument("--start", type=dt.date.fromisoformat, default=None,
                    help="first candidate training day (default: appliances 2016-02-01, "
                         "Room Climate the report's first day)")
    ap.add_argument("--train-days", type=int, default=5, help="training days (%(default)s)")
    ap.add_argument("--every", type=int, default=1,
                    help="the desk sensor's training days are every N-th day from --start "
                         "(%(default)s: consecutive days, as the report trains)")
    ap.add_argument("--score-from", type=dt.date.fromisoformat, default=None,
                    help="score no day before this one (default: every day after training)")
    ap.add_argument("--early-days", type=int, default=14,
                    help="coverage is also given for the days up to this many after the last "
                         "training day and for the days after (%(default)s)")
    ap.add_argument("--models", default=",".join(m for m in QUICK if m != "triv-cov"),
                    help="models trained (%(default)s)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (%(default)s)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    if a.train_days < MIN_DAYS or min(a.early_days, a.jobs, a.every) < 1:
        ap.error(f"--train-days must be at least {MIN_DAYS} (validation holds days out); "
                 "--early-days, --jobs and --every at least 1")
    models = tuple(m.strip() for m in a.models.split(",") if m.strip())
    if "triv" not in models:
        ap.error("--models must include triv (the floor and the ratios are against it)")
    house = HOUSES[a.house]
    start = a.start or house.start
    pairs = house.pairs()
    t0 = time.perf_counter()
    n = len(pairs)
    with ProcessPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(one, [a.house] * n, pairs, [start] * n, [a.train_days] * n,
                             [a.early_days] * n, [models] * n, [a.every] * n,
                             [a.score_from] * n))
    print_markdown([r for r in rows if "error" not in r], [
        ("pair", "run", None), ("trained to", "training_end", None), ("days", "test_days", 0),
        ("primary", "primary", None), ("estimate %", "estimate_pct", 2),
        ("triv %", "triv_pct", 2), ("floor %", "floor_pct", 2),
        ("est / floor", "ratio_floor", 3), ("±2σ cover %", "cover2_pct", 1),
        (f"cover, days 1–{a.early_days} %", "cover2_early_pct", 1),
        ("cover, later %", "cover2_late_pct", 1),
        ("nested cover % (training)", "nested_cover2_pct", 1),
        ("RMS σ / RMSE", "std_over_rmse", 2), ("CRPS / RMSE", "crps_over_rmse", 3),
        ("odd training day", "odd_day", None)])
    for r in rows:
        if "error" in r:
            print(f"{r['run']}: failed: {r['error']}")
    print()
    total = {**summary(rows, "all pairs"), **oracle(rows)}
    ok = [r for r in rows if "error" not in r]
    for key in ("cover2_early_pct", "cover2_late_pct", "std_over_rmse"):
        found = [r[key] for r in ok if math.isfinite(r[key])]
        # --score-from past the early days leaves none of them
        total[f"median_{key}"] = float(np.median(found)) if found else math.nan
    # train's advice of one training day unlike the others: how often it fires, and the
    # coverage of the pairs it fires on (the day kept, as training keeps it) and of the rest
    odd = [r for r in ok if r["odd_day"]]
    total["odd_day_pct"] = 100.0 * len(odd) / len(ok) if ok else math.nan
    for name, group in (("odd", odd), ("even", [r for r in ok if not r["odd_day"]])):
        found = [r["cover2_pct"] for r in group if math.isfinite(r["cover2_pct"])]
        total[f"median_cover2_{name}_pct"] = float(np.median(found)) if found else math.nan
    print(f"{len(rows)} pairs of {a.house} from {start}, {a.train_days} training days "
          f"({'consecutive' if a.every == 1 else f'every {a.every} days'}), "
          f"{'every later day' if a.score_from is None else f'days from {a.score_from} on'} "
          f"scored, {len(models)} "
          f"models ({', '.join(models)}), "
          f"{time.perf_counter() - t0:.0f} s")
    print_table("pairs", [total], [
        ("pairs", "origins", 0), ("failed", "failed", 0),
        ("est ≤ 1.02 × floor %", "floor_ok_pct", 0), ("est ≤ 0.9 × triv %", "triv_0_9_pct", 0),
        ("median est / floor", "median_ratio_floor", 3),
        ("worst est / floor", "worst_ratio_floor", 2),
        ("cover 90–98 %", "cover_in_pct", 0), ("cover < 90 %", "cover_low_pct", 0),
        ("cover > 98 %", "cover_high_pct", 0), ("median ±2σ cover %", "median_cover2_pct", 1),
        (f"median cover, days 1–{a.early_days} %", "median_cover2_early_pct", 1),
        ("median cover, later %", "median_cover2_late_pct", 1),
        ("median nested cover %", "median_nested_pct", 1),
        ("median RMS σ / RMSE", "median_std_over_rmse", 2),
        ("mean CRPS / RMSE", "mean_crps_over_rmse", 3),
        ("oracle σ factor", "oracle_factor", 2), ("oracle cover 90–98 %", "oracle_in_pct", 0),
        ("odd training day %", "odd_day_pct", 0),
        ("median cover, odd day %", "median_cover2_odd_pct", 1),
        ("median cover, no odd day %", "median_cover2_even_pct", 1)])


if __name__ == "__main__":
    main()
