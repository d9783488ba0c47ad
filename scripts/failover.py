#!/usr/bin/env python3
"""Reference failover on the shared runs with several references: each reference silenced in
turn on every test day, the published estimate's error against the full twin's.

Per run (scripts/results.py's runs with ≥ 2 references, and ``room-climate-a3``: Room
Climate A with all three of its permanent sensors A1, A2, A3 as references), trains as
results.py does (same days, same models, validation picks the primary and the failovers),
then replays the test days through the daemon's twin (analysis/replay.py, the daemon's
``stale_after``) three ways: with every reference (the full twin), and with the readings of
one reference (with three references, also of each two) removed from every test day (their
last values before the test days are then older than ``stale_after`` all day), once with the
artifact's failovers and once without them (what older artifacts publish). Reports the mean
daily NRMSE of the published estimate, its ratio to the full twin's (Issue 10: ≤ 1.2), the
scored instants (true target readings in operating hours) left unanswered (no estimate, or
quality ``stale``), and ±2σ coverage of the failover's estimates.

Prints a Markdown table and, last, one JSON line.

    .venv/bin/python scripts/failover.py [--runs NAME,...] [--models ref,triv,corrgp-triv]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import logging
import sys
import time
from itertools import combinations
from typing import Any

import numpy as np
import pandas as pd

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy does any work)
from pseudotwin.analysis.evaluate import ESTIMATE, daily_scores, first_scored_day, replay_estimates
from pseudotwin.analysis.report.runs import RUNS
from pseudotwin.analysis.training import train_twin
from pseudotwin.history.convert import load
from pseudotwin.live import metrics
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.failover import picked
from pseudotwin.models.registry import ALL_MODELS
from tables import print_table

STALE_AFTER = dt.timedelta(minutes=30)  # the daemon's default stale_after_minutes
MULTI = [r for r in RUNS if len(r.references) >= 2]
# A2 (on a shelf by the door, 0.91 m) is left out of results.py's run; here it makes a third
# reference, so that two can be silenced at once.
_A = next(r for r in RUNS if r.name == "room-climate-a")
MULTI.append(dataclasses.replace(_A, name="room-climate-a3",
                                 references=("A1/temp", "A2/temp", "A3/temp")))


def _published(art: Artifact, history: pd.DataFrame, start: dt.date,
               stale_after: dt.timedelta) -> tuple[pd.DataFrame, int]:
    """The ``estimate`` rows (what <twin>/estimate carries) at every scored instant, and how
    many instants were scored (every true target reading in operating hours: the raw
    references' rows mark them all, whoever answered)."""
    est = replay_estimates(art, history, start, [art.primary], stale_after=stale_after)
    return est[est["model"] == ESTIMATE], int(est["ts"].nunique())


def _mean_nrmse(rows: pd.DataFrame, art: Artifact) -> float:
    answered = rows[rows["quality"] != "stale"]
    if answered.empty:
        return float("nan")
    daily = daily_scores(answered, art.hours)
    return float(daily["nrmse_pct"].mean())


def run(spec: Any, models: tuple[str, ...], history: pd.DataFrame) -> list[dict[str, Any]]:
    t0 = time.perf_counter()
    art = train_twin(history, spec.twin, spec.train_start, spec.train_days, models)
    start = first_scored_day(art)
    days, _ = art.hours.day_and_hours(history["ts"])
    full, total = _published(art, history, start, STALE_AFTER)
    full_nrmse = _mean_nrmse(full, art)
    bare = dataclasses.replace(art, failover={}, failover_alone={})
    out = []
    refs = art.references
    # each reference; with three or more, also every set of all references but one
    for lost in [(r,) for r in refs] + (list(combinations(refs, len(refs) - 1))
                                        if len(refs) >= 3 else []):
        silenced = history[~(history["sensor"].isin(lost) & (days >= np.datetime64(start)))]
        with_fo, _ = _published(art, silenced, start, STALE_AFTER)
        without, _ = _published(bare, silenced, start, STALE_AFTER)
        fo_rows = with_fo[with_fo["quality"] == "fallback"]
        answered = int((with_fo["quality"] != "stale").sum())
        nrmse = _mean_nrmse(with_fo, art)
        # the one the twin picks while they are silent all day (live/failover.py); none when
        # the primary reads none of them (it answers itself)
        fo = (picked(art.failovers, lost)
              if set(lost) & set(art.models[art.primary].references_) else None)
        out.append({
            "run": spec.name, "primary": art.primary,
            "primary_refs": list(art.models[art.primary].references_), "lost": ", ".join(lost),
            "failover": (f"{fo.kind} on {', '.join(fo.model.references_)}" if fo else None),
            "test_days": int(daily_scores(full, art.hours)["day"].nunique()),
            "full_nrmse_pct": full_nrmse, "silenced_nrmse_pct": nrmse,
            "ratio": nrmse / full_nrmse if full_nrmse > 0 else float("nan"),
            "instants": total, "full_unanswered": total - int((full["quality"] != "stale").sum()),
            "unanswered": total - answered,
            "unanswered_without_failover": total - int((without["quality"] != "stale").sum()),
            "fallback_share_pct": 100 * len(fo_rows) / max(len(with_fo), 1),
            "cover2_fallback_pct": (metrics.coverage_pct(fo_rows["truth"], fo_rows["value"],
                                                         fo_rows["std"], 2.0)
                                    if len(fo_rows) else float("nan")),
            "seconds": round(time.perf_counter() - t0, 1),
        })
        print(f"# {spec.name}: {', '.join(lost)} silenced done ({out[-1]['seconds']} s)",
              flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    names = [r.name for r in MULTI]
    ap.add_argument("--runs", default=",".join(names),
                    help=f"comma-separated runs with ≥ 2 references (default: all, "
                         f"{', '.join(names)})")
    ap.add_argument("--models", default=",".join(ALL_MODELS),
                    help="models trained, as results.py does (default %(default)s; "
                         "ref,triv,corrgp-triv is quicker)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    wanted = [r.strip() for r in a.runs.split(",") if r.strip()]
    unknown = sorted(set(wanted) - set(names))
    if unknown:
        ap.error(f"unknown run(s) {', '.join(unknown)}; runs with ≥ 2 references: "
                 f"{', '.join(names)}")
    models = tuple(m.strip() for m in a.models.split(",") if m.strip())
    rows: list[dict[str, Any]] = []
    for spec in (r for r in MULTI if r.name in wanted):
        rows.extend(run(spec, models, load(spec.dataset)))
    print_table("failover", rows, [
        ("run", "run", None), ("primary", "primary", None), ("silenced", "lost", None),
        ("failover", "failover", None), ("days", "test_days", 0),
        ("NRMSE full %", "full_nrmse_pct", 2), ("NRMSE silenced %", "silenced_nrmse_pct", 2),
        ("ratio", "ratio", 2), ("instants", "instants", 0),
        ("unanswered full", "full_unanswered", 0), ("unanswered", "unanswered", 0),
        ("unanswered w/o failover", "unanswered_without_failover", 0),
        ("fallback %", "fallback_share_pct", 1), ("±2σ cov fallback %", "cover2_fallback_pct", 1),
    ])


if __name__ == "__main__":
    main()
