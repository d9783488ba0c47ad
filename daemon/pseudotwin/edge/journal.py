"""The daemon's checkpoint: an append-only journal of every accepted reading.

A twin's state is a pure function of the readings it was fed, so the checkpoint is those
readings: one JSON line each, in arrival order, one file per UTC day. Restarting replays the
last days' journals through fresh twins and arrives at exactly the state of a daemon that
never stopped. Each line is flushed before the MQTT message is acknowledged, so a SIGKILL loses
nothing: what was not journaled was not acknowledged, and the broker delivers it again. A
durable journal (``journal_fsync``, the default) is also on disk before the acknowledgement,
through one :meth:`Journal.sync` per batch of readings: a power cut loses nothing either.
"""

from __future__ import annotations

import datetime as dt
import errno
import functools
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO

from pseudotwin.core.files import write_replacing
from pseudotwin.edge import readinglines
from pseudotwin.live.readings import Reading

log = logging.getLogger(__name__)

KEEP_DAYS = 3


class Journal:
    def __init__(self, folder: Path, keep_days: int = KEEP_DAYS, durable: bool = False) -> None:
        """durable: :meth:`sync` puts what was written on disk (fsync), new files' directory
        entries included; without, it does nothing (lines reach the kernel, not the disk)."""
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.keep_days = keep_days
        self.durable = durable
        self._unsynced = False  # lines written to the current file since the last sync
        # Earlier days' files written since the last sync (a durable journal's stragglers),
        # and whether one of them was made new (its folder's entry to sync too).
        self._earlier: set[Path] = set()
        self._earlier_made = False
        self._day: dt.date | None = None
        self._fh: BinaryIO | None = None  # the current day's file: appended to, and read
        # The file before it (yesterday's carry-over), kept open: should the state dir be
        # deleted under us, both are rebuilt from their open descriptors (an unlinked file
        # stays readable through them), never from a copy of every line held in memory.
        self._prev: tuple[dt.date, BinaryIO] | None = None
        self._torn = False  # a write failed: end a torn last line before the next one
        self.recreated = 0  # times the journal file vanished and was rebuilt
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
        power loss; see fsync()). A failed write is retried on the next call (a torn line
        ended first), so a transient fault (full disk, a directory briefly unwritable) ends
        when it clears."""
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
            self._rebuild()
        assert self._fh is not None
        if self._torn:
            if readinglines.torn(self._fh):
                self._fh.write(b"\n")
            self._torn = False
        block = b"".join(readinglines.encode(readings))
        self._unsynced = True  # even a short write may have put part of a line there
        try:
            if self._fh.write(block) != len(block):
                raise OSError(errno.ENOSPC, "short write to the journal")
        except OSError:
            self._torn = True  # the next append ends a torn line first
            raise

    def _write_earlier(self, day: dt.date, readings: Sequence[Reading]) -> None:
        """Readings of a UTC day before the current file's (stamped before midnight, arriving
        after): appended to that day's file as they come, the current file staying open.
        Rotating back and forth re-read the whole of each file at every switch, which two
        sensors straddling midnight did at every reading."""
        if self._vanished():  # the state dir went: rebuild the files first
            self._rebuild()
        path = self._path(day)
        if self.durable:  # synced with the current file, at the next sync()
            self._earlier_made |= not path.exists()
            self._earlier.add(path)
        readinglines.append(path, readings)

    def _vanished(self) -> bool:
        """True when the open file is no longer the one at its path (deleted, replaced)."""
        assert self._fh is not None and self._day is not None
        try:
            st = os.stat(self._path(self._day))
        except FileNotFoundError:
            return True
        return (st.st_dev, st.st_ino) != self._identity

    def _rebuild(self) -> None:
        """The current file (or the whole state dir) was deleted while running: writing on
        into the unlinked file would lose everything at the next restart. Rebuild it, and
        the file before it, from their open descriptors; older days' files are gone."""
        assert self._fh is not None and self._day is not None
        self.folder.mkdir(parents=True, exist_ok=True)
        rebuilt: list[str] = []
        for d, fh in ((self._day, self._fh), *([self._prev] if self._prev else [])):
            path = self._path(d)
            if not path.exists():
                # Whole or not at all: a copy cut short (a full disk) must not stand at the
                # path, where the retry would take it for the rebuilt file. The descriptors
                # stay open until every copy is in place (OSError: the caller retries).
                size = os.fstat(fh.fileno()).st_size
                write_replacing(path, functools.partial(_copy_open, fh), follow_symlinks=False)
                rebuilt.append(f"{d} ({size / 1e3:.0f} kB)")
        if rebuilt:
            log.error("journal file %s was deleted while running (state dir removed?); "
                      "recreated it from the open files: %s; older days' journals are lost",
                      self._path(self._day), ", ".join(rebuilt))
            self.recreated += 1
        if self._prev is not None:  # its descriptor is of the deleted file now
            d, old = self._prev
            old.close()
            self._prev = (d, open(self._path(d), "rb"))  # noqa: SIM115
        day = self._day
        self._fh.close()
        self._fh, self._day = None, None
        self._open(day)
        if self.durable and rebuilt:  # the copies, and the folders' entries up to the
            assert self._fh is not None  # state dir's own (the whole of it may have gone)
            os.fsync(self._fh.fileno())
            if self._prev is not None:
                os.fsync(self._prev[1].fileno())
            readinglines.sync_folder(self.folder)
            readinglines.sync_folder(self.folder.parent)
            readinglines.sync_folder(self.folder.parent.parent)

    def fsync(self) -> None:
        if self._fh is not None:
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._unsynced = False

    def sync(self) -> bool:
        """A durable journal: what was appended since the last sync is on disk when this
        returns (OSError: maybe not). True when it had anything to sync."""
        if not (self.durable and (self._unsynced or self._earlier)):
            return False
        # Taken off first: a failed fsync is not retried (the kernel may have dropped the
        # pages it failed to write; the caller says so), and one failure must not stick.
        earlier, made = sorted(self._earlier), self._earlier_made
        self._earlier, self._earlier_made = set(), False
        for path in earlier:
            try:
                readinglines.sync_file(path, folder=False)
            except FileNotFoundError:  # pruned, or the state dir went: nothing to sync
                continue
        if made:
            readinglines.sync_folder(self.folder)
        if self._unsynced:
            self.fsync()
        return True

    def _rotate(self, day: dt.date) -> None:
        """Make ``day``'s file the current one; the current one becomes the file before."""
        if self._fh is not None and self._day is not None:
            self.fsync()
            self._set_prev((self._day, self._fh))
            self._fh, self._day = None, None
        self.folder.mkdir(parents=True, exist_ok=True)  # recreated if it was deleted
        self._open(day)
        before = day - dt.timedelta(days=1)
        if self._prev is None and self._path(before).exists():  # a start: the day before
            self._prev = (before, open(self._path(before), "rb"))  # noqa: SIM115
        self.prune(day)

    def _open(self, day: dt.date) -> None:
        created = self.durable and not self._path(day).exists()
        # never through a symlink planted in the state dir (a root daemon appended there)
        fd = os.open(self._path(day), os.O_RDWR | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW,
                     0o600)
        if created:  # the new day's file survives a power cut only with its folder's entry
            try:  # (and the folder with its own, should it have been made again just now)
                readinglines.sync_folder(self.folder)
                readinglines.sync_folder(self.folder.parent)
            except OSError:
                os.close(fd)
                raise
        fh = open(fd, "a+b", buffering=0)  # noqa: SIM115
        try:
            if readinglines.torn(fh):  # a crash cut the last line short: never glue the next
                fh.write(b"\n")        # one onto it
        except OSError:
            fh.close()
            raise
        # Only once the file is open: a failed open leaves the journal closed, not broken.
        self._fh, self._day, self._torn = fh, day, False
        own = os.fstat(fh.fileno())  # an open file keeps its identity: one stat per check
        self._identity = (own.st_dev, own.st_ino)

    def _set_prev(self, prev: tuple[dt.date, BinaryIO] | None) -> None:
        if self._prev is not None:
            self._prev[1].close()
        self._prev = prev

    def prune(self, today: dt.date) -> None:
        for p in self.folder.glob("*.jsonl"):
            try:
                d = dt.date.fromisoformat(p.stem)
            except ValueError:
                continue
            if (today - d).days >= self.keep_days:
                p.unlink(missing_ok=True)

    def close(self) -> None:
        try:
            if self._fh is not None:
                try:
                    self.fsync()
                finally:
                    self._fh.close()
                    self._fh = None
        finally:
            self._day = None
            self._set_prev(None)

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


def _copy_open(fh: BinaryIO, path: Path) -> None:
    """Copy everything in the open file ``fh`` (deleted or not) to a new file ``path``,
    in the kernel, without moving ``fh``; OSError if it falls short."""
    fd = fh.fileno()
    size = os.fstat(fd).st_size
    with open(path, "wb") as out:
        done = 0
        while done < size:
            sent = os.sendfile(out.fileno(), fd, done, size - done)
            if sent == 0:
                raise OSError(errno.EIO, f"journal copy ended at {done} of {size} bytes")
            done += sent
