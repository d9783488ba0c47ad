"""``pseudotwin backfill``: the daemon's estimates for past days, from the history store.

Stored readings are replayed day by day through the same :class:`~pseudotwin.live.twin.Twin` the
daemon runs, in the order the daemon would have seen them, and what the daemon would have
published is written to the estimates table: at every reference reading that moves the twin
the primary model's estimate (every model's with ``[service] baselines = "reading"``), at
every instant of the publish grid every model's (upserted on twin, model, ts — a rerun
rewrites, never duplicates). Readings outside the operating window are skipped but each
sensor's last before it and after it (:func:`window_frame`): the twin would only have
noted them as the sensor's latest value. Each finished day is
recorded (per artifact version) after its rows are written, so an interrupted backfill
continues with the days not yet finished, and a retrained twin is backfilled anew. Only a
day with reference readings that has ended (in the twin's time zone) is finished: a day
without readings is skipped and a day not over yet is estimated from the readings so far,
both left unrecorded, so a later run fills them once the readings are there (rewriting a
day's rows leaves one row per key). One day of readings is in memory at a time.

Days are independent: a day's estimates depend only on that day's readings and on the last
reading of each reference from before the day's init start (the carried-over value). A run
of days (a :class:`Chunk`) therefore starts with a fresh twin seeded with exactly those
readings from the store, which is what the twin of a serial run holds at that point; that
is why chunks can run in any order, in any process (:mod:`pseudotwin.history.backfill_pool`)
and give the same rows.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import time
import traceback
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import pandas as pd

from pseudotwin.config import ServiceConfig
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.twinlog import twin_context
from pseudotwin.errors import ConfigError, PseudotwinError
from pseudotwin.history.store import EstimateRow, Store
from pseudotwin.live.artifact import Artifact, artifact_hash, check_artifact
from pseudotwin.live.readings import in_range
from pseudotwin.live.twin import MAX_CARRY, Twin, TwinEstimate

log = logging.getLogger(__name__)

#: Longest run of days one chunk covers: bounds how much work one progress line stands for
#: and how much a Ctrl-C or a failure leaves to a rerun.
MAX_CHUNK_DAYS = 31

class StopFlag(Protocol):
    """Asked between days: a threading or multiprocessing Event."""

    def is_set(self) -> bool: ...


class BackfillError(PseudotwinError):
    """Days of a backfill failed (each failure names its twin and day)."""


@dataclass
class BackfillSummary:
    """What a backfill of one twin did."""

    days: int = 0
    estimates: int = 0
    skipped: dict[str, list[str]] = field(default_factory=dict)  # reason → days
    unended: list[str] = field(default_factory=list)  # of ``days``: estimated, not done
    # of ``days``: estimated from readings before the day opened only (stale), not done
    silent: list[str] = field(default_factory=list)
    out_of_range: int = 0  # stored readings outside their sensor's range: left out
    seconds: float = 0.0

    def skip(self, day: dt.date | str, reason: str) -> None:
        self.skipped.setdefault(reason, []).append(str(day))

    def lines(self) -> list[str]:
        # seconds: summed over the twin's runs of days, which may have run side by side
        out = [f"backfilled {self.days} day(s), {self.estimates} estimates written "
               f"in {self.seconds:.1f} s of work"]
        if self.unended:
            out.append("not marked done " + _day_list(
                self.unended, "the day has not ended (a run after its end completes it)"))
        if self.silent:
            out.append("not marked done " + _day_list(
                self.silent, "no reference reading from the init phase on, its estimates "
                "stale or held (a run after more readings are stored redoes it)"))
        for reason, days in self.skipped.items():
            out.append(f"skipped {_day_list(days, reason)}")
        if self.out_of_range:
            out.append(f"left out {self.out_of_range} stored reading(s) outside their sensor's "
                       "configured min..max, as the daemon rejects them")
        return out


def _day_list(days: list[str], reason: str = "") -> str:
    """``N day(s)[, reason]: d1, d2, …`` (the first ten days, sorted)."""
    days = sorted(days)
    shown = ", ".join(days[:10]) + (f" … (+{len(days) - 10})" if len(days) > 10 else "")
    return f"{len(days)} day(s){', ' + reason if reason else ''}: {shown}"


@dataclass(frozen=True)
class TwinJob:
    """One twin's backfill: its artifact version and the days still to do."""

    twin_id: str
    artifact_path: str
    digest: str
    todo: tuple[dt.date, ...]
    done: tuple[dt.date, ...]  # already finished with this artifact version
    # Of ``todo``: not over yet when planned (twin's time zone): estimated, never marked done.
    unended: tuple[dt.date, ...] = ()
    # When planned: an unended day's grid stops there (no estimates of instants to come).
    now: dt.datetime | None = None

    @property
    def progress_key(self) -> str:
        # Progress belongs to an artifact version: after a retrain every day is due again.
        return f"{self.twin_id}@{self.digest[:16]}"


