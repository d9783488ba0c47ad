"""One reading per JSON line: the on-disk format of the daemon's journal and the recorder's
spool (``{"sensor": …, "ts": ISO 8601 with offset, "value": …}``)."""

from __future__ import annotations

import datetime as dt
import errno
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import BinaryIO

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


def append(path: Path, readings: Iterable[Reading]) -> list[bytes]:
    """Append one line per reading to the file at ``path`` (created if need be) and return
    the lines. A last line cut short by a crash or a full disk is ended first: the next
    reading is never glued onto it and lost with it. OSError when the write falls short."""
    lines = encode(readings)
    block = b"".join(lines)
    with open(path, "a+b") as fh:
        if torn(fh):
            block = b"\n" + block
        if fh.write(block) != len(block):
            raise OSError(errno.ENOSPC, f"short write to {path}")
    return lines


def sync_file(path: Path, folder: bool = True) -> None:
    """Put what was written to the file at ``path`` on disk (fsync), and with ``folder`` its
    directory entry (needed once, after the file was made): a power cut then loses none."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    if folder:
        sync_folder(path.parent)


def sync_folder(folder: Path) -> None:
    """fsync a folder: a file created in it survives a power cut only once its directory
    entry is on disk too."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def torn(fh: BinaryIO) -> bool:
    """Whether the open file's last line is cut short (a crash or a full disk mid-write):
    the next line must not be glued onto it. Reads one byte, without moving ``fh``."""
    fd = fh.fileno()
    size = os.fstat(fd).st_size
    return size > 0 and os.pread(fd, 1, size - 1) != b"\n"
