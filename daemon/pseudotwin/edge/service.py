"""The live daemon: MQTT readings in, pseudo-measurements out, for days on end.

Threads, and why:
- paho's network thread only turns a message into a queue item (no parsing, no model work);
- one worker owns every twin and does all model work, in arrival order, so estimates are
  deterministic and equal to ``evaluate``'s for the same readings;
- a ticker enqueues the publish-grid instants; a watchdog tells systemd the worker is alive.

Delivery: QoS 1, persistent session (clean_session False, stable client id), manual acks. A
reading is acknowledged only after it is journaled (see journal.py) and applied, so neither
a broker restart nor a SIGKILL of the daemon loses one; redeliveries are recognized as
duplicates by the twins.
"""

from __future__ import annotations

import datetime as dt
import logging
import queue
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import paho.mqtt.client as mqtt

from pseudotwin.config import SensorConfig, ServiceConfig, TwinConfig
from pseudotwin.edge.clock import Clock, SystemClock
from pseudotwin.edge.journal import Journal
from pseudotwin.edge.mqttconn import make_client
from pseudotwin.edge.outputs import estimate_payload, monitor_payload
from pseudotwin.edge.sdnotify import notify, watchdog_interval
from pseudotwin.errors import ConfigError
from pseudotwin.live.artifact import Artifact, artifact_hash
from pseudotwin.live.readings import Reading, Rejected, RejectionCounter, parse_payload
from pseudotwin.live.twin import Twin, TwinEstimate

log = logging.getLogger(__name__)

LOG_REJECTIONS_PER_KEY = 10  # per sensor, reason and day; the rest are only counted


def check_artifact(twin: TwinConfig, art: Artifact | None = None, hours=None) -> list[str]:
    """Problems between a twin's configuration and its artifact (empty when they fit)."""
    art = art or Artifact.load(twin.artifact)
    problems = []
    if set(twin.references) != set(art.references):
        problems.append(
            f"references {sorted(twin.references)} differ from the artifact's "
            f"{sorted(art.references)}"
        )
    if twin.target is not None and twin.target != art.target:
        problems.append(f"target {twin.target!r} differs from the artifact's {art.target!r}")
    if twin.quantity != art.quantity:
        problems.append(f"quantity {twin.quantity!r} differs from the artifact's {art.quantity!r}")
    if hours is not None and hours != art.hours:
        problems.append(
            f"operating hours / slot grid / time zone {hours.to_dict()} differ from those the "
            f"artifact was trained with {art.hours.to_dict()}"
        )
    return problems


@dataclass
class TwinRuntime:
    """One configured twin with its live bookkeeping for today's monitor."""

    cfg: TwinConfig
    twin: Twin
    artifact_hash: str
    day: dt.date | None = None
    stds: list[float] = field(default_factory=list)
    pairs: list[tuple[float, float]] = field(default_factory=list)  # (truth, estimate)

    def roll(self, day: dt.date) -> None:
        if day != self.day:
            self.day, self.stds, self.pairs = day, [], []


