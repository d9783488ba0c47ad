"""The live daemon: MQTT readings in, pseudo-measurements out, for days on end.

Threads, and why:
- paho's network thread only turns a message into a queue item (no parsing, no model work);
- one worker owns every twin and does all model work, in arrival order, so estimates are
  deterministic and equal to ``evaluate``'s for the same readings;
- a ticker enqueues the publish-grid instants; a watchdog tells systemd the worker is alive.
  A reading stamped past a grid instant the ticker has not delivered yet (a starved ticker
  thread, a burst) starts that instant's grid work first, so a grid estimate never sees a
  later reading, however late its tick: the same as ``evaluate`` and backfill.

Delivery: QoS 1, persistent session (clean_session False, stable client id), manual acks. A
reading is acknowledged only after it is journaled (see journal.py) and applied, so neither
a broker restart nor a SIGKILL of the daemon loses one; redeliveries are recognized as
duplicates by the twins.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import logging
import math
import os
import queue
import socket
import threading
import time
from collections import Counter, defaultdict, deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from operator import attrgetter
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import MQTTErrorCode

from pseudotwin.config import SensorConfig, ServiceConfig, TwinConfig
from pseudotwin.config.validate import absent_sqlite_file
from pseudotwin.core.files import write_replacing
from pseudotwin.core.logpace import doubled
from pseudotwin.core.twinlog import twin_context
from pseudotwin.edge import homeassistant as ha
from pseudotwin.edge.clock import EX_TEMPFAIL, Clock, SystemClock
from pseudotwin.edge.fleet import FleetMember
from pseudotwin.edge.health import Health
from pseudotwin.edge.journal import Journal
from pseudotwin.edge.mqttconn import (
    StaleTopics,
    Subscription,
    make_client,
    refused_fatally,
    watch_takeover,
)
from pseudotwin.edge.outputs import estimate_payload, monitor_payload
from pseudotwin.edge.ownership import CLAIM_EVERY, CLAIMS_SUFFIX, Ownership
from pseudotwin.edge.prometheus import DaemonMetrics
from pseudotwin.edge.sdnotify import notify, watchdog_interval
from pseudotwin.edge.statelock import StateLock
from pseudotwin.edge.wakeup import WakeCoalescer
from pseudotwin.errors import ConfigError
from pseudotwin.live.artifact import UNVALIDATED, Artifact, artifact_hash, check_artifact
from pseudotwin.live.monitor import TwinMonitor
from pseudotwin.live.readings import (
    UNPROCESSABLE,
    Reading,
    Reason,
    Rejected,
    RejectionCounter,
    in_range,
    parse_payload,
)
from pseudotwin.live.twin import Quality, Twin, TwinEstimate

log = logging.getLogger(__name__)

LOG_REJECTIONS_PER_KEY = 10  # per sensor, reason and day; the rest are only counted
SILENCE_LINES_PER_DAY = 3  # "reference silent" lines per twin, reference and local day
JOURNAL_RETRY_SECONDS = 2.0  # how often a failing journal is tried again
STOP_JOIN_SECONDS = 5.0  # the worker finishes its current item within this on stop
# Messages journaled with one write (and taken from the queue at once): the journal's cost
# per reading falls with the batch, while a reading waits behind at most this many others.
BATCH_MAX = 64
# Twins whose grid work is done between two batches of readings: at 1,000 twins one tick
# would otherwise hold every reading behind 1,000 estimates and monitors.
TICK_CHUNK = 5
# Grid work waits while this many of the daemon's QoS 1 messages wait for the broker's
# PUBACK: paho sends in order, so a reading's estimate then queues behind at most these,
# not behind the 6,000 messages of a thousand twins' tick (scripts/bench_daemon.py --twins
# 1000 shows the p99 latency; rerun it with other values here to compare).
TICK_BACKLOG = 20
# ... for at most this long per chunk [s]: a broker that stops acknowledging must not stop
# the grid (the messages stay queued in paho and go out on reconnect).
TICK_MAX_PAUSE = 0.05
# The baselines and the monitor go out at QoS 0: they are for monitoring, and the next grid
# instant replaces one lost with a dropped connection. They are most of a twin's messages
# per grid step (five of six with every baseline published; the monitor is hourly), and a
# QoS 1 message costs paho about twice the CPU of a QoS 0 one (the PUBACK and its
# bookkeeping): at 1,000 twins this is ~15 % of the daemon's CPU and most of the grid's burst
# (scripts/bench_daemon.py).
# Estimates and status stay QoS 1.
MONITORING_QOS = 0
# state_dir's record of the retained output topics published (Service._plan_outputs).
OUTPUTS_FILE = "outputs.json"
#: A step back of the clock this small (or up to max_skew_seconds) is let pass: NTP's
#: corrections of a few seconds, not a clock that ran hours or days ahead.
CLOCK_BACK_TOLERANCE = dt.timedelta(minutes=1)
#: The last grid instant ticked (state_dir): how recent a retained estimate the run before
#: this one may have left (TwinRuntime.published_floor).
GRID_FILE = "grid.json"
# A grid instant's estimates are made this long after it (clock time): a reading stamped
# exactly at the instant (a bridge polling on the quarter hour) reaches the daemon a little
# after it, and evaluate and backfill count it in. A reading stamped past the instant
# starts the instant's work at once (_catch_up_grid): it must not be in it.
TICK_GRACE = dt.timedelta(seconds=2)
# A worker batch that holds the readings behind it longer than this [s] is logged with its
# wall time, the worker's own CPU in it and its journal writes: wall time without CPU is the
# worker blocked (the disk under the journal, another thread holding the GIL), not
# computing. A batch normally takes a few ms.
LONG_BATCH_S = 0.5
#: The log line of one (scripts/bench_daemon.py counts the daemon's warnings by kind).
LONG_BATCH_PATTERN = (r"a worker batch took (\d+) ms \((\d+) ms of it the worker's CPU; "
                      r"journal (\d+) ms")


def _clock(t: dt.datetime | None) -> str:
    """An instant for the log: ISO 8601 in UTC, or that there is none."""
    if t is None:
        return "none since the daemon started or restored its state"
    return t.astimezone(dt.UTC).isoformat(timespec="seconds")


@dataclass
class TwinRuntime:
    """One configured twin with its live bookkeeping for today's monitor, and what its
    messages need that never changes (asked for every message: built once)."""

    cfg: TwinConfig
    twin: Twin
    monitor: TwinMonitor
    reading_kinds: tuple[str, ...] | None  # the models estimated at a reading (None: all)
    estimate_topic: str
    monitor_topic: str
    baseline_topics: dict[str, str]
    # (uncertain since and why, failover since and lost) as last published on the monitor:
    # a change goes out at the next grid instant, whatever monitor_every_minutes says.
    monitor_state: tuple[object, ...] = (None, (), None, ())
    # The references the primary's last estimate went without (silent longer than
    # stale_after): logged when it changes, as the payloads alone would not tell the log.
    silent: tuple[str, ...] = ()
    # Reference → its silences on silence_day (local day), to log a flapping one only so often.
    silence_day: dt.date | None = None
    silence_told: Counter[str] = field(default_factory=Counter)
    # The artifact file as loaded ((mtime_ns, size, inode), its hash) and the hash on disk
    # last told: a retrained artifact is only taken at a restart, which the log says.
    artifact_file: tuple[int, int, int] | None = None
    artifact_told: str | None = None
    # Time [unix s] of the last reading that moved the twin: the grid work goes to the
    # twins that heard from their sensors longest ago first (see Service._start_tick).
    last_input: float = 0.0
    # Model → the latest instant it has published: an estimate of an earlier instant (a
    # reading that arrived after a later grid estimate) goes out unretained, so the retained
    # message, what a new subscriber gets, never goes back in time.
    newest_published: dict[str, dt.datetime] = field(default_factory=dict)
    # What the run before this start may have left retained, at the latest: its last grid
    # instant, or its newest journaled input reading (restore() sets it).
    published_floor: dt.datetime | None = None
    # Topic → the last payload retained on it (the estimate, the baselines): sent again
    # when the broker comes back without our session, its retained messages maybe lost.
    retained: dict[str, bytes] = field(default_factory=dict)
    # The last primary estimate published had no value (stale, no reading to hold): the
    # next such one changes nothing and is not sent again.
    without_value: bool = False

    def retains(self, kind: str, topic: str, ts: dt.datetime, payload: bytes) -> bool:
        """Whether ``kind``'s estimate at ``ts`` goes out retained: not when one of a later
        instant has (newest_published, published_floor); if so, it is remembered as the
        newest and as the topic's retained payload."""
        newest = self.newest_published.get(kind, self.published_floor)
        if newest is not None and ts < newest:
            return False
        self.newest_published[kind] = ts
        self.retained[topic] = payload
        return True


