"""The daemon's checkpoint: an append-only journal of every accepted reading.

A twin's state is a pure function of the readings it was fed, so the checkpoint is those
readings: one JSON line each, in arrival order, one file per UTC day. Restarting replays the
last days' journals through fresh twins and arrives at exactly the state of a daemon that
never stopped. Each line is flushed before the MQTT message is acknowledged, so a SIGKILL loses
nothing: what was not journaled was not acknowledged, and the broker delivers it again.
"""

from __future__ import annotations

import datetime as dt
import errno
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO

from pseudotwin.edge import readinglines
from pseudotwin.live.readings import Reading

log = logging.getLogger(__name__)

KEEP_DAYS = 3


class Journal:
    def __init__(self, folder: Path, keep_days: int = KEEP_DAYS) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.keep_days = keep_days
        self._day: dt.date | None = None
        self._fh: BinaryIO | None = None
        # The lines of the current file and of the one before (yesterday's carry-over), to
        # rebuild them if the state dir is deleted under us.
        self._lines: list[bytes] = []
        self._lines_day: dt.date | None = None
        self._prev: tuple[dt.date, list[bytes]] | None = None
        self.recreated = 0  # times the journal file vanished and was rebuilt from memory
        self._identity = (0, 0)  # (st_dev, st_ino) of the open file

    def _path(self, day: dt.date) -> Path:
        return self.folder / f"{day.isoformat()}.jsonl"

    def append(self, r: Reading) -> None:
        """Write one line, or raise OSError (nothing is then owed: the caller must not ack)."""
        self.append_many([r])

    def append_many(self, readings: Sequence[Reading]) -> None:
        """Write one line per reading, one system call per UTC day's file, or raise OSError
        (then none of them is owed: the caller acks none; lines written before a failure
        are written again by the retry, and a replay drops such duplicates).
        Unbuffered: the lines are in the kernel before the acks and survive SIGKILL (not
        power loss; see fsync()). After a failure the file is reopened on the next call, so a
        transient fault (full disk, a directory briefly unwritable) ends when it clears."""
        start = 0
        while start < len(readings):
            day = readings[start].ts.astimezone(dt.UTC).date()
            end = start + 1
            while end < len(readings) and readings[end].ts.astimezone(dt.UTC).date() == day:
                end += 1
            self._write_day(day, readings[start:end])
            start = end

    def _write_day(self, day: dt.date, readings: Sequence[Reading]) -> None:
        if self._day is not None and self._fh is not None and day < self._day:
            self._write_earlier(day, readings)
            return
        if day != self._day or self._fh is None:
            self._rotate(day)
        elif self._vanished():
            self._abandon()
            self._rotate(day)  # rebuilds the file from memory
        assert self._fh is not None
        lines = readinglines.encode(readings)
        block = b"".join(lines)
        try:
            if self._fh.write(block) != len(block):
                raise OSError(errno.ENOSPC, "short write to the journal")
        except OSError:
            self._abandon()  # the next append reopens (and ends a torn line first)
            raise
        self._lines.extend(lines)

    def _write_earlier(self, day: dt.date, readings: Sequence[Reading]) -> None:
        """Readings of a UTC day before the current file's (stamped before midnight, arriving
        after): appended to that day's file as they come, the current file staying open.
        Rotating back and forth re-read the whole of each file at every switch, which two
        sensors straddling midnight did at every reading."""
        if self._vanished():  # the state dir went: rebuild the files from memory first
            current = self._day
            assert current is not None
            self._abandon()
            self._rotate(current)
        lines = readinglines.append(self._path(day), readings)
        if self._prev is not None and self._prev[0] == day:
            self._prev[1].extend(lines)  # rebuildable as yesterday's file

    def _vanished(self) -> bool:
        """True when the open file is no longer the one at its path (deleted, replaced)."""
        assert self._fh is not None and self._day is not None
        try:
            st = os.stat(self._path(self._day))
        except FileNotFoundError:
            return True
        return (st.st_dev, st.st_ino) != self._identity

    def _abandon(self) -> None:
        if self._fh is not None:
            try:
                self._fh.close()
            except OSError:
                pass
        self._fh, self._day = None, None

    def fsync(self) -> None:
        if self._fh is not None:
            self._fh.flush()
            os.fsync(self._fh.fileno())

    def _rotate(self, day: dt.date) -> None:
        self.close()
        path = self._path(day)
        self.folder.mkdir(parents=True, exist_ok=True)  # recreated if it was deleted
        old = path.read_bytes() if path.exists() else b""
        if self._lines_day is not None and self._lines_day != day:
            self._prev = (self._lines_day, self._lines)  # the file before stays rebuildable
            self._lines, self._lines_day = [], None
        if not old and self._lines_day == day and self._lines:
            # The file (or the whole state dir) was deleted while running: writing on into
            # the unlinked file would lose everything at the next restart. Rebuild it, and
            # the file before it, from the lines held in memory; older ones are gone.
            restored = [(day, self._lines), *([self._prev] if self._prev else [])]
            for d, lines in restored:
                if not self._path(d).exists():
                    with open(self._path(d), "wb") as fresh:
                        fresh.write(b"".join(lines))
            log.error("journal file %s was deleted while running (state dir removed?); "
                      "recreated it from the %d readings held in memory (%s); older days' "
                      "journals are lost", path, sum(len(x) for _, x in restored),
                      ", ".join(str(d) for d, _ in restored))
            old = b"".join(self._lines)
            self.recreated += 1
        fh = open(path, "ab", buffering=0)  # noqa: SIM115
        if old and not old.endswith(b"\n"):  # a crash cut the last line short: never glue
            try:                               # the next one onto it
                fh.write(b"\n")
            except OSError:
                fh.close()
                raise
            old += b"\n"
        # Only once the file is open: a failed open leaves the journal closed, not broken.
        self._fh, self._day, self._lines_day = fh, day, day
        own = os.fstat(fh.fileno())  # an open file keeps its identity: one stat per check
        self._identity = (own.st_dev, own.st_ino)
        self._lines = old.splitlines(keepends=True)
        self.prune(day)

    def prune(self, today: dt.date) -> None:
        for p in self.folder.glob("*.jsonl"):
            try:
                d = dt.date.fromisoformat(p.stem)
            except ValueError:
                continue
            if (today - d).days >= self.keep_days:
                p.unlink(missing_ok=True)

    def close(self) -> None:
        if self._fh is not None:
            try:
                self.fsync()
            finally:
                self._fh.close()
                self._fh = None
        self._day = None

    def replay(self, since: dt.datetime) -> Iterator[Reading]:
        """Journaled readings of the files that may hold readings at or after ``since``."""
        first = since.astimezone(dt.UTC).date()
        for p in sorted(self.folder.glob("*.jsonl")):
            try:
                d = dt.date.fromisoformat(p.stem)
            except ValueError:
                continue
            if d < first:
                continue
            with open(p, "rb") as fh:  # bytes: invalid UTF-8 is one bad line, not a crash
                for n, line in enumerate(fh, 1):
                    try:
                        yield readinglines.decode(line)
                    except ValueError:
                        # A line cut short by a crash mid-write: everything before it counts.
                        log.warning("journal %s line %d unreadable, skipped", p.name, n)