class Service:
    """Runs the configured twins against an MQTT broker until stopped."""

    def __init__(self, cfg: ServiceConfig, clock: Clock | None = None) -> None:
        self.cfg = cfg
        self.clock = clock or SystemClock()
        self.hours = cfg.hours
        self.twins: dict[str, TwinRuntime] = {}
        self.by_sensor: dict[str, list[TwinRuntime]] = defaultdict(list)
        problems = []
        for tid, tc in cfg.twins.items():
            art = Artifact.load(tc.artifact)
            for p in check_artifact(tc, art, cfg.hours):
                problems.append(f"twins.{tid}: {p}")
            twin = Twin(art, stale_after=cfg.stale_after)
            rt = TwinRuntime(tc, twin, artifact_hash(tc.artifact))
            self.twins[tid] = rt
            for s in {*tc.references, *([tc.target] if tc.target else [])}:
                self.by_sensor[s].append(rt)
        if problems:
            raise ConfigError("\n".join(problems))
        self.queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=cfg.queue_size)
        self.stop_event = threading.Event()
        self.connected = threading.Event()
        self.journal = Journal(Path(cfg.state_dir) / "journal")
        self.rejections = RejectionCounter(log, LOG_REJECTIONS_PER_KEY)
        self.accepted = 0
        self.published = 0
        self.heartbeat = time.monotonic()
        self._gen = 0
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self.client = self._make_client()
        self.status_topic = f"{cfg.base_topic}/status"

    # -- MQTT (network thread: no model work here) -----------------------------------------
    def _make_client(self) -> mqtt.Client:
        c = make_client(self.cfg.broker, self.cfg.broker.client_id,
                        f"{self.cfg.base_topic}/status")
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_message = self._on_message
        return c

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            log.error("broker refused the connection: %s", reason_code)
            return
        with self._lock:
            self._gen += 1
        topics = [(s.topic, 1) for s in self.cfg.sensors.values()]
        client.subscribe(topics)
        client.publish(self.status_topic, "online", qos=1, retain=True)
        log.info("connected to %s:%d (session present: %s); subscribed to %d sensor topics",
                 self.cfg.broker.host, self.cfg.broker.port, flags.session_present, len(topics))
        self.connected.set()

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        self.connected.clear()
        if not self.stop_event.is_set():
            log.warning("disconnected from the broker (%s); reconnecting", reason_code)

    def _on_message(self, client, userdata, msg: mqtt.MQTTMessage) -> None:
        sensor = self.cfg.sensor_for_topic(msg.topic)
        item = ("msg", sensor, msg.topic, msg.payload, self.clock.now(),
                (self._gen, msg.mid, msg.qos))
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
        gen, mid, qos = token
        # A mid from an earlier connection may name another message now: the broker
        # redelivers the old one anyway, and the twins drop it as a duplicate. The lock keeps
        # a reconnect from slipping in between the check and the ack.
        with self._lock:
            if qos > 0 and gen == self._gen:
                self.client.ack(mid, qos)

    def _publish(self, topic: str, payload: bytes, retain: bool = True) -> None:
        self.client.publish(topic, payload, qos=1, retain=retain)
        self.published += 1

    # -- the worker -----------------------------------------------------------------------
    def _worker(self) -> None:
        while True:
            try:
                item = self.queue.get(timeout=1.0)
            except queue.Empty:
                self.heartbeat = time.monotonic()
                continue
            self.heartbeat = time.monotonic()
            kind = item[0]
            if kind == "stop":
                return
            try:
                if kind == "msg":
                    self._handle_message(*item[1:])
                elif kind == "tick":
                    self._handle_tick(item[1])
            except Exception:  # the daemon must outlive any one bad event
                # Not acknowledged: what failed before the journal is delivered again.
                log.exception("unexpected error while handling a %s event", kind)

    def _not_before(self, now: dt.datetime) -> dt.datetime:
        # Yesterday's window start: readings redelivered after a night's outage still give
        # today's carry-over; anything older is of no use to any window.
        day = self.hours.day_of(now) - dt.timedelta(days=1)
        return self.hours.at(day, self.hours.init_start)

    def _handle_message(self, sensor: SensorConfig | None, topic: str, payload: bytes,
                        arrival: dt.datetime, token: tuple[int, int, int]) -> None:
        if sensor is None:
            log.warning("message on unexpected topic %s ignored", topic)
            self._ack(token)
            return
        try:
            r = parse_payload(sensor, payload, arrival, max_skew=self.cfg.max_skew,
                              not_before=self._not_before(arrival))
        except Rejected as rej:
            self.rejections.add(sensor.id, rej, self.hours.day_of(arrival))
            self._ack(token)
            return
        try:
            self.journal.append(r)
        except OSError as exc:
            # Not acknowledged: the broker keeps it and delivers it again after a reconnect.
            log.error("journal write failed (%s); reading of %s not acknowledged", exc, r.sensor)
            return
        self.accepted += 1
        try:
            self._apply(r, publish=True)
        finally:
            self._ack(token)  # journaled: a restart replays it, whatever happened here

    def _apply(self, r: Reading, publish: bool) -> None:
        for rt in self.by_sensor.get(r.sensor, ()):
            try:  # one twin's failure must not keep the reading from the others
                if r.sensor in rt.twin.references:
                    if rt.twin.observe(r.sensor, r.ts, r.value) and publish:
                        self._publish_estimates(rt, rt.twin.estimate(r.ts))
                elif r.sensor == rt.cfg.target:
                    self._score_target(rt, r)
            except Exception:  # noqa: BLE001 — logged with its traceback; the rest goes on
                log.exception("twin %s failed on a reading of %s", rt.cfg.id, r.sensor)

    def _score_target(self, rt: TwinRuntime, r: Reading) -> None:
        h = self.hours.hours_of(r.ts)
        if not self.hours.in_operating_hours(h):
            return
        est = rt.twin.estimate(r.ts).get(rt.twin.artifact.primary)
        if est is not None and est.finite:
            rt.roll(self.hours.day_of(r.ts))
            rt.pairs.append((r.value, est.value))

    def _publish_estimates(self, rt: TwinRuntime, ests: dict[str, TwinEstimate]) -> None:
        primary = rt.twin.artifact.primary
        unit = rt.twin.artifact.unit
        for kind, e in ests.items():
            if not e.publishable:
                continue
            if kind == primary:
                topic = self.cfg.twin_topic(rt.cfg.id, "estimate")
                rt.roll(self.hours.day_of(e.ts))
                rt.stds.append(e.std)
            else:
                topic = self.cfg.twin_topic(rt.cfg.id, "baseline", kind)
            self._publish(topic, estimate_payload(e, unit))

    def _handle_tick(self, instant: dt.datetime) -> None:
        for rt in self.twins.values():
            self._publish_estimates(rt, rt.twin.estimate(instant))
            self._publish(self.cfg.twin_topic(rt.cfg.id, "monitor"),
                          monitor_payload(self._monitor(rt, instant)), retain=False)

    def _monitor(self, rt: TwinRuntime, now: dt.datetime) -> dict[str, Any]:
        tw = rt.twin
        out: dict[str, Any] = {
            "ts": now, "day": str(self.hours.day_of(now)), "twin": rt.cfg.id,
            "artifact": rt.artifact_hash[:16],
            "window_readings": len(tw.window),
            "mean_std": float(np.mean(rt.stds)) if rt.stds else None,
            "fallbacks": tw.fallbacks,
            "rejected": {f"{s}:{why}": n for (s, why), n in self.rejections.counts.items()
                         if s in rt.cfg.sensors},
            "refs_pearson_r": _ref_correlations(tw),
        }
        out.update(tw.numerics())
        if rt.pairs:
            truth = np.array([p[0] for p in rt.pairs])
            est = np.array([p[1] for p in rt.pairs])
            mean = float(np.mean(truth)) or float("nan")
            out["target"] = {
                "n": len(truth),
                "nrmse_pct": 100 * float(np.sqrt(np.mean((est - truth) ** 2))) / abs(mean),
                "dmax_pct": 100 * float(np.max(np.abs(est - truth))) / abs(mean),
                "pearson_r": _corr(truth, est),
            }
        return out

    # -- timers ---------------------------------------------------------------------------
    def _next_grid(self, after: dt.datetime) -> dt.datetime:
        step_h = self.cfg.publish_every.total_seconds() / 3600.0
        day = self.hours.day_of(after)
        for k in range(3):
            for t in self.hours.grid(day + dt.timedelta(days=k), step_h):
                if t > after:
                    return t
        raise RuntimeError("no grid instant in three days")  # unreachable with valid config

    def _ticker(self) -> None:
        t = self.clock.now()
        while not self.stop_event.is_set():
            t = self._next_grid(t)
            if not self.clock.wait_until(t, self.stop_event):
                return
            self.queue.put(("tick", t))

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
        since = self._not_before(now) - dt.timedelta(days=1)
        for r in self.journal.replay(since):
            self._apply(r, publish=False)  # guarded per twin, as live
            n += 1
        if n:
            log.info("restored state from %d journaled readings", n)
        elif self.cfg.store:
            n = self._warm_start(since, now)
        return n

    def _warm_start(self, since: dt.datetime, now: dt.datetime) -> int:
        from pseudotwin.history.store import open_store

        sensors = sorted(self.by_sensor)
        try:
            with open_store(self.cfg.store) as store:
                frame = store.read_readings(sensors, since, now + dt.timedelta(seconds=1))
        except Exception as exc:  # noqa: BLE001 — a warm start is best effort
            log.warning("warm start from the history store failed (%s); starting empty", exc)
            return 0
        for s, ts, v in zip(frame["sensor"], frame["ts"], frame["value"], strict=True):
            self._apply(Reading(s, ts.to_pydatetime(), float(v)), publish=False)
        log.info("warm start: rebuilt today's windows from %d stored readings", len(frame))
        return len(frame)

    def start(self, wait_connected: float | None = 30.0) -> None:
        self.restore()
        b = self.cfg.broker
        self.client.connect_async(b.host, b.port, keepalive=b.keepalive)
        self.client.loop_start()
        for target, args in ((self._worker, ()), (self._ticker, ())):
            th = threading.Thread(target=target, args=args, daemon=True,
                                  name=target.__name__.strip("_"))
            th.start()
            self._threads.append(th)
        interval = watchdog_interval()
        if interval:
            th = threading.Thread(target=self._watchdog, args=(interval,), daemon=True,
                                  name="watchdog")
            th.start()
        if wait_connected is not None and not self.connected.wait(wait_connected):
            log.warning("not connected to %s:%d yet; still trying", b.host, b.port)
        notify("READY=1")
        log.info("pseudotwin running: %d twin(s), %d sensor(s)", len(self.twins),
                 len(self.cfg.sensors))

    def stop(self) -> None:
        """Stop cleanly: drain the queue, close the journal, publish status offline."""
        notify("STOPPING=1")
        self.stop_event.set()
        self.queue.put(("stop",))
        for th in self._threads:
            # The worker drains the queue first; the journal must outlive it (systemd's
            # TimeoutStopSec bounds a stuck drain).
            th.join()
        self.journal.close()
        if self.client.is_connected():
            info = self.client.publish(self.status_topic, "offline", qos=1, retain=True)
            try:
                info.wait_for_publish(timeout=5)
            except (RuntimeError, ValueError):
                pass
        self.client.disconnect()
        self.client.loop_stop()
        log.info("stopped: %d readings accepted, %d messages published, %d rejected",
                 self.accepted, self.published, self.rejections.total())


def _corr(a: np.ndarray, b: np.ndarray) -> float | None:
    if len(a) < 3 or np.std(a) == 0 or np.std(b) == 0:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def _ref_correlations(tw: Twin) -> dict[str, float | None]:
    """Daily Pearson r between the references on today's slot grid (sample-and-hold)."""
    refs = tw.references
    if len(refs) < 2 or not tw.window:
        return {}
    grid = tw.slot_values()
    out = {}
    for i in range(len(refs)):
        for j in range(i + 1, len(refs)):
            a, b = grid[refs[i]], grid[refs[j]]
            ok = np.isfinite(a) & np.isfinite(b)
            out[f"{refs[i]}|{refs[j]}"] = _corr(a[ok], b[ok])
    return out

