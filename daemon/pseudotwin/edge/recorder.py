"""``pseudotwin record``: every valid reading of the configured sensors into the history store.

Readings arrive over MQTT (QoS 1, persistent session, manual acks) and are written in batches
(at most ``flush_seconds`` old). A message is acknowledged only once its reading is in the
store or in the on-disk spool (synced to disk, both, with ``journal_fsync``): when the
store is unreachable, batches go to ``state_dir/recorder-spool.jsonl`` and are retried until
they are in; store writes are idempotent, so a retry never duplicates. Bad payloads are
counted and skipped exactly as in the daemon (the same parser and the same
:class:`RejectionCounter`).
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pandas as pd

from pseudotwin.config import SensorConfig, ServiceConfig
from pseudotwin.config.validate import absent_sqlite_file
from pseudotwin.core import series
from pseudotwin.core.logpace import doubled
from pseudotwin.core.series import write_history
from pseudotwin.edge import readinglines
from pseudotwin.edge.clock import Clock, SystemClock
from pseudotwin.edge.mqttconn import (
    StaleTopics,
    Subscription,
    make_client,
    refused_fatally,
    watch_takeover,
)
from pseudotwin.edge.prometheus import RecorderMetrics
from pseudotwin.edge.sdnotify import notify
from pseudotwin.edge.silence import SilenceWatch
from pseudotwin.edge.spool import Spool
from pseudotwin.edge.statelock import StateLock
from pseudotwin.errors import ConfigError, PseudotwinError
from pseudotwin.history.store import RowsRejected, Store, open_store, to_ms
from pseudotwin.live.readings import (
    UNPROCESSABLE,
    Reading,
    Rejected,
    RejectionCounter,
    parse_payload,
)

log = logging.getLogger(__name__)

#: The oldest reading the recorder stores, as files are read (core/series.py): older stamps
#: are a device clock never set, and year-1 times would not survive pandas' round trip.
OLDEST = series.OLDEST.to_pydatetime()

#: In the state dir: readings the store refused one by one (canonical CSV, appended).
REFUSED_FILE = "recorder-refused.csv"
SILENCE_CHECK = dt.timedelta(minutes=1)  # how often silent sensors are looked for


#: Readings the spool hands to the store at a time: a spool of days (a long store outage)
#: is read and written in such pieces, never held in memory whole.
SPOOL_CHUNK = 10_000
#: Pieces written per flush: the readings arriving meanwhile wait behind at most these.
SPOOL_CHUNKS_PER_FLUSH = 10


class Recorder:
    def __init__(self, cfg: ServiceConfig, store: Store | None = None,
                 clock: Clock | None = None, flush_seconds: float = 1.0,
                 batch_max: int = 2000, retry_seconds: float = 5.0) -> None:
        if store is None and cfg.store is None:
            raise ConfigError("service.store: the recorder needs a history store "
                              "(a SQLite file path, postgresql://host/db or "
                              "crate://host:4200)")
        self.cfg = cfg
        self.store_url = cfg.store
        self.store = store
        self.clock = clock or SystemClock()
        self.flush_seconds = flush_seconds
        self.batch_max = batch_max
        self.retry_seconds = retry_seconds
        self.queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=cfg.queue_size)
        # journal_fsync: a spooled reading is acknowledged next, so on disk first
        self.spool = Spool(Path(cfg.state_dir) / "recorder-spool.jsonl",
                           durable=cfg.journal_fsync)
        self.refused_path = Path(cfg.state_dir) / REFUSED_FILE
        self.state_lock = StateLock(Path(cfg.state_dir) / "recorder.lock", "recorder")
        self.metrics = RecorderMetrics()  # served only with [metrics] record_port
        self.rejections = RejectionCounter(log, on_reject=self.metrics.rejected_one)
        self.stop_event = threading.Event()
        self.connected = threading.Event()
        self.written = 0
        self.spooled = 0
        # Consecutive failed store writes, and flushes neither the store nor the spool took
        # (a full disk): logged at the 1st, 2nd, 4th, ... of a run, not at every retry.
        self._store_failures = 0
        self._spool_failures = 0  # retries that could not read the spool or mark it
        self._spool_written = 0  # spooled readings stored by the flushes of this drain
        self._stuck: int = 0
        self._stuck_since = 0.0
        self.already_stored = 0  # readings whose key was in the store already (first kept)
        self.refused = 0  # readings the store refused while taking others: in refused_path
        self.fatal: tuple[int, str] | None = None  # (exit status, why): the process must end
        self._store_ident: tuple[int, int] | None = None
        self._gen = 0
        self._next_retry = 0.0
        self.status_topic = f"{cfg.base_topic}/recorder/status"
        self.client = make_client(cfg.broker, f"{cfg.broker.client_id}-recorder",
                                  self.status_topic)
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = lambda *a: self.connected.clear()
        watch_takeover(self.client, f"{cfg.broker.client_id}-recorder")
        self.client.on_message = self._on_message
        self._stale_topics = StaleTopics("recorder")
        self._said_new_store = False
        self._subscription = Subscription([(s.topic, 1) for s in cfg.sensors.values()],
                                          self.connected)
        self.client.on_subscribe = self._subscription.on_subscribe
        # Sensors silent in operating hours (a dead desk sensor on a commissioning day):
        # watched from the start on (_start), checked by the worker once a minute.
        self.silence: SilenceWatch | None = None
        self._next_silence_check: dt.datetime | None = None
        self._worker = threading.Thread(target=self._run, name="recorder", daemon=True)
        self.metrics.watch(queue_size=self.queue.qsize, connected=self.connected.is_set,
                           spool=self.spool.path)

    # -- MQTT (network thread) --------------------------------------------------------------
    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: mqtt.ConnectFlags,
                    reason_code: Any, properties: Any) -> None:
        if reason_code.is_failure:
            self.fatal = refused_fatally(reason_code)
            log.error("broker refused the connection: %s%s", reason_code,
                      "; giving up (fix the credentials)" if self.fatal else "; retrying")
            return
        self._gen += 1
        if self.silence is not None:  # nothing could be heard while away
            self.silence.listening(self.clock.now())
        self._subscription.subscribe(client)
        self._send_status()
        log.info("recorder connected; recording %d sensor topics", len(self.cfg.sensors))

    def _on_message(self, client: mqtt.Client, userdata: Any, msg: mqtt.MQTTMessage) -> None:
        item = (self.cfg.sensor_for_topic(msg.topic), msg.topic, msg.payload,
                self.clock.now(), (self._gen, msg.mid, msg.qos), bool(msg.retain))
        while not self.stop_event.is_set():
            try:
                self.queue.put(item, timeout=1.0)
                return
            except queue.Full:
                log.warning("recorder queue full; the store is behind")

    def _ack(self, token: tuple[int, int, int]) -> None:
        gen, mid, qos = token
        if qos > 0 and gen == self._gen:
            self.client.ack(mid, qos)

    # -- the worker -----------------------------------------------------------------------
    def _parse(self, sensor: SensorConfig | None, payload: bytes,
               arrival: dt.datetime, retained: bool = False) -> Reading | None:
        if sensor is None:
            return None
        day = self.cfg.hours.day_of(arrival)
        try:
            return parse_payload(sensor, payload, arrival, max_skew=self.cfg.max_skew,
                                 not_before=OLDEST,  # history keeps late readings too
                                 on_ahead=lambda s: self.rejections.ahead(sensor.id, s, day),
                                 retained=retained)
        except Rejected as rej:
            self.rejections.add(sensor.id, rej, day)
            return None
        except Exception as exc:  # noqa: BLE001 — a parser bug must not kill the recorder
            log.exception("payload of %s could not be processed", sensor.id)
            self.rejections.add_reason(sensor.id, UNPROCESSABLE, repr(exc)[:200], day)
            return None

    def _store(self) -> Store:
        if self.store is not None and self._store_vanished():
            log.error("history store file %s was deleted or replaced while recording; "
                      "reopening it (a new, empty database: what was stored before is gone "
                      "unless restored from a backup)", getattr(self.store, "path", "?"))
            self._drop_store()
        if self.store is None:
            assert self.store_url is not None
            file = absent_sqlite_file(self.store_url)
            if file is not None and not self._said_new_store:
                self._said_new_store = True  # once: a failing open is retried every few s
                log.info("creating the history store %s (a new SQLite file; a relative path "
                         "is from the configuration's folder)", file)
            # journal_fsync: a reading is acknowledged once committed, so committed must
            # mean on disk (SQLite's default here would lose the last commits to a power cut).
            self.store = open_store(self.store_url, durable=self.cfg.journal_fsync)
            self._store_ident = _file_ident(self.store)
        return self.store

    def _store_vanished(self) -> bool:
        """A SQLite file deleted under an open connection takes every later write into the
        void: check it is still the file we opened before each batch (one stat)."""
        if self._store_ident is None or self.store_url is None or self.store is None:
            return False
        return _file_ident(self.store) != self._store_ident

    def _write(self, readings: list[Reading], spooled: bool = False) -> bool:
        """Store ``readings``; False (logged, to be spooled or kept in the spool: ``spooled``,
        readings taken from it) when the store cannot take them."""
        # (a spool is tried a piece at a time: the count is the piece's, not the spool's)
        then = "they and the rest of the spool stay in it" if spooled else "spooling them to disk"
        refused: list[Reading] = []
        try:
            try:
                n = self._store().write_readings(readings)
            except RowsRejected as exc:
                keys = {(row[0], row[1]) for row in exc.rows}
                refused = [r for r in readings if (r.sensor, to_ms(r.ts)) in keys]
                if len(refused) == len(readings):
                    raise  # nothing taken: the store is unusable for now, as if it were away
                self._refuse(refused, exc)
                n = exc.written
            if not spooled:  # a spool's retry says so when all of it is in
                self._store_back()
            self.written += n
            self.metrics.stored.inc(n)
            # Readings are immutable: a key stored already keeps its first value. Counted,
            # since a backlog stamped on arrival can collapse this way (README, Delivery).
            if (kept_first := len(readings) - len(refused) - n) > 0:
                self.already_stored += kept_first
                self.metrics.already_stored.inc(kept_first)
            return True
        except (PseudotwinError, OSError) as exc:
            self._store_failed(f"history store unavailable ({exc}); {len(readings)} readings: "
                               f"{then}")
            return False
        except Exception as exc:  # e.g. the crate client's connection errors
            self._store_failed(f"history store write failed ({type(exc).__name__}: {exc}); "
                               f"{len(readings)} readings: {then}")
            return False

    def _store_failed(self, what: str) -> None:
        self.metrics.store_errors.inc()
        self._store_failures += 1
        n = self._store_failures
        if doubled(n - 1, n):  # an outage of days must not write a line every retry
            log.warning("%s%s", what, f" ({n} failed writes in a row)" if n > 1 else "")
        self._drop_store()

    def _store_back(self) -> None:
        if self._store_failures:
            log.info("history store writable again after %d failed write(s)",
                     self._store_failures)
            self._store_failures = 0

    def _refuse(self, readings: list[Reading], why: RowsRejected) -> None:
        """Readings the store refused while it took the others of their batch (CrateDB
        answers per row): kept out of the spool, which they would otherwise block for good,
        and appended to ``refused_path`` as canonical CSV, for ``pseudotwin import``."""
        frame = pd.DataFrame({"sensor": [r.sensor for r in readings],
                              "ts": pd.DatetimeIndex([r.ts for r in readings]).tz_convert("UTC"),
                              "value": [r.value for r in readings]})
        # exact: raw readings are never modified (OSError: the batch is retried)
        write_history(frame, self.refused_path, append=True, exact=True)
        if self.cfg.journal_fsync:  # acknowledged next, as a spooled reading (seldom: the
            readinglines.sync_file(self.refused_path)  # folder's entry each time too)
        self.refused += len(readings)
        self.metrics.refused.inc(len(readings))
        log.error("the history store refused %d readings and took the others (%s); they are "
                  "in %s: once the cause is fixed, load them with 'pseudotwin import %s "
                  "--store URL'", len(readings), why, self.refused_path, self.refused_path)

    def _drop_store(self) -> None:
        if self.store is not None and self.store_url is not None:
            try:
                self.store.close()
            except Exception:  # noqa: BLE001 — closing a broken connection may fail too
                pass
            self.store = None

    def _retry_spool(self) -> None:
        """Hand the spool to the store, SPOOL_CHUNK readings at a time, oldest first, at
        most SPOOL_CHUNKS_PER_FLUSH pieces per call (the next flush goes on at once): with
        the store still away that is one piece read per retry, not the whole outage."""
        if time.monotonic() < self._next_retry or not self.spool.path.exists():
            return
        written, through, pieces = 0, 0, 0
        try:
            for piece, end in self.spool.chunks(SPOOL_CHUNK):
                if pieces == SPOOL_CHUNKS_PER_FLUSH:
                    self.spool.consume(through)
                    self._spool_written += written
                    return  # _next_retry not moved: the next flush goes on
                if not self._write(piece, spooled=True):
                    break
                written, through, pieces = written + len(piece), end, pieces + 1
            else:
                if total := self._spool_written + written:
                    log.info("wrote %d spooled readings to the history store", total)
                self._spool_written = 0
                self.spool.clear()
                self._store_back()
                self._spool_failures = 0
                return
            if through:
                log.info("wrote %d spooled readings to the history store; the rest stays "
                         "in the spool", self._spool_written + written)
                self.spool.consume(through)
                self._spool_written = 0
        except OSError as exc:
            self._spool_failures += 1
            if doubled(self._spool_failures - 1, self._spool_failures):
                log.error("cannot read the spool %s or mark what was stored (%s); retrying "
                          "(%d failures in a row)", self.spool.path, exc,
                          self._spool_failures)
        self._next_retry = time.monotonic() + self.retry_seconds

    def _flush(self, batch: list[Reading], tokens: list[tuple[int, int, int]]) -> bool:
        """Store or spool ``batch`` and acknowledge it; False (nothing acknowledged, keep
        the batch and call again) when neither the store nor the spool can take it."""
        self._retry_spool()  # older readings first
        if batch and (self.spool.path.exists() or not self._write(batch)):
            try:
                remade, _ = self.spool.add(batch)
            except OSError as exc:
                self._stuck_on(len(batch), exc)
                return False
            if remade:
                log.error("the state dir %s was deleted while recording; made again for the "
                          "spool", self.spool.path.parent)
                self.state_lock.renew()  # it went with the lock file
            self.spooled += len(batch)
            self.metrics.spooled.inc(len(batch))
            self._next_retry = min(self._next_retry or time.monotonic(),
                                   time.monotonic() + self.retry_seconds)
        self._unstuck()
        for t in tokens:  # in the store or in the spool: safe to acknowledge
            self._ack(t)
        return True

    def _stuck_on(self, n: int, exc: OSError) -> None:
        """Neither the store nor the spool takes readings: status ``degraded``, logged at
        the 1st, 2nd, 4th, ... failed flush; nothing is acknowledged meanwhile."""
        self._next_retry = time.monotonic() + self.retry_seconds
        self._stuck += 1
        if self._stuck == 1:
            self._stuck_since = time.monotonic()
            self._send_status()
        if doubled(self._stuck - 1, self._stuck):
            log.error("cannot spool %d readings either (%s): NOT acknowledged (the broker "
                      "keeps them); status degraded, retrying (%d failed flushes so far)", n,
                      exc, self._stuck)

    def _unstuck(self) -> None:
        if self._stuck:
            log.warning("spooling again after %.0f s (%d failed flushes); status online",
                        time.monotonic() - self._stuck_since, self._stuck)
            self._stuck = 0
            self._send_status()

    def _send_status(self) -> None:
        if self.client.is_connected():
            self.client.publish(self.status_topic, "degraded" if self._stuck else "online",
                                qos=1, retain=True)

    def _run(self) -> None:
        batch: list[Reading] = []
        tokens: list[tuple[int, int, int]] = []
        deadline = time.monotonic() + self.flush_seconds
        while True:
            timeout = max(0.0, deadline - time.monotonic())
            try:
                item = self.queue.get(timeout=timeout)
            except queue.Empty:
                item = None
            if item is not None and item[0] == "stop":
                self._guarded_flush(batch, tokens)
                return
            if item is not None:
                sensor, topic, payload, arrival, token, retained = item
                if sensor is None:
                    self._stale_topics.drop(self.client, topic)
                r = self._parse(sensor, payload, arrival, retained)
                if r is not None:
                    batch.append(r)
                    tokens.append(token)
                    if self.silence is not None and not retained:  # (a retained one is old)
                        self.silence.heard(r.sensor, arrival)
                else:
                    self._ack(token)
            self._check_silence()
            if time.monotonic() >= deadline or len(batch) >= self.batch_max:
                if self._guarded_flush(batch, tokens):
                    batch, tokens = [], []
                deadline = time.monotonic() + self.flush_seconds

    def _check_silence(self) -> None:
        if self.silence is None or not self.connected.is_set():  # (away: nothing is heard)
            return
        now = self.clock.now()
        if self._next_silence_check is None or now >= self._next_silence_check:
            self._next_silence_check = now + SILENCE_CHECK
            self.silence.check(now)

    def _guarded_flush(self, batch: list[Reading], tokens: list[tuple[int, int, int]]) -> bool:
        try:
            return self._flush(batch, tokens)
        except Exception:  # the worker must outlive anything; nothing was acknowledged
            log.exception("unexpected error while storing %d readings; retrying", len(batch))
            self._drop_store()
            return False

    # -- life cycle -----------------------------------------------------------------------
    def start(self, wait_connected: float | None = 30.0) -> None:
        # first: a second recorder here must not share the spool
        self.state_lock.starting(lambda: self._start(wait_connected), self.metrics.close)

    def _start(self, wait_connected: float | None) -> None:
        if self.cfg.metrics.record_port is not None:
            self.metrics.serve(self.cfg.metrics.host, self.cfg.metrics.record_port, "recorder")
        self.silence = SilenceWatch(self.cfg.sensors, self.cfg.hours, self.cfg.stale_after,
                                    self.clock.now())
        self._worker.start()
        b = self.cfg.broker
        self.client.connect_async(b.host, b.port, keepalive=b.keepalive)
        self.client.loop_start()
        # READY=1 comes once subscribed (mqttconn.Subscription).
        if wait_connected is not None and not self.connected.wait(wait_connected):
            log.warning("recorder not connected to %s:%d yet; still trying", b.host, b.port)

    def stop(self) -> None:
        notify("STOPPING=1")
        self.stop_event.set()
        self.queue.put(("stop",))
        self._worker.join()  # drains the queue: everything received ends up stored or spooled
        if self.client.is_connected():
            self.client.publish(self.status_topic, "offline", qos=1, retain=True) \
                .wait_for_publish(timeout=5)
        self.client.disconnect()
        self.client.loop_stop()
        if self.store is not None:
            self.store.close()
        self.metrics.close()
        self.state_lock.release()
        log.info("recorder stopped: %d readings written, %d spooled, %d rejected, %d not "
                 "written as their sensor and millisecond were stored already%s", self.written,
                 self.spooled, self.rejections.run_total, self.already_stored,
                 f", {self.refused} refused by the store (in {self.refused_path})"
                 if self.refused else "")


def _file_ident(store: Store) -> tuple[int, int] | None:
    """(device, inode) of a file-backed store's database file; None when not file-backed
    (CrateDB, :memory:) or when the file is missing."""
    path = getattr(store, "path", None)
    if not isinstance(path, str) or path == ":memory:":
        return None
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino
