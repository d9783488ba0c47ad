#!/usr/bin/env python3
"""Rolling origins: the shared runs trained from many start days, not only the report's one.

docs/results.md trains each run once, on the five days from a fixed start, and scores the
days after. One origin says little about a method whose σ and choice of primary come from
five days: this script moves the start through each dataset (every ``--step-days``), trains
as results.py does (validation picks the primary and calibrates σ on the five training days
only) and scores the next ``--test-days`` days. Per origin: the published estimate's mean
daily NRMSE against TRIV's and the floor (the lower of TRIV's and the best raw reference's),
the ±2σ coverage of the estimate on the test days next to the nested coverage validation
measured on the training days, RMS σ / RMSE and CRPS / RMSE (the mean CRPS of the estimate,
a proper score of estimate and σ together, over its RMSE: for the same estimates, lower means
a σ of the better size). Then per run and over all origins: how
often each figure of docs/results.md holds.

The default models are the quick candidates (no GP: a Corr-GP fit per origin and fold would
take hours) and VARMA, whose order validation chooses (``--varma-p`` pins it instead);
``--models`` adds others. The summary also gives an *oracle*: per run, the one factor on σ
that the test days themselves call right (pooled ±2σ coverage over all the run's origins
95.45 %), and the share of origins that would land in 90–98 % with it: what σ of the right
size for a data set as a whole still cannot do, because test spans differ from each other.
Prints the origins' table, the summary table and, last, one JSON line.

    .venv/bin/python scripts/origins.py [--runs NAME,...] [--step-days 4] [--test-days 14]
                                        [--models MODEL,...] [--jobs 2] [--varma-p P]
"""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import pandas as pd

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy does any work)
from pseudotwin.analysis.commissioning.oddday import odd_training_day
from pseudotwin.analysis.evaluate import ESTIMATE, evaluate
from pseudotwin.analysis.report.runs import RUNS, RunResult, RunSpec
from pseudotwin.analysis.report.verdicts import COVER2_RANGE, figures
from pseudotwin.errors import DataError
from pseudotwin.history.convert import load
from tables import print_markdown, print_table

QUICK = ("ref", "triv", "triv-shrunk", "triv-smooth", "triv-week", "triv-cov", "blend",
         "varma")
TRIV_RATIO = 0.9  # Trust II: the estimate ≤ this × TRIV's mean daily NRMSE
SLACK_DAYS = 16  # calendar days beyond the test days: training skips days a sensor missed


