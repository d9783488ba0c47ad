"""Prometheus metrics (issue 12 item 2): ``[metrics]`` config, then the real HTTP endpoint of
an in-process daemon and recorder, fed real readings through the real Mosquitto, scraped
with urllib and parsed by prometheus_client's own parser."""

from __future__ import annotations

import datetime as dt
import socket
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from daemon_support import DAY, HOURS, REF, config, off_grid, wait_for, write_config
from pseudotwin.config import ConfigProblems, load_config
from pseudotwin.config.model import MetricsConfig
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.prometheus import DaemonMetrics
from pseudotwin.edge.recorder import Recorder
from pseudotwin.edge.service import Service
from pseudotwin.errors import ConfigError
from pseudotwin.live.artifact import Artifact
from test_daemon import Viewer, publisher, reading

TOPIC = "house/dining/temp"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def with_metrics(path: Path, table: str) -> Path:
    """Append a [metrics] table to a config file written by daemon_support."""
    path.write_text(path.read_text(encoding="utf-8") + "\n[metrics]\n" + table,
                    encoding="utf-8")
    return path


def scrape(port: int) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of the endpoint: (name, sorted labels) → value."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as resp:
        assert resp.status == 200
        assert resp.headers["Content-Type"].startswith("text/plain")
        text = resp.read().decode()
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def sample(samples: dict, name: str, **labels: str) -> float:
    return samples[(name, tuple(sorted(labels.items())))]


# -- configuration ------------------------------------------------------------------------
def test_metrics_are_off_by_default_and_the_table_is_validated(tmp_path: Path) -> None:
    desk_artifact = tmp_path / "desk.json"  # load_config does not open artifacts
    cfg = config(tmp_path, 1883, desk_artifact)
    assert cfg.metrics == MetricsConfig() and cfg.metrics.port is None
    assert cfg.metrics.record_port is None

    p = with_metrics(write_config(tmp_path, 1883, desk_artifact),
                     'host = "0.0.0.0"\nport = 9108\nrecord_port = 9109\n')
    m = load_config(p).metrics
    assert (m.host, m.port, m.record_port) == ("0.0.0.0", 9108, 9109)

    bad = with_metrics(write_config(tmp_path, 1883, desk_artifact),
                       'port = 70000\nrecord_port = "9109"\nprot = 1\nhost = ""\n')
    with pytest.raises(ConfigProblems) as err:
        load_config(bad)
    problems = err.value.problems
    assert any(p.startswith("metrics.port: must be a TCP port") for p in problems), problems
    assert any(p.startswith("metrics.record_port: expected an integer") for p in problems)
    assert any(p.startswith("metrics.prot: unknown key (did you mean 'port'?)")
               for p in problems), problems
    assert any(p.startswith("metrics.host: must not be empty") for p in problems)

    same = with_metrics(write_config(tmp_path, 1883, desk_artifact),
                        "port = 9108\nrecord_port = 9108\n")
    with pytest.raises(ConfigProblems, match="record_port: must differ from port"):
        load_config(same)


def test_registries_are_per_instance() -> None:
    a, b = DaemonMetrics(["s"], ["t"]), DaemonMetrics(["s"], ["t"])
    a.accepted.labels("s").inc()
    assert a.registry.get_sample_value("pseudotwin_readings_accepted_total",
                                       {"sensor": "s"}) == 1
    assert b.registry.get_sample_value("pseudotwin_readings_accepted_total",
                                       {"sensor": "s"}) == 0


# -- the daemon ---------------------------------------------------------------------------
@pytest.fixture
def metered(mosquitto, desk_artifact: Path, tmp_path: Path) -> Iterator[tuple[Service, int]]:
    port = free_port()
    path = with_metrics(write_config(tmp_path, mosquitto.port, desk_artifact),
                        f"port = {port}\n")
    svc = Service(load_config(path), clock=ReplayClock(off_grid(9.0), 1.0))
    svc.start(wait_connected=15)
    yield svc, port
    if not svc.stop_event.is_set():
        svc.stop()


def test_the_time_of_the_last_estimate_never_goes_back() -> None:
    """A late reading's estimate goes out with its own, older ts; the gauge followed it back,
    and an alert on the estimate's age fired on a live twin."""
    m = DaemonMetrics([REF], ["desk"])
    grid, late = HOURS.at(DAY, 8.25), HOURS.at(DAY, 8.1)
    m.published("desk", "ok", grid)
    m.published("desk", "ok", late)
    assert m.registry.get_sample_value("pseudotwin_last_estimate_timestamp_seconds",
                                       {"twin": "desk"}) == grid.timestamp()
    assert m.registry.get_sample_value("pseudotwin_estimates_published_total",
                                       {"twin": "desk", "quality": "ok"}) == 2


