"""``pseudotwin run`` as a process: SIGKILL and resume, SIGTERM, systemd notify, bad config."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from daemon_support import (
    DAY,
    HOURS,
    day_readings,
    sml,
    uninterrupted_estimates,
    wait_for,
    write_config,
)
from test_daemon import Viewer, publisher, reading

EXE = [sys.executable, "-m", "pseudotwin.cli"]
REPLAY_FROM = HOURS.at(DAY, 12.0).isoformat()  # the morning's readings all lie in the past


def start_daemon(cfg: Path, log: Path, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [*EXE, "run", "--config", str(cfg), "--replay-from", REPLAY_FROM],
        stdout=open(log, "a"), stderr=subprocess.STDOUT,  # noqa: SIM115
        env={**os.environ, **(env or {})},
    )


@contextlib.contextmanager
def notified_daemon(cfg: Path, log: Path, env: dict | None = None
                    ) -> Iterator[tuple[subprocess.Popen, socket.socket]]:
    """``pseudotwin run`` with a systemd notify socket of our own beside ``log``: (the
    process, the socket to read its READY=1/WATCHDOG=1/STOPPING=1); killed if still alive."""
    path = log.parent / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(20)
    d = start_daemon(cfg, log, {"NOTIFY_SOCKET": str(path), **(env or {})})
    try:
        yield d, sock
    finally:
        if d.poll() is None:
            d.kill()
        sock.close()


def test_sigkill_mid_day_then_resume_publishes_what_a_daemon_that_never_stopped_would(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    cfg = write_config(tmp_path, mosquitto.port, desk_artifact, target=False, keepalive=2)
    readings = day_readings(sml())
    readings = readings[readings["ts"] < HOURS.at(DAY, 11.0)]
    split = HOURS.at(DAY, 9.0)  # both halves hold readings in operating hours
    first, second = readings[readings["ts"] < split], readings[readings["ts"] >= split]
    viewer = Viewer(mosquitto.port, "pt/#", client_id="kill-viewer", clean=False)
    pub = publisher(mosquitto.port, "kill-proc-bridge")
    log = tmp_path / "daemon.log"
    d1 = start_daemon(cfg, log)
    wait_for(lambda: "online" in [b for t, b in viewer.msgs if t == "pt/status"],
             what="daemon 1 online")
    for _, r in first.iterrows():
        pub.publish("house/dining/temp", reading(r["ts"].to_pydatetime(), r["value"]), qos=1)
    in_hours = lambda df: int((df["ts"] >= HOURS.at(DAY, 8.0)).sum())  # noqa: E731
    assert in_hours(first) > 0 and in_hours(second) > 0
    wait_for(lambda: len(viewer.on("/estimate")) == in_hours(first), what="first estimates")
    d1.send_signal(signal.SIGKILL)
    d1.wait(10)
    assert list((tmp_path / "state" / "journal").glob("*.jsonl"))
    # the last will tells subscribers the daemon is gone (keepalive 2 s)
    wait_for(lambda: [b for t, b in viewer.msgs if t == "pt/status"][-1] == "offline",
             what="last will")
    for _, r in second.iterrows():  # published while the daemon is dead
        pub.publish("house/dining/temp", reading(r["ts"].to_pydatetime(), r["value"]),
                    qos=1).wait_for_publish(10)
    d2 = start_daemon(cfg, log)
    try:
        wait_for(lambda: len(viewer.on("/estimate")) == in_hours(readings),
                 what=lambda: f"all estimates ({len(viewer.on('/estimate'))} of "
                              f"{in_hours(readings)}):\n{log.read_text()[-2000:]}")
        assert "restored state from" in log.read_text()
        # what a daemon that never stopped publishes: one twin fed every reading in order
        expected = {ts: e for ts, e in uninterrupted_estimates(desk_artifact, readings).items()
                    if e.quality != "init"}
        got = {e["ts"]: e for e in viewer.on("/estimate")}
        assert set(got) == set(expected)
        for ts, e in expected.items():
            assert got[ts]["value"] == round(e.value, 6) and got[ts]["std"] == round(e.std, 6)
            assert got[ts]["quality"] == e.quality
    finally:
        d2.send_signal(signal.SIGTERM)
        assert d2.wait(30) == 0
        pub.loop_stop()
        viewer.close()


def test_sigterm_stops_cleanly_with_systemd_notify_and_watchdog(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    cfg = write_config(tmp_path, mosquitto.port, desk_artifact)
    log = tmp_path / "daemon.log"
    with notified_daemon(cfg, log, {"WATCHDOG_USEC": "1000000"}) as (d, sock):
        got: list[str] = []
        while "WATCHDOG=1" not in got:
            got.append(sock.recv(256).decode())
        assert got[0] == "READY=1"
        # a second daemon on the same configuration and state dir: refused, and worth
        # retrying later (75, not 78: systemd starts it once this one has ended)
        second = subprocess.run([*EXE, "run", "--config", str(cfg), "--replay-from",
                                 REPLAY_FROM], capture_output=True, text=True, timeout=60)
        assert second.returncode == 75, second.stderr
        assert f"in use by another pseudotwin daemon (PID {d.pid})" in second.stderr
        d.send_signal(signal.SIGTERM)
        while got[-1] != "STOPPING=1":
            got.append(sock.recv(256).decode())
        assert d.wait(30) == 0
    text = log.read_text()
    assert "received SIGTERM; stopping" in text and "stopped:" in text
    viewer = Viewer(mosquitto.port, "pt/status")  # the retained status
    viewer.c.on_message = lambda c, u, m: viewer.msgs.append((m.topic, m.payload.decode()))
    viewer.c.unsubscribe("pt/status")
    viewer.c.subscribe("pt/status", 1)
    wait_for(lambda: ("pt/status", "offline") in viewer.msgs, what="retained offline")
    viewer.close()


@pytest.mark.parametrize(
    "mutate,message",
    [
        (lambda t: t.replace('min = -10', 'min = -10\nmni = 3', 1), "unknown key"),
        (lambda t: t.replace('references = ["dining/temp"]', 'references = ["room/temp"]'),
         "target"),
        (lambda t: t.replace('timezone = "Europe/Madrid"', 'timezone = "Europe/Berlin"'),
         "time zone"),
    ],
)
def test_bad_configuration_exits_78_with_each_problem(
    mosquitto, desk_artifact, tmp_path: Path, mutate, message: str
) -> None:
    cfg = write_config(tmp_path, mosquitto.port, desk_artifact)
    cfg.write_text(mutate(cfg.read_text()))
    p = subprocess.run([*EXE, "run", "--config", str(cfg)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 78
    assert message in p.stderr and "Traceback" not in p.stderr


def test_check_config_reports_an_artifact_that_does_not_fit(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    cfg = write_config(tmp_path, mosquitto.port, desk_artifact)
    cfg.write_text(cfg.read_text().replace('quantity = "temperature"', 'quantity = "co2"'))
    p = subprocess.run([*EXE, "check-config", str(cfg)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 1
    assert "quantity 'co2' differs from the artifact's 'temperature'" in p.stderr


def test_sighup_stops_the_daemon_cleanly_and_says_it_reloads_nothing(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    """A terminal closed under a foreground run sent SIGHUP, which killed the daemon without
    a log line, a clean stop or its retained offline status."""
    cfg = write_config(tmp_path, mosquitto.port, desk_artifact)
    log = tmp_path / "daemon.log"
    with notified_daemon(cfg, log) as (d, sock):
        assert sock.recv(256).decode() == "READY=1"
        d.send_signal(signal.SIGHUP)
        assert d.wait(30) == 0
    text = log.read_text()
    assert "received SIGHUP; stopping (SIGHUP reloads nothing" in text and "stopped:" in text
