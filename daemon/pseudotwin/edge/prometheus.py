"""Prometheus metrics of the daemon (``pseudotwin run``) and the recorder (``record``).

Optional: ``[metrics] port`` / ``record_port`` start an HTTP endpoint (prometheus_client's
own server, a daemon thread) that serves the text exposition format on any path
(``/metrics`` by convention). Every :class:`DaemonMetrics`/:class:`RecorderMetrics` owns
its own :class:`~prometheus_client.CollectorRegistry`: several daemons can run in one
process (the tests do), and nothing of the library's global default registry (process
metrics) is mixed in.

The metric objects always exist (an increment costs about a microsecond); only the endpoint
is optional. Counters are bumped where the event happens (the worker thread; rejections also
through :class:`~pseudotwin.live.readings.RejectionCounter`'s hook). Queue depth, MQTT
connection, journal size and journal health are read when scraped (``set_function``), so
they need no hook and no thread of their own. Labels are low-cardinality: sensor and twin
ids come from the configuration, reasons and qualities are fixed vocabularies.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import os
import socket
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, make_server

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    disable_created_metrics,
    make_wsgi_app,
)
from prometheus_client.core import CounterMetricFamily
from prometheus_client.exposition import ThreadingWSGIServer
from prometheus_client.registry import Collector

from pseudotwin.errors import ConfigError
from pseudotwin.live.readings import UNPROCESSABLE, Reason
from pseudotwin.live.twin import Quality

log = logging.getLogger(__name__)

# No ``*_created`` sample beside every counter series: it doubles the scrape (54k → 27k
# samples at 1,000 twins) for a timestamp Prometheus does not need. Process-wide, and this
# process is the daemon's (or the recorder's).
disable_created_metrics()

#: Reading dequeued → its estimates handed to the MQTT client [s]: a GP update takes
#: milliseconds, a slow one (refactorization, VARMA) tens of ms.
LATENCY_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
                   2.5, 5.0)

#: Every reason a rejection can carry (the ``reason`` label's vocabulary). Not pre-created
#: per sensor: sensors × reasons series, nearly all 0, would dominate the scrape.
REJECTION_REASONS = (*(str(r) for r in Reason), UNPROCESSABLE)


#: Scrapes served at once at most; a connection beyond them is closed at once.
MAX_SCRAPERS = 8
#: A scrape's connection may be silent this long [s] before it is closed.
SCRAPE_TIMEOUT = 10.0


class _QuietHandler(WSGIRequestHandler):
    """No access log line per scrape; a connection silent for SCRAPE_TIMEOUT is closed."""

    timeout = SCRAPE_TIMEOUT

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the stdlib's name)
        pass


class _BoundedServer(ThreadingWSGIServer):
    """prometheus_client's thread-per-connection server, with at most MAX_SCRAPERS
    connections at once: idle connections that never sent a request each held a thread
    and a file descriptor for good, and some hundreds of them left the daemon none to
    reconnect to the broker or open tomorrow's journal with."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._slots = threading.BoundedSemaphore(MAX_SCRAPERS)
        super().__init__(*args, **kwargs)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            self.shutdown_request(request)  # busy: the scraper retries at its next interval
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


def _serve(registry: CollectorRegistry, host: str, port: int
           ) -> tuple[_BoundedServer, threading.Thread]:
    family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
    server_class = type("MetricsHTTPServer", (_BoundedServer,), {"address_family": family})
    server: _BoundedServer = make_server(host, port, make_wsgi_app(registry), server_class,
                                         handler_class=_QuietHandler)
    thread = threading.Thread(target=server.serve_forever, name="metrics", daemon=True)
    thread.start()
    return server, thread


class MetricsServer:
    """The HTTP endpoint of one registry (at most MAX_SCRAPERS connections at once, each
    closed after SCRAPE_TIMEOUT of silence); :meth:`close` stops it."""

    def __init__(self, registry: CollectorRegistry, host: str, port: int, what: str) -> None:
        try:
            self._server, self._thread = _serve(registry, host, port)
        except OSError as exc:
            hint = "; each daemon on one host needs its own: `run --metrics-port`" \
                if what == "daemon" else ""
            raise ConfigError(f"metrics.{'port' if what == 'daemon' else 'record_port'}: "
                              f"cannot listen on {host}:{port} ({exc.strerror or exc}){hint}") \
                from None
        self.port = int(self._server.server_port)
        log.info("%s Prometheus metrics on http://%s:%d/metrics", what, host, self.port)

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)


