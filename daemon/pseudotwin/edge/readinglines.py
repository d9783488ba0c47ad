"""One reading per JSON line: the on-disk format of the daemon's journal and the recorder's
spool (``{"sensor": …, "ts": ISO 8601 with offset, "value": …}``)."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Iterable

from pseudotwin.live.readings import Reading


def encode(readings: Iterable[Reading]) -> list[bytes]:
    """One line per reading, newline included."""
    return [(json.dumps({"sensor": r.sensor, "ts": r.ts.isoformat(), "value": r.value})
             + "\n").encode() for r in readings]


def decode(line: bytes) -> Reading:
    """The reading of one line; ValueError when the line is not one (cut short by a crash,
    invalid UTF-8, a field missing or of the wrong type)."""
    try:
        o = json.loads(line)
        return Reading(o["sensor"], dt.datetime.fromisoformat(o["ts"]), float(o["value"]))
    except (ValueError, KeyError, TypeError) as exc:  # UnicodeDecodeError is a ValueError
        raise ValueError(f"not a reading line ({exc})") from None
