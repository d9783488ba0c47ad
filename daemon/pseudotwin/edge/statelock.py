"""One process per state dir: an exclusive lock held while a daemon or recorder runs.

Two daemons on one configuration share the broker's client id and the journal: the broker
hands the session from one to the other every time either reconnects (each knocks the other
off, forever), and both append to one journal. A second instance therefore refuses to start,
naming the first one's PID. The lock is ``flock`` on a file in the state dir, so it goes with
the process: a crashed daemon leaves a file, never a stale lock. On a file system without
``flock`` (some network mounts) the process runs unlocked and says so.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
from collections.abc import Callable
from pathlib import Path

from pseudotwin.errors import ConfigError, StateInUseError

log = logging.getLogger(__name__)

# flock is not offered here: run unlocked rather than not at all
_NO_FLOCK = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS}
#: What two daemons (or recorders) on one state dir would do to each other.
CONFLICT = ("two on one state dir would share the broker session, each knocking the other "
            "off, and one journal; stop it, or give this one its own state_dir and client_id")


class StateLock:
    """The lock file ``path`` (in a state dir) of one ``role`` (``daemon``, ``recorder``,
    ``bridge``); ``conflict``: what two of them would do to each other, and the way out."""

    def __init__(self, path: Path, role: str, conflict: str = CONFLICT) -> None:
        self.path = path
        self.role = role
        self.conflict = conflict
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock; StateInUseError naming the process that holds it, ConfigError
        when the lock file cannot be opened (the state dir's owner or file system)."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # never through a symlink planted there: a root daemon truncated its target
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        except OSError as exc:
            raise ConfigError(f"{self.path}: the {self.role}'s lock file cannot be opened "
                              f"({exc.strerror or exc}); is the state dir another user's? "
                              "(chown it to the service's user)") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise StateInUseError(
                f"{self.path.parent} is in use by another pseudotwin {self.role} (PID "
                f"{holder}): {self.conflict}") from None
        except OSError as exc:
            os.close(fd)
            if exc.errno not in _NO_FLOCK:
                raise ConfigError(f"{self.path}: cannot lock ({exc.strerror or exc})") from None
            log.warning("%s: the file system offers no flock (%s); running without the lock "
                        "that keeps a second %s off this state dir", self.path,
                        exc.strerror or exc, self.role)
            return
        try:  # the PID is for the message above only: a failure here costs nothing else
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError:
            pass
        self._fd = fd

    def starting(self, start: Callable[[], None], undo: Callable[[], None]) -> None:
        """Take the lock, then ``start``; if that fails anywhere, ``undo`` what it may have
        begun and let the lock go (an in-process caller may try again)."""
        self.acquire()
        try:
            start()
        except BaseException:
            undo()
            self.release()
            raise

    def renew(self) -> None:
        """Lock the file at ``path`` again when it is no longer the one held (the state dir
        was deleted while running, and rebuilt): else a second process could take a fresh
        lock file there. Logs, never raises: the running process keeps running."""
        if self._fd is None:
            return
        try:
            held, there = os.fstat(self._fd), os.stat(self.path)
            if (held.st_dev, held.st_ino) == (there.st_dev, there.st_ino):
                return
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("%s: cannot check the lock file (%s)", self.path, exc)
            return
        self.release()
        try:
            self.acquire()
        except (StateInUseError, ConfigError) as exc:
            log.error("the %s's lock could not be renewed after its state dir was rebuilt: "
                      "%s", self.role, exc)
        else:
            log.warning("%s: lock file renewed (the state dir was rebuilt)", self.path)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays, harmlessly
            self._fd = None
