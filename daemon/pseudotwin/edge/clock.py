"""The daemon's sense of time: the wall clock, or an accelerated replay clock.

Replay is a feature, not a test hack: ``pseudotwin run --replay-from T --speed 60`` runs the
daemon in a past day at 60× (the demo and the daemon benchmark use it), and everything that
reads the time — the publish grid, staleness, arrival stamps of bare-number payloads, the
future-skew check — reads it from here.
"""

from __future__ import annotations

import datetime as dt
import threading
import time
from typing import Protocol

#: Exit status of a long-running process that a restart may cure (sysexits EX_TEMPFAIL):
#: another process holds the state dir, or the clock went back past the daemon's grid.
EX_TEMPFAIL = 75


class Clock(Protocol):
    def now(self) -> dt.datetime:
        """The current instant (aware, UTC)."""

    def wait_until(self, instant: dt.datetime, stop: threading.Event) -> bool:
        """Sleep until ``instant``; False if ``stop`` was set first."""


class SystemClock:
    def now(self) -> dt.datetime:
        return dt.datetime.now(dt.UTC)

    def wait_until(self, instant: dt.datetime, stop: threading.Event) -> bool:
        while not stop.is_set():
            left = (instant - self.now()).total_seconds()
            if left <= 0:
                return True
            stop.wait(min(left, 5.0))  # re-read the clock: it may be stepped by NTP
        return False


class ReplayClock:
    """Time runs from ``start`` at ``speed`` × real time (monotonic underneath)."""

    def __init__(self, start: dt.datetime, speed: float = 1.0) -> None:
        if start.tzinfo is None:
            raise ValueError("replay start must be timezone-aware")
        if not speed > 0:
            raise ValueError("replay speed must be positive")
        self.start = start.astimezone(dt.UTC)
        self.speed = float(speed)
        self._t0 = time.monotonic()

    def now(self) -> dt.datetime:
        return self.start + dt.timedelta(seconds=(time.monotonic() - self._t0) * self.speed)

    def wait_until(self, instant: dt.datetime, stop: threading.Event) -> bool:
        while not stop.is_set():
            left = (instant - self.now()).total_seconds() / self.speed
            if left <= 0:
                return True
            stop.wait(min(left, 1.0))
        return False
