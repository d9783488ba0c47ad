"""One wake-up of paho's network thread per burst of messages, not one per message.

paho queues every packet handed to it from another thread (``publish``, ``ack``) and then
writes one byte to a socket pair to break its network thread out of ``select``. The daemon's
worker hands it two packets per reading (the reading's PUBACK and its estimate) and six per
twin on the grid: each was a ``send`` system call on the worker and a full loop iteration
(``select``, socket-pair read, write, housekeeping) on the network thread — about a quarter
of the worker's CPU and most of the network thread's at 1,000 twins
(``scripts/bench_daemon.py``, profiled with py-spy).

:class:`WakeCoalescer` replaces the socket pair's writing end with :class:`_Waker`, which
passes the byte on at once except on a thread inside :meth:`WakeCoalescer.held`: there the
first packet's wake-up is deferred until the block ends, or until the thread queues another
packet at least :data:`MAX_HOLD_SECONDS` after it. A packet therefore waits at most for the
rest of its block: the service's blocks are one worker batch (at most a queue batch of
readings and one slice of grid work), a few milliseconds.
Every other thread (the network thread itself, the main thread's status messages) wakes it
as before. It relies on paho's ``_sockpairW`` attribute (paho-mqtt 2.x); without it
:meth:`WakeCoalescer.install` returns False and the client works unchanged.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import paho.mqtt.client as mqtt

#: The longest a packet queued inside :meth:`WakeCoalescer.held` waits before the network
#: thread is woken for it [s]: small against the 100 ms latency budget, long enough to
#: gather a reading's ack and estimate with the next readings' when they come in a burst.
MAX_HOLD_SECONDS = 0.005


class _Hold(threading.local):
    depth = 0
    since: float | None = None  # when the first unsent wake-up of this hold was deferred


class _Waker:
    """The socket pair's writing end as paho sees it (``send`` and ``close`` only)."""

    def __init__(self, sock: socket.socket, hold: _Hold) -> None:
        self.sock = sock
        self.hold = hold

    def send(self, data: bytes) -> int:
        h = self.hold
        if h.depth:
            now = time.monotonic()
            if h.since is None:
                h.since = now
                return len(data)
            if now - h.since < MAX_HOLD_SECONDS:
                return len(data)
            h.since = None
        return self.sock.send(data)

    def wake(self) -> None:
        try:
            self.sock.send(b"0")
        except (BlockingIOError, OSError):
            pass  # full: the network thread is awake already; closed: the client stopped

    def close(self) -> None:
        self.sock.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.sock, name)


class WakeCoalescer:
    """Defers paho's network-thread wake-ups within :meth:`held` blocks of one thread."""

    def __init__(self, client: mqtt.Client) -> None:
        self.client = client
        self._hold = _Hold()
        self._waker: _Waker | None = None

    def install(self) -> bool:
        """Call after ``loop_start`` (which creates the socket pair; it lives as long as the
        network thread). False when this paho has no socket pair to wrap."""
        w = getattr(self.client, "_sockpairW", None)
        if isinstance(w, _Waker):
            return True
        if not isinstance(w, socket.socket):
            return False
        self._waker = _Waker(w, self._hold)
        self.client._sockpairW = self._waker  # type: ignore[assignment]  # noqa: SLF001
        return True

    def flush(self) -> None:
        """Wake the network thread now for the packets this thread's hold has deferred (the
        estimates of a batch, before the worker blocks on the journal's fsync); the hold
        goes on for the packets after."""
        h = self._hold
        if h.since is not None:
            h.since = None
            if self._waker is not None:
                self._waker.wake()

    @contextmanager
    def held(self) -> Iterator[None]:
        """Packets queued by this thread inside wake the network thread once, at the end
        (or after :data:`MAX_HOLD_SECONDS`). Nests."""
        h = self._hold
        h.depth += 1
        try:
            yield
        finally:
            h.depth -= 1
            if not h.depth and h.since is not None:
                h.since = None
                if self._waker is not None:
                    self._waker.wake()
