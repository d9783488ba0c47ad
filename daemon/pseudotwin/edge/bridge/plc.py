"""The PLC bridge at runtime: ADS device notifications of configured PLC symbols → MQTT
sensor readings.

``pseudotwin bridge --config FILE`` (:mod:`pseudotwin.cli.bridge`) runs it. Per configured
symbol the bridge registers an ADS device notification (transmission mode "on change") and
publishes every change as one reading on the topic of the symbol's sensor, in that sensor's
payload format (:func:`pseudotwin.edge.replay.payload_for`), QoS 1. The reading's time is
the FILETIME stamp the PLC puts on the notification, so a reading delayed by a slow network
or a broker outage still carries the instant the PLC saw the value.

Threads, and why:

- the ADS notification thread (adslib's dispatcher; pyads' test server calls it from its
  connection thread) runs :meth:`Bridge._on_notification`: decode, timestamp, ``put_nowait``
  on a bounded queue and nothing else. It must never block: a blocked dispatcher delays
  every other symbol's notifications, and on a full queue dropping (counted, logged) is
  better than stalling the PLC link;
- one publisher thread turns queue items into MQTT messages (paho keeps QoS 1 messages that
  cannot be sent right now and sends them after the broker reconnect). At most
  ``queue_size`` readings wait for the broker; beyond that the publisher holds back only the
  newest reading of each sensor and sends it as soon as there is room again, so after a
  long broker outage the daemon gets every sensor's current value, not the outage's first
  hours only (the readings in between are dropped and counted). With a spool
  (``[bridge] spool_dir``, :mod:`pseudotwin.edge.bridge.outbox`) nothing is dropped for want
  of room in paho's queue: every reading is on disk before paho has it, those beyond
  ``queue_size`` wait there in order, and a restart sends again what the broker had not
  acknowledged. The status messages have
  room of their own in paho's queue, so a full queue never leaves ``offline`` retained;
- paho's network thread (``loop_start``), which also reconnects to the broker by itself;
- one supervisor thread owns the ADS connection: connect, validate the symbols, register the
  notifications, publish each symbol's current value (the first notification, which a
  TwinCAT runtime sends at registration, or else a read), then poll ``read_state`` every
  ``poll_seconds``. ADS has no heartbeat: without the poll, a dropped route or a PLC stopped
  by its operator would just look like values that never change. On failure it tears the
  connection down and reconnects with exponential backoff (1 s doubling up to
  ``reconnect_max_seconds``), re-registering every notification.

Outputs besides the readings (retained, QoS 1):

- ``<base_topic>/bridge/status``: ``online``; the MQTT last will sets ``offline``;
- ``<base_topic>/bridge/plc``: ``up`` while the PLC is connected, in RUN and its
  notifications are registered, ``down`` otherwise.

Configuration problems found on the PLC itself (an unknown symbol, a symbol whose PLC type
differs from ``plc_type``) are fatal at the first successful connection: the bridge stops and
``pseudotwin bridge`` exits with 78 (EX_CONFIG), so systemd does not restart it in a loop. If
they appear only after a later reconnect (a PLC program changed under a running bridge), the
affected symbols are skipped with an error in the log, the others keep working, and the
skipped ones are looked for again every ``SYMBOL_RETRY_SECONDS`` while the link is up.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import queue
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import paho.mqtt.client as mqtt
import pyads
from paho.mqtt.enums import CallbackAPIVersion
from pyads import constants as adsc
from pyads.structs import SAdsSymbolEntry

from pseudotwin.config import ConfigProblems, SensorConfig
from pseudotwin.core.logpace import doubled
from pseudotwin.edge.bridge.config import (
    ADS_TCP_PORT,
    NON_NUMERIC_TYPES,
    PLC_TYPES,
    BridgeConfig,
    SymbolConfig,
)
from pseudotwin.edge.bridge.outbox import Outbox
from pseudotwin.edge.clock import Clock, SystemClock
from pseudotwin.edge.mqttconn import log_connect_failures, refused_fatally, watch_takeover
from pseudotwin.edge.replay import payload_for
from pseudotwin.edge.sdnotify import notify, watchdog_interval
from pseudotwin.live.readings import Reading

__all__ = [
    "ADSERR_SYMBOL_NOT_FOUND",
    "Bridge",
    "SymbolProblems",
    "filetime_to_utc",
]

# One logger for the whole bridge (``pseudotwin.edge.bridge``), whichever module logs.
log = logging.getLogger(__package__)

#: ADS error "symbol not found" (0x710): what a TwinCAT runtime answers for an unknown name.
ADSERR_SYMBOL_NOT_FOUND = 0x710
#: How long a newly registered symbol's first notification is waited for before its value
#: is read instead [s] (plus its cycle_ms and max_delay_ms; at most timeout_seconds).
INITIAL_NOTIFICATION_SECONDS = 0.3
#: ADS error "timeout elapsed" (1861): the request was sent and no answer came.
ADSERR_CLIENT_SYNCTIMEOUT = 1861
#: While tearing down a link that is known to be dead, each notification delete would wait
#: the full request timeout (adslib deletes them one by one, also when closing the port).
TEARDOWN_TIMEOUT_MS = 250
#: paho's reconnect backoff towards the broker [s].
MQTT_RECONNECT_MIN, MQTT_RECONNECT_MAX = 1, 30
#: How often a symbol skipped at a reconnect (gone from the PLC, or of another type) is
#: looked for again while the link is up [s]; at least every poll_seconds.
SYMBOL_RETRY_SECONDS = 30.0
#: A PLC clock this far from ours is logged: the daemon rejects readings more than its
#: max_skew in the future and older than its window, so the operator should know why.
CLOCK_SKEW_WARN = dt.timedelta(minutes=5)
_FILETIME_EPOCH = dt.datetime(1601, 1, 1, tzinfo=dt.UTC)
_ADS_STATES = {v: k.removeprefix("ADSSTATE_") for k, v in vars(adsc).items()
               if k.startswith("ADSSTATE_") and isinstance(v, int)}


def filetime_to_utc(filetime: int) -> dt.datetime:
    """A Windows FILETIME (100 ns ticks since 1601-01-01 UTC) as an aware UTC datetime.

    pyads' own conversion goes through a float of seconds since 1970, which loses the
    sub-microsecond part and can round; integer arithmetic keeps every microsecond.
    """
    return _FILETIME_EPOCH + dt.timedelta(microseconds=filetime // 10)


class SymbolProblems(ConfigProblems):
    """The PLC does not have a configured symbol, or declares it with another type."""


class _PlcNotRunning(Exception):
    """The PLC answers, but its runtime is not in RUN: values are frozen, and a restart may
    invalidate notification handles, so the link counts as down."""


#: Failures of the PLC link itself (anything else is logged with a traceback).
_EXPECTED = (pyads.ADSError, _PlcNotRunning, OSError, RuntimeError)


@dataclass
class _Resolved:
    """A configured symbol as found on the PLC."""

    cfg: SymbolConfig
    sensor: SensorConfig
    index_group: int
    index_offset: int


@dataclass
class _Link:
    """One ADS connection and what was registered on it."""

    conn: pyads.Connection
    gen: int
    symbols: list[_Resolved] = field(default_factory=list)
    handles: list[tuple[int, int | None]] = field(default_factory=list)
    missing: list[int] = field(default_factory=list)  # indexes of symbols skipped
    # symbols a notification came for on this link, and a condition notified as they do
    notified: set[str] = field(default_factory=set)
    first_values: threading.Condition = field(default_factory=threading.Condition)


@dataclass(frozen=True)
class _Item:
    """One reading on its way from the ADS thread to the publisher."""

    symbol: SymbolConfig
    sensor: SensorConfig
    ts: dt.datetime
    value: float
    arrival: dt.datetime
    source: str  # "notification" or "read"


EARLY_ACKS_KEPT = 1000  # far fewer than the 65535 mids before they wrap
#: Room in paho's queue beyond queue_size readings, for the retained status and PLC state
#: messages (a few per reconnect): they must never be refused for readings.
STATUS_HEADROOM = 16
#: How often the publisher looks for room for held-back readings while no new one comes [s].
HELD_RETRY_SECONDS = 0.2
#: Readings written to the spool (and fsynced) at a time when the queue has many.
SPOOL_BATCH = 1000
_STOP = object()


class Bridge:
    """Runs the PLC → MQTT bridge of one configuration until stopped.

    ``start()`` returns at once; the bridge then keeps both links up by itself.
    ``stop()`` deletes the notifications, closes ADS, publishes ``offline`` and disconnects.
    ``finished`` is set when the supervisor has ended: after ``stop()``, or by itself when
    the PLC showed configuration problems at the first connection (``fatal``).
    """

    def __init__(self, cfg: BridgeConfig, clock: Clock | None = None) -> None:
        self.cfg = cfg
        self.clock: Clock = clock or SystemClock()
        self.queue: queue.Queue[Any] = queue.Queue(maxsize=cfg.queue_size)
        self.stop_event = threading.Event()
        self.finished = threading.Event()
        self.plc_up = threading.Event()
        self.mqtt_connected = threading.Event()
        self.fatal: SymbolProblems | None = None
        # (exit status, why) when the broker refused the credentials: retrying cannot help
        self.refused: tuple[int, str] | None = None
        # Counters (read by tests and worth a look in a debugger; only ever incremented).
        self.ads_connects = 0
        self.published = 0
        self.dropped = 0
        self.decode_errors = 0
        self.not_finite = 0  # PLC values that were NaN or infinite (not published)
        self._not_finite_of: dict[str, int] = {}  # symbol → its values that were
        self._gen = 0  # generation of the current ADS link; older callbacks are ignored
        self._validated = False
        self._down_logged = False
        self._down_since: float | None = None
        self._skew_warned_gen = -1
        # The PLC's clock minus this host's, as the latest stamped notification showed it
        # (its delivery delay included): reads are stamped on the PLC's clock with it.
        self._plc_offset = dt.timedelta(0)
        self._local_net_id: str | None = None  # this host's, as pyads' router has it
        self._heartbeat = time.monotonic()
        self._count_lock = threading.Lock()  # counters are bumped from several threads
        # Readings handed to paho whose PUBACK has not come (by mid), and PUBACKs that came
        # before publish() returned their mid: ``published`` counts acknowledged readings,
        # so one still in paho's memory at stop is reported lost, not published.
        self._unacked: set[int] = set()
        # insertion-ordered, the oldest let go past EARLY_ACKS_KEPT: the status messages'
        # acks land here too, and paho's mids wrap at 65535
        self._early_acks: dict[int, None] = {}
        self._other_mids: set[int] = set()  # status and PLC state messages not acknowledged
        self._acked = threading.Condition(self._count_lock)  # notified at every acknowledgement
        # sensor id → its newest reading that found the broker's queue full (publisher only)
        self._held: dict[str, _Item] = {}
        # the spool (opened by start()), and whether writing to it fails right now
        self.outbox: Outbox | None = None
        self._spool_failing = False
        # Setting plc_up and publishing it happen under one lock, in the supervisor and in
        # paho's on_connect alike: otherwise a connect racing a PLC state change could leave
        # the opposite state retained on the broker.
        self._state_lock = threading.Lock()
        self._publisher_thread: threading.Thread | None = None
        self._supervisor_thread: threading.Thread | None = None
        self._started = False
        self.client = self._make_client()

    # -- MQTT --------------------------------------------------------------------------
    def _make_client(self) -> mqtt.Client:
        b = self.cfg.broker
        c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=self.cfg.client_id,
                        clean_session=False)
        c.will_set(self.cfg.status_topic, "offline", qos=1, retain=True)
        if b.username:
            c.username_pw_set(b.username, b.password())
        if b.tls:
            c.tls_set(ca_certs=str(b.ca_file) if b.ca_file else None)
        c.reconnect_delay_set(MQTT_RECONNECT_MIN, MQTT_RECONNECT_MAX)
        # Readings published while the broker is away wait in paho's queue (QoS 1, sent
        # after the reconnect); the publisher keeps them to queue_size, so a long outage
        # does not eat the memory, and the headroom is the status messages'.
        c.max_queued_messages_set(self.cfg.queue_size + STATUS_HEADROOM)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        watch_takeover(c, self.cfg.client_id)  # e.g. two bridges on the default client id
        c.on_publish = self._on_publish
        c.on_connect_fail = log_connect_failures(b)  # an unreachable broker is said at once
        return c

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason_code: Any,
                    properties: Any) -> None:
        if reason_code.is_failure:
            if (refused := refused_fatally(reason_code)) is not None:
                if self.refused is None:
                    log.error("%s; giving up (fix the credentials)", refused[1])
                self.refused = refused  # run() stops the bridge
            else:
                log.error("broker refused the connection: %s", reason_code)
            return
        self._publish_other(self.cfg.status_topic, "online")
        with self._state_lock:
            self._publish_state(self.plc_up.is_set())
        log.info("connected to the broker %s:%d as %r (session present: %s)",
                 self.cfg.broker.host, self.cfg.broker.port, self.cfg.client_id,
                 flags.session_present)
        self.mqtt_connected.set()

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason_code: Any,
                       properties: Any) -> None:
        self.mqtt_connected.clear()
        if not self.stop_event.is_set():
            kept = (f"in the spool {self.outbox.path}" if self.outbox is not None
                    else f"up to {self.cfg.queue_size}")
            log.warning("disconnected from the broker (%s); reconnecting, readings are kept "
                        "until it is back (%s)", reason_code, kept)

    def _on_publish(self, client: mqtt.Client, userdata: Any, mid: int, reason_code: Any,
                    properties: Any) -> None:
        with self._count_lock:
            if mid in self._unacked:
                self._unacked.discard(mid)
                self.published += 1
                self._acked.notify_all()  # stop() waits for none, held readings for room
            elif mid in self._other_mids:
                self._other_mids.discard(mid)
            else:  # before publish() returned its mid
                self._early_acks[mid] = None
                if len(self._early_acks) > EARLY_ACKS_KEPT:
                    del self._early_acks[next(iter(self._early_acks))]

    def _publisher(self) -> None:
        while True:
            try:
                item = self.queue.get(timeout=HELD_RETRY_SECONDS if self._held else None)
            except queue.Empty:
                self._release_held()  # guarded per reading
                continue
            if item is _STOP:
                self._release_held_at_stop()
                return
            try:
                self._release_held()
                self._publish_reading(item)
            except Exception:  # the bridge must outlive one bad reading
                log.exception("unexpected error while publishing a reading of %s",
                              item.symbol.symbol)

    def _publish_other(self, topic: str, payload: str) -> mqtt.MQTTMessageInfo:
        """Publish a status or PLC state message (retained, QoS 1), its acknowledgement
        expected: a stray one kept among the early acks would, once paho's mids wrap, count
        a reading with the same mid as acknowledged before the broker has it."""
        info = self.client.publish(topic, payload, qos=1, retain=True)
        if info.rc != mqtt.MQTT_ERR_QUEUE_SIZE:
            with self._count_lock:
                self._acked_early(info.mid, self._other_mids)
        return info

    def _acked_early(self, mid: int, expected: set[int]) -> bool:
        """(Under ``_count_lock``, once publish() returned ``mid``.) Whether its ack came
        before (kept among the early acks, now taken out); else it is ``expected``."""
        if mid in self._early_acks:
            del self._early_acks[mid]
            return True
        expected.add(mid)
        return False

    def _has_room(self) -> bool:
        with self._count_lock:
            return len(self._unacked) < self.cfg.queue_size

    def _release_held(self) -> None:
        """Send held-back readings, oldest first, while the broker's queue has room."""
        for sensor, item in sorted(self._held.items(), key=lambda kv: kv[1].ts):
            if not self._has_room():
                return
            try:
                sent = self._send(item) is not None
            except Exception:  # one bad reading must not block every later one
                log.exception("unexpected error while publishing a held-back reading of %s; "
                              "dropped", item.symbol.symbol)
                del self._held[sensor]
                with self._count_lock:
                    self.dropped += 1
                continue
            if not sent:
                return
            del self._held[sensor]

    def _release_held_at_stop(self, timeout: float = 5.0) -> None:
        """Send what is held back as room comes while the broker is there; count the rest."""
        deadline = time.monotonic() + timeout
        self._release_held()
        while self._held and self.mqtt_connected.is_set() and time.monotonic() < deadline:
            with self._acked:  # notified at every acknowledgement
                self._acked.wait_for(lambda: len(self._unacked) < self.cfg.queue_size,
                                     max(0.0, deadline - time.monotonic()))
            self._release_held()
        if self._held:
            with self._count_lock:
                self.dropped += len(self._held)
            log.warning("%d held-back reading(s) (the newest of %s) not sent at stop: the "
                        "broker's queue was full", len(self._held), ", ".join(sorted(self._held)))
            self._held.clear()

    def _hold(self, item: _Item) -> None:
        """Keep ``item`` as its sensor's newest unsent reading; an older one is dropped."""
        if self._held.pop(item.sensor.id, None) is not None:
            self._count_drop(f"the MQTT queue is full ({self.cfg.queue_size} readings waiting "
                             "for the broker); the newest reading of each sensor is kept "
                             "and sent when there is room")
        self._held[item.sensor.id] = item

    def _warn_skew(self, item: _Item) -> None:
        if item.source == "notification" and self._skew_warned_gen != self._gen:
            skew = item.ts - item.arrival
            if abs(skew) > CLOCK_SKEW_WARN:
                self._skew_warned_gen = self._gen
                log.warning("the PLC's clock differs from this host's by %.0f s (reading of "
                            "%s); readings carry the PLC's time, and the daemon rejects "
                            "readings too far in the future or the past",
                            skew.total_seconds(), item.symbol.symbol)

    def _publish_reading(self, item: _Item) -> None:
        self._warn_skew(item)
        if self._held or not self._has_room() or self._send(item) is None:
            self._hold(item)

    def _send(self, item: _Item) -> int | None:
        return self._send_value(item.sensor, item.ts, item.value)

    def _send_value(self, s: SensorConfig, ts: dt.datetime, value: float) -> int | None:
        """Hand one reading to paho; its message id, None if paho's queue refused it."""
        payload = payload_for(s.format, s.ts_key, s.value_key, ts, value)
        info = self.client.publish(s.topic, payload, qos=1)
        if info.rc == mqtt.MQTT_ERR_QUEUE_SIZE:
            return None
        # MQTT_ERR_NO_CONN means queued by paho for after the reconnect: not lost yet,
        # published once the broker acknowledges it (_on_publish).
        with self._count_lock:
            if self._acked_early(info.mid, self._unacked):
                self.published += 1
        return info.mid

    # -- the publisher with a spool (outbox.py) -----------------------------------------
    def _pending(self, mid: int) -> bool:
        return mid in self._unacked  # a set lookup: atomic, no lock needed

    def _spool_publisher(self) -> None:
        outbox = self.outbox
        assert outbox is not None
        while True:
            waiting = outbox.busy or bool(self._held)
            try:
                first = self.queue.get(timeout=HELD_RETRY_SECONDS if waiting else None)
            except queue.Empty:
                first = None
            batch: list[_Item] = []
            stopping = first is _STOP
            if first is not None and not stopping:
                batch.append(first)
                while len(batch) < SPOOL_BATCH:  # one write (and fsync) for what is queued
                    try:
                        more = self.queue.get_nowait()
                    except queue.Empty:
                        break
                    if more is _STOP:
                        stopping = True
                        break
                    batch.append(more)
            try:
                # the acks that came meanwhile first: a busy sensor leaves no moment with
                # every reading acknowledged, and the spool is cut where they end
                outbox.settle(self._pending)
                if batch:
                    self._spool_batch(outbox, batch)
                self._release_held()
                self._send_unsent(outbox)
                outbox.settle(self._pending)
            except Exception:  # the bridge must outlive one bad reading or spool trouble
                log.exception("unexpected error while publishing readings from the spool %s",
                              outbox.path)
            if stopping:
                self._spool_at_stop(outbox)
                return

    def _spool_batch(self, outbox: Outbox, batch: list[_Item]) -> None:
        """Write ``batch`` to the spool, then hand to paho what it has room for, if nothing
        older waits; when the spool cannot take them (a disk that refuses them, or a fault
        of its own), publish them as without a spool."""
        for item in batch:
            self._warn_skew(item)
        try:
            spans = outbox.add([Reading(i.sensor.id, i.ts, i.value) for i in batch])
        except Exception as exc:  # a disk that refuses them, or a fault of the spool's own:
            if not self._spool_failing:  # the batch must not go down with the spool
                log.error("cannot write the spool %s (%s); readings go to the broker "
                          "without it meanwhile (up to %d waiting in memory)", outbox.path,
                          exc, self.cfg.queue_size,
                          exc_info=not isinstance(exc, OSError))
            self._spool_failing = True
            for item in batch:
                self._publish_reading(item)
            return
        if self._spool_failing:
            log.info("the spool %s can be written again", outbox.path)
            self._spool_failing = False
        for item, (start, end) in zip(batch, spans, strict=True):
            if outbox.cursor != start or not self._has_room():
                return  # older readings first: _send_unsent takes it from the file
            mid = self._send(item)
            if mid is None:
                return
            outbox.sent(mid, end)

    def _send_unsent(self, outbox: Outbox) -> None:
        """Hand the spool's unsent readings to paho, oldest first, while it has room."""
        if outbox.cursor >= outbox.end or not self._has_room():
            return
        for reading, end in outbox.unsent():
            if reading is None:
                outbox.sent(None, end)  # unreadable (logged): nothing to wait for
                continue
            sensor = self.cfg.sensors.get(reading.sensor)
            if sensor is None:  # spooled by an earlier run under another configuration
                self._count_drop(f"{reading.sensor!r} from the spool is no longer a "
                                 "configured sensor")
                outbox.sent(None, end)
                continue
            if not self._has_room():
                return
            mid = self._send_value(sensor, reading.ts, reading.value)
            if mid is None:
                return
            outbox.sent(mid, end)

    def _spool_at_stop(self, outbox: Outbox, timeout: float = 5.0) -> None:
        """Send what the spool holds as room comes while the broker is there; what is left
        stays in the spool for the next start."""
        deadline = time.monotonic() + timeout
        self._release_held_at_stop(timeout)
        self._send_unsent(outbox)
        while (outbox.cursor < outbox.end and self.mqtt_connected.is_set()
               and time.monotonic() < deadline):
            with self._acked:  # notified at every acknowledgement
                self._acked.wait_for(lambda: len(self._unacked) < self.cfg.queue_size,
                                     max(0.0, deadline - time.monotonic()))
            before = outbox.cursor
            self._send_unsent(outbox)
            if outbox.cursor == before and self._has_room():
                break  # no progress with room (paho refuses): the rest stays for next time
        outbox.settle(self._pending)

    def _count_drop(self, why: str) -> None:
        with self._count_lock:
            self.dropped += 1
            n = self.dropped
        if doubled(n - 1, n):  # visible, but not one line per reading
            log.warning("reading dropped: %s (%d dropped so far)", why, n)

    def _publish_state(self, up: bool) -> None:
        """The PLC state, retained; only while connected (call under ``_state_lock``):
        queued for a broker that is away, every PLC flap of an outage would take room in
        paho's queue, and ``_on_connect`` publishes the state of that moment anyway."""
        if not self.client.is_connected():
            return
        info = self._publish_other(self.cfg.plc_topic, "up" if up else "down")
        if info.rc == mqtt.MQTT_ERR_QUEUE_SIZE:
            log.warning("the PLC state could not be queued for the broker (its queue is "
                        "full); it goes out at the next change or reconnect")

    # -- ADS notification thread: decode, stamp, enqueue; nothing that can block -------
    def _enqueue(self, item: _Item) -> None:
        try:
            self.queue.put_nowait(item)
        except queue.Full:
            self._count_drop(f"the reading queue is full ({self.cfg.queue_size}); the "
                             "publisher is behind")

    def _callback(self, link: _Link, r: _Resolved) -> Callable[[Any, Any], None]:
        gen = link.gen
        decode = link.conn.notification(r.cfg.type.ctype, timestamp_as_filetime=True)

        @decode
        def on_change(handle: int, name: Any, filetime: int, raw: Any) -> None:
            if gen != self._gen:
                return  # a late notification of a link already torn down
            arrival = self.clock.now()
            # A zero stamp means the server did not set one; arrival time is then the best.
            ts = filetime_to_utc(filetime) if filetime > 0 else arrival
            if filetime > 0:
                self._plc_offset = ts - arrival
            self._accept(r, raw, ts, arrival, "notification")
            if r.cfg.symbol not in link.notified:
                with link.first_values:
                    link.notified.add(r.cfg.symbol)
                    link.first_values.notify_all()

        def guarded(notification: Any, data: Any) -> None:
            # An exception must not escape into the ctypes callback (it would be printed
            # and lost); a sample of an unexpected size makes struct.unpack raise.
            try:
                on_change(notification, data)
            except Exception as exc:  # noqa: BLE001 - counted and logged, never fatal
                with self._count_lock:
                    self.decode_errors += 1
                    n = self.decode_errors
                if doubled(n - 1, n):
                    log.warning("cannot decode a notification of %s as %s: %s (%d so far)",
                                r.cfg.symbol, r.cfg.plc_type, exc, n)

        return guarded

    def _accept(self, r: _Resolved, raw: Any, ts: dt.datetime, arrival: dt.datetime,
                source: str) -> None:
        value = r.cfg.convert(raw)
        if not math.isfinite(value):
            # JSON has no NaN/Infinity; the daemon would reject it anyway.
            symbol = r.cfg.symbol
            with self._count_lock:
                self.not_finite += 1
                n = self._not_finite_of[symbol] = self._not_finite_of.get(symbol, 0) + 1
            if doubled(n - 1, n):  # a flickering wire break must not flood the log
                log.warning("%s is %r; not published (%d such value(s) of it so far)",
                            symbol, value, n)
            return
        self._enqueue(_Item(r.cfg, r.sensor, ts, value, arrival, source))

    # -- the supervisor: connect, validate, register, poll, reconnect ------------------
    def _sleep(self, seconds: float) -> bool:
        """Wait ``seconds`` (keeping the watchdog heartbeat fresh); True if asked to stop."""
        deadline = time.monotonic() + seconds
        while True:
            self._heartbeat = time.monotonic()
            left = deadline - self._heartbeat
            if left <= 0:
                return self.stop_event.is_set()
            if self.stop_event.wait(min(left, 1.0)):
                return True

    def _supervise(self) -> None:
        plc = self.cfg.plc
        delay = 1.0
        try:
            while not self.stop_event.is_set():
                self._heartbeat = time.monotonic()
                try:
                    link = self._connect()
                except SymbolProblems as exc:
                    self.fatal = exc
                    log.error("the PLC does not match the configuration:\n%s", exc)
                    return
                except Exception as exc:  # noqa: BLE001 - any failure: back off and retry
                    if not isinstance(exc, _EXPECTED):
                        # A bug rather than the network; retrying beats a supervisor thread
                        # that died silently while the process looks alive.
                        log.exception("unexpected error while connecting to the PLC")
                    self._mark_down(f"cannot connect: {_describe(exc)}{self._route_hint(exc)}")
                    if self._sleep(delay):
                        return
                    delay = min(delay * 2, plc.reconnect_max_seconds)
                    continue
                delay = 1.0
                self._mark_up(link)
                lost = self._poll(link)
                self._gen += 1  # from here on, callbacks of this link are ignored
                self._teardown(link, alive=lost is None or isinstance(lost, _PlcNotRunning))
                if lost is None:
                    return
                self._mark_down(_describe(lost))
        finally:
            self.plc_up.clear()
            self.finished.set()

    def _connect(self) -> _Link:
        plc = self.cfg.plc
        # pyads' open() blocks in the OS's TCP connect (~2 min to a host that drops the
        # packets): the watchdog's heartbeat would go stale and systemd kill the bridge
        # before it said why, and a stop would wait. A probe bounded by timeout_seconds
        # first says "unreachable" and comes back to the back-off loop.
        try:
            socket.create_connection((plc.ip_address, ADS_TCP_PORT),
                                     timeout=plc.timeout_seconds).close()
        except OSError as exc:
            raise OSError(f"{plc.ip_address}:{ADS_TCP_PORT} unreachable within "
                          f"{plc.timeout_seconds:g} s ({exc.strerror or exc})") from None
        self._heartbeat = time.monotonic()
        conn = pyads.Connection(plc.ams_net_id, plc.port, plc.ip_address)
        conn.open()  # adds the route; raises ADSError when the PLC cannot be reached
        self._gen += 1
        link = _Link(conn, self._gen)
        try:
            if self._local_net_id is None:
                local = conn.get_local_address()
                if local is not None:
                    self._local_net_id = local.netid
                    log.info("this host's AMS net id is %s: the PLC needs a static route to "
                             "it (with this host's IP address)", self._local_net_id)
            conn.set_timeout(max(1, round(plc.timeout_seconds * 1000)))
            self._check_running(conn)
            found, link.missing = self._resolve(conn)
            for r in found:
                self._register(link, r)
            self._read_now(link, found)
        except BaseException:
            self._gen += 1
            self._teardown(link, alive=False)
            raise
        return link

    def _register(self, link: _Link, r: _Resolved) -> None:
        attr = pyads.NotificationAttrib(r.cfg.type.size, adsc.ADSTRANS_SERVERONCHA,
                                        r.cfg.max_delay_ms, r.cfg.cycle_ms)
        # By index group/offset rather than by name: one lookup per connect, and it also
        # works with servers that cannot notify by handle (pyads' own test server).
        # Limitation: a PLC program download or online change that moves a variable
        # without a state change seen by the poll leaves the notification on the old
        # offset until the next reconnect (watching the PLC's symbol version, index group
        # 0xF008, would catch it).
        handles = link.conn.add_device_notification(
            (r.index_group, r.index_offset), attr, self._callback(link, r)
        )
        if handles is not None:
            link.handles.append(handles)
        link.symbols.append(r)

    def _read_now(self, link: _Link, symbols: list[_Resolved]) -> None:
        """Each of ``symbols``' current value right after its registration: the symbols
        may not change for hours. A TwinCAT runtime sends it by itself as the first
        notification, with the PLC's time stamp: that one is waited for a moment, and only
        the symbols without it are read. A read is stamped on the PLC's clock as far as
        notifications have shown it: on this host's, a PLC running behind would stamp its
        next change before the read, and the daemon, taking readings in time order, would
        hold the read's value until then."""
        if not symbols:
            return
        wait = INITIAL_NOTIFICATION_SECONDS + max(
            (r.cfg.cycle_ms + r.cfg.max_delay_ms) / 1000 for r in symbols)
        with link.first_values:
            link.first_values.wait_for(
                lambda: all(r.cfg.symbol in link.notified for r in symbols),
                min(wait, self.cfg.plc.timeout_seconds))
            unsent = [r for r in symbols if r.cfg.symbol not in link.notified]
        now = self.clock.now()
        for r in unsent:
            raw = link.conn.read_by_name(r.cfg.symbol, r.cfg.type.ctype)
            self._accept(r, raw, now + self._plc_offset, now, "read")

    def _route_hint(self, exc: BaseException) -> str:
        """What to check when the PLC took the TCP connection and never answered: a PLC
        without a static route to this host drops its requests silently."""
        if getattr(exc, "err_code", None) != ADSERR_CLIENT_SYNCTIMEOUT:
            return ""
        return (" (the PLC took the connection but did not answer: check that it has a "
                f"static route to this host's AMS net id {self._local_net_id or '?'} and IP "
                "address, and plc.port)")

    def _check_running(self, conn: pyads.Connection) -> None:
        state = conn.read_state()
        if state is None:
            raise RuntimeError("ADS port is not open")
        if state[0] != adsc.ADSSTATE_RUN:
            raise _PlcNotRunning(f"PLC state is {_ADS_STATES.get(state[0], state[0])}, not RUN")

    def _resolve(self, conn: pyads.Connection) -> tuple[list[_Resolved], list[int]]:
        """Look every symbol up on the PLC: the ones found, and the indexes of the others.
        SymbolProblems at the first validation; after it the bad ones are logged, skipped
        and looked for again while the link is up (:meth:`_retry_missing`)."""
        good: list[_Resolved] = []
        problems: list[str] = []
        missing: list[int] = []
        for i in range(len(self.cfg.plc.symbols)):
            found = self._lookup(conn, i)
            if isinstance(found, str):
                problems.append(found)
                missing.append(i)
            else:
                good.append(found)
        if problems:
            if not self._validated:
                raise SymbolProblems(problems)
            for p in problems:
                log.error("skipping a symbol, looked for again every %g s: %s",
                          self._retry_seconds(), p)
        self._validated = True
        return good, missing

    def _lookup(self, conn: pyads.Connection, i: int) -> _Resolved | str:
        """The i-th configured symbol as the PLC has it, or why it cannot be used."""
        plc = self.cfg.plc
        sym = plc.symbols[i]
        loc = f"plc.symbols[{i}]"
        try:
            info = conn.read_write(adsc.ADSIGRP_SYM_INFOBYNAMEEX, 0, SAdsSymbolEntry,
                                   sym.symbol, pyads.PLCTYPE_STRING)
        except pyads.ADSError as exc:
            if getattr(exc, "err_code", None) != ADSERR_SYMBOL_NOT_FOUND:
                raise
            return (f"{loc}.symbol: {sym.symbol!r} is not a symbol of the PLC at "
                    f"{plc.ams_net_id}:{plc.port} ({plc.ip_address}) (check the spelling and "
                    "the POU/GVL prefix, e.g. 'MAIN.' or 'GVL.')")
        problem = _type_problem(sym, info)
        if problem:
            return f"{loc}.plc_type: {problem}"
        return _Resolved(sym, self.cfg.sensor_of(sym), info.iGroup, info.iOffs)

    def _retry_seconds(self) -> float:
        return max(self.cfg.plc.poll_seconds, SYMBOL_RETRY_SECONDS)

    def _retry_missing(self, link: _Link) -> None:
        """Look for the symbols skipped at this connect again (a PLC program changed under
        the bridge may bring them back); register and read the ones found."""
        back: list[_Resolved] = []
        for i in list(link.missing):
            found = self._lookup(link.conn, i)
            if isinstance(found, str):
                log.debug("still skipped: %s", found)
                continue
            self._register(link, found)
            link.missing.remove(i)
            back.append(found)
            log.warning("plc.symbols[%d] %r found on the PLC again; registered (%d of %d "
                        "symbols)", i, found.cfg.symbol, len(link.symbols),
                        len(self.cfg.plc.symbols))
        self._read_now(link, back)  # one wait for their first notifications, as at connect

    def _poll(self, link: _Link) -> BaseException | None:
        """Read the PLC state every poll_seconds; the reason the link is lost, or None when
        asked to stop."""
        next_retry = time.monotonic() + self._retry_seconds()
        while not self._sleep(self.cfg.plc.poll_seconds):
            try:
                self._check_running(link.conn)
                if link.missing and time.monotonic() >= next_retry:
                    next_retry = time.monotonic() + self._retry_seconds()
                    self._retry_missing(link)
            except Exception as exc:  # noqa: BLE001 - whatever it is, the link is not usable
                if not isinstance(exc, _EXPECTED):
                    log.exception("unexpected error while polling the PLC state")
                return exc
        return None

    def _teardown(self, link: _Link, *, alive: bool) -> None:
        """Delete the notifications and close the connection; never raises.

        Deleting also drops pyads' reference to our callback. On a dead link the deletes
        cannot reach the PLC (which forgets a closed connection's notifications anyway), so
        they get a short timeout instead of the full one each.
        """
        conn = link.conn
        try:
            if not alive:
                conn.set_timeout(TEARDOWN_TIMEOUT_MS)
        except pyads.ADSError:
            pass
        for notification, user in link.handles:
            try:
                conn.del_device_notification(notification, user)
            except pyads.ADSError as exc:
                log.debug("deleting notification %d: %s", notification, _describe(exc))
        link.handles.clear()
        try:
            conn.close()
        except (pyads.ADSError, OSError) as exc:
            log.debug("closing the ADS connection: %s", _describe(exc))

    def _mark_up(self, link: _Link) -> None:
        self.ads_connects += 1
        plc = self.cfg.plc
        since = ""
        if self._down_since is not None:
            since = f" after {time.monotonic() - self._down_since:.0f} s"
        log.log(logging.WARNING if link.missing else logging.INFO,
                "PLC %s:%d (%s) connected%s; %d of %d symbols registered for notifications",
                plc.ams_net_id, plc.port, plc.ip_address, since, len(link.symbols),
                len(plc.symbols))
        self._down_logged = False
        self._down_since = None
        with self._state_lock:
            self.plc_up.set()
            self._publish_state(True)

    def _mark_down(self, reason: str) -> None:
        with self._state_lock:
            was_up = self.plc_up.is_set()
            self.plc_up.clear()
            if was_up or not self._down_logged:
                # Also at the start of an outage that began before we were ever up: a
                # retained "up" may be left over from a bridge that was killed.
                self._publish_state(False)
        if self._down_since is None:
            self._down_since = time.monotonic()
        plc = self.cfg.plc
        if not self._down_logged:
            # Once per outage: a PLC away for a weekend must not fill the journal.
            self._down_logged = True
            log.warning("PLC %s:%d (%s) %s: %s; reconnecting (backoff 1..%g s)",
                        plc.ams_net_id, plc.port, plc.ip_address,
                        "lost" if was_up else "unavailable", reason, plc.reconnect_max_seconds)
        else:
            log.debug("PLC still unavailable: %s", reason)

    # -- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        if self._started:
            raise RuntimeError("a Bridge can only be started once")
        self._started = True
        if self.cfg.unstamped_note:
            log.warning("%s", self.cfg.unstamped_note)
        if (path := self.cfg.spool_path) is not None:
            # StateInUseError (another bridge on this spool), ConfigError (not writable)
            self.outbox = Outbox(path, fsync=self.cfg.spool_fsync)
            if self.outbox.busy:
                log.info("%d reading(s) of an earlier run wait in the spool %s (not "
                         "acknowledged by the broker then); they go out first",
                         self.outbox.unsent_count(), path)
        if self.cfg.plc.local_ams_net_id:
            # Process-wide in pyads' router: the net id the PLC's route points back to.
            pyads.set_local_address(self.cfg.plc.local_ams_net_id)
        b = self.cfg.broker
        # connect_async: the bridge starts (and watches the PLC) even if the broker is down.
        self.client.connect_async(b.host, b.port, keepalive=b.keepalive)
        self.client.loop_start()
        self._publisher_thread = threading.Thread(
            target=self._publisher if self.outbox is None else self._spool_publisher,
            name="bridge-publisher", daemon=True)
        self._supervisor_thread = threading.Thread(target=self._supervise,
                                                   name="bridge-supervisor", daemon=True)
        self._publisher_thread.start()
        self._supervisor_thread.start()
        interval = watchdog_interval()
        if interval is not None:
            threading.Thread(target=self._watchdog, args=(interval,), name="bridge-watchdog",
                             daemon=True).start()
        notify("READY=1")

    def _watchdog(self, interval: float) -> None:
        while not self.stop_event.wait(interval):
            # Only while the supervisor is alive: a hung ADS call must get us restarted.
            if time.monotonic() - self._heartbeat < 2 * interval + self.cfg.plc.timeout_seconds:
                notify("WATCHDOG=1")

    def request_stop(self) -> None:
        """Ask the bridge to stop (safe from a signal handler); ``stop()`` finishes it."""
        self.stop_event.set()

    def stop(self, timeout: float = 10.0) -> None:
        notify("STOPPING=1")
        self.stop_event.set()
        if self._supervisor_thread is not None:
            self._supervisor_thread.join(timeout)  # deletes the notifications, closes ADS
            if self._supervisor_thread.is_alive():
                log.warning("the ADS connection did not close within %g s", timeout)
        if self._publisher_thread is not None:
            # The publisher empties the queue before it sees _STOP: nothing already read
            # from the PLC is left behind.
            try:
                self.queue.put(_STOP, timeout=timeout)
            except queue.Full:
                log.warning("reading queue still full at stop; %d readings not published",
                            self.queue.qsize())
            self._publisher_thread.join(timeout)
        if self.mqtt_connected.is_set():
            # Retained: "up" would stay the PLC's state for every later subscriber.
            self._publish_other(self.cfg.plc_topic, "down")
            info = self._publish_other(self.cfg.status_topic, "offline")
            try:
                info.wait_for_publish(timeout)
            except (RuntimeError, ValueError) as exc:
                log.warning("could not publish the offline status: %s", exc)
        if self.mqtt_connected.is_set():  # give what is in flight its acknowledgement
            with self._acked:
                self._acked.wait_for(lambda: not self._unacked, timeout)
        self.client.disconnect()
        self.client.loop_stop()
        lost = self.unacknowledged()
        if self.outbox is not None:
            if self._publisher_thread is not None and self._publisher_thread.is_alive():
                # still writing the spool: its mark on disk stays where it is (safe)
                log.warning("the publisher did not end within %g s; the spool %s is left "
                            "as it is", timeout, self.outbox.path)
                lost = 0
            else:
                with self._count_lock:  # sent while the spool failed: not in it
                    lost = len(self._unacked - self.outbox.in_flight())
                self._close_outbox(self.outbox)
            if lost:
                log.warning("%d readings sent while the spool could not be written were "
                            "never acknowledged by the broker %s:%d and are lost with this "
                            "stop", lost, self.cfg.broker.host, self.cfg.broker.port)
        elif lost:
            log.warning("%d readings were never acknowledged by the broker %s:%d and are lost "
                        "with this stop (paho keeps them in memory only)", lost,
                        self.cfg.broker.host, self.cfg.broker.port)
        log.info("bridge stopped: %d readings published (acknowledged by the broker), %d "
                 "dropped, %d lost at stop, %d not a number (not published)", self.published,
                 self.dropped, lost, self.not_finite)

    def _close_outbox(self, outbox: Outbox) -> None:
        """The last acknowledgements into the mark; say what stays for the next start."""
        try:
            outbox.settle(self._pending, force=True)
            if kept := outbox.waiting(self._pending):
                log.warning("%d reading(s) not acknowledged by the broker %s:%d stay in the "
                            "spool %s; the next start sends them", kept,
                            self.cfg.broker.host, self.cfg.broker.port, outbox.path)
        except OSError as exc:
            log.error("cannot read the spool %s at stop (%s)", outbox.path, exc)
        finally:
            outbox.close()

    def unacknowledged(self) -> int:
        """Readings handed to the MQTT client that the broker has not acknowledged."""
        with self._count_lock:
            return len(self._unacked)

    def run(self) -> None:
        """Start, wait until ``request_stop()`` or a fatal problem, then stop."""
        self.start()
        try:
            # stop_event too: a supervisor stuck in an ADS call must not hold a SIGTERM up
            while (not self.finished.wait(1.0) and self.refused is None
                   and not self.stop_event.is_set()):
                pass
        finally:
            self.stop()


