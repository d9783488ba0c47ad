"""One process per state dir: an exclusive lock held while a daemon or recorder runs.

Two daemons on one configuration share the broker's client id and the journal: the broker
hands the session from one to the other every time either reconnects (each knocks the other
off, forever), and both append to one journal. A second instance therefore refuses to start,
naming the first one's PID. The lock is ``flock`` on a file in the state dir, so it goes with
the process: a crashed daemon leaves a file, never a stale lock.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from pseudotwin.errors import ConfigError


class StateLock:
    """The lock file ``path`` (in a state dir) of one ``role`` (``daemon``, ``recorder``)."""

    def __init__(self, path: Path, role: str) -> None:
        self.path = path
        self.role = role
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock, or raise ConfigError naming the process that holds it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise ConfigError(
                f"{self.path.parent} is in use by another pseudotwin {self.role} (PID "
                f"{holder}): two on one state dir would share the broker session, each "
                f"knocking the other off, and one journal; stop it, or give this one its own "
                f"state_dir and client_id") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays, harmlessly
            self._fd = None