class Service:
    """Runs the configured twins against an MQTT broker until stopped."""

    def __init__(self, cfg: ServiceConfig, clock: Clock | None = None,
                 member: FleetMember | None = None) -> None:
        """``member``: this instance's part of a fleet, with ``cfg`` narrowed to it
        (fleet.narrow); None for the one daemon of a site."""
        self.cfg = cfg
        self.member = member
        # One instance of a fleet going offline must not mark the others' twins unavailable.
        self.status_topic = f"{cfg.base_topic}/status" + (f"/{member.name}" if member else "")
        self.clock = clock or SystemClock()
        self.hours = cfg.hours
        # The daemon's clock at start: a reference unheard of since is "silent" only once
        # stale_after has passed (at a fresh start every reference is unheard of at first).
        self.up_since: dt.datetime | None = None
        # The start, the latest connect or the latest journal recovery: readings arriving
        # late for a while after it are a backlog, not a sensor's clock behind.
        self.backlog_since: dt.datetime | None = None
        self.twins: dict[str, TwinRuntime] = {}
        self.by_sensor: dict[str, list[TwinRuntime]] = defaultdict(list)
        problems = []
        for tid, tc in cfg.twins.items():
            art = Artifact.load(tc.artifact)
            for p in check_artifact(tc, art, cfg.hours, cfg.thinning):
                problems.append(f"twins.{tid}: {p}")
            twin = Twin(art, models=cfg.running_kinds(art.primary),
                        stale_after=cfg.stale_after, thinning=cfg.thinning)
            for kind, why in art.withheld.items():
                log.info("twin %s: %s is not published (%s)", tid, kind, why)
            if not art.calibration:
                log.warning("twin %s: %s", tid, UNVALIDATED)
            monitor = TwinMonitor(tid, twin, artifact_hash(tc.artifact), cfg.hours, tc.sensors)
            rt = TwinRuntime(
                tc, twin, monitor, cfg.per_reading_kinds(art.primary),
                cfg.twin_topic(tid, "estimate"), cfg.twin_topic(tid, "monitor"),
                {k: cfg.twin_topic(tid, "baseline", k) for k in twin.kinds if k != art.primary})
            rt.artifact_file = _file_state(tc.artifact)
            self.twins[tid] = rt
            end, today = art.training_end, self.hours.day_of(self.clock.now())
            age = "" if end is None else f"; trained through {end} ({(today - end).days} days ago)"
            log.info("twin %s: %s from %s, estimates on %s%s", tid, art.primary,
                     ", ".join(tc.references), rt.estimate_topic, age)
            for s in {*tc.inputs, *([tc.target] if tc.target else [])}:
                self.by_sensor[s].append(rt)
        if problems:
            raise ConfigError("\n".join(problems))
        self.queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=cfg.queue_size)
        self.stop_event = threading.Event()
        self.connected = threading.Event()
        self.journal = Journal(Path(cfg.state_dir) / "journal", durable=cfg.journal_fsync)
        self.state_lock = StateLock(Path(cfg.state_dir) / "daemon.lock", "daemon")
        self.rejections = RejectionCounter(log, LOG_REJECTIONS_PER_KEY)
        self.health = Health(self._set_status, cfg.queue_size)
        self.metrics = DaemonMetrics(cfg.sensors, self.twins)  # served only with [metrics]
        self.metrics.watch(queue_size=self.queue.qsize, queue_bound=cfg.queue_size,
                           connected=self.connected.is_set, journal_dir=self.journal.folder,
                           journal_healthy=lambda: self.health.journal_failing_since is None,
                           fallbacks=lambda: {t: rt.twin.fallbacks
                                              for t, rt in self.twins.items()})
        self.rejections.on_reject = self.metrics.rejected_one
        for tid, rt in self.twins.items():
            if (end := rt.twin.artifact.training_end) is not None:
                self.metrics.training_end.labels(tid).set(
                    self.hours.at(end + dt.timedelta(days=1), 0.0).timestamp())
        # Readings the journal could not take, in order, not acknowledged: retried every
        # JOURNAL_RETRY_SECONDS (bounded by the broker's in-flight window; see _hold).
        self._held: list[tuple[Reading, tuple[int, int, int]]] = []
        self._republish = threading.Event()  # set on a connect without our session
        self._stale_topics = StaleTopics("daemon")
        self._journal_retry_at = 0.0
        self._journal_s = 0.0  # the current batch's journal writes [s] (_log_long_batch)
        self._journal_recreated = 0
        # Acknowledgements of journaled readings waiting for the journal's sync (a durable
        # journal: sent once the batch's lines are on disk); None: each goes out at once.
        self._unsynced_acks: list[tuple[int, int, int]] | None = None
        self._sync_failing = False  # the last sync failed (logged once per spell)
        # Grid work of the current tick(s) not done yet: the twins in the order to do them,
        # and per twin its pending (instant, health snapshot; None: no monitor then).
        self._tick_work: deque[TwinRuntime] = deque()
        self._tick_due: dict[str, list[tuple[dt.datetime, dict[str, Any] | None]]] = {}
        # The last grid instant started (None: none yet), and the next one the ticker or a
        # reading past it will start (see _catch_up_grid; set again by start()).
        self._grid_started: dt.datetime | None = None
        self._grid_next = self._next_grid(self.clock.now())
        self._paced_since: float | None = None
        # QoS 1 messages handed to paho / acknowledged by the broker (see TICK_BACKLOG).
        self._sent = 0
        self._confirmed = 0
        # QoS 0 messages handed to paho and not written yet: paho calls on_publish for them
        # too (once written), which must not count as a PUBACK. Dropped unwritten by a
        # disconnect (no callback then), so forgotten on connect.
        self._unwritten_qos0: set[int] = set()
        self._awaiting_acks = False  # the worker waits for PUBACKs: wake it (_on_publish)
        self.dropped = 0  # messages paho refused to queue
        self._sent_lock = threading.Lock()
        self._not_before_cache: tuple[dt.date | None, dt.datetime] = (None, dt.datetime.min)
        self.fatal: tuple[int, str] | None = None  # (exit status, why): the process must end
        self.accepted = 0
        self.published = 0
        self.heartbeat = time.monotonic()
        self._gen = 0
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        # Claims of twins (ownership.py): a second daemon publishing one of ours is told.
        self.claims_topic = f"{cfg.base_topic}/{CLAIMS_SUFFIX}"
        self.ownership = Ownership(cfg.broker.client_id, socket.gethostname(), os.getpid(),
                                   self.twins)
        self._claims_refused = 0  # messages on the claims topic that were not claims
        self._next_claim = math.inf  # monotonic time of the next periodic claim
        self._subscription = Subscription(
            [(s.topic, 1) for s in self.cfg.sensors.values()]
            + ([(self.claims_topic, 1)] if self.twins else []), self.connected)
        self.client = self._make_client()
        self.wakeups = WakeCoalescer(self.client)
        self.discovery, self.undiscovery = self._plan_discovery()
        self.outputs, self.unretain = self._plan_outputs()
        self._unretained = False  # the topics of unretain cleared (at the first connect)

    # -- MQTT (network thread: no model work here) -----------------------------------------
    def _make_client(self) -> mqtt.Client:
        c = make_client(self.cfg.broker, self.cfg.broker.client_id, self.status_topic)
        # No in-flight cap: with one, paho walks every unacknowledged message on each PUBACK
        # (Client._update_inflight), a cost per message that grows with the backlog. The
        # grid pacing (TICK_BACKLOG) already keeps what is in flight small.
        c.max_inflight_messages_set(0)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        watch_takeover(c, self.cfg.broker.client_id)
        c.on_message = self._on_message
        c.on_publish = self._on_publish
        c.on_subscribe = self._subscription.on_subscribe
        return c

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: mqtt.ConnectFlags,
                    reason_code: Any, properties: Any) -> None:
        if reason_code.is_failure:
            self.fatal = refused_fatally(reason_code)
            log.error("broker refused the connection: %s%s", reason_code,
                      "; giving up (fix the credentials)" if self.fatal else "; retrying")
            return
        with self._lock:
            self._gen += 1
        self.backlog_since = self.clock.now()  # what the broker kept for us comes now
        with self._sent_lock:
            self._unwritten_qos0.clear()
        self._subscription.subscribe(client)
        self._send(self.status_topic, self.health.status)
        for topic in self.undiscovery:  # Home Assistant entities of twins no longer configured
            self._send(topic, b"")
        if not self._unretained:  # their last estimates, so no one takes them as current
            for topic in self.unretain:
                self._send(topic, b"")
            self._forget_unretained()
        for topic, body in self.discovery.items():
            self._send(topic, body)
        if self.twins:  # after the subscription: the others' answers come to it
            for part in self.ownership.claim():
                self._send(self.claims_topic, part, retain=False)
            self._next_claim = time.monotonic() + CLAIM_EVERY
        if not flags.session_present:
            # A broker that lost our session (restarted without persistence) may have lost
            # the retained estimates too: the worker sends them again (in order with its
            # own publishing, so a newer one is never overtaken by the copy of an older).
            self._republish.set()
            try:
                self.queue.put_nowait(("wake",))
            except queue.Full:
                pass  # busy anyway: it looks at the flag before its next batch
        log.info("connected to %s:%d (session present: %s); subscribing to %d sensor topics%s",
                 self.cfg.broker.host, self.cfg.broker.port, flags.session_present,
                 len(self.cfg.sensors), f" and {self.claims_topic}" if self.twins else "")

    def _plan_discovery(self) -> tuple[dict[str, bytes], list[str]]:
        """Home Assistant discovery: (config topic → payload, config topics to clear)."""
        hc = self.cfg.homeassistant
        twins = [ha.TwinEntities(tid, rt.cfg.quantity, rt.twin.artifact.unit,
                                 rt.twin.artifact.primary,
                                 tuple(k for k in rt.twin.kinds
                                       if k != rt.twin.artifact.primary))
                 for tid, rt in self.twins.items()]
        # Baselines come only on the grid: one late tick must not blank their entities.
        expire = round(max(self.cfg.stale_after, 2 * self.cfg.publish_every).total_seconds())
        current = ha.discovery_messages(
            twins, prefix=hc.discovery_prefix, base_topic=self.cfg.base_topic,
            expire_after=expire, baselines=hc.baselines,
            availability_topic=self.status_topic) if hc.enabled else {}
        published = ha.load_published(Path(self.cfg.state_dir))
        # Twins of other fleet instances are not gone: their owners announce them.
        others = self.member.others if self.member else ()
        return current, ha.removals(published, current, others)

    def _plan_outputs(self) -> tuple[list[str], list[str]]:
        """The retained output topics of the configured twins (estimate, published
        baselines), and those an earlier run published that no twin publishes now (a twin
        removed or renamed, a baseline withheld or turned off): an empty retained payload
        clears each, else a controller still subscribed to an old id gets the last estimate
        as if it were current (``status`` stays ``online``)."""
        current = [topic for rt in self.twins.values()
                   for topic in (rt.estimate_topic, *rt.baseline_topics.values())]
        # Twins of other fleet instances are not gone: their owners publish them.
        theirs = tuple(self.cfg.twin_topic(t, "") for t in
                       (self.member.others if self.member else ()))
        state = Path(self.cfg.state_dir)
        remembered = ha.load_published(state, OUTPUTS_FILE, output_topic)
        # The daemon's own files: the recorder may share the folder and start first, and
        # the lock is there after a first start that failed before publishing anything.
        used = any((state / f).exists() for f in (GRID_FILE, ha.STATE_FILE)) \
            or any(self.journal.folder.glob("*.jsonl"))
        if used and not (state / OUTPUTS_FILE).exists():
            # A state dir of an earlier run without the file: a release before it, or the
            # file deleted. What that run published is unknown, so nothing can be cleared.
            log.warning("%s is missing from %s, which an earlier run used (an older release, "
                        "or the file deleted): the retained estimates and baselines of twins "
                        "removed or renamed before this start are not known and stay retained "
                        "as if current; clear each by hand (mosquitto_pub -r -n -t "
                        "%s/<twin>/estimate, and .../baseline/<kind>). From now on they are "
                        "remembered", OUTPUTS_FILE, state, self.cfg.base_topic)
        gone = sorted(t for t in remembered - set(current) if not t.startswith(theirs))
        return current, gone

    def _forget_unretained(self) -> None:
        """Once cleared, the topics are forgotten: cleared at every connect, they would wipe
        the estimate of a twin another daemon now publishes under that id."""
        self._unretained = True
        if not self.unretain:
            return
        try:
            ha.save_published(Path(self.cfg.state_dir), self.outputs, OUTPUTS_FILE)
        except OSError as exc:  # cleared again at the next start: harmless
            log.warning("cannot update the retained output topics (%s)", exc)

    def _set_status(self, status: str) -> None:
        """``<base>/status`` (a fleet instance's own: ``<base>/status/<instance>``):
        online | degraded (the journal fails) | offline (last will)."""
        if self.client.is_connected():
            self._send(self.status_topic, status)

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any,
                       reason_code: Any, properties: Any) -> None:
        self.connected.clear()
        if not self.stop_event.is_set():
            log.warning("disconnected from the broker (%s); reconnecting", reason_code)

    def _on_message(self, client: mqtt.Client, userdata: Any, msg: mqtt.MQTTMessage) -> None:
        if self.stop_event.is_set():
            return  # stopping: not queued, not acknowledged, redelivered on the next start
        if msg.topic == self.claims_topic:  # bookkeeping, not model work: done here
            self._hear_claim(bytes(msg.payload))
            if msg.qos > 0:  # (on this thread no reconnect can come between: no _lock)
                client.ack(msg.mid, msg.qos)
            return
        token = (self._gen, msg.mid, msg.qos)
        self.health.received += 1
        sensor = self.cfg.sensor_for_topic(msg.topic)
        # perf_counter: the arrival the reading-to-estimate latency counts from.
        item = ("msg", sensor, msg.topic, msg.payload, self.clock.now(), time.perf_counter(),
                token, bool(msg.retain))
        while True:
            try:
                self.queue.put(item, timeout=1.0)
                return
            except queue.Full:
                # Blocking here is the backpressure: unacknowledged QoS 1 messages stay with
                # the broker, nothing is dropped.
                log.warning("reading queue full (%d); the worker is behind", self.queue.maxsize)
                if self.stop_event.is_set():
                    return

    def _ack(self, token: tuple[int, int, int]) -> None:
        if self._unsynced_acks is not None:
            self._unsynced_acks.append(token)
            return
        gen, mid, qos = token
        # A mid from an earlier connection may name another message now: the broker
        # redelivers the old one anyway, and the twins drop it as a duplicate. The lock keeps
        # a reconnect from slipping in between the check and the ack.
        with self._lock:
            if qos > 0 and gen == self._gen:
                self.client.ack(mid, qos)

    def _send(self, topic: str, payload: bytes | str, retain: bool = True, qos: int = 1
              ) -> mqtt.MQTTMessageInfo:
        """Every message of the daemon; QoS 1 ones are counted until the broker acknowledges
        them."""
        if qos == 0:
            # The lock is held across publish: paho's network thread may write the message
            # (and call on_publish) before publish() returns its mid here.
            with self._sent_lock:
                info = self.client.publish(topic, payload, qos=0, retain=retain)
                if info.rc == MQTTErrorCode.MQTT_ERR_SUCCESS:
                    self._unwritten_qos0.add(info.mid)
            return info
        with self._sent_lock:  # from the worker and the network thread
            self._sent += 1
        try:
            info = self.client.publish(topic, payload, qos=1, retain=retain)
        except Exception:
            self._uncount()
            raise
        if info.rc == MQTTErrorCode.MQTT_ERR_QUEUE_SIZE:
            # paho dropped it (e.g. all 65,535 message ids held by unacknowledged messages
            # after a long outage): no PUBACK will ever come for it.
            self._uncount()
            self.dropped += 1
            if self.dropped == 1 or self.dropped % 1000 == 0:
                log.error("%d message(s) dropped by the MQTT client (its queue of "
                          "unacknowledged messages is full), the latest on %s",
                          self.dropped, topic)
        return info

    def _uncount(self) -> None:
        with self._sent_lock:
            self._sent -= 1

    def _on_publish(self, client: mqtt.Client, userdata: Any, mid: int, reason_code: Any,
                    properties: Any) -> None:
        with self._sent_lock:
            if mid in self._unwritten_qos0:  # a QoS 0 message written, not a PUBACK
                self._unwritten_qos0.discard(mid)
                return
        self._confirmed += 1  # only the network thread writes it
        if self._awaiting_acks and self.unconfirmed() < TICK_BACKLOG:
            self._awaiting_acks = False
            try:  # wake the worker: its paced grid work may go on
                self.queue.put_nowait(("wake",))
            except queue.Full:
                pass  # it is busy with readings anyway

    def unconfirmed(self) -> int:
        """Messages sent and not yet acknowledged by the broker."""
        return max(self._sent - self._confirmed, 0)

    def _publish(self, topic: str, payload: bytes, retain: bool = True, qos: int = 1) -> None:
        self._send(topic, payload, retain, qos)
        self.published += 1

    def _tick_paced(self) -> bool:
        """Whether the pending grid work waits for the broker to take what was sent (see
        TICK_BACKLOG); at most TICK_MAX_PAUSE at a time."""
        if not self._tick_work or self.unconfirmed() < TICK_BACKLOG:
            self._paced_since = None
            return False
        now = time.monotonic()
        if self._paced_since is None:
            self._paced_since = now
        elif now - self._paced_since >= TICK_MAX_PAUSE:
            self._paced_since = now  # one chunk anyway, then wait again
            return False
        self._awaiting_acks = True  # before the check again: no PUBACK slips in between
        if self.unconfirmed() < TICK_BACKLOG:
            self._awaiting_acks = False
            return False
        return True

    # -- the worker -----------------------------------------------------------------------
    def _worker(self) -> None:
        # Stops at the next batch once stop_event is set, whatever the queue still holds:
        # those messages are not acknowledged, so the broker delivers them again.
        while not self.stop_event.is_set():
            if self._clock_went_back():
                return
            if self._republish.is_set():
                self._republish.clear()
                self._guarded("reconnect", self._send_retained_again)
            if time.monotonic() >= self._next_claim and self.connected.is_set():
                self._guarded("claim", self._claim_again)
            if self._held and time.monotonic() >= self._journal_retry_at:
                try:
                    self._retry_held()
                except Exception:  # noqa: BLE001 — the worker must outlive a failed retry
                    log.exception("retrying the held readings failed; trying again later")
                    self._journal_retry_at = time.monotonic() + JOURNAL_RETRY_SECONDS
            paced = self._tick_paced()
            wait = (TICK_MAX_PAUSE if paced else 0.0) if self._tick_work \
                else JOURNAL_RETRY_SECONDS if self._held else 1.0
            batch = self._take(wait)
            self.heartbeat = time.monotonic()
            if not batch and not self._tick_work:
                self.health.idle()
                continue
            t0, cpu0, self._journal_s = time.perf_counter(), time.thread_time(), 0.0
            # The batch's acks and messages wake paho's network thread once (wakeup.py).
            with self.wakeups.held():
                if not self._work(batch, paced):
                    return
            if (took := time.perf_counter() - t0) > LONG_BATCH_S:
                self._log_long_batch(batch, took, time.thread_time() - cpu0)

    def _clock_went_back(self) -> bool:
        """A clock stepped back past a grid instant done already (more than max_skew: NTP
        correcting a clock that ran ahead, a VM resumed): the twins' windows, the grid and
        the retained estimates are of a time that has not come. The process ends with
        EX_TEMPFAIL; restarted (systemd, Docker), it rebuilds today from the journal, whose
        readings from that future it keeps out, as a restart after the step would."""
        started = self._grid_started
        if started is None or self.fatal is not None:
            return self.fatal is not None
        now = self.clock.now()
        # In UTC: a local instant minus minutes can land in a DST gap (03:00 − 5 min on the
        # spring day is 02:55, read as an hour earlier), which made the first grid instant
        # after the gap a "step back" that ended the daemon.
        if now >= started.astimezone(dt.UTC) - max(self.cfg.max_skew, CLOCK_BACK_TOLERANCE):
            return False
        # (logged by whoever ends the process: `run` says it with the exit status)
        self.fatal = (EX_TEMPFAIL, f"the clock went back to {now.isoformat()}, before grid "
                                   f"instant {started.isoformat()} done already: today's "
                                   "windows and retained estimates are of a time not come "
                                   "yet; a restart rebuilds them from the journal")
        return True

    def _hear_claim(self, payload: bytes) -> None:
        """A message on the claims topic (network thread): another daemon's claim of twins of
        ours is answered once, and reported once its sender is known to run (ownership.py)."""
        try:
            heard = self.ownership.heard(payload)
        except ValueError as exc:
            self._claims_refused += 1
            if doubled(self._claims_refused - 1, self._claims_refused):
                log.warning("%d message(s) on %s that are not claims of twins, ignored; the "
                            "latest: %s", self._claims_refused, self.claims_topic, exc)
            return
        if heard.answer is not None:
            for part in heard.answer.payloads():
                self._send(self.claims_topic, part, retain=False)
        if heard.reported is not None:
            twins = sorted(heard.twins)
            log.error("%d twin(s) of this daemon are published by another daemon too: %s. "
                      "Each sends its own estimates, and a controller gets both, interleaved. "
                      "Give each twin one owner (overlapping --twins lists? a plain `run` "
                      "beside a fleet?) and stop the other. Twins (those heard yet: a claim "
                      "of many comes in parts, and the gauge "
                      "pseudotwin_twin_other_publishers counts them all): %s%s", len(twins),
                      heard.reported.who(), ", ".join(twins[:10]),
                      f" and {len(twins) - 10} more" if len(twins) > 10 else "")
        if heard.counted:
            self._count_publishers(heard.counted)

    def _count_publishers(self, twins: frozenset[str] | None = None) -> None:
        """The other-publishers gauge of ``twins`` (None: every twin)."""
        for twin, n in self.ownership.publishers(twins).items():
            self.metrics.other_publishers.labels(twin).set(n)

    def _claim_again(self) -> None:
        """The periodic claim (worker): the others see this daemon still runs; and those
        reported whose claims stopped coming are said to be gone."""
        self._next_claim = time.monotonic() + CLAIM_EVERY
        for part in self.ownership.claim():
            self._send(self.claims_topic, part, retain=False)
        gone = self.ownership.gone()
        for claim in gone:
            log.info("no claim from %s for two hours: it no longer publishes twins of this "
                     "daemon", claim.who())
        if gone:
            self._count_publishers()

    def _send_retained_again(self) -> None:
        n = 0
        for rt in self.twins.values():
            for topic, payload in rt.retained.items():
                qos = 1 if topic == rt.estimate_topic else MONITORING_QOS
                self._publish(topic, payload, retain=True, qos=qos)
                n += 1
        if n:
            log.info("the broker had no session of this daemon: its %d retained estimate(s) "
                     "sent again", n)

    def _log_long_batch(self, batch: list[tuple[Any, ...]], took: float, cpu: float) -> None:
        readings = sum(1 for item in batch if item[0] == "msg")
        log.warning("a worker batch took %.0f ms (%.0f ms of it the worker's CPU; journal %.0f "
                    "ms) for %d reading(s) and %d twins' grid work left; the readings behind "
                    "it waited", took * 1e3, cpu * 1e3, self._journal_s * 1e3, readings,
                    len(self._tick_work))

    def _work(self, batch: list[tuple[Any, ...]], paced: bool) -> bool:
        """Handle a batch of queue items, then a slice of grid work; False on stop."""
        messages: list[tuple[Any, ...]] = []
        for item in batch:
            kind = item[0]
            if kind == "stop":
                return False
            if kind == "msg":
                messages.append(item)
            # ("wake",): the broker took enough of what was sent; the loop goes on
            elif kind == "tick":  # readings before it go first, as they arrived
                self._guarded("msg", self._handle_messages, messages)
                messages = []
                if self._grid_started is None or item[1] > self._grid_started:
                    # (else a reading past it started it already)
                    self._start_tick(item[1])
        self._guarded("msg", self._handle_messages, messages)
        # Then a slice of the grid work, so no reading waits behind every twin's tick.
        if not paced:
            self._guarded("tick", self._tick_step)
        return True

    def _take(self, wait: float) -> list[tuple[Any, ...]]:
        """The next queue items: the first within ``wait`` seconds (0: only what is there),
        then what else is there, up to BATCH_MAX."""
        try:
            first = self.queue.get(timeout=wait) if wait > 0 else self.queue.get_nowait()
        except queue.Empty:
            return []
        batch = [first]
        while len(batch) < BATCH_MAX:
            try:
                batch.append(self.queue.get_nowait())
            except queue.Empty:
                break
        return batch

    def _guarded(self, kind: str, handler: Any, *args: Any) -> None:
        try:
            handler(*args)
        except Exception:  # the daemon must outlive any one bad event
            log.exception("unexpected error while handling a %s event", kind)

    def _retry_held(self) -> None:
        """Journal the held readings again, oldest first; on success apply and ack them."""
        done = 0
        # Held before a reconnect: their acks would name other messages now, and the broker
        # redelivers them (never acknowledged) on the new connection anyway.
        # (QoS 0 readings are never redelivered: they stay.)
        self._held = [(r, tok) for r, tok in self._held if tok[0] == self._gen or tok[2] == 0]
        try:
            with self._acks_after_sync():
                while self._held:
                    r, token = self._held[0]
                    self.journal.append(r)
                    self._held.pop(0)
                    self._accept(r, token)
                    done += 1
        except OSError as exc:
            self.health.journal_failed(exc, len(self._held))
            self._journal_retry_at = time.monotonic() + JOURNAL_RETRY_SECONDS
            return
        if self.health.journal_failing_since is not None:
            self.backlog_since = self.clock.now()  # the broker's kept readings come now
        self.health.journal_ok(done)

    def _hold(self, r: Reading, token: tuple[int, int, int]) -> None:
        """Keep an unjournaled reading for the retry. The broker sends no more than its
        in-flight window of unacknowledged messages, so this stays small; past the queue
        bound the oldest is let go unacknowledged (the broker redelivers it on reconnect)."""
        self._held.append((r, token))
        if len(self._held) > self.queue.maxsize:
            self._held.pop(0)

    def _accept(self, r: Reading, token: tuple[int, int, int]) -> None:
        try:
            twins = self.by_sensor.get(r.sensor, ())
            if twins and all(rt.twin.before_window(r.ts) for rt in twins):
                # Yesterday's readings give today's carry-over only until today's window
                # opens; after that no window can take them (DESIGN §6: rejected, counted).
                self.rejections.add(r.sensor, Rejected(
                    Reason.TOO_OLD, f"timestamp {r.ts.isoformat()} is before the current "
                    "window of every twin it feeds"), self.hours.day_of(self.clock.now()))
                return
            self.accepted += 1
            self.metrics.accepted_one(r.sensor)
            if r.ts > self._grid_next:
                self._catch_up_grid(r.ts)
            self._apply(r, publish=True)
        finally:
            self._ack(token)  # journaled: a restart replays it, whatever happened here

    def _not_before(self, today: dt.date) -> dt.datetime:
        # Yesterday's window start: readings redelivered after a night's outage still give
        # today's carry-over; anything older is of no use to any window. Cached per day:
        # asked for every message.
        if self._not_before_cache[0] != today:
            start = self.hours.at(today - dt.timedelta(days=1), self.hours.init_start)
            self._not_before_cache = (today, start)
        return self._not_before_cache[1]

    def _handle_messages(self, items: list[tuple[Any, ...]]) -> None:
        """Parse a batch of messages, journal the valid readings with one write, then apply
        and acknowledge them one by one (each ack after its line is in the kernel)."""
        good: list[tuple[Reading, tuple[int, int, int], float, float]] = []
        for i, item in enumerate(items):
            t0 = time.perf_counter()
            _, sensor, topic, payload, arrival, arrived, token, retained = item
            try:
                # the rest of the batch is still waiting, as if in the queue
                r = self._parse(sensor, topic, payload, arrival, token,
                                backlog=self.queue.qsize() + len(items) - i - 1,
                                retained=retained)
            except Exception:  # noqa: BLE001 — counted, acknowledged: it must not come back
                log.exception("unexpected error while handling a msg event")
                r = None
            if r is None:
                self._ack(token)
            else:
                good.append((r, token, t0, arrived))
        if not good:
            return
        if self._held:  # degraded: keep the order, retry on the worker's schedule
            for r, token, *_ in good:
                self._hold(r, token)
            return
        t_journal = time.perf_counter()
        try:
            self.journal.append_many([r for r, *_ in good])
        except (OSError, ValueError) as exc:  # ValueError: a file closed under the worker
            # Not acknowledged: held and retried; the broker keeps them meanwhile and
            # redelivers them should the daemon stop first.
            for r, token, *_ in good:
                self._hold(r, token)
            self.health.journal_failed(exc, len(self._held))
            self._journal_retry_at = time.monotonic() + JOURNAL_RETRY_SECONDS
            return
        finally:
            self._journal_s += time.perf_counter() - t_journal
        if self.journal.recreated > self._journal_recreated:
            self._journal_recreated = self.journal.recreated
            self.health.journal_rebuilt(self.journal.recreated)
            self.state_lock.renew()  # the state dir went with its lock file
        with self._acks_after_sync():
            for r, token, t0, arrived in good:
                published = self.published
                try:
                    self._accept(r, token)
                except Exception:  # noqa: BLE001 — acked by _accept; the batch goes on
                    log.exception("unexpected error while applying a reading of %s", r.sensor)
                if self.published > published:  # the reading moved a twin: estimates are out
                    t1 = time.perf_counter()
                    self.metrics.latency.observe(t1 - t0)
                    self.metrics.reading_latency.observe(t1 - arrived)

    @contextlib.contextmanager
    def _acks_after_sync(self) -> Iterator[None]:
        """Hold back the acknowledgements of the readings applied inside, then put the
        journal on disk (a durable journal: one fsync for them all) and send them.
        The network thread is woken for the batch's estimates before the sync, so the
        fsync does not hold them back; a power cut before it loses readings the broker has
        not let go of (not yet acknowledged), which it delivers again. A failed sync (the
        disk failing) is logged and the readings acknowledged all the same: they are in the
        kernel, as without journal_fsync, and holding them would stop the broker's
        deliveries."""
        if not self.journal.durable or self._unsynced_acks is not None:
            yield  # (nested: the outer block syncs and sends them all)
            return
        self._unsynced_acks = []
        try:
            yield
        finally:
            acks, self._unsynced_acks = self._unsynced_acks, None
            self.wakeups.flush()  # the estimates go out while the worker waits for the disk
            t0 = time.perf_counter()
            try:
                self.journal.sync()
                if self._sync_failing:
                    self._sync_failing = False
                    log.warning("journal: syncing to disk works again (%s)", self.journal.folder)
            except Exception as exc:  # noqa: BLE001 — OSError, or ValueError: a closed file
                if not self._sync_failing:
                    self._sync_failing = True
                    log.error("journal: syncing %s to disk failed (%s); readings are "
                              "acknowledged from the kernel's cache, so a power cut may lose "
                              "the latest; check the disk", self.journal.folder, exc)
            finally:
                self._journal_s += time.perf_counter() - t0
            for token in acks:
                self._ack(token)

    def _parse(self, sensor: SensorConfig | None, topic: str, payload: bytes,
               arrival: dt.datetime, token: tuple[int, int, int], *, backlog: int,
               retained: bool = False) -> Reading | None:
        """The message's reading, or None (rejected and counted; the caller acks).
        backlog: messages waiting behind this one (the health's flood detection)."""
        if sensor is None:
            self._stale_topics.drop(self.client, topic)
            return None
        day = self.hours.day_of(arrival)
        try:
            r = parse_payload(sensor, payload, arrival, max_skew=self.cfg.max_skew,
                              not_before=self._not_before(day),
                              on_ahead=lambda s: self.rejections.ahead(sensor.id, s, day),
                              retained=retained)
        except Rejected as rej:
            self.rejections.add(sensor.id, rej, day)
            return None
        except Exception as exc:  # noqa: BLE001 — a parser bug must not stall the pipeline
            log.exception("payload on %s could not be processed", topic)
            self.rejections.add_reason(sensor.id, UNPROCESSABLE, repr(exc)[:200], day)
            return None
        # Late past stale_after, once a backlog (readings queued while the daemon was down,
        # disconnected or held by a failing journal) is through: a clock behind, or a
        # bridge on another time zone.
        lag = arrival - r.ts
        if lag > self.cfg.stale_after and self.backlog_since is not None \
                and arrival - self.backlog_since > self.cfg.stale_after:
            self.rejections.behind(sensor.id, lag.total_seconds(), day)
        self.health.processed_one(lag.total_seconds(), backlog)
        return r

    def _apply(self, r: Reading, publish: bool) -> None:
        for rt in self.by_sensor.get(r.sensor, ()):
            if rt.cfg.id in self._tick_due:  # the tick came first: its estimates go first
                self._guarded("tick", self._run_due, rt)
            with twin_context(rt.cfg.id):  # the twin's log lines name it
                try:  # one twin's failure must not keep the reading from the others
                    if r.sensor in rt.twin.inputs:
                        if rt.twin.observe(r.sensor, r.ts, r.value):
                            rt.last_input = r.ts.timestamp()
                            if publish:
                                # A late reading (another input is newer) revises the
                                # estimate of the newest instant: the retained estimate
                                # never goes back in time. Nor ahead of the clock: a
                                # sensor's clock running fast (within max_skew) must not
                                # stamp estimates that outrank the grid's after them.
                                at = min(max(r.ts, rt.twin.newest() or r.ts),
                                         self.clock.now())
                                self._publish_estimates(
                                    rt, rt.twin.estimate(at, kinds=rt.reading_kinds))
                    elif r.sensor == rt.cfg.target:
                        self._score_target(rt, r)
                except Exception:  # noqa: BLE001 — logged with its traceback; the rest goes on
                    log.exception("failed on a reading of %s", r.sensor)

    def _score_target(self, rt: TwinRuntime, r: Reading) -> None:
        h = self.hours.hours_of(r.ts)
        if not self.hours.in_operating_hours(h):
            return
        primary = rt.twin.artifact.primary
        est = rt.twin.estimate(r.ts, kinds=(primary,)).get(primary)
        if est is not None and est.finite:
            rt.monitor.roll(self.hours.day_of(r.ts))
            rt.monitor.record_truth(r.value, est.value, est.std)

    def _publish_estimates(self, rt: TwinRuntime, ests: dict[str, TwinEstimate]) -> None:
        primary = rt.twin.artifact.primary
        unit = rt.twin.artifact.unit
        for kind, e in ests.items():
            if not e.publishable:
                if kind == primary and e.quality == Quality.STALE:
                    self._note_silence(rt, e)  # no value: a reference never heard
                    self._publish_no_value(rt, e)
                continue
            if kind == primary:
                topic, qos = rt.estimate_topic, 1
                rt.monitor.roll(self.hours.day_of(e.ts))
                rt.monitor.record_estimate(e.std)
            else:
                topic, qos = rt.baseline_topics[kind], MONITORING_QOS
            payload = estimate_payload(e, unit)
            retain = rt.retains(kind, topic, e.ts, payload)
            if retain and kind == primary:
                rt.without_value = False
            self._publish(topic, payload, retain=retain, qos=qos)
            if kind == primary:
                self.metrics.published(rt.cfg.id, e.quality, e.ts)
                self._note_silence(rt, e)

    def _publish_no_value(self, rt: TwinRuntime, e: TwinEstimate) -> None:
        """A stale primary estimate without a value (no reading of a reference to hold,
        e.g. after a weekend's restart) goes out once, retained, with ``value`` and ``std``
        null: the retained message would otherwise stay the last one with a value, often
        ``ok``, what every new subscriber takes for the current state."""
        if rt.without_value:
            return  # said already
        payload = estimate_payload(e, rt.twin.artifact.unit)
        if not rt.retains(rt.twin.artifact.primary, rt.estimate_topic, e.ts, payload):
            return  # an older instant: it must not replace the retained message
        rt.without_value = True
        # Not counted among the published estimates: the age of the last estimate (with a
        # value) is what an alert on a silent twin watches.
        self._publish(rt.estimate_topic, payload, retain=True, qos=1)

    def _note_silence(self, rt: TwinRuntime, e: TwinEstimate) -> None:
        """Log when references fall silent for the primary (a failover answers, or the
        estimate is stale) and when they report again: a sensor, bridge or broker ACL that
        stops delivering shows in the payloads' quality, and now in the log, once."""
        limit = self.cfg.stale_after
        silent = e.lost or (rt.twin.silent_references(rt.twin.artifact.primary, e.ts)
                            if e.quality == Quality.STALE else ())
        if self.up_since is not None and e.ts - self.up_since <= limit:
            # unheard of since a start less than stale_after ago: not silent for that long
            silent = tuple(s for s in silent if e.refs.get(s) is not None)
        if silent == rt.silent:
            return
        day = self.hours.day_of(e.ts)
        if day != rt.silence_day:
            rt.silence_day, rt.silence_told = day, Counter()
        went = [s for s in silent if s not in rt.silent]
        rt.silence_told.update(went)
        # A sensor reporting just slower than stale_after flips at every reading: its first
        # SILENCE_LINES_PER_DAY silences of a day are logged, and that it flaps, then nothing.
        if told := [s for s in went if rt.silence_told[s] <= SILENCE_LINES_PER_DAY]:
            last = ", ".join(f"{s} (last reading {_clock(e.refs.get(s))})" for s in told)
            now = (f"a failover answers ({e.model}, quality {e.quality})" if e.lost
                   else "the estimate is stale")
            flapping = [s for s in told if rt.silence_told[s] == SILENCE_LINES_PER_DAY]
            log.warning("reference(s) silent for more than %g min at %s: %s; %s. Check the "
                        "sensor, its bridge, and that the broker lets this client read the "
                        "topic (ACL)%s", limit.total_seconds() / 60, _clock(e.ts), last, now,
                        f". {', '.join(flapping)}: silent {SILENCE_LINES_PER_DAY} times today "
                        "(reporting about as slowly as stale_after?); not logged again today"
                        if flapping else "")
        back = [s for s in rt.silent if s not in silent]
        if back := [s for s in back if rt.silence_told[s] <= SILENCE_LINES_PER_DAY]:
            log.info("reference(s) %s report again at %s: estimate from %s (quality %s)",
                     ", ".join(back), _clock(e.ts), e.model, e.quality)
        rt.silent = silent

    def _catch_up_grid(self, ts: dt.datetime) -> None:
        """Start the grid instants before reading time ``ts`` that are due by the clock but
        whose tick has not come yet (within its TICK_GRACE, or a late ticker): their
        estimates must not see this reading. Not those still ahead of the clock: a sensor
        whose clock runs fast does not move the grid."""
        now = self.clock.now()
        while self._grid_next < ts and self._grid_next <= now:
            self._start_tick(self._grid_next)

    def _start_tick(self, instant: dt.datetime) -> None:
        """Queue every twin's grid work for ``instant``; the worker does it TICK_CHUNK twins
        at a time between batches of readings (one health snapshot for all of them), and a
        twin's own before any later reading reaches it (see _apply): the estimate at the
        instant sees exactly the readings that arrived before the tick."""
        self._grid_started = instant
        self._grid_next = self._next_grid(instant)
        self._remember_tick(instant)
        health = self.health.snapshot() if self._monitor_at(instant) else None
        # A reading of a twin whose grid work is still queued does that work first (its
        # estimates and messages, ~1 ms): in config order, most of the readings arriving
        # during a thousand twins' grid work did. The twins that heard from their sensors
        # longest ago are the next to hear again (cyclic or heartbeat sensors): theirs first.
        for rt in sorted(self.twins.values(), key=attrgetter("last_input")):
            self._tick_due.setdefault(rt.cfg.id, []).append((instant, health))
            self._tick_work.append(rt)

    def _monitor_at(self, instant: dt.datetime) -> bool:
        """Whether ``<twin>/monitor`` goes out at grid instant ``instant``: the day's first and
        last grid instants (the day's final figures), and the first one at or after each
        multiple of ``monitor_every_minutes`` since local midnight."""
        every = self.cfg.monitor_every_minutes * 60.0
        step = self.cfg.publish_every.total_seconds()
        grid = self.hours.grid(self.hours.day_of(instant), step / 3600.0)
        s = round(self.hours.hours_of(instant) * 3600.0, 3)
        return instant in (grid[0], grid[-1]) or s // every != (s - step) // every

    def _tick_step(self) -> None:
        done = 0
        while done < TICK_CHUNK and self._tick_work:
            rt = self._tick_work.popleft()
            if rt.cfg.id in self._tick_due:  # else a reading already ran it
                self._run_due(rt)
                done += 1

    def _run_due(self, rt: TwinRuntime) -> None:
        """The twin's pending grid work (none when a reading already ran it)."""
        for instant, health in self._tick_due.pop(rt.cfg.id, ()):
            self._handle_tick_of(rt, instant, health)

    def _handle_tick_of(self, rt: TwinRuntime, instant: dt.datetime,
                        health: dict[str, Any] | None) -> None:
        with twin_context(rt.cfg.id):
            self._publish_estimates(rt, rt.twin.estimate(instant))
        tw = rt.twin
        state = (tw.uncertain_since, tw.uncertain_why, tw.failover_since, tw.failover_lost)
        if health is None:  # not a monitor instant (_monitor_at) ...
            if state == rt.monitor_state and not tw.spells_ended:
                return
            health = self.health.snapshot()  # ... but why the estimate changed must not wait
        rt.monitor_state = state
        self._artifact_replaced(rt)
        rejected = self.rejections.of_day(self.hours.day_of(instant))
        self._publish(rt.monitor_topic,
                      monitor_payload({**rt.monitor.snapshot(instant, rejected),
                                       "ended": tw.take_ended_spells(), "health": health}),
                      retain=False, qos=MONITORING_QOS)

    def _artifact_replaced(self, rt: TwinRuntime) -> None:
        """Log, once per new file, that the twin's artifact on disk is no longer the one
        this daemon runs (retrained while it ran): the daemon keeps the one it loaded, and
        nothing else would say that the new one waits for a restart."""
        now = _file_state(rt.cfg.artifact)
        if now is None or now == rt.artifact_file:
            return
        try:
            disk = artifact_hash(rt.cfg.artifact)
        except OSError:
            return
        rt.artifact_file = now  # hashed once per state of the file, not at every monitor
        if disk == rt.monitor.artifact_hash:  # touched or copied, the same artifact
            return
        if disk != rt.artifact_told:
            rt.artifact_told = disk
            log.warning("twin %s: %s changed on disk (now %s; this daemon runs %s, loaded at "
                        "start): the new artifact is taken at the next restart, after "
                        "check-config", rt.cfg.id, rt.cfg.artifact, disk[:16],
                        rt.monitor.artifact_hash[:16])

    # -- timers ---------------------------------------------------------------------------
    def _next_grid(self, after: dt.datetime) -> dt.datetime:
        step_h = self.cfg.publish_every.total_seconds() / 3600.0
        day = self.hours.day_of(after)
        for k in range(3):
            for t in self.hours.grid(day + dt.timedelta(days=k), step_h):
                if t > after:
                    return t
        raise RuntimeError("no grid instant in three days")  # unreachable with valid config

    def _ticker(self, origin: dt.datetime) -> None:
        t = origin
        while not self.stop_event.is_set():
            t = self._next_grid(t)
            if not self.clock.wait_until(t + TICK_GRACE, self.stop_event):
                return
            while not self.stop_event.is_set():  # never block a stop on a full queue
                try:
                    self.queue.put(("tick", t), timeout=1.0)
                    break
                except queue.Full:
                    continue

    def _watchdog(self, interval: float) -> None:
        while not self.stop_event.wait(interval):
            if time.monotonic() - self.heartbeat < 4 * interval:
                notify("WATCHDOG=1")
            else:
                log.error("worker unresponsive for %.0f s; withholding the watchdog ping",
                          time.monotonic() - self.heartbeat)

    # -- life cycle -----------------------------------------------------------------------
    def restore(self) -> int:
        """Rebuild today's windows from the journal — or, with no journal of today and a
        history store configured (a warm start), from the store. Returns readings replayed."""
        n = 0
        now = self.clock.now()
        since = self._not_before(self.hours.day_of(now)) - dt.timedelta(days=1)
        horizon = now + self.cfg.max_skew
        later: list[Reading] = []
        for r in self.journal.replay(since):
            if r.ts > horizon:
                # Journaled by a run whose clock was ahead (the clock jumped back, a replay's
                # state dir run again, state copied from elsewhere): a reading of a day to
                # come would move the twins' window to it and silence today's, one of later
                # today would stand in the window as the latest reading all morning. Kept on
                # disk, not replayed.
                later.append(r)
                continue
            self._apply(r, publish=False)  # guarded per twin, as live
            n += 1
        if later:
            log.warning("journal holds %d readings after the daemon's clock (%s .. %s, clock "
                        "%s, more than max_skew ahead): did the clock jump back, or is this "
                        "state dir a replay's run again? They are not replayed; today's window "
                        "starts from the rest", len(later), min(r.ts for r in later).isoformat(),
                        max(r.ts for r in later).isoformat(), now.isoformat())
        if n:
            log.info("restored state from %d journaled readings", n)
        self._set_published_floor(now)  # from the journal's readings, not the store's
        if not n and self.cfg.store:
            n = self._warm_start(since, now)
        return n

    def _set_published_floor(self, now: dt.datetime) -> None:
        """The retained estimate never goes back in time, across a restart too. The run
        before published, at the latest, at the last grid instant it ticked (GRID_FILE) and
        at its newest journaled input reading (restored from the journal, before any warm
        start): an estimate of an earlier instant now goes out unretained, as it would have
        in that run. A first start (neither) has no floor."""
        ticked = self._last_ticked()
        if ticked is not None and ticked > now + self.cfg.max_skew:
            # Ticked by a run whose clock was ahead: as a floor it would keep every estimate
            # of today unretained, and the stale one of that future instant retained.
            log.warning("%s says grid instant %s was done, after the daemon's clock %s: did "
                        "the clock jump back? It is not taken as the floor of the retained "
                        "estimates", GRID_FILE, ticked.isoformat(), now.isoformat())
            ticked = None
        for rt in self.twins.values():
            newest = rt.twin.newest()
            floors = [t for t in (ticked, None if newest is None else min(newest, now))
                      if t is not None]
            rt.published_floor = max(floors, default=None)

    def _last_ticked(self) -> dt.datetime | None:
        path = Path(self.cfg.state_dir) / GRID_FILE
        try:
            ticked = dt.datetime.fromisoformat(json.loads(path.read_text())["ticked"])
            if ticked.utcoffset() is None:
                raise ValueError(f"{ticked.isoformat()} has no UTC offset")
            return ticked
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("%s unreadable (%s): a late reading's estimate may replace a newer "
                        "retained one once", path, exc)
            return None

    def _remember_tick(self, instant: dt.datetime) -> None:
        """Written before the instant's estimates go out: a floor too late by one crash
        only sends a late reading's estimate unretained, never the other way round."""
        path = Path(self.cfg.state_dir) / GRID_FILE
        text = json.dumps({"ticked": instant.isoformat()})
        try:
            write_replacing(path, lambda tmp: tmp.write_text(text, encoding="utf-8"),
                            follow_symlinks=False)
        except OSError as exc:
            log.debug("cannot remember the grid instant in %s: %s", path, exc)

    def _warm_start(self, since: dt.datetime, now: dt.datetime) -> int:
        from pseudotwin.history.store import open_store

        sensors = sorted(self.by_sensor)
        assert self.cfg.store is not None
        if (file := absent_sqlite_file(self.cfg.store)) is not None:
            # The recorder makes it; an empty one made here would hide a mistyped path.
            log.warning("warm start: no history store at %s yet (the recorder creates it; "
                        "a relative path is from the configuration's folder); today's "
                        "windows start empty", file)
            return 0
        try:
            # Only readings are read: a store older recorders write to stays as it is.
            with open_store(self.cfg.store, existing=True, migrate=False) as store:
                # as far ahead as restore() takes journaled readings: a sensor whose clock
                # runs ahead has its latest reading stamped up to max_skew after now
                frame = store.read_readings(sensors, since, now + self.cfg.max_skew
                                            + dt.timedelta(seconds=1))
        except Exception as exc:  # noqa: BLE001 — a warm start is best effort
            log.warning("warm start from the history store failed (%s); starting empty", exc)
            return 0
        if len(taken := in_range(frame, self.cfg.sensors)) < len(frame):
            log.warning("warm start: left out %d stored reading(s) outside their sensor's "
                        "configured min..max, as a reading over MQTT would be rejected",
                        len(frame) - len(taken))
            frame = taken
        readings = [Reading(s, ts.to_pydatetime(), float(v))
                    for s, ts, v in zip(frame["sensor"], frame["ts"], frame["value"], strict=True)]
        for r in readings:
            self._apply(r, publish=False)
        # Journaled too: a restart later today restores from the journal alone, and without
        # them it would lose the morning the store gave.
        try:
            self.journal.append_many(readings)
        except OSError as exc:
            log.warning("warm start: the %d stored readings could not all be journaled (%s); "
                        "a restart today may start without some of them", len(readings), exc)
        log.info("warm start: rebuilt today's windows from %d stored readings", len(frame))
        return len(frame)

    def start(self, wait_connected: float | None = 30.0) -> None:
        # first: a second daemon here must not touch the journal
        self.state_lock.starting(lambda: self._start(wait_connected), self.metrics.close)

    def _start(self, wait_connected: float | None) -> None:
        if self.member is not None:  # first: a failing start says which instance it was
            log.info("fleet: %s; client id %s, state %s, status %s", self.member.describe(),
                     self.cfg.broker.client_id, self.cfg.state_dir, self.status_topic)
        self.up_since = self.backlog_since = self.clock.now()
        self.ownership.start(dt.datetime.now(dt.UTC))  # a run's identity: not a replay's clock
        if self.cfg.metrics.port is not None:  # a port in use fails before anything runs
            self.metrics.serve(self.cfg.metrics.host, self.cfg.metrics.port, "daemon")
        self.restore()
        if self.discovery or self.undiscovery:  # remembered before they go out: see _on_connect
            try:
                ha.save_published(Path(self.cfg.state_dir), [*self.discovery, *self.undiscovery])
            except OSError as exc:  # published all the same; only a later removal needs it
                log.warning("cannot remember the Home Assistant discovery topics (%s)", exc)
        try:
            ha.save_published(Path(self.cfg.state_dir), [*self.outputs, *self.unretain],
                              OUTPUTS_FILE)
        except OSError as exc:
            log.warning("cannot remember the retained output topics (%s)", exc)
        if self.unretain:
            log.info("clearing the retained outputs of %d topic(s) no twin publishes now: %s",
                     len(self.unretain), ", ".join(self.unretain[:10]))
        b = self.cfg.broker
        self.client.connect_async(b.host, b.port, keepalive=b.keepalive)
        self.client.loop_start()
        if not self.wakeups.install():
            log.info("this paho-mqtt has no wake-up socket pair: every message wakes its "
                     "network thread")
        # The grid's first instant is the first whose tick is still to come: a daemon up
        # within TICK_GRACE after an instant (at a restart on the hour, say) does its work.
        origin = self.clock.now() - TICK_GRACE
        self._grid_next = self._next_grid(origin)
        for target, args in ((self._worker, ()), (self._ticker, (origin,))):
            th = threading.Thread(target=target, args=args, daemon=True,
                                  name=target.__name__.strip("_"))
            th.start()
            self._threads.append(th)
        interval = watchdog_interval()
        if interval:
            th = threading.Thread(target=self._watchdog, args=(interval,), daemon=True,
                                  name="watchdog")
            th.start()
        # READY=1 is sent once subscribed (mqttconn.Subscription): systemd's start waits for the
        # broker (bounded by TimeoutStartSec). Connection failures are logged as they
        # happen (mqttconn.py).
        if wait_connected is not None and not self.connected.wait(wait_connected):
            log.warning("not connected to %s:%d yet; still trying", b.host, b.port)
        log.info("pseudotwin started: %d twin(s), %d sensor(s)%s", len(self.twins),
                 len(self.cfg.sensors), "" if self.connected.is_set()
                 else f"; connecting to {b.host}:{b.port}")
        if self.member is not None:
            if not self.twins:
                log.warning("fleet: %s owns no twin; it stays connected and idle (more "
                            "instances than twins, or an unlucky split)", self.member.label)

    def stop(self) -> None:
        """Stop within seconds: the worker finishes the item in hand and leaves the rest of
        the queue unacknowledged (the broker redelivers it); close the journal, publish
        status offline."""
        notify("STOPPING=1")
        self.stop_event.set()
        try:
            self.queue.put_nowait(("stop",))
        except queue.Full:
            pass  # the worker sees stop_event after its current item
        for th in self._threads:
            th.join(STOP_JOIN_SECONDS)  # the journal must outlive the worker
            if th.is_alive():
                log.error("%s thread still busy after %.0f s; stopping anyway", th.name,
                          STOP_JOIN_SECONDS)
        left = self.queue.qsize() + len(self._held)
        if left:
            log.info("%d received messages left unacknowledged; the broker delivers them "
                     "again on the next start", left)
        try:
            self.journal.close()
        except OSError as exc:
            log.error("closing the journal failed (%s)", exc)
        if self.client.is_connected():
            info = self._send(self.status_topic, "offline")
            try:
                info.wait_for_publish(timeout=2)  # behind queued estimates: bounded
            except (RuntimeError, ValueError):
                pass
        self.client.disconnect()
        self.client.loop_stop()
        self.metrics.close()
        self.state_lock.release()
        log.info("stopped: %d readings accepted, %d messages published, %d rejected",
                 self.accepted, self.published, self.rejections.run_total)


def _file_state(path: Path) -> tuple[int, int, int] | None:
    """(mtime_ns, size, inode) of ``path``, None when it cannot be read: what tells a file
    replaced (train writes a new file over the old one) without reading it."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


def output_topic(topic: str) -> bool:
    """Whether ``topic`` has the shape of a twin's retained output: ``<base>/<twin>/estimate``
    or ``<base>/<twin>/baseline/<kind>`` (of any base: one changed since is cleared too)."""
    levels = topic.split("/")
    return (len(levels) >= 3 and levels[-1] == "estimate") or \
        (len(levels) >= 4 and levels[-2] == "baseline")
