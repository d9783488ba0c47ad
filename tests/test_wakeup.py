"""edge/wakeup.py: one wake-up of paho's network thread per burst, every message delivered."""

from __future__ import annotations

import socket
import threading
import time

from pseudotwin.edge.wakeup import MAX_HOLD_SECONDS, WakeCoalescer, _Hold, _Waker


def _drain(sock: socket.socket) -> int:
    got = 0
    while True:
        try:
            got += len(sock.recv(65536))
        except BlockingIOError:
            return got


def _coalesced() -> tuple[socket.socket, _Waker, WakeCoalescer]:
    """A non-blocking socket pair's reading end, and a coalescer wrapping its writing end as
    install() wraps paho's."""
    r, w = socket.socketpair()
    r.setblocking(False)
    w.setblocking(False)
    hold = _Hold()
    waker = _Waker(w, hold)
    coalescer = WakeCoalescer.__new__(WakeCoalescer)
    coalescer._hold, coalescer._waker = hold, waker
    return r, waker, coalescer


def test_a_held_burst_wakes_once_per_hold_interval_and_once_at_the_end() -> None:
    r, waker, coalescer = _coalesced()
    t0 = time.monotonic()
    with coalescer.held():
        for _ in range(200):
            waker.send(b"0")
        with coalescer.held():  # nested: only the outermost block ends the hold
            waker.send(b"0")
        assert _drain(r) <= 1 + (time.monotonic() - t0) / MAX_HOLD_SECONDS
    elapsed = time.monotonic() - t0
    woken = _drain(r)
    # at least the final wake-up; at most one per elapsed hold interval besides it
    assert 1 <= woken <= 2 + elapsed / MAX_HOLD_SECONDS
    assert woken < 201


def test_flush_wakes_for_what_the_hold_deferred_and_the_hold_goes_on() -> None:
    r, waker, coalescer = _coalesced()
    with coalescer.held():
        coalescer.flush()  # nothing deferred yet: no wake-up
        assert _drain(r) == 0
        waker.send(b"0")  # an estimate: deferred
        assert _drain(r) == 0
        coalescer.flush()  # before the worker blocks on the disk: out now
        assert _drain(r) == 1
        waker.send(b"0")  # the acks after: held again, to the end of the block
        assert _drain(r) == 0
    assert _drain(r) == 1


def test_other_threads_wake_at_once_while_one_holds() -> None:
    r, waker, coalescer = _coalesced()
    with coalescer.held():
        waker.send(b"0")  # deferred: this thread holds
        other = threading.Thread(target=lambda: [waker.send(b"0") for _ in range(3)])
        other.start()
        other.join()
        assert _drain(r) == 3
    assert _drain(r) == 1
    waker.send(b"0")  # outside any hold: passed on
    assert _drain(r) == 1


def test_held_messages_all_reach_the_broker(mqtt_client) -> None:
    sub = mqtt_client()
    sub.subscribe("wakeup/#", qos=1)
    pub = mqtt_client()
    coalescer = WakeCoalescer(pub.client)
    assert coalescer.install(), "paho-mqtt no longer has the socket pair edge/wakeup.py wraps"
    assert coalescer.install()  # idempotent: never wraps its own wrapper
    with coalescer.held():
        infos = [pub.client.publish(f"wakeup/{i % 3}", str(i), qos=i % 2) for i in range(300)]
    for info in infos:
        info.wait_for_publish(10)
    got = [int(sub.get().payload) for _ in range(300)]
    assert sorted(got) == list(range(300))  # the broker may interleave QoS 0 and QoS 1