@dataclass(frozen=True)
class Chunk:
    """A run of days of one twin, processed by one fresh twin (days ascending)."""

    job: TwinJob
    days: tuple[dt.date, ...]

    def label(self) -> str:
        first, last = self.days[0], self.days[-1]
        return f"{self.job.twin_id} {first}" + (f" … {last}" if last != first else "")


@dataclass
class ChunkResult:
    """What one chunk did. ``failed`` (day, message) stops the chunk at that day;
    ``stopped`` means it was asked to stop (Ctrl-C) before its last day."""

    chunk: Chunk
    days: int = 0  # estimated, ``unended`` among them
    estimates: int = 0
    empty: list[dt.date] = field(default_factory=list)  # no reference readings: not marked
    out_of_range: int = 0  # stored readings left out as the daemon would reject them
    unended: list[dt.date] = field(default_factory=list)  # estimated, not over: not marked
    silent: list[dt.date] = field(default_factory=list)  # estimated, no reading: not marked
    failed: tuple[dt.date, str] | None = None
    detail: str = ""  # the failure's traceback, for --log-level DEBUG
    stopped: bool = False
    seconds: float = 0.0

    @property
    def unfinished(self) -> int:
        """Days of the chunk neither done nor empty (failed or not attempted)."""
        return len(self.chunk.days) - self.days - len(self.empty)

    def failure_line(self) -> str:
        assert self.failed is not None
        day, msg = self.failed
        rest = self.unfinished - 1
        later = f"; {rest} later day(s) of its chunk not attempted" if rest else ""
        return f"twin {self.chunk.job.twin_id}, day {day}: {msg}{later}"


def day_ended(hours: OperatingHours, day: dt.date, now: dt.datetime) -> bool:
    """Whether local ``day`` lies entirely before ``now`` (aware) in the zone of ``hours``."""
    return hours.day_of(now) > day


def plan(cfg: ServiceConfig, twin_ids: list[str], start: dt.date, end: dt.date,
         store: Store, now: dt.datetime | None = None, redo: bool = False) -> list[TwinJob]:
    """The jobs of ``twin_ids`` over local days start … end, with the days already done
    (of each twin's current artifact version) taken out, unless ``redo`` (readings a day
    lacked were imported since), and the days not ended by ``now`` (default: the clock)
    noted as such. Checks twins, dates and artifacts before any work starts."""
    unknown = [t for t in twin_ids if t not in cfg.twins]
    if unknown:
        raise ConfigError(f"no twin {', '.join(repr(t) for t in unknown)} in the configuration "
                          f"(twins: {', '.join(cfg.twins)})")
    if not twin_ids:
        raise ConfigError("the configuration has no twins to backfill")
    if end < start:
        raise ConfigError(f"--to {end} is before --from {start}")
    # Taken before any day's readings are read: a day ended by then has all it will get.
    now = now or dt.datetime.now(dt.UTC)
    if now.tzinfo is None:
        raise ValueError(f"now must be timezone-aware, not {now}")
    days = [start + dt.timedelta(days=i) for i in range((end - start).days + 1)]
    jobs = []
    for twin_id in dict.fromkeys(twin_ids):
        path = cfg.twins[twin_id].artifact
        art = Artifact.load(path)  # a broken artifact fails here, before any work
        # An artifact that does not fit its twin (another twin's, other hours) would replace
        # the stored estimates with wrong ones: refused as `run` refuses it.
        if problems := check_artifact(cfg.twins[twin_id], art, cfg.hours, cfg.thinning):
            raise ConfigError("\n".join(f"twins.{twin_id}.artifact: {p}" for p in problems))
        hours = art.hours
        if never := [r for r in art.references if store.reading_range([r]) is None]:
            # A misspelt id in a nightly job would otherwise look like quiet days forever.
            log.warning("twin %s: the store holds no reading at all of %s (not recorded yet, "
                        "or under another name?): every day is skipped as without reference "
                        "readings", twin_id, ", ".join(never))
        digest = artifact_hash(path)
        job = TwinJob(twin_id, str(path), digest, (), ())
        done = set() if redo else store.done_days(job.progress_key)
        todo = tuple(d for d in days if d not in done)
        jobs.append(TwinJob(twin_id, str(path), digest, todo,
                            tuple(d for d in days if d in done),
                            tuple(d for d in todo if not day_ended(hours, d, now)), now))
    return jobs