def _type_problem(sym: SymbolConfig, info: SAdsSymbolEntry) -> str | None:
    """Why the PLC's declaration of ``sym`` does not fit its configured plc_type, or None."""
    want = sym.type
    declared = info.symbol_type.strip()
    name = declared.upper()
    size = int(info.size)
    if name == want.name and size == want.size:
        return None
    if name in NON_NUMERIC_TYPES:  # a TIME is a UDINT on the wire, yet no reading
        return (f"configured {want.name}, but the PLC declares {sym.symbol!r} as {declared}, "
                "which is not a reading (a duration, date or bit string)")
    # An alias (TYPE T_Celsius : LREAL) reports its own name but the base type's ADS type
    # id and size; a different elementary type name is a mismatch even when the encoding
    # happens to agree (WORD vs UINT), because it usually means the wrong variable.
    if name not in PLC_TYPES and info.dataType == want.ads_type and size == want.size:
        return None
    return (f"configured {want.name}, but the PLC declares {sym.symbol!r} as {declared} "
            f"({size} bytes); set plc_type = \"{declared}\" if that is right"
            if name in PLC_TYPES else
            f"configured {want.name}, but the PLC declares {sym.symbol!r} as {declared} "
            f"({size} bytes), which is not an elementary numeric type")


def _describe(exc: BaseException) -> str:
    return str(exc).removeprefix("ADSError: ").strip().rstrip(".") or type(exc).__name__