class _Metrics:
    rejected: Counter

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.server: MetricsServer | None = None

    def serve(self, host: str, port: int, what: str) -> MetricsServer:
        self.server = MetricsServer(self.registry, host, port, what)
        return self.server

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
            self.server = None

    def rejected_one(self, sensor: str, reason: str) -> None:
        """The :class:`~pseudotwin.live.readings.RejectionCounter` hook."""
        self.rejected.labels(sensor, reason).inc()

    def _rejected_counter(self, name: str) -> Counter:
        return Counter(name, "Payloads rejected (not a valid reading), by sensor and reason "
                             f"({', '.join(REJECTION_REASONS)}); a series appears with its "
                             "first rejection", ["sensor", "reason"], registry=self.registry)


def _dir_bytes(folder: Path) -> float:
    """Total size of the regular files directly in ``folder`` (0 when it is missing)."""
    total = 0
    try:
        with os.scandir(folder) as it:
            for entry in it:
                try:
                    if entry.is_file(follow_symlinks=False):
                        total += entry.stat(follow_symlinks=False).st_size
                except OSError:
                    continue  # rotated away while we looked
    except OSError:
        return 0.0
    return float(total)


class DaemonMetrics(_Metrics):
    """The daemon's metrics (prefix ``pseudotwin_``)."""

    def __init__(self, sensors: Iterable[str], twins: Iterable[str]) -> None:
        super().__init__()
        sensors, twins = list(sensors), list(twins)
        r = self.registry
        self.accepted = Counter(
            "pseudotwin_readings_accepted",
            "Readings journaled and fed to the twins, by sensor (a QoS 1 redelivery or a "
            "repeat too: the twins keep the first of a sensor and time)",
            ["sensor"], registry=r)
        self.rejected = self._rejected_counter("pseudotwin_readings_rejected")
        self.estimates = Counter(
            "pseudotwin_estimates_published",
            "Primary estimates published on <base>/<twin>/estimate, by twin and quality",
            ["twin", "quality"], registry=r)
        self.latency = Histogram(
            "pseudotwin_update_latency_seconds",
            "From a reading taken off the worker queue to its estimates handed to the MQTT "
            "client", buckets=LATENCY_BUCKETS, registry=r)
        self.reading_latency = Histogram(
            "pseudotwin_reading_to_estimate_seconds",
            "From a reading's arrival on the MQTT network thread to its estimates handed to "
            "the MQTT client: the update plus the wait in the worker queue behind other "
            "readings and grid work", buckets=LATENCY_BUCKETS, registry=r)
        self.last_estimate = Gauge(
            "pseudotwin_last_estimate_timestamp_seconds",
            "Time (unix seconds) of the last primary estimate published, by twin",
            ["twin"], registry=r)
        self.queue_depth = Gauge(
            "pseudotwin_queue_depth", "Items waiting in the worker queue", registry=r)
        self.queue_bound = Gauge(
            "pseudotwin_queue_capacity", "Bound of the worker queue", registry=r)
        self.connected = Gauge(
            "pseudotwin_mqtt_connected", "1 while connected to the MQTT broker", registry=r)
        self.journal_bytes = Gauge(
            "pseudotwin_journal_size_bytes", "Size of the journal files in state_dir",
            registry=r)
        self.training_end = Gauge(
            "pseudotwin_training_end_timestamp_seconds",
            "End (unix seconds, local midnight) of the last day the twin's artifact was "
            "trained on: σ was measured before it, and months later it has measured too narrow; "
            "alert on time() minus this to plan a check with the desk sensor", ["twin"],
            registry=r)
        self.other_publishers = Gauge(
            "pseudotwin_twin_other_publishers",
            "Other daemons (MQTT client ids) known to publish the twin too, from their claims "
            "on <base>/claims: both publish its estimates; alert on > 0", ["twin"],
            registry=r)
        self.journal_healthy = Gauge(
            "pseudotwin_journal_healthy",
            "1 while the journal can be written (status online), 0 while degraded",
            registry=r)
        # The children bumped per reading, looked up once: ``labels()`` validates and locks
        # on every call, thousands of times a second at 1,000 twins.
        self._accepted = {s: self.accepted.labels(s) for s in sensors}
        self._estimates = {(t, str(q)): self.estimates.labels(t, str(q))
                           for t in twins for q in Quality
                           if q != Quality.INIT}  # never published
        for t in twins:  # exported from 0, as every twin has its series
            self.other_publishers.labels(t).set(0)
        self._last_estimate: dict[str, Gauge] = {}
        self._last_stamp: dict[str, float] = {}

    def watch(self, *, queue_size: Callable[[], int], queue_bound: int,
              connected: Callable[[], bool], journal_dir: Path,
              journal_healthy: Callable[[], bool],
              fallbacks: Callable[[], Mapping[str, int]]) -> None:
        """What is read at scrape time. ``fallbacks``: twin → numerical failures so far (the
        twin's own counter, the monitor's ``fallbacks``)."""
        self.registry.register(_FallbackCollector(fallbacks))
        self.queue_depth.set_function(lambda: float(queue_size()))
        self.queue_bound.set(queue_bound)
        self.connected.set_function(lambda: float(connected()))
        self.journal_bytes.set_function(lambda: _dir_bytes(journal_dir))
        self.journal_healthy.set_function(lambda: float(journal_healthy()))

    def accepted_one(self, sensor: str) -> None:
        """One reading journaled and fed to the twins."""
        child = self._accepted.get(sensor)
        if child is None:
            child = self._accepted[sensor] = self.accepted.labels(sensor)
        child.inc()

    def published(self, twin: str, quality: str, ts: dt.datetime) -> None:
        """One primary estimate handed to the MQTT client."""
        child = self._estimates.get((twin, quality))
        if child is None:
            child = self._estimates[(twin, quality)] = self.estimates.labels(twin, quality)
        child.inc()
        gauge = self._last_estimate.get(twin)
        if gauge is None:  # created with the first estimate: no series before one exists
            gauge = self._last_estimate[twin] = self.last_estimate.labels(twin)
        # A late reading's estimate goes out with its own, older ts: the time of the last
        # estimate never goes back (an alert on its age would fire on a live twin).
        stamp = ts.timestamp()
        if stamp > self._last_stamp.get(twin, -math.inf):
            self._last_stamp[twin] = stamp
            gauge.set(stamp)


