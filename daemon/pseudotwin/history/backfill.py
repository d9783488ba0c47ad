"""``pseudotwin backfill``: the daemon's estimates for past days, from the history store.

Stored readings are replayed day by day through the same :class:`~pseudotwin.live.twin.Twin` the
daemon runs, in the order the daemon would have seen them: at every reference reading, and at
every instant of the publish grid, every model's estimate is written to the estimates table
(upserted on twin, model, ts — a rerun rewrites, never duplicates). Each finished day is
recorded (per artifact version), so an interrupted backfill continues after the last finished
day, and a retrained twin is backfilled anew. One day of
readings is in memory at a time.
"""

from __future__ import annotations

import datetime as dt
import logging
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TextIO

import pandas as pd

from pseudotwin.config import ServiceConfig, TwinConfig
from pseudotwin.errors import ConfigError
from pseudotwin.history.store import EstimateRow, Store
from pseudotwin.live.artifact import Artifact, artifact_hash
from pseudotwin.live.twin import Twin, TwinEstimate

log = logging.getLogger(__name__)


@dataclass
class BackfillSummary:
    days: int = 0
    estimates: int = 0
    skipped: dict[str, list[str]] = field(default_factory=dict)  # reason → days
    seconds: float = 0.0

    def skip(self, day: dt.date, reason: str) -> None:
        self.skipped.setdefault(reason, []).append(str(day))

    def lines(self) -> list[str]:
        out = [f"backfilled {self.days} day(s), {self.estimates} estimates written "
               f"in {self.seconds:.1f} s"]
        for reason, days in self.skipped.items():
            shown = ", ".join(days[:10]) + (f" … (+{len(days) - 10})" if len(days) > 10 else "")
            out.append(f"skipped {len(days)} day(s), {reason}: {shown}")
        return out


def grid_instants(cfg: ServiceConfig, day: dt.date) -> list[dt.datetime]:
    """The daemon's publish grid of one local day."""
    return cfg.hours.grid(day, cfg.publish_every.total_seconds() / 3600.0)


def day_estimates(
    twin: Twin, readings: pd.DataFrame, grid: list[dt.datetime]
) -> Iterator[tuple[str, TwinEstimate]]:
    """Feed one day's readings (time order) and yield (kind, estimate) as the daemon would
    publish them: after each accepted reference reading, and at each grid instant (after the
    readings up to it). Init-phase and empty estimates are not published, so not yielded."""
    gi = 0
    rows = zip(readings["sensor"], readings["ts"], readings["value"], strict=True)
    for sensor, ts, value in rows:
        t = ts.to_pydatetime()
        while gi < len(grid) and grid[gi] < t:
            yield from _publishable(twin.estimate(grid[gi]))
            gi += 1
        if twin.observe(sensor, t, float(value)):
            yield from _publishable(twin.estimate(t))
    for g in grid[gi:]:
        yield from _publishable(twin.estimate(g))


def _publishable(ests: dict[str, TwinEstimate]) -> Iterator[tuple[str, TwinEstimate]]:
    return ((kind, e) for kind, e in ests.items() if e.publishable)


class Progress:
    """A progress bar on a terminal, plain lines otherwise (logs, CI, systemd)."""

    def __init__(self, total: int, stream: TextIO = sys.stderr) -> None:
        self.total = max(total, 1)
        self.stream = stream
        self.tty = hasattr(stream, "isatty") and stream.isatty()
        self.t0 = time.monotonic()
        self.last_line = 0.0

    def update(self, done: int, day: dt.date, estimates: int) -> None:
        frac = done / self.total
        rate = done / max(time.monotonic() - self.t0, 1e-9)
        if self.tty:
            bar = "#" * int(30 * frac)
            self.stream.write(f"\r[{bar:<30}] {done}/{self.total} days  {day}  "
                              f"{estimates} estimates  {rate:.1f} days/s ")
            self.stream.flush()
        elif time.monotonic() - self.last_line >= 5 or done == self.total:
            self.last_line = time.monotonic()
            self.stream.write(f"backfill: {done}/{self.total} days ({frac:.0%}), at {day}, "
                              f"{estimates} estimates, {rate:.2f} days/s\n")
            self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")


def backfill(
    cfg: ServiceConfig,
    twin_id: str,
    start: dt.date,
    end: dt.date,
    store: Store,
    progress: bool = True,
    batch_rows: int = 20_000,
) -> BackfillSummary:
    """Backfill ``twin_id`` for local days start … end (inclusive)."""
    if twin_id not in cfg.twins:
        raise ConfigError(f"no twin {twin_id!r} in the configuration "
                          f"(twins: {', '.join(cfg.twins)})")
    if end < start:
        raise ConfigError(f"--to {end} is before --from {start}")
    tc: TwinConfig = cfg.twins[twin_id]
    art = Artifact.load(tc.artifact)
    digest = artifact_hash(tc.artifact)
    hours = art.hours
    refs = list(art.references)
    summary = BackfillSummary()
    t0 = time.perf_counter()
    # Progress belongs to an artifact version: after a retrain every day is due again.
    progress_key = f"{twin_id}@{digest[:16]}"
    done = store.done_days(progress_key)
    days = [start + dt.timedelta(days=i) for i in range((end - start).days + 1)]
    todo = [d for d in days if d not in done]
    for d in days:
        if d in done:
            summary.skip(d, "already backfilled")
    bar = Progress(len(todo)) if progress else None
    twin: Twin | None = None
    prev: dt.date | None = None
    for i, (day, frame) in enumerate(_iter_todo(store, refs, todo, hours.timezone)):
        if twin is None or prev != day - dt.timedelta(days=1):
            # A fresh twin (first day, or after a gap of finished days): seed the carry-over
            # with the last stored readings before the day, as the daemon would hold them.
            twin = Twin(art, stale_after=cfg.stale_after)
            init = hours.at(day, hours.init_start)
            for s, (ts, v) in store.last_readings_before(refs, init).items():
                twin.observe(s, ts, v)
        prev = day
        if frame.empty:
            summary.skip(day, "no reference readings")
            store.mark_day_done(progress_key, day, 0)
            continue
        # One row per (model, instant): a grid instant that coincides with a reading gives
        # the same estimate twice, and the store would only overwrite it.
        rows: dict[tuple[str, dt.datetime], EstimateRow] = {}
        for kind, e in day_estimates(twin, frame, grid_instants(cfg, day)):
            rows[(kind, e.ts)] = EstimateRow.from_estimate(twin_id, kind, e, digest)
        batch = list(rows.values())
        n = 0
        for k in range(0, len(batch), batch_rows):
            n += store.write_estimates(batch[k:k + batch_rows])
        store.mark_day_done(progress_key, day, n)
        summary.days += 1
        summary.estimates += n
        if bar:
            bar.update(i + 1, day, summary.estimates)
    if bar:
        bar.close()
    summary.seconds = time.perf_counter() - t0
    return summary


def _iter_todo(store: Store, sensors: list[str], days: list[dt.date],
               tz: str) -> Iterator[tuple[dt.date, pd.DataFrame]]:
    """Stream the days still to do, one store query per contiguous run of days."""
    if not days:
        return
    run = [days[0]]
    for d in [*days[1:], None]:
        if d is not None and d == run[-1] + dt.timedelta(days=1):
            run.append(d)
            continue
        yield from store.iter_days(sensors, run[0], run[-1], tz)
        if d is not None:
            run = [d]