def _origins(spec: RunSpec, history: pd.DataFrame, step: int, test_days: int) -> list[dt.date]:
    """Start days from the target's first day on, while a full training and test span fits."""
    days, _ = spec.twin.hours.day_and_hours(history.loc[history["sensor"] == spec.target, "ts"])
    have = sorted(set(pd.to_datetime(days).date))
    out, start = [], have[0]
    while start + dt.timedelta(days=spec.train_days + test_days // 2) <= have[-1]:
        out.append(start)
        start += dt.timedelta(days=step)
    return out


def one(name: str, start: dt.date, test_days: int, models: tuple[str, ...],
        varma: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train the report's run ``name`` from ``start``, score the next ``test_days`` days after
    the training days. varma: VARMA's settings (None: its defaults, the order validation
    chooses)."""
    return score_span(next(r for r in RUNS if r.name == name), start, test_days, models, varma)


def score_span(spec: RunSpec, start: dt.date, test_days: int, models: tuple[str, ...],
               varma: dict[str, Any] | None = None, history: pd.DataFrame | None = None,
               score_from: dt.date | None = None) -> dict[str, Any]:
    """``spec``'s twin trained from ``start`` and scored on the ``test_days`` calendar days
    after its training days, measured by the report's own figures (one row). history: the
    canonical readings (default: ``spec``'s whole dataset); score_from: score no day before
    it (twins trained differently, scored on the same days)."""
    t0 = time.perf_counter()
    history = load(spec.dataset) if history is None else history
    row: dict[str, Any] = {"run": spec.name, "start": str(start)}
    cut = pd.Timestamp(start + dt.timedelta(days=spec.train_days + test_days + SLACK_DAYS),
                       tz="UTC")
    try:
        ev = evaluate(history[history["ts"] < cut], spec.twin, start, spec.train_days, models,
                      options={"varma": varma} if varma else None)
    except DataError as exc:
        return {**row, "error": str(exc)}
    end = dt.date.fromisoformat(ev.artifact.training["end"])
    scored = [d for d in ev.daily["day"].unique()
              if (dt.date.fromisoformat(d) - end).days <= test_days
              and (score_from is None or dt.date.fromisoformat(d) >= score_from)]
    days, _ = spec.twin.hours.day_and_hours(ev.estimates["ts"])
    in_span = pd.to_datetime(days).strftime("%Y-%m-%d").isin(scored)
    # the report's own figures (floor, coverage, their thresholds) over the scored span
    f = figures(RunResult(spec, ev, ev.daily[ev.daily["day"].isin(scored)], ev.monthly,
                          ev.estimates[in_span], ev.seconds))
    v = ev.artifact.validation
    est = ev.estimates[in_span & (ev.estimates["model"] == ESTIMATE)]
    est = est[np.isfinite(est["std"]) & (est["std"] > 0)]
    return {
        **row, "training_days": ",".join(ev.artifact.training["days"]),
        "training_end": str(end), "test_days": f.days, "primary": f.primary,
        "estimate_pct": f.estimate, "triv_pct": f.triv, "floor_pct": f.floor,
        "ratio_floor": f.ratio, "ratio_triv": f.estimate / f.triv, "floor_met": f.floor_met,
        "cover2_pct": f.cover2, "cover_met": f.cover_met,
        "nested_cover2_pct": float(v["scores"][f.primary]["cover2_pct"]),
        "std_over_rmse": f.rms_std / f.rmse if f.rmse > 0 else math.nan,
        "crps_over_rmse": f.crps / f.rmse if f.rmse > 0 else math.nan,
        # VARMA (when trained): its ratio to TRIV on the test span, whether it is published
        # live, the figure's verdict, and the order it ran with
        "varma_ratio": f.varma_ratio, "varma_live": "no" if f.varma_withheld else "yes",
        "varma_met": f.varma_met if math.isfinite(f.varma) else math.nan,
        "varma_p": getattr(ev.artifact.models.get("varma"), "p", math.nan),
        # the training day train calls unlike the others (commissioning/oddday.py), or ""
        "odd_day": str(odd.day) if (odd := odd_training_day(v)) else "",
        "seconds": round(time.perf_counter() - t0, 1),
        # for the oracle (dropped before printing): |error| and σ of each scored estimate,
        # and its day's age: calendar days after the last training day
        "_abs_err": np.abs(est["value"] - est["truth"]).to_numpy(), "_std": est["std"].to_numpy(),
        "_age": _age(spec, est["ts"], end),
    }


def _age(spec: RunSpec, ts: pd.Series, end: dt.date) -> np.ndarray:
    """Calendar days [n] from the last training day ``end`` to each instant's local day."""
    days, _ = spec.twin.hours.day_and_hours(ts)
    return (days - np.datetime64(end, "D")).astype(int)


def oracle(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The coverage an oracle would reach, for one run's origins: σ × m with m set from the
    test days themselves, the one factor that makes the ±2σ coverage pooled over all the run's
    origins 95.45 %. Returns m and the share of origins whose own coverage with it lies in
    90–98 %: what no σ of the right size for the data set *as a whole* can do better than,
    because the test spans themselves differ."""
    ok = [r for r in rows if "_abs_err" in r and len(r["_abs_err"])]
    if not ok:
        return {"oracle_factor": math.nan, "oracle_in_pct": math.nan}
    err = np.concatenate([r["_abs_err"] for r in ok])
    std = np.concatenate([r["_std"] for r in ok])
    # the pooled coverage of σ × m rises with m: the m at which it crosses 95.45 %
    m = float(np.quantile(err / (2.0 * std), 0.9545))
    lo, hi = COVER2_RANGE
    inside = [lo <= 100.0 * float(np.mean(r["_abs_err"] <= 2.0 * m * r["_std"])) <= hi
              for r in ok]
    return {"oracle_factor": m, "oracle_in_pct": 100.0 * float(np.mean(inside))}


def summary(rows: list[dict[str, Any]], name: str) -> dict[str, Any]:
    ok = [r for r in rows if "error" not in r]
    cov = np.array([r["cover2_pct"] for r in ok])

    def share(mask: Any) -> float:
        return 100.0 * float(np.mean(mask)) if ok else math.nan

    return {
        "run": name, "origins": len(ok), "failed": len(rows) - len(ok),
        "floor_ok_pct": share([r["floor_met"] for r in ok]),
        "triv_0_9_pct": share([r["ratio_triv"] <= TRIV_RATIO for r in ok]),
        "median_ratio_floor": float(np.median([r["ratio_floor"] for r in ok])) if ok else math.nan,
        "worst_ratio_floor": max((r["ratio_floor"] for r in ok), default=math.nan),
        "cover_in_pct": share([r["cover_met"] for r in ok]),
        "cover_low_pct": share(cov < COVER2_RANGE[0]),
        "cover_high_pct": share(cov > COVER2_RANGE[1]),
        "median_cover2_pct": float(np.median(cov)) if ok else math.nan,
        "median_nested_pct": (float(np.median([r["nested_cover2_pct"] for r in ok]))
                              if ok else math.nan),
        "mean_crps_over_rmse": (float(np.nanmean([r["crps_over_rmse"] for r in ok]))
                                if ok else math.nan),
        **_varma_summary(ok),
    }


def _varma_summary(ok: list[dict[str, Any]]) -> dict[str, Any]:
    """VARMA's figure over the origins that trained it: the share that meets it (≤ 1.5×
    TRIV, or not published live), the share published live, the median ratio to TRIV."""
    rows = [r for r in ok if isinstance(r.get("varma_met"), bool)]
    if not rows:
        return {"varma_met_pct": math.nan, "varma_live_pct": math.nan,
                "median_varma_ratio": math.nan}
    return {"varma_met_pct": 100.0 * float(np.mean([r["varma_met"] for r in rows])),
            "varma_live_pct": 100.0 * float(np.mean([r["varma_live"] == "yes" for r in rows])),
            "median_varma_ratio": float(np.median([r["varma_ratio"] for r in rows]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    names = [r.name for r in RUNS]
    ap.add_argument("--runs", default=",".join(names), help="comma-separated runs (default: all)")
    ap.add_argument("--step-days", type=int, default=4, help="days between origins (%(default)s)")
    ap.add_argument("--test-days", type=int, default=14,
                    help="calendar days scored after the training days (%(default)s)")
    ap.add_argument("--models", default=",".join(QUICK), help="models trained (%(default)s)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (%(default)s)")
    ap.add_argument("--varma-p", type=int, default=None,
                    help="pin VARMA's order to VAR(p) by least squares (default: the order "
                         "validation chooses; 4 reproduces the fixed order before it did)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    wanted = [r.strip() for r in a.runs.split(",") if r.strip()]
    if unknown := sorted(set(wanted) - set(names)):
        ap.error(f"unknown run(s) {', '.join(unknown)}; runs: {', '.join(names)}")
    if a.step_days < 1 or a.test_days < 1 or a.jobs < 1 or (a.varma_p or 1) < 1:
        ap.error("--step-days, --test-days, --jobs and --varma-p must be at least 1")
    varma = {"p": a.varma_p, "force_fallback": True} if a.varma_p else None
    models = tuple(m.strip() for m in a.models.split(",") if m.strip())
    if "triv" not in models:
        ap.error("--models must include triv (the floor and the ratios are against it)")
    t0 = time.perf_counter()
    work = [(spec.name, start) for spec in RUNS if spec.name in wanted
            for start in _origins(spec, load(spec.dataset), a.step_days, a.test_days)]
    with ProcessPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(one, *zip(*work, strict=True), [a.test_days] * len(work),
                             [models] * len(work), [varma] * len(work)))
    # a start day without data trains on the same days as the next one: count those once
    unique: dict[tuple[str, str], dict[str, Any]] = {}
    for r in rows:
        unique.setdefault((r["run"], r.get("training_days", r["start"])), r)
    rows = list(unique.values())
    cols = [("run", "run", None), ("start", "start", None), ("trained to", "training_end", None),
            ("days", "test_days", 0), ("primary", "primary", None),
            ("estimate %", "estimate_pct", 2), ("triv %", "triv_pct", 2),
            ("floor %", "floor_pct", 2), ("est / floor", "ratio_floor", 3),
            ("est / triv", "ratio_triv", 3), ("±2σ cover %", "cover2_pct", 1),
            ("nested cover % (training)", "nested_cover2_pct", 1),
            ("RMS σ / RMSE", "std_over_rmse", 2), ("CRPS / RMSE", "crps_over_rmse", 3)]
    if "varma" in models:
        cols += [("varma p", "varma_p", 0), ("varma / triv", "varma_ratio", 2),
                 ("varma live", "varma_live", None)]
    print_markdown([r for r in rows if "error" not in r], cols)
    for r in rows:
        if "error" in r:
            print(f"{r['run']} from {r['start']}: failed: {r['error']}")
    print()
    summaries = [{**summary(sel, n), **oracle(sel)}
                 for n in wanted for sel in [[r for r in rows if r["run"] == n]]]
    every = summary(rows, "all")
    # over all runs: each run's origins judged with its own oracle factor
    judged = [(s["origins"], s["oracle_in_pct"]) for s in summaries
              if math.isfinite(s["oracle_in_pct"])]
    summaries.append({**every, "oracle_factor": math.nan, "oracle_in_pct": (
        sum(n * x for n, x in judged) / sum(n for n, _ in judged) if judged else math.nan)})
    for r in rows:
        for k in ("_abs_err", "_std", "_age"):
            r.pop(k, None)
    print(f"{len(rows)} origins, {len(models)} models ({', '.join(models)}), test span "
          f"{a.test_days} days, {time.perf_counter() - t0:.0f} s")
    print_table("origins", summaries, [
        ("run", "run", None), ("origins", "origins", 0), ("failed", "failed", 0),
        ("est ≤ 1.02 × floor %", "floor_ok_pct", 0), ("est ≤ 0.9 × triv %", "triv_0_9_pct", 0),
        ("median est / floor", "median_ratio_floor", 3),
        ("worst est / floor", "worst_ratio_floor", 2),
        ("cover 90–98 %", "cover_in_pct", 0), ("cover < 90 %", "cover_low_pct", 0),
        ("cover > 98 %", "cover_high_pct", 0), ("median ±2σ cover %", "median_cover2_pct", 1),
        ("median nested cover %", "median_nested_pct", 1),
        ("mean CRPS / RMSE", "mean_crps_over_rmse", 3),
        ("oracle σ factor", "oracle_factor", 2), ("oracle cover 90–98 %", "oracle_in_pct", 0),
        *([("varma ≤ 1.5 × triv or not live %", "varma_met_pct", 0),
           ("varma live %", "varma_live_pct", 0),
           ("median varma / triv", "median_varma_ratio", 2)] if "varma" in models else [])])


if __name__ == "__main__":
    main()