def chunk_size(total_days: int, workers: int) -> int:
    """Days per chunk: about four chunks per worker so the last ones balance the load,
    at most :data:`MAX_CHUNK_DAYS`."""
    return max(1, min(MAX_CHUNK_DAYS, math.ceil(total_days / (4 * max(workers, 1)))))


def chunks(jobs: list[TwinJob], size: int) -> list[Chunk]:
    return [Chunk(job, job.todo[i:i + size])
            for job in jobs for i in range(0, len(job.todo), size)]


def grid_instants(cfg: ServiceConfig, day: dt.date) -> list[dt.datetime]:
    """The daemon's publish grid of one local day."""
    return cfg.hours.grid(day, cfg.publish_every.total_seconds() / 3600.0)


def day_estimates(
    twin: Twin, readings: pd.DataFrame, grid: list[dt.datetime],
    per_reading: Sequence[str] | None = None,
) -> Iterator[tuple[str, TwinEstimate]]:
    """Feed one day's readings (time order) and yield (kind, estimate) as the daemon would
    publish them: ``per_reading``'s (None: every model's) after each accepted reference
    reading, and every model's at each grid instant (after the readings up to it).
    Init-phase and empty estimates are not published, so not yielded.

    A grid instant that is also the time of the reading just estimated (1-minute readings
    on a 15-minute grid: every instant) would give the very same estimates again, since
    nothing has reached the twin in between: only the models not estimated at the reading
    are computed there.
    """
    gi = 0
    # The instant of the last estimate when nothing has reached the twin since (else None).
    fresh: dt.datetime | None = None
    # Plain Python values up front: pandas' per-row boxing costs more than the loop itself.
    rows = zip(readings["sensor"].tolist(), pd.DatetimeIndex(readings["ts"]).to_pydatetime(),
               readings["value"].tolist(), strict=True)
    for sensor, t, value in rows:
        while gi < len(grid) and grid[gi] < t:
            yield from _publishable(_at_grid(twin, grid[gi], fresh, per_reading))
            gi += 1
        # A rejected reading may still move the twin (its staleness clock): no reuse then.
        fresh = None
        if twin.observe(sensor, t, float(value)):
            yield from _publishable(twin.estimate(t, kinds=per_reading))
            fresh = t
    for g in grid[gi:]:
        yield from _publishable(_at_grid(twin, g, fresh, per_reading))


def _at_grid(twin: Twin, g: dt.datetime, fresh: dt.datetime | None,
             per_reading: Sequence[str] | None) -> dict[str, TwinEstimate]:
    """Every model's estimate at grid instant ``g``, but those already estimated at ``g``
    (``fresh``: nothing moved the twin since)."""
    if g != fresh:
        return twin.estimate(g)
    if per_reading is None:
        return {}
    rest = [k for k in twin.kinds if k not in per_reading]
    return twin.estimate(g, kinds=rest) if rest else {}


