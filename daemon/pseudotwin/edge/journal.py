"""The daemon's checkpoint: an append-only journal of every accepted reading.

A twin's state is a pure function of the readings it was fed, so the checkpoint is those
readings: one JSON line each, in arrival order, one file per UTC day. Restarting replays the
last days' journals through fresh twins and arrives at exactly the state of a daemon that
never stopped. Each line is flushed before the MQTT message is acknowledged, so a SIGKILL loses
nothing: what was not journaled was not acknowledged, and the broker delivers it again.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path

from pseudotwin.live.readings import Reading

log = logging.getLogger(__name__)

KEEP_DAYS = 3


class Journal:
    def __init__(self, folder: Path, keep_days: int = KEEP_DAYS) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.keep_days = keep_days
        self._day: dt.date | None = None
        self._fh = None

    def _path(self, day: dt.date) -> Path:
        return self.folder / f"{day.isoformat()}.jsonl"

    def append(self, r: Reading) -> None:
        day = r.ts.astimezone(dt.UTC).date()
        if day != self._day:
            self._rotate(day)
        line = json.dumps({"sensor": r.sensor, "ts": r.ts.isoformat(), "value": r.value})
        self._fh.write(line + "\n")
        # Into the kernel before the ack: survives SIGKILL (not power loss; see fsync()).
        self._fh.flush()

    def fsync(self) -> None:
        if self._fh is not None:
            self._fh.flush()
            os.fsync(self._fh.fileno())

    def _rotate(self, day: dt.date) -> None:
        self.close()
        self._day = day
        path = self._path(day)
        torn = path.exists() and path.stat().st_size and not path.read_bytes().endswith(b"\n")
        self._fh = open(path, "a", encoding="utf-8")  # noqa: SIM115
        if torn:  # a crash cut the last line short: never glue the next one onto it
            self._fh.write("\n")
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
            self.fsync()
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
            with open(p, encoding="utf-8") as fh:
                for n, line in enumerate(fh, 1):
                    try:
                        o = json.loads(line)
                        yield Reading(o["sensor"], dt.datetime.fromisoformat(o["ts"]),
                                      float(o["value"]))
                    except (ValueError, KeyError, TypeError):
                        # A line cut short by a crash mid-write: everything before it counts.
                        log.warning("journal %s line %d unreadable, skipped", p.name, n)
