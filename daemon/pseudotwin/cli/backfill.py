"""``pseudotwin backfill``: its options and its run (the work is
:mod:`pseudotwin.history.backfill_pool`)."""

from __future__ import annotations

import argparse
import datetime as dt
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from pseudotwin.cli.util import whole_number

if TYPE_CHECKING:
    from pseudotwin.history.backfill import TwinJob

EX_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C


def _date(text: str) -> dt.date:
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a date YYYY-MM-DD") from None


_jobs = whole_number(1, what="a number of processes")


def default_jobs() -> int:
    """The CPUs this process may run on (its affinity mask, e.g. a container's cpuset)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, help="TOML configuration file")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--twin", action="append", metavar="ID[,ID...]",
                       help="twin id(s) from the configuration; repeat or separate with "
                            "commas (--twin a --twin b, or --twin a,b)")
    which.add_argument("--all-twins", action="store_true",
                       help="every twin of the configuration")
    p.add_argument("--from", dest="start", required=True, type=_date, metavar="YYYY-MM-DD",
                   help="first day, YYYY-MM-DD (a local day in the configured time zone)")
    p.add_argument("--to", dest="end", required=True, type=_date, metavar="YYYY-MM-DD",
                   help="last day (inclusive), YYYY-MM-DD (a local day in the configured "
                        "time zone)")
    p.add_argument("--jobs", "-j", type=_jobs, default=default_jobs(), metavar="N",
                   help="worker processes (default: the CPUs available, here "
                        f"{default_jobs()}); twins and runs of days are spread over them, "
                        "with the same rows as --jobs 1, which runs in this process")
    p.add_argument("--redo", action="store_true",
                   help="estimate days already backfilled with this artifact again and "
                        "write their rows again: after importing readings a day lacked (a day "
                        "with some reference readings counts as done)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress lines (one per finished run of days, on stderr)")


def run(a: argparse.Namespace) -> int:
    """Backfill; 0 when every day finished, 1 when some failed (each named on stderr),
    130 when interrupted (finished days stay written; the same command resumes)."""
    from pseudotwin.cli.util import load_named_config
    from pseudotwin.core.heap import freeze_long_lived
    from pseudotwin.errors import ConfigError
    from pseudotwin.history.backfill import plan
    from pseudotwin.history.backfill_pool import backfill_twins
    from pseudotwin.history.store import open_store

    cfg = load_named_config(a.config)
    if cfg.store is None:
        raise ConfigError(f"{a.config}: no store configured in [service] (store = ...)")
    if a.all_twins:
        twins = list(cfg.twins)
    else:
        twins = [t.strip() for arg in a.twin for t in arg.split(",") if t.strip()]
        if not twins:
            raise ConfigError("--twin: no twin id given")
    freeze_long_lived()
    with open_store(cfg.store, existing=True) as store:
        # planned once: the note names the days still to do (done ones are skipped)
        planned = plan(cfg, twins, a.start, a.end, store, redo=a.redo)
        _say_training_days(planned)
        summary = backfill_twins(cfg, twins, a.start, a.end, store, jobs=a.jobs,
                                 progress=not a.quiet, redo=a.redo, planned=planned)
    print("\n".join(summary.lines()))
    for res in summary.failures:
        print(f"pseudotwin backfill: error: {res.failure_line()}", file=sys.stderr)
    if summary.interrupted:
        print("pseudotwin backfill: interrupted; finished days stay written, the same "
              "command resumes with the others", file=sys.stderr)
        return EX_INTERRUPTED
    return 1 if summary.failures else 0


def _say_training_days(jobs: list[TwinJob]) -> None:
    """A note per twin whose artifact trained on days the backfill is to do: their
    estimates are in-sample, and after a retrain with more days they replace the causal ones
    the earlier artifact wrote, with nothing said."""
    from pseudotwin.live.artifact import Artifact

    for job in jobs:
        trained = Artifact.load(job.artifact_path).training.get("days", [])
        if inside := [str(d) for d in job.todo if str(d) in trained]:
            print(f"pseudotwin backfill: note: {job.twin_id}: {', '.join(inside)} "
                  f"{'is a day' if len(inside) == 1 else 'are days'} its artifact was trained "
                  "on: their estimates are in-sample (better than the twin does on days it "
                  "never saw), and they replace any the twin's earlier artifact wrote",
                  file=sys.stderr)
