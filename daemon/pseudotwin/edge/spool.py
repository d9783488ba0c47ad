"""Readings waiting on disk for whoever takes them next: the recorder's history store, the
bridge's broker.

One reading per JSON line (:mod:`pseudotwin.edge.readinglines`), appended. What was taken
already is not cut off the file (a copy of the rest each time would be quadratic in a long
spool) but marked by the byte offset it ends at, in a file beside it (``<name>.offset``).
After a crash between a take and its mark, a piece is taken again: both takers keep a
reading once (the store is keyed, the daemon drops a duplicate).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

from pseudotwin.core.files import write_replacing
from pseudotwin.edge import readinglines
from pseudotwin.live.readings import Reading

log = logging.getLogger(__name__)


class Spool:
    """The spool file ``path`` and its mark.

    durable: what :meth:`add` returns from is on disk (fsync), the directory entries that
    keep the file included: a power cut loses none of it. Otherwise it is in the kernel.
    """

    def __init__(self, path: Path, durable: bool = False) -> None:
        self.path = path
        self.offset_path = path.with_name(path.name + ".offset")
        self.durable = durable
        # Directory entries not known to be on disk, synced once at the first sync: the
        # file's and its folder's (either may be new, made by an earlier run that never
        # synced, or by a lock file just before this).
        self._entry_unsynced = self._folder_entry_unsynced = True
        self._remade = False  # the folder made again since the last add, by a mark
        path.parent.mkdir(parents=True, exist_ok=True)

    def add(self, readings: list[Reading]) -> tuple[bool, list[bytes]]:
        """Append ``readings`` (synced when durable); whether the folder had to be made
        again (the state dir was deleted under a running process: it spools all the same),
        and the lines written. OSError when they may not be (all) written or synced."""
        made, self._remade = self._remade or not self.path.parent.is_dir(), False
        if made:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._folder_entry_unsynced = True
        if not self.path.exists():
            self._entry_unsynced = True
            # A mark without its file (a clear() whose two unlinks reached the disk in the
            # other order) would skip the new file's first lines.
            self.offset_path.unlink(missing_ok=True)
        lines = readinglines.append(self.path, readings)  # a torn last line is ended first
        if self.durable:
            self.sync()
        return made, lines

    def size(self) -> int:
        """The file's length in bytes (0 when there is none): where the next line starts."""
        try:
            return self.path.stat().st_size
        except FileNotFoundError:
            return 0

    def sync(self) -> None:
        """Put what was added on disk (fsync), and the directory entries not known to be
        there yet: the file's and its folder's at the first call, the file's again after it
        was made again, its folder's after that was. An entry whose sync failed is synced
        at the next call."""
        readinglines.sync_file(self.path, folder=False)
        if self._entry_unsynced:
            readinglines.sync_folder(self.path.parent)
            self._entry_unsynced = False
        if self._folder_entry_unsynced:
            readinglines.sync_folder(self.path.parent.parent)
            self._folder_entry_unsynced = False

    def consumed(self) -> int:
        """Bytes at the spool's start that were taken (0: none, or no mark)."""
        try:
            return max(0, int(self.offset_path.read_text(encoding="ascii")))
        except (OSError, ValueError):
            return 0

    def lines(self, start: int) -> Iterator[tuple[Reading | None, int]]:
        """Each line from byte ``start`` on, in file order: its reading (None when the line
        is unreadable, logged) and the byte offset where it ends."""
        if not self.path.exists():
            return
        with open(self.path, "rb") as fh:  # bytes: invalid UTF-8 is one bad line
            fh.seek(start)
            while line := fh.readline():
                try:
                    reading: Reading | None = readinglines.decode(line)
                except ValueError:
                    log.warning("%s: a line is unreadable (cut short by a crash?), skipped",
                                self.path)
                    reading = None
                yield reading, fh.tell()

    def chunks(self, size: int, start: int | None = None
               ) -> Iterator[tuple[list[Reading], int]]:
        """The readings from byte ``start`` on (default: the first not taken), in file
        order, ``size`` at a time, each piece with the byte offset where it ends (for
        :meth:`consume`)."""
        out: list[Reading] = []
        end = 0
        for reading, end in self.lines(self.consumed() if start is None else start):
            if reading is not None:
                out.append(reading)
            if len(out) >= size:
                yield out, end
                out = []
        if out:
            yield out, end

    def load(self) -> list[Reading]:
        return [r for piece, _ in self.chunks(10_000) for r in piece]

    def consume(self, offset: int) -> None:
        """Mark the spool's first ``offset`` bytes as taken."""
        if not self.path.parent.is_dir():  # deleted: the mark makes it again, say so at add
            self._remade = self._folder_entry_unsynced = True
        text = str(offset)
        write_replacing(self.offset_path, lambda tmp: tmp.write_text(text, encoding="ascii"),
                        follow_symlinks=False)

    def keep_from(self, offset: int) -> None:
        """Cut the spool's first ``offset`` bytes off: the rest, copied to a new file that
        replaces it (synced first when durable), starts at 0 and nothing of it is
        marked taken. The mark goes first: a crash in between leaves the old file taken
        again whole, never an old mark that would skip the new file's first lines."""
        self.offset_path.unlink(missing_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.tmp{os.getpid()}")
        try:
            with open(self.path, "rb") as src, open(tmp, "wb") as dst:
                src.seek(offset)
                while block := src.read(1 << 20):
                    dst.write(block)
                if self.durable:
                    dst.flush()
                    os.fsync(dst.fileno())
            os.replace(tmp, self.path)
        finally:
            tmp.unlink(missing_ok=True)
        self._entry_unsynced = True  # a new file
        if self.durable:
            try:
                self.sync()
            except OSError as exc:
                # The cut is done: raising would have the caller (offsets unmoved) cut again.
                # The next add syncs the entry before it returns; a power cut meanwhile
                # leaves the old file, whose lines go out again (at least once).
                log.warning("%s: cut, but its new directory entry is not synced yet (%s); "
                            "the next write tries again", self.path, exc)

    def clear(self) -> None:
        # The mark first: a crash in between leaves a spool taken again whole (kept once),
        # never a mark that would skip a new spool's first readings.
        self.offset_path.unlink(missing_ok=True)
        self.path.unlink(missing_ok=True)
