"""Backfill of several twins on all cores: chunks of days in worker processes.

The work is split into :class:`~pseudotwin.history.backfill.Chunk` s (runs of one twin's days,
independent of each other, see :mod:`pseudotwin.history.backfill`) and run by a
``ProcessPoolExecutor``: the GP updates are CPU-bound Python, so threads would share one
core. Workers are *spawned* (never forked: the caller may hold threads and open
connections), and each opens its own store connection, writes its days' rows and marks each
day done after its rows: resume and idempotence are those of a serial run. SQLite serializes
the writers (WAL, ``BEGIN IMMEDIATE`` with a busy timeout); a day's write is a few
thousand rows, so the lock is held for milliseconds.

Ctrl-C: workers ignore SIGINT (blocked from their spawn until they do); the parent sets a
shared stop flag, which each worker checks between days, so every day is either finished
(rows and mark) or untouched, and waits for them. Progress is one line per finished chunk,
printed by the parent only.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.synchronize
import multiprocessing.util
import signal
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TextIO

from pseudotwin.errors import ConfigError
from pseudotwin.history.backfill import (
    BackfillSummary,
    Chunk,
    ChunkResult,
    TwinJob,
    chunk_size,
    chunks,
    plan,
    run_chunk,
)
from pseudotwin.history.store import Store, is_memory_url, open_store
from pseudotwin.live.artifact import Artifact

if TYPE_CHECKING:
    import datetime as dt

    from pseudotwin.config import ServiceConfig

log = logging.getLogger(__name__)


@dataclass
class RunSummary:
    """A backfill of several twins: per twin, and the chunks that failed."""

    twins: dict[str, BackfillSummary] = field(default_factory=dict)
    failures: list[ChunkResult] = field(default_factory=list)
    interrupted: bool = False
    workers: int = 1
    seconds: float = 0.0

    def add(self, res: ChunkResult) -> None:
        s = self.twins[res.chunk.job.twin_id]
        s.days += res.days
        s.estimates += res.estimates
        s.seconds += res.seconds
        s.unended += [str(d) for d in res.unended]
        s.silent += [str(d) for d in res.silent]
        s.out_of_range += res.out_of_range
        for d in res.empty:
            s.skip(d, "no reference readings")
        if res.failed is not None:
            self.failures.append(res)

    def lines(self) -> list[str]:
        out = [f"{twin}: {line}" for twin, s in self.twins.items() for line in s.lines()]
        days = sum(s.days for s in self.twins.values())
        est = sum(s.estimates for s in self.twins.values())
        out.append(f"total: {len(self.twins)} twin(s), {days} day(s), {est} estimates in "
                   f"{self.seconds:.1f} s with {self.workers} process(es)")
        out += [f"FAILED {r.failure_line()}" for r in self.failures]
        return out


class _ChunkProgress:
    """One line per finished chunk (workers finish in any order, so no bar)."""

    def __init__(self, chunks: list[Chunk], stream: TextIO) -> None:
        self.total_chunks = len(chunks)
        self.total_days = sum(len(c.days) for c in chunks)
        self.stream = stream
        self.chunks = 0
        self.days = 0
        self.t0 = time.monotonic()

    def update(self, res: ChunkResult) -> None:
        self.chunks += 1
        self.days += len(res.chunk.days) - res.unfinished
        rate = self.days / max(time.monotonic() - self.t0, 1e-9)
        if res.failed is not None:
            what = f"FAILED {res.failure_line()}"
        else:
            what = (f"{res.days + len(res.empty)} day(s), {res.estimates} estimates"
                    + (" (stopped)" if res.stopped else ""))
        self.stream.write(f"backfill {res.chunk.label()}: {what}  [{self.chunks}/"
                          f"{self.total_chunks} chunks, {self.days}/{self.total_days} days, "
                          f"{rate:.2f} days/s]\n")
        self.stream.flush()


def backfill_twins(
    cfg: ServiceConfig,
    twin_ids: list[str],
    start: dt.date,
    end: dt.date,
    store: Store,
    jobs: int = 1,
    progress: bool = True,
    chunk_days: int | None = None,
    stream: TextIO | None = None,
    now: dt.datetime | None = None,
    redo: bool = False,
    planned: list[TwinJob] | None = None,
) -> RunSummary:
    """Backfill ``twin_ids`` for local days start … end with up to ``jobs`` processes.

    jobs 1 runs in this process on ``store``; more spawn workers that open ``store.url``
    themselves. chunk_days: days per chunk (default: see
    :func:`~pseudotwin.history.backfill.chunk_size`). Failures do not stop other chunks;
    they are in the summary's ``failures``. Ctrl-C returns a summary with ``interrupted``.
    Progress lines go to ``stream`` (default stderr). ``now`` (default: the clock) decides
    which days have ended: one not ended is estimated but not marked done. redo: estimate
    the days done already again too (their rows are written again). planned: the jobs
    :func:`~pseudotwin.history.backfill.plan` gave for these arguments (None: planned here).
    """
    if jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, not {jobs}")
    if chunk_days is not None and chunk_days < 1:
        raise ConfigError(f"chunk_days must be at least 1, not {chunk_days}")
    t0 = time.perf_counter()
    twin_jobs = planned if planned is not None else plan(cfg, twin_ids, start, end, store,
                                                         now, redo)
    total = sum(len(j.todo) for j in twin_jobs)
    work = chunks(twin_jobs, chunk_days or chunk_size(total, jobs))
    run = RunSummary(workers=max(1, min(jobs, len(work))))
    for j in twin_jobs:
        run.twins[j.twin_id] = BackfillSummary()
        for d in j.done:
            run.twins[j.twin_id].skip(d, "already backfilled")
    bar = _ChunkProgress(work, stream or sys.stderr) if progress else None
    if run.workers == 1:
        _run_here(cfg, work, store, run, bar)
    else:
        if is_memory_url(store.url):
            raise ConfigError("an in-memory store cannot be shared with worker processes; "
                              "use --jobs 1")
        _run_pool(cfg, work, store.url, run, bar)
    for summary in run.twins.values():  # chunks finish in any order
        summary.unended.sort()
        summary.silent.sort()
        for days in summary.skipped.values():
            days.sort()
    run.seconds = time.perf_counter() - t0
    return run


def _run_here(cfg: ServiceConfig, work: list[Chunk], store: Store, run: RunSummary,
              bar: _ChunkProgress | None) -> None:
    artifacts: dict[str, Artifact] = {}
    for chunk in work:
        path = chunk.job.artifact_path
        art = artifacts.get(path) or artifacts.setdefault(path, Artifact.load(path))
        res = run_chunk(cfg, chunk, store, art)  # no stop flag: Ctrl-C ends it (stopped)
        run.add(res)
        _log_failure(res)
        if bar:
            bar.update(res)
        if res.stopped:
            run.interrupted = True
            break


def _run_pool(cfg: ServiceConfig, work: list[Chunk], store_url: str, run: RunSummary,
              bar: _ChunkProgress | None) -> None:
    ctx = multiprocessing.get_context("spawn")
    stop = ctx.Event()
    level = logging.getLogger().getEffectiveLevel()
    with ProcessPoolExecutor(max_workers=run.workers, mp_context=ctx,
                             initializer=_init_worker,
                             initargs=(cfg, store_url, stop, level)) as pool:
        # The workers are spawned by these submits. A Ctrl-C while one is still importing
        # would raise KeyboardInterrupt in it before its initializer can ignore SIGINT; so
        # SIGINT is blocked while they start (the mask is inherited), and the parent gets
        # a Ctrl-C of that moment as soon as it is unblocked.
        futures: dict[Future[ChunkResult], Chunk] = {}
        collected: set[Future[ChunkResult]] = set()
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            try:
                for c in work:
                    futures[pool.submit(_work, c)] = c
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # may raise it here
            for fut in as_completed(futures):
                _collect(fut, futures[fut], run, bar)
                collected.add(fut)
        except KeyboardInterrupt:
            run.interrupted = True
            stop.set()
            for fut in futures:
                fut.cancel()
            # Running chunks end after their current day; keep what they finished (once).
            for fut in futures:
                if not fut.cancelled() and fut not in collected:
                    _collect(fut, futures[fut], run, bar)


def _collect(fut: Future[ChunkResult], chunk: Chunk, run: RunSummary,
             bar: _ChunkProgress | None) -> None:
    try:
        res = fut.result()
    except BrokenProcessPool as exc:  # a worker died (killed, out of memory)
        res = ChunkResult(chunk, failed=(chunk.days[0], f"worker process died ({exc})"))
    except Exception as exc:  # noqa: BLE001 - e.g. the worker cannot open the store
        res = ChunkResult(chunk, failed=(chunk.days[0], f"{type(exc).__name__}: {exc}"))
    run.add(res)
    _log_failure(res)
    if bar:
        bar.update(res)


def _log_failure(res: ChunkResult) -> None:
    if res.failed is not None and res.detail:
        log.debug("backfill of %s failed:\n%s", res.chunk.label(), res.detail)


# -- in the worker processes -----------------------------------------------------------

_worker: dict[str, Any] = {}


def _init_worker(cfg: ServiceConfig, store_url: str, stop: multiprocessing.synchronize.Event,
                 level: int) -> None:
    # Ctrl-C reaches the whole process group; the parent alone decides, via ``stop``.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # blocked at spawn
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")
    _worker.update(cfg=cfg, url=store_url, stop=stop, store=None, artifacts={})


def _work(chunk: Chunk) -> ChunkResult:
    if _worker["store"] is None:
        store = open_store(_worker["url"])
        _worker["store"] = store
        # Close the connection when the worker exits: SQLite then checkpoints its WAL.
        multiprocessing.util.Finalize(None, store.close, exitpriority=10)
    artifacts: dict[str, Artifact] = _worker["artifacts"]
    path = chunk.job.artifact_path
    if path not in artifacts:
        artifacts[path] = Artifact.load(path)
    return run_chunk(_worker["cfg"], chunk, _worker["store"], artifacts[path], _worker["stop"])
