"""The daemon's own health: can it journal (and so acknowledge), and is it keeping up.

Two things a daemon must *say* rather than suffer in silence (issue 13):

- **The journal cannot be written** (full disk, state dir unwritable): a reading is
  acknowledged only once journaled, so the daemon stops acknowledging. :class:`Health`
  logs it once with the reason, publishes ``<base>/status`` = ``degraded`` (retained), shows
  it in every ``<twin>/monitor`` (``health``) and logs the recovery with its duration.
- **A flood**: the broker hands the daemon at most its in-flight window of unacknowledged
  QoS 1 messages (mosquitto ``max_inflight_messages``); the rest waits in the broker's queue
  for the session, which drops beyond ``max_queued_messages`` *without telling the
  subscriber*. The daemon cannot see that queue, but it can see the symptom: its own queue
  never runs empty (it processes as fast as it can and more is always waiting). After
  :data:`BACKLOG_SECONDS` of that it logs rate, lag and the suspicion, every
  :data:`REPORT_SECONDS` while it lasts, and once when it is over.

Thread use: ``received`` is bumped on the MQTT network thread (an int increment under the
GIL); everything else runs on the worker.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger("pseudotwin.edge.service")

REPORT_SECONDS = 10.0
BACKLOG_SECONDS = 10.0


class Health:
    def __init__(self, set_status: Callable[[str], None], queue_max: int) -> None:
        self._set_status = set_status
        self.queue_max = queue_max
        self.report_seconds = REPORT_SECONDS
        self.backlog_seconds = BACKLOG_SECONDS
        # journal
        self.journal_failing_since: float | None = None
        self.journal_failures = 0  # readings not acknowledged because the journal failed
        self.journal_error = ""
        self.degraded_episodes = 0
        self.last_recovery_s: float | None = None
        self.journal_recreated = 0  # the state dir was deleted under us (journal.py logs it)
        # ingest
        self.received = 0
        self.processed = 0
        self.max_queue = 0
        self._window_start = time.monotonic()
        self._window_in = 0
        self._window_done = 0
        self._lags: list[float] = []
        self._busy_since: float | None = None
        self.backlog_reports = 0
        self.last_rates: dict[str, Any] = {}

    @property
    def status(self) -> str:
        return "degraded" if self.journal_failing_since is not None else "online"

    # -- journal --------------------------------------------------------------------------
    def journal_failed(self, exc: BaseException, held: int) -> None:
        self.journal_failures += 1
        self.journal_error = str(exc)
        if self.journal_failing_since is None:
            self.journal_failing_since = time.monotonic()
            self.degraded_episodes += 1
            log.error("journal cannot be written (%s): readings are NOT acknowledged until it "
                      "can (the broker keeps them); status degraded; retrying", exc)
            self._set_status("degraded")
        elif self.journal_failures % 100 == 0:
            log.error("journal still cannot be written (%s): %d readings held, %d failures",
                      exc, held, self.journal_failures)

    def journal_ok(self, recovered: int) -> None:
        if self.journal_failing_since is None:
            return
        self.last_recovery_s = time.monotonic() - self.journal_failing_since
        self.journal_failing_since = None
        log.warning("journal writable again after %.1f s: %d held readings journaled and "
                    "acknowledged; status online", self.last_recovery_s, recovered)
        self._set_status("online")

    def journal_rebuilt(self, times: int) -> None:
        self.journal_recreated = times

    # -- ingest ---------------------------------------------------------------------------
    def processed_one(self, lag_s: float | None, queued: int) -> None:
        """One message done; ``lag_s``: the daemon's clock minus the reading's time."""
        self.processed += 1
        self._window_done += 1
        if lag_s is not None:
            self._lags.append(lag_s)
        self.max_queue = max(self.max_queue, queued)
        now = time.monotonic()
        if queued == 0:
            self.idle(now)
        elif self._busy_since is None:
            self._busy_since = now
        self.maybe_report(now)

    def idle(self, now: float | None = None) -> None:
        if self._busy_since is not None and self.backlog_reports:
            log.warning("backlog cleared after %.0f s", (now or time.monotonic())
                        - self._busy_since)
            self.backlog_reports = 0
        self._busy_since = None

    def maybe_report(self, now: float) -> None:
        span = now - self._window_start
        if span < self.report_seconds:
            return
        lags = sorted(self._lags)
        self.last_rates = {
            "in_per_s": round((self.received - self._window_in) / span, 1),
            "done_per_s": round(self._window_done / span, 1),
            "lag_s_median": round(lags[len(lags) // 2], 1) if lags else None,
            "lag_s_max": round(lags[-1], 1) if lags else None,
        }
        self._window_start, self._window_in, self._window_done = now, self.received, 0
        self._lags = []
        if self._busy_since is not None and now - self._busy_since >= self.backlog_seconds:
            self.backlog_reports += 1
            r = self.last_rates
            log.warning(
                "flood: behind for %.0f s — %.0f msgs/s arriving, %.0f/s processed, reading "
                "lag median %s s, max %s s; the broker queues the rest for this session and "
                "DROPS what exceeds its max_queued_messages: readings are probably being lost "
                "(see deploy/mosquitto.conf)", now - self._busy_since, r["in_per_s"],
                r["done_per_s"], r["lag_s_median"], r["lag_s_max"])

    def snapshot(self, now: float | None = None) -> dict[str, Any]:
        """The ``health`` part of the monitor payload, its rates over the last full report
        window (``now`` [monotonic s], default the time): computed here too, since only a
        message computed them, and with none arriving they stayed those of the last busy
        minute."""
        self.maybe_report(time.monotonic() if now is None else now)
        failing = self.journal_failing_since
        return {
            "status": self.status,
            "journal": {
                "ok": failing is None,
                "failing_for_s": None if failing is None else round(time.monotonic() - failing, 1),
                "failures": self.journal_failures,
                "last_error": self.journal_error or None,
                "last_recovery_s": self.last_recovery_s,
                "recreated": self.journal_recreated,
            },
            "ingest": {
                "received": self.received, "processed": self.processed,
                "queue_max_seen": self.max_queue, "queue_bound": self.queue_max,
                "backlog": self._busy_since is not None
                and time.monotonic() - self._busy_since >= self.backlog_seconds,
                **self.last_rates,
            },
        }
