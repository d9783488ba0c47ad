#!/usr/bin/env python3
"""Benchmark: accuracy and cost of merging the GP models' points (gp/points.py).

For Room Climate A and B (evaluate's runs, scripts/results.py): trains triv, corrgp-triv
and corrgp-lcm once (primary corrgp-triv, no validation: the scored estimates do not depend
on it), then replays the test days as ``evaluate`` does (an estimate at every target
reading) with the GP points merged per interval (0: one GP point per 1-minute window
point, the behaviour before merging) and reports each model's mean daily NRMSE and the
replay's CPU seconds. ``--raw`` also replays Room Climate A's raw samples (one every ~4 s
per node: the chatty sensor), which the window thins to one point per minute first.

Prints a table and, last, one JSON line.
Usage: .venv/bin/python scripts/bench_gp_points.py [--intervals 0,5] [--runs room-climate-a,
       room-climate-b] [--raw]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy does any work)
from pseudotwin.analysis.evaluate import daily_scores, first_scored_day
from pseudotwin.analysis.replay import replay_estimates
from pseudotwin.analysis.report.runs import RUNS
from pseudotwin.analysis.training import train_twin
from pseudotwin.gp import points
from pseudotwin.history.convert import load
from pseudotwin.live.artifact import Artifact

MODELS = ("triv", "corrgp-triv", "corrgp-lcm")
GP = ("corrgp-triv", "corrgp-lcm")


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--intervals", default="0,5",
                    help="GP point intervals [min], comma-separated; 0: no merging")
    ap.add_argument("--runs", default="room-climate-a,room-climate-b")
    ap.add_argument("--raw", action="store_true",
                    help="also replay the raw samples of Room Climate A (chatty sensor)")
    a = ap.parse_args()
    intervals = [float(x) for x in a.intervals.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="pseudotwin-gp-points-") as tmp:
        for name in a.runs.split(","):
            run = next(r for r in RUNS if r.name == name)
            hist = load(run.dataset)
            art = train_twin(hist, run.twin, run.train_start, run.train_days, MODELS,
                             primary="corrgp-triv", validate=False)
            path = Path(tmp) / f"{name}.json"
            art.save(path)
            art = Artifact.load(path)
            start = first_scored_day(art)
            feeds = [("1-min", hist)]
            if a.raw and run.dataset == "room-climate-a":
                feeds.append(("raw", load(run.dataset, raw=True)))
            for feed, data in feeds:
                for iv in intervals:
                    points.INTERVAL_H = iv / 60 if iv else None
                    c0 = time.process_time()
                    est = replay_estimates(art, data, start, list(MODELS))
                    cpu = time.process_time() - c0
                    d = daily_scores(est, art.hours)
                    m = d.groupby("model")["nrmse_pct"].mean()
                    rows.append({"run": name, "feed": feed, "interval_min": iv,
                                 "days": int(d["day"].nunique()), "cpu_s": round(cpu, 2),
                                 **{k: round(float(m[k]), 4) for k in GP}})
    print(f"{'run':<16} {'feed':<6} {'interval':>8} {'days':>5} {'CPU s':>7} "
          f"{'corrgp-triv %':>14} {'corrgp-lcm %':>13}")
    for r in rows:
        print(f"{r['run']:<16} {r['feed']:<6} {r['interval_min']:>6g} m {r['days']:>5} "
              f"{r['cpu_s']:>7.2f} {r['corrgp-triv']:>14.4f} {r['corrgp-lcm']:>13.4f}")
    print(json.dumps({"runs": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