class _FallbackCollector(Collector):
    """``pseudotwin_fallbacks_total{twin}``: numerical failures after which TRIV answered
    (quality fallback), read from the twins when scraped."""

    def __init__(self, counts: Callable[[], Mapping[str, int]]) -> None:
        self.counts = counts

    def collect(self) -> Iterator[CounterMetricFamily]:
        fam = CounterMetricFamily(
            "pseudotwin_fallbacks",
            "Numerical model failures after which TRIV answered with quality fallback, by "
            "twin", labels=["twin"])
        for twin, n in sorted(self.counts().items()):
            fam.add_metric([twin], n)
        yield fam


class RecorderMetrics(_Metrics):
    """The recorder's metrics (prefix ``pseudotwin_recorder_``)."""

    def __init__(self) -> None:
        super().__init__()
        r = self.registry
        self.stored = Counter(
            "pseudotwin_recorder_readings_stored",
            "Readings written to the history store (spooled ones once they are in)",
            registry=r)
        self.spooled = Counter(
            "pseudotwin_recorder_readings_spooled",
            "Readings spooled to disk because the store could not take them", registry=r)
        self.already_stored = Counter(
            "pseudotwin_recorder_readings_already_stored",
            "Readings not written because their sensor and millisecond were stored already "
            "(a redelivery, or readings stamped on arrival within one ms): the first stays",
            registry=r)
        self.refused = Counter(
            "pseudotwin_recorder_readings_refused",
            "Readings the history store refused while it took the others of their batch "
            "(CrateDB answers per row); appended to recorder-refused.csv in the state dir",
            registry=r)
        self.rejected = self._rejected_counter("pseudotwin_recorder_readings_rejected")
        self.store_errors = Counter(
            "pseudotwin_recorder_store_errors", "Failed writes to the history store",
            registry=r)
        self.queue_depth = Gauge(
            "pseudotwin_recorder_queue_depth", "Items waiting in the recorder's queue",
            registry=r)
        self.connected = Gauge(
            "pseudotwin_recorder_mqtt_connected", "1 while connected to the MQTT broker",
            registry=r)
        self.spool_bytes = Gauge(
            "pseudotwin_recorder_spool_size_bytes", "Size of the on-disk spool (0: empty)",
            registry=r)

    def watch(self, *, queue_size: Callable[[], int], connected: Callable[[], bool],
              spool: Path) -> None:
        self.queue_depth.set_function(lambda: float(queue_size()))
        self.connected.set_function(lambda: float(connected()))
        self.spool_bytes.set_function(lambda: _file_bytes(spool))


def _file_bytes(path: Path) -> float:
    try:
        return float(path.stat().st_size)
    except OSError:
        return 0.0


__all__ = ["DaemonMetrics", "MetricsServer", "RecorderMetrics"]