def test_daemon_endpoint_counts_what_went_through_the_broker(metered, mosquitto) -> None:
    svc, port = metered
    viewer = Viewer(mosquitto.port, "pt/desk/estimate")
    pub = publisher(mosquitto.port, "prom-bridge")
    good = [reading(HOURS.at(DAY, 8.0 + i / 12), 20.0 + i / 10) for i in range(6)]
    bad = [b"{not json", reading(HOURS.at(DAY, 8.1), 99.0)]  # not-json, out-of-range
    for p in [*good[:3], *bad, *good[3:]]:
        pub.publish(TOPIC, p, qos=1).wait_for_publish(10)
    wait_for(lambda: svc.accepted == len(good) and svc.rejections.run_total == len(bad)
             and len(viewer.on("/estimate")) == len(good), what="every payload handled")
    m = scrape(port)

    assert sample(m, "pseudotwin_readings_accepted_total", sensor=REF) == len(good)
    assert sample(m, "pseudotwin_readings_accepted_total", sensor="room/temp") == 0
    assert sample(m, "pseudotwin_readings_rejected_total", sensor=REF, reason="not-json") == 1
    assert sample(m, "pseudotwin_readings_rejected_total", sensor=REF,
                  reason="out-of-range") == 1
    assert not any(name == "pseudotwin_readings_rejected_total" and ("reason", "future") in lab
                   for name, lab in m)  # a series per reason seen, not per reason possible
    assert not any(name.endswith("_created") for name, _ in m)
    # estimates by quality: exactly what a subscriber of <base>/desk/estimate received
    got: dict[str, int] = {}
    for e in viewer.on("/estimate"):
        got[e["quality"]] = got.get(e["quality"], 0) + 1
    for quality in ("ok", "stale", "fallback", "uncertain"):
        assert sample(m, "pseudotwin_estimates_published_total", twin="desk",
                      quality=quality) == got.get(quality, 0), quality
    assert sum(got.values()) == len(good)
    last = max(dt.datetime.fromisoformat(e["ts"]) for e in viewer.on("/estimate"))
    assert sample(m, "pseudotwin_last_estimate_timestamp_seconds", twin="desk") \
        == pytest.approx(last.timestamp())
    assert sample(m, "pseudotwin_fallbacks_total", twin="desk") == 0
    # the midnight that ends the artifact's last training day, in the building's time zone:
    # 2012-03-19 00:00 in Madrid (UTC+1 then), 2012-03-18 23:00 UTC
    assert Artifact.load(svc.cfg.twins["desk"].artifact).training["end"] == "2012-03-18"
    assert sample(m, "pseudotwin_training_end_timestamp_seconds", twin="desk") == 1332111600.0
    # every accepted reading moved the twin: one latency observation each
    assert sample(m, "pseudotwin_update_latency_seconds_count") == len(good)
    assert 0 < sample(m, "pseudotwin_update_latency_seconds_sum") < len(good) * 5.0
    # from arrival on the network thread: the same readings, each waited at least its update
    assert sample(m, "pseudotwin_reading_to_estimate_seconds_count") == len(good)
    assert sample(m, "pseudotwin_reading_to_estimate_seconds_sum") \
        >= sample(m, "pseudotwin_update_latency_seconds_sum")
    assert sample(m, "pseudotwin_queue_depth") == 0
    assert sample(m, "pseudotwin_queue_capacity") == svc.cfg.queue_size
    assert sample(m, "pseudotwin_mqtt_connected") == 1
    assert sample(m, "pseudotwin_journal_healthy") == 1
    journal = sum(f.stat().st_size for f in svc.journal.folder.iterdir())
    assert sample(m, "pseudotwin_journal_size_bytes") == journal > 0

    svc.stop()  # the endpoint goes with the daemon
    with pytest.raises(urllib.error.URLError):
        scrape(port)
    pub.loop_stop()
    viewer.close()


def test_a_metrics_port_in_use_is_reported_before_anything_starts(
    mosquitto, desk_artifact: Path, tmp_path: Path
) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = with_metrics(write_config(tmp_path, mosquitto.port, desk_artifact),
                            f"port = {port}\n")
        svc = Service(load_config(path), clock=ReplayClock(off_grid(9.0), 1.0))
        with pytest.raises(ConfigError, match=f"metrics.port: cannot listen on 127.0.0.1:{port}"
                                              ".*its own: `run --metrics-port`"):
            svc.start(wait_connected=1)
    assert not svc.client.is_connected() and not svc._threads


