"""Long-lived objects out of the cyclic garbage collector's way.

A process that loads its modules and twins once and then allocates many short-lived objects
(a reading, an estimate, a row) triggers collections that traverse every object alive, the
imported numpy/scipy/pandas and the twins included. ``gc.freeze`` moves what is alive now
into a permanent generation that no collection traverses: the daemon's full collections over
a thousand twins stopped every thread for ~0.7 s, and a backfill in one process spent ~20 %
of its CPU in them (30 days of one twin: 6.0 s → 4.8–5.2 s). The backfill's worker processes
measured no gain (their work is the same, their heap smaller), so they do not freeze.

What is allocated later still gets collected, and a full collection holds every Python
thread: :func:`watch_full_collections` records each one longer than :data:`LONG_PAUSE_S`, and
:func:`log_long_collections` (called by the process's main loop, not inside the collection)
logs them, so a latency spike in a daemon's log has its cause next to it. It then freezes
what is alive (after a young collection, so young cycles are freed rather than frozen): most
of it survived the full collection, so it is long-lived (the state each twin builds at its
first readings, ~20 objects a twin: at 10,000 twins the full collections traversed 200k of
them for up to 214 ms, again and again). A frozen object is still freed when its last
reference goes; only a reference cycle that dies after it was frozen is not, so every
:data:`THAW_S` every frozen object goes back to the collector (``gc.unfreeze``), the startup
freeze's included: the next full collection frees such cycles, and whatever its length, what
it leaves is frozen again.
"""

from __future__ import annotations

import gc
import logging
import time
from collections import deque
from typing import Any

log = logging.getLogger(__name__)

#: A full collection holding the process for longer than this is logged [s].
LONG_PAUSE_S = 0.1
#: Frozen objects go back to the collector this often [s], so no dead cycle outlives a day.
THAW_S = 24 * 3600.0
#: The log line of one (scripts/bench_daemon.py counts them): pause [ms], tracked objects.
LONG_PAUSE_PATTERN = r"a full garbage collection took (\d+) ms\b.*?(\d+) tracked objects"


def freeze_long_lived() -> None:
    """Collect once, then exempt every object alive now from later collections. For the
    processes pseudotwin's commands own (daemon, recorder, backfill), after loading."""
    gc.collect()
    gc.freeze()


class _FullCollectionWatch:
    """A ``gc.callbacks`` entry timing generation-2 collections; the long ones wait in
    ``long`` as (pause [s], objects freed, tracked objects left) until logged."""

    def __init__(self, threshold_s: float) -> None:
        self.threshold_s = threshold_s
        self.long: deque[tuple[float, int, int]] = deque(maxlen=100)
        self._started: float | None = None
        self.full = 0  # full collections finished
        self.thawed_at = time.monotonic()  # the last gc.unfreeze (or the watch's start)
        self.thawed_after = 0  # ``full`` at the last gc.unfreeze
        self.refreeze = False  # freeze after the next full collection, however short

    def __call__(self, phase: str, info: dict[str, Any]) -> None:
        if info.get("generation") != 2:
            return
        if phase == "start":
            self._started = time.perf_counter()
        elif self._started is not None:
            pause = time.perf_counter() - self._started
            self._started = None
            self.full += 1
            if pause > self.threshold_s:
                # Counted after the pause was taken (a walk over what survived; a few ms).
                self.long.append((pause, int(info.get("collected", 0)),
                                  len(gc.get_objects(generation=2))))


def watch_full_collections(threshold_s: float = LONG_PAUSE_S) -> None:
    """Record every full collection that holds the process longer than ``threshold_s`` [s].
    Once per process; a second call changes nothing."""
    if _watch() is None:
        gc.callbacks.append(_FullCollectionWatch(threshold_s))


def log_long_collections(now: float | None = None) -> None:
    """Log the long full collections recorded since the last call (a warning each) and freeze
    what they left; every :data:`THAW_S` of ``now`` [s] (``time.monotonic``), unfreeze, and
    freeze again after the next full collection."""
    watch = _watch()
    if watch is None:
        return
    now = time.monotonic() if now is None else now
    # Not ``now - thawed_at >= THAW_S``: that difference of two large floats can round
    # below THAW_S when ``now`` is exactly thawed_at + THAW_S (the tests flaked with it).
    if now >= watch.thawed_at + THAW_S:
        log.info("%d frozen objects handed back to the garbage collector (every %.0f h)",
                 gc.get_freeze_count(), THAW_S / 3600)
        gc.unfreeze()
        watch.thawed_at, watch.thawed_after, watch.refreeze = now, watch.full, True
    logged = bool(watch.long)
    while watch.long:
        pause, freed, tracked = watch.long.popleft()
        log.warning("a full garbage collection took %.0f ms, holding every Python thread "
                    "(%d objects freed, %d tracked objects left)", pause * 1e3, freed, tracked)
    # Not before a full collection has passed over what a thaw handed back.
    if (logged or watch.refreeze) and watch.full > watch.thawed_after:
        gc.collect(1)
        gc.freeze()  # later full collections need not traverse the survivors again
        watch.refreeze = False


def _watch() -> _FullCollectionWatch | None:
    return next((cb for cb in gc.callbacks if isinstance(cb, _FullCollectionWatch)), None)