def _publishable(ests: dict[str, TwinEstimate]) -> Iterator[tuple[str, TwinEstimate]]:
    return ((kind, e) for kind, e in ests.items() if e.publishable)


#: Slack around the operating window when dropping readings outside it [h]: a reading this
#: close to its edge is left for the twin to judge, so rounding can never drop one it keeps.
_EDGE_H = 1e-6


def window_frame(frame: pd.DataFrame, hours: OperatingHours) -> pd.DataFrame:
    """The readings of one local day (time order) that can change what the twin estimates:
    those in the operating window (init start … day end), and of those before it and of
    those after it only each sensor's last with a finite value.

    A reading outside the window only becomes its sensor's last value (the next window's
    carry-over, and how long the sensor has been silent), and readings outside the window
    come in a block before it and a block after it: the last of each block per sensor
    leaves the twin exactly as all of them would, at half the readings of a 1-minute day.
    """
    if frame.empty:
        return frame
    _, h = hours.day_and_hours(frame["ts"])
    if (np.diff(h) < 0).any():
        # A DST fold: outside readings need not come in one block per side; keep them all.
        return frame
    before = h < hours.init_start - _EDGE_H
    after = h > hours.day_end + _EDGE_H
    keep = ~(before | after)
    finite = np.isfinite(frame["value"].to_numpy(dtype=float))
    sensors = frame["sensor"].to_numpy()
    for block in (before, after):
        pos = np.flatnonzero(block & finite)[::-1]  # newest first: unique keeps the last
        _, newest = np.unique(sensors[pos], return_index=True)
        keep[pos[newest]] = True
    return frame if keep.all() else frame[keep]


def day_rows(cfg: ServiceConfig, job: TwinJob, twin: Twin, day: dt.date,
             frame: pd.DataFrame) -> list[EstimateRow]:
    """The rows of one day: one per (model, instant); of a day not over when planned, only
    the grid instants up to then (the daemon has not published the later ones either)."""
    rows: dict[tuple[str, dt.datetime], EstimateRow] = {}
    grid = grid_instants(cfg, day)
    if day in job.unended and job.now is not None:
        grid = [g for g in grid if g <= job.now]
    for kind, e in day_estimates(twin, window_frame(frame, twin.hours), grid,
                                 cfg.per_reading_kinds(twin.artifact.primary)):
        rows[(kind, e.ts)] = EstimateRow.from_estimate(job.twin_id, kind, e, job.digest)
    return list(rows.values())


def _seed(cfg: ServiceConfig, store: Store, sensors: list[str], init: dt.datetime
          ) -> dict[str, tuple[dt.datetime, float]]:
    """Each sensor's last stored reading before ``init`` that its configured range takes,
    within the twin's carry-over (24 h): what a daemon, rejecting the others, would hold."""
    last = store.last_readings_before(sensors, init)
    out = {s: x for s, x in last.items() if cfg.sensors[s].accepts(x[1])}
    if wild := [s for s in last if s not in out]:
        # In UTC: a local instant minus 24 h is wall-clock arithmetic, 23 h back across a
        # spring DST change, where the twin's carry-over reaches 24 h (live/twin.py).
        since = init.astimezone(dt.UTC) - MAX_CARRY
        frame = in_range(store.read_readings(wild, since, init), cfg.sensors)
        for s, g in frame.groupby("sensor", sort=False):
            out[str(s)] = (g["ts"].iloc[-1].to_pydatetime(), float(g["value"].iloc[-1]))
    return out