# -- the recorder -------------------------------------------------------------------------
def test_recorder_endpoint_counts_stored_spooled_rejected_repeated_and_store_errors(
    mosquitto, desk_artifact: Path, tmp_path: Path
) -> None:
    port = free_port()
    db = tmp_path / "later" / "history.db"  # its folder does not exist yet: store "down"
    path = with_metrics(write_config(tmp_path, mosquitto.port, desk_artifact, store=str(db)),
                        f"record_port = {port}\n")
    rec = Recorder(load_config(path), retry_seconds=0.2)
    rec.start(wait_connected=15)
    try:
        pub = publisher(mosquitto.port, "prom-rec-bridge")
        ts = [HOURS.at(DAY, 8 + i / 60) for i in range(10)]
        for i, t in enumerate(ts[:5]):
            pub.publish(TOPIC, reading(t, 20 + i / 100), qos=1)
        pub.publish(TOPIC, b"{broken", qos=1)
        wait_for(lambda: rec.spooled == 5 and rec.rejections.run_total == 1,
                 what="spooled while the store is down")
        m = scrape(port)
        assert sample(m, "pseudotwin_recorder_readings_spooled_total") == 5
        assert sample(m, "pseudotwin_recorder_readings_stored_total") == 0
        assert sample(m, "pseudotwin_recorder_store_errors_total") >= 1
        assert sample(m, "pseudotwin_recorder_spool_size_bytes") > 0
        assert sample(m, "pseudotwin_recorder_readings_rejected_total", sensor=REF,
                      reason="not-json") == 1
        assert sample(m, "pseudotwin_recorder_mqtt_connected") == 1
        db.parent.mkdir()  # the store comes back
        for i, t in enumerate(ts[5:], start=5):
            pub.publish(TOPIC, reading(t, 20 + i / 100), qos=1)
        wait_for(lambda: rec.written == 10, what="spool and new readings written")
        # one of them again (a redelivery): its sensor and instant are stored, the first stays
        pub.publish(TOPIC, reading(ts[-1], 21.0), qos=1)
        wait_for(lambda: rec.already_stored == 1, what="the repeated reading counted")
        m = scrape(port)
        assert sample(m, "pseudotwin_recorder_readings_stored_total") == 10
        assert sample(m, "pseudotwin_recorder_readings_already_stored_total") == 1
        assert sample(m, "pseudotwin_recorder_spool_size_bytes") == 0
        assert sample(m, "pseudotwin_recorder_queue_depth") == 0
        pub.loop_stop()
    finally:
        rec.stop()
    with pytest.raises(urllib.error.URLError):
        scrape(port)


def test_idle_connections_cannot_take_the_endpoints_file_descriptors() -> None:
    """Connections that never send a request each held a thread and a file descriptor for
    good (hostile-input audit: some hundreds left the daemon none to reconnect to the broker
    with). At most MAX_SCRAPERS are served at once, the others closed at once; once the idle
    ones go, a scrape is served."""
    import os

    from pseudotwin.edge.prometheus import MAX_SCRAPERS

    metrics = DaemonMetrics([REF], ["desk"])
    server = metrics.serve("127.0.0.1", free_port(), "daemon")

    def fds() -> int:
        return len(os.listdir("/proc/self/fd"))

    def closed_by_server(s: socket.socket) -> bool:
        try:
            return s.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            return False

    try:
        before = fds()
        idle = [socket.create_connection(("127.0.0.1", server.port))
                for _ in range(4 * MAX_SCRAPERS)]
        try:
            wait_for(lambda: sum(map(closed_by_server, idle)) == 3 * MAX_SCRAPERS,
                     what=lambda: f"{sum(map(closed_by_server, idle))} closed by the server")
            held = fds() - before - len(idle)  # the server's side of the open ones
            assert held <= MAX_SCRAPERS
        finally:
            for s in idle:
                s.close()
        def served() -> bool:
            try:  # (a slot is free once its thread saw its connection end)
                return sample(scrape(server.port), "pseudotwin_readings_accepted_total",
                              sensor=REF) == 0
            except (urllib.error.URLError, ConnectionError):
                return False

        wait_for(served, what="a scrape served once the idle connections went")
    finally:
        metrics.close()
