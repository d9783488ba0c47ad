"""The bridge's outbox: every reading on disk before MQTT has it, until the broker
acknowledged it (``[bridge] spool_dir``).

paho keeps QoS 1 messages the broker has not acknowledged in memory only: a restart of the
bridge during a broker outage lost them, and beyond ``queue_size`` the bridge could only keep
each sensor's newest reading. With an outbox the publisher appends each batch of readings to
a spool file (:class:`pseudotwin.edge.spool.Spool`, fsynced unless ``spool_fsync = false``)
first, then hands to paho only as many as ``queue_size`` allows; the rest wait in the file,
in order, and go out as the broker acknowledges earlier ones. The spool's mark (the byte
offset up to which every reading was acknowledged) moves with the acknowledgements, at most
every ``MARK_SECONDS``; a restart sends everything after it again. The daemon and the
recorder keep a reading once, so a resent one costs nothing (at-least-once delivery).

Offsets, all in bytes of the spool file: ``acked_to`` ≤ ``cursor`` ≤ ``end``: everything
before ``acked_to`` was acknowledged, before ``cursor`` handed to paho, before ``end`` written.
Used by the publisher thread only (and by ``Bridge.stop`` once it has ended).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path

from pseudotwin.edge.spool import Spool
from pseudotwin.edge.statelock import StateLock
from pseudotwin.errors import ConfigError
from pseudotwin.live.readings import Reading

log = logging.getLogger(__package__)

#: What two bridges on one spool would do to each other (the lock's message).
CONFLICT = ("two bridges with one client id on one spool would share the broker session, "
            "each knocking the other off, and one spool of readings; stop it, or give this "
            "one its own bridge.client_id")

#: How often the acknowledged offset is written to the mark file at most [s]: a crash
#: resends at most this much of what was acknowledged.
MARK_SECONDS = 1.0
#: The acknowledged part of the spool is cut off once it is this long [bytes] and nothing
#: waits to be sent (the few readings still in flight are copied to the new file), and at
#: every clean stop: not at every batch, which would make and delete a file each.
COMPACT_BYTES = 1 << 20


class Outbox:
    """The spool file ``path`` of one bridge and where its readings stand."""

    def __init__(self, path: Path, fsync: bool = True) -> None:
        """Lock the spool against a second bridge on it (StateInUseError), open it and pick
        up what an earlier run left unacknowledged; ConfigError when the folder cannot be
        made or written."""
        self.lock = StateLock(path.with_suffix(".lock"), "bridge", CONFLICT)
        self.lock.acquire()
        try:
            self.spool = Spool(path, durable=fsync)
            self.spool.add([])  # the file, writable (and synced): found now, not mid-outage
        except OSError as exc:
            self.lock.release()
            raise ConfigError(f"{path}: the bridge's spool cannot be written "
                              f"({exc.strerror or exc}); is its folder (bridge.spool_dir, by "
                              "default the daemon's state_dir) another user's?") from None
        self.end = self.spool.size()
        self.acked_to = self.cursor = self.mark = self.spool.consumed()
        if self.mark > self.end:  # a mark of another file (the spool replaced by hand)
            self.acked_to = self.cursor = self.mark = 0
        # (mid, end offset) of each reading handed to paho and not settled, in spool order;
        # mid None: a line with nothing to wait for (unreadable, or of an unknown sensor)
        self._sent: deque[tuple[int | None, int]] = deque()
        self._mark_at = time.monotonic()
        self._mark_failing = False

    @property
    def path(self) -> Path:
        return self.spool.path

    @property
    def busy(self) -> bool:
        """Whether readings wait to be sent, or sent ones for their acknowledgement."""
        return self.cursor < self.end or bool(self._sent) or self.mark < self.acked_to

    def unsent_count(self) -> int:
        """Lines written but not handed to paho yet: counted, not decoded (a week's outage
        is millions of them)."""
        count, left = 0, self.end - self.cursor
        if left <= 0:
            return 0
        with open(self.path, "rb") as fh:
            fh.seek(self.cursor)
            while left > 0 and (block := fh.read(min(left, 1 << 20))):
                count += block.count(b"\n")
                left -= len(block)
        return count

    def in_flight(self) -> set[int]:
        """The mids of the readings handed to paho that are not settled yet."""
        return {mid for mid, _ in self._sent if mid is not None}

    def add(self, readings: list[Reading]) -> list[tuple[int, int]]:
        """Write ``readings`` (synced with spool_fsync); each one's (start, end) byte
        offsets. OSError when the disk refuses them (nothing counts as written then)."""
        remade, lines = self.spool.add(readings)
        size = self.spool.size()
        lengths = [len(line) for line in lines]
        start = size - sum(lengths)
        if remade or start < self.end:
            # The file is not the one written so far (deleted, or cut, by someone else):
            # what it held unsent is gone; go on from the new readings.
            log.error("the spool %s was deleted or cut short while the bridge ran; what "
                      "it held not yet sent (%d bytes) went with it", self.path,
                      max(0, self.end - self.cursor))
            if remade:
                self.lock.renew()
            self._sent.clear()
            self.acked_to = self.cursor = self.mark = start
            self.spool.consume(start)
        spans = []
        for n in lengths:
            spans.append((start, start + n))
            start += n
        self.end = size
        return spans

    def unsent(self) -> Iterator[tuple[Reading | None, int]]:
        """The readings written and not handed to paho yet, in order, each with the offset
        its line ends at (None: an unreadable line, logged)."""
        for reading, end in self.spool.lines(self.cursor):
            if end > self.end:
                return
            yield reading, end

    def sent(self, mid: int | None, end: int) -> None:
        """The reading whose line ends at ``end`` went to paho as message ``mid`` (None:
        skipped, nothing to wait for)."""
        self._sent.append((mid, end))
        self.cursor = end

    def settle(self, pending: Callable[[int], bool], force: bool = False) -> None:
        """Move the acknowledged offset past every leading reading whose message is no
        longer ``pending``; write the mark when ``MARK_SECONDS`` have passed (or ``force``);
        empty the spool when all of it was acknowledged and it has grown long (or
        ``force``), and cut off its acknowledged part when that is long and nothing waits to
        be sent. A reused mid of a newer message only holds the offset back a while."""
        while self._sent and (self._sent[0][0] is None or not pending(self._sent[0][0])):
            self.acked_to = self._sent.popleft()[1]
        now = time.monotonic()
        done = self.acked_to == self.end and not self._sent
        try:
            if done and self.end > 0 and (force or self.end >= COMPACT_BYTES):
                self.spool.clear()
                self.end = self.cursor = self.acked_to = self.mark = 0
                self._mark_at = now
            elif self.acked_to >= COMPACT_BYTES and self.cursor == self.end:
                # Readings keep coming faster than acks: a moment with all of them
                # acknowledged may never come, so the few in flight move to a new file.
                cut = self.acked_to
                self.spool.keep_from(cut)
                self._sent = deque((mid, end - cut) for mid, end in self._sent)
                self.end -= cut
                self.cursor -= cut
                self.acked_to = self.mark = 0
                self._mark_at = now
            elif self.acked_to > self.mark and (force or now - self._mark_at >= MARK_SECONDS):
                self.spool.consume(self.acked_to)
                self.mark = self.acked_to
                self._mark_at = now
            else:
                return
        except OSError as exc:  # tried again at the next settle; said once
            if not self._mark_failing:
                log.error("cannot mark the spool %s as acknowledged (%s); a restart would "
                          "send those readings again", self.path, exc)
            self._mark_failing = True
            return
        if self._mark_failing:
            log.info("the spool %s can be marked again", self.path)
            self._mark_failing = False

    def waiting(self, pending: Callable[[int], bool]) -> int:
        """Readings not acknowledged yet: handed to paho and pending, and not yet sent."""
        in_flight = sum(1 for mid, _ in self._sent if mid is not None and pending(mid))
        return in_flight + self.unsent_count()

    def close(self) -> None:
        self.lock.release()