def run_chunk(cfg: ServiceConfig, chunk: Chunk, store: Store, artifact: Artifact,
              stop: StopFlag | None = None) -> ChunkResult:
    """Backfill the days of ``chunk``: write each day's rows, then mark the day done,
    unless it has no reference readings (nothing written) or has not ended yet.

    Checks ``stop`` between days (a day is finished or not started, never half marked).
    A failing day ends the chunk; the failure names the day.
    """
    t0 = time.perf_counter()
    job = chunk.job
    res = ChunkResult(chunk)
    refs = list(artifact.inputs)  # the readings the twin reads: references and covariates
    hours = artifact.hours
    twin: Twin | None = None
    prev: dt.date | None = None
    day = chunk.days[0]
    with twin_context(job.twin_id):  # its log lines (a model's fallback, say) name it
        try:
            for day, frame in _iter_todo(store, refs, list(chunk.days), hours.timezone):
                if stop is not None and stop.is_set():
                    res.stopped = True
                    break
                if twin is None or prev != day - dt.timedelta(days=1):
                    # A fresh twin (first day, or after a gap of finished days): seed the
                    # carry-over with the last stored readings before the day, as the
                    # daemon (and a serial backfill's twin) would hold them.
                    twin = Twin(artifact, models=cfg.running_kinds(artifact.primary),
                                stale_after=cfg.stale_after, thinning=cfg.thinning)
                    for s, (ts, v) in _seed(cfg, store, refs,
                                            hours.at(day, hours.init_start)).items():
                        twin.observe(s, ts, v)
                prev = day
                # The store holds what import took unchecked (it has no configuration):
                # the daemon rejects a reading outside its sensor's range, and so does this.
                taken = in_range(frame, cfg.sensors)
                res.out_of_range += len(frame) - len(taken)
                frame = taken
                if not frame["sensor"].isin(artifact.references).any():
                    # not marked: readings imported later fill it (covariates alone give
                    # nothing the daemon would publish as an estimate)
                    res.empty.append(day)
                    continue
                # The day's rows replace the twin's stored ones of that day whole: none of
                # an earlier artifact's (a model no longer run, an instant no longer
                # estimated) stay beside them.
                n = store.replace_estimates(job.twin_id, hours.at(day, 0.0),
                                            hours.at(day + dt.timedelta(days=1), 0.0),
                                            day_rows(cfg, job, twin, day, frame))
                if day in job.unended:  # not marked: a run after its end completes it
                    res.unended.append(day)
                elif not _reported(frame, artifact, day):
                    # Readings of the night before only (a store filled up to then, or a
                    # dead reference): not marked, so readings stored later fill the day.
                    res.silent.append(day)
                else:
                    store.mark_day_done(job.progress_key, day, n)
                log.debug("day %s written: %d estimates", day, n)
                res.days += 1
                res.estimates += n
        except KeyboardInterrupt:
            # In this process (--jobs 1): the day in progress is not marked done (its rows,
            # if written, are rewritten by the rerun); the caller reports the interruption.
            res.stopped = True
        except Exception as exc:  # noqa: BLE001 - reported with its twin and day
            res.failed = (day, f"{type(exc).__name__}: {exc}")
            res.detail = traceback.format_exc()
    res.seconds = time.perf_counter() - t0
    return res


def _reported(frame: pd.DataFrame, artifact: Artifact, day: dt.date) -> bool:
    """Whether a reference has a reading of ``day`` in ``frame`` from the init phase to the
    end of the operating hours: the part of the day its estimates come from."""
    hours = artifact.hours
    ts = frame["ts"]
    return bool((frame["sensor"].isin(artifact.references)
                 & (ts >= hours.at(day, hours.init_start))
                 & (ts <= hours.at(day, hours.day_end))).any())


def _iter_todo(store: Store, sensors: list[str], days: list[dt.date],
               tz: str) -> Iterator[tuple[dt.date, pd.DataFrame]]:
    """Stream the days still to do, one store query per day."""
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


def backfill(
    cfg: ServiceConfig,
    twin_id: str,
    start: dt.date,
    end: dt.date,
    store: Store,
    progress: bool = True,
    now: dt.datetime | None = None,
) -> BackfillSummary:
    """Backfill ``twin_id`` for local days start … end (inclusive), in this process.
    ``now`` (default: the clock) decides which days have ended (see :func:`plan`)."""
    from pseudotwin.history.backfill_pool import backfill_twins

    run = backfill_twins(cfg, [twin_id], start, end, store, jobs=1, progress=progress,
                         now=now)
    if run.failures:
        raise BackfillError("; ".join(r.failure_line() for r in run.failures))
    return run.twins[twin_id]
