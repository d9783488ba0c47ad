"""Issue 13: no input, fault or flood may stall, deafen or silently lose readings.

Every scenario runs against the real Mosquitto of conftest.py; the ones about the process
(signals, exit statuses, file modes, connection logging) run the real ``pseudotwin run``.
"""

from __future__ import annotations

import datetime as dt
import errno
import json
import logging
import math
import os
import shutil
import signal
import socket
import stat
import subprocess
import threading
from pathlib import Path

import pytest

from conftest import closed_port
from daemon_support import (
    DAY,
    HOURS,
    REF,
    day_readings,
    off_grid,
    sml,
    wait_for,
    watch_acks,
    write_config,
)
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.mqttconn import EX_NOPERM
from pseudotwin.edge.recorder import Recorder
from pseudotwin.edge.service import Service
from pseudotwin.history.store import open_store
from test_daemon import Viewer, publisher, reading
from test_daemon_process import EXE, start_daemon

TOPIC = "house/dining/temp"
BAD_TS = [b'{"ts": "0001-01-01T00:00:00+01:00", "value": 20}',
          b'{"ts": "9999-12-31T23:59:59-01:00", "value": 20}']


def morning(n: int | None = None) -> list[bytes]:
    """The day's reference readings before 11:00 (all in the past of a clock past noon)."""
    df = day_readings(sml())
    df = df[df["ts"] < HOURS.at(DAY, 11.0)]
    out = [reading(r["ts"].to_pydatetime(), float(r["value"])) for _, r in df.iterrows()]
    return out[:n] if n else out


def journal_lines(folder: Path) -> int:
    return sum(len(p.read_bytes().splitlines()) for p in (folder / "state" / "journal")
               .glob("*.jsonl"))


def journaled_readings(folder: Path) -> int:
    """Distinct readings journaled: one journaled but not yet acknowledged when the daemon
    stopped comes back (at-least-once delivery) and is journaled again; replay and the
    twins drop the copy."""
    return len({line for p in (folder / "state" / "journal").glob("*.jsonl")
                for line in p.read_bytes().splitlines()})


def send(port: int, payloads: list[bytes], name: str) -> None:
    pub = publisher(port, name)
    for b in payloads:
        pub.publish(TOPIC, b, qos=1).wait_for_publish(10)
    pub.disconnect()
    pub.loop_stop()


# -- 1. edge-of-range timestamps ----------------------------------------------------------
def test_edge_of_range_timestamps_are_rejected_and_never_stall_the_daemon(
    service_factory, mosquitto
) -> None:
    svc = service_factory()
    good = morning(40)
    send(mosquitto.port, BAD_TS * 30 + good, "rel-ts-daemon")  # 60 > the in-flight window
    wait_for(lambda: svc.accepted == len(good), what=lambda: f"{svc.accepted} accepted")
    assert svc.rejections.counts[(REF, "bad-timestamp")] == 60


def test_edge_of_range_timestamps_are_rejected_by_the_recorder(service_factory, mosquitto,
                                                               tmp_path: Path) -> None:
    rec = service_factory(kind=Recorder, store="history.db")
    good = morning(40)
    send(mosquitto.port, BAD_TS * 30 + good, "rel-ts-recorder")
    wait_for(lambda: rec.written == len(good), what=lambda: f"{rec.written} written")
    assert rec._worker.is_alive()
    assert rec.rejections.counts[(REF, "bad-timestamp")] == 60


# -- 2 + 3. the journal fails, then works again -------------------------------------------
def test_journal_failure_degrades_and_recovers_by_itself_without_losing_a_reading(
    service_factory, mosquitto, tmp_path: Path
) -> None:
    status = Viewer(mosquitto.port, "pt/status")
    svc = service_factory()
    readings = morning(60)
    send(mosquitto.port, readings[:10], "rel-journal-1")
    wait_for(lambda: svc.accepted == 10, what="first readings")
    jdir = tmp_path / "state" / "journal"
    shutil.rmtree(jdir)
    jdir.write_text("a file where the journal directory was")  # open() fails, even as root
    send(mosquitto.port, readings[10:], "rel-journal-2")
    wait_for(lambda: "degraded" in [b for _, b in status.msgs], what="status degraded")
    # A barrier behind every reading the broker has handed the daemon: a QoS 0 message is
    # not held back by the broker's in-flight window, so it reaches the daemon after the
    # unacknowledged readings sent before it (the rest wait in the broker for acks), and the
    # worker takes it in that order. Its rejection shows the worker's batch holding it;
    # the worker's next heartbeat (set when it next takes a batch, so after this one) shows
    # that batch finished.
    pub = publisher(mosquitto.port, "rel-journal-barrier")
    pub.publish(TOPIC, BAD_TS[0], qos=0).wait_for_publish(10)
    pub.disconnect()
    pub.loop_stop()
    wait_for(lambda: svc.rejections.counts.get((REF, "bad-timestamp")) == 1,
             what="the barrier reading rejected")
    beat = svc.heartbeat
    wait_for(lambda: svc.heartbeat > beat, what="the worker's next batch")
    assert svc.accepted == 10  # nothing acknowledged while the journal cannot take it
    assert svc.health.snapshot()["journal"]["ok"] is False
    jdir.unlink()  # the fault clears
    # recovered by itself: no restart, no message needed (wait_for's timeout catches a hang)
    wait_for(lambda: svc.accepted == len(readings), what=lambda: f"{svc.accepted} accepted")
    wait_for(lambda: [b for _, b in status.msgs][-1] == "online", what="status online again")
    assert journal_lines(tmp_path) == len(readings)  # the first 10 rebuilt from memory
    status.close()


@pytest.mark.parametrize("durable", [True, False], ids=["journal_fsync", "no fsync"])
def test_a_reading_is_acknowledged_only_once_its_journal_line_is_on_disk(
    service_factory, mosquitto, monkeypatch: pytest.MonkeyPatch, durable: bool,
    tmp_path: Path
) -> None:
    """With journal_fsync (the default), whenever the daemon acknowledges a reading nothing
    it journaled is only in the kernel's cache: the fsync came first, so a power cut loses
    no reading the broker let go. Switched off, readings are acknowledged with their lines
    still in the kernel's cache. (os.fsync and the client's ack are watched, both doing
    their real work.)"""
    synced: dict[int, int] = {}  # inode → the file's size at its latest fsync
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        real_fsync(fd)
        st = os.fstat(fd)
        synced[st.st_ino] = st.st_size

    monkeypatch.setattr(os, "fsync", fsync)
    svc = service_factory(**({} if durable else {"journal_fsync": False}))
    jdir = tmp_path / "state" / "journal"
    unsynced_at_ack = watch_acks(svc.client, monkeypatch, lambda: sum(
        st.st_size - synced.get(st.st_ino, 0) for st in (p.stat() for p in jdir.glob("*.jsonl"))))
    readings = morning()
    send(mosquitto.port, readings, f"rel-fsync-{durable}")
    wait_for(lambda: len(unsynced_at_ack) >= len(readings),
             what=lambda: f"{len(unsynced_at_ack)} acknowledged")
    assert journal_lines(tmp_path) == len(readings)
    journal_files = {p.stat().st_ino for p in jdir.glob("*.jsonl")}
    if durable:
        assert unsynced_at_ack == [0] * len(unsynced_at_ack)
        assert journal_files <= set(synced)
    else:
        assert max(unsynced_at_ack) > 0  # acknowledged from the kernel's cache


def test_a_failing_fsync_is_logged_once_and_the_readings_are_still_acknowledged(
    service_factory, mosquitto, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    """The disk fails under a durable journal: the lines are in the kernel, so the readings
    are acknowledged all the same (holding them would stop the broker's deliveries), the
    failure is logged once for the spell, and its end is logged too."""
    svc = service_factory()
    acked = watch_acks(svc.client, monkeypatch, lambda: None)
    readings = morning()
    send(mosquitto.port, readings[:5], "rel-eio-1")  # the day's file made while all is well
    wait_for(lambda: len(acked) >= 5, what="the first readings acknowledged")
    real_fsync = os.fsync

    def failing(fd: int) -> None:
        if stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(errno.EIO, "Input/output error")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", failing)
    with caplog.at_level(logging.WARNING, logger="pseudotwin.edge.service"):
        send(mosquitto.port, readings[5:-1], "rel-eio-2")
        wait_for(lambda: len(acked) >= len(readings) - 1, what=lambda: f"{len(acked)} acked")
        failed = [r for r in caplog.records if "to disk failed" in r.getMessage()]
        assert len(failed) == 1 and failed[0].levelno == logging.ERROR
        assert "Input/output error" in failed[0].getMessage()
        monkeypatch.setattr(os, "fsync", real_fsync)  # the disk is back
        send(mosquitto.port, readings[-1:], "rel-eio-3")
        wait_for(lambda: len(acked) >= len(readings), what="the last reading acknowledged")
        wait_for(lambda: any("works again" in r.getMessage() for r in caplog.records),
                 what="the end of the spell logged")
    assert journal_lines(tmp_path) == len(readings)


# -- 4. invalid UTF-8 in a journal ---------------------------------------------------------
def test_invalid_utf8_in_the_journal_is_skipped_and_the_daemon_starts(
    service_factory, tmp_path: Path, caplog
) -> None:
    jdir = tmp_path / "state" / "journal"
    jdir.mkdir(parents=True)
    good = [json.dumps({"sensor": REF, "ts": json.loads(b)["ts"], "value": json.loads(b)["value"]})
            .encode() for b in morning()]
    (jdir / f"{DAY.isoformat()}.jsonl").write_bytes(
        b"\n".join(good[:10]) + b"\n\xff\xfe\x00garbage\n" + b"\n".join(good[10:]) + b"\n")
    with caplog.at_level(logging.INFO):
        svc = service_factory()
    assert svc.connected.is_set()
    assert f"restored state from {len(good)} journaled readings" in caplog.text
    assert "unreadable, skipped" in caplog.text


# -- 5. state dir / store deleted while running -------------------------------------------
def test_deleted_state_dir_is_detected_and_rebuilt(service_factory, mosquitto, tmp_path: Path,
                                                   caplog) -> None:
    svc = service_factory()
    readings = morning(40)
    send(mosquitto.port, readings[:20], "rel-rm-1")
    wait_for(lambda: svc.accepted == 20, what="first half")
    with caplog.at_level(logging.ERROR):
        shutil.rmtree(tmp_path / "state")
        send(mosquitto.port, readings[20:], "rel-rm-2")
        wait_for(lambda: svc.accepted == 40, what="second half")
    assert "was deleted while running" in caplog.text
    assert journal_lines(tmp_path) == 40
    assert svc.health.snapshot()["journal"]["recreated"] == 1
    # its lock file went with the folder: renewed, so a second daemon is still refused
    from pseudotwin.errors import StateInUseError

    with pytest.raises(StateInUseError):
        service_factory()
    svc.stop()
    again = Service(svc.cfg, ReplayClock(off_grid(12.0), 1.0))
    assert again.restore() == 40
    again.journal.close()


def test_deleted_store_is_detected_and_recreated_by_the_recorder(
    service_factory, mosquitto, tmp_path: Path, caplog
) -> None:
    rec = service_factory(kind=Recorder, store="history.db")
    readings = morning(40)
    send(mosquitto.port, readings[:20], "rel-rmdb-1")
    wait_for(lambda: rec.written == 20, what="first half stored")
    with caplog.at_level(logging.ERROR):
        for p in tmp_path.glob("history.db*"):
            p.unlink()
        send(mosquitto.port, readings[20:], "rel-rmdb-2")
        wait_for(lambda: rec.written == 40, what="second half stored")
    assert "was deleted or replaced while recording" in caplog.text
    with open_store(tmp_path / "history.db") as store:
        assert len(store.read_readings([REF])) == 20  # into the new file, not the void


# -- 6. flood: reported, bounded, and SIGTERM within seconds -------------------------------
def test_flood_is_reported(service_factory, mosquitto, caplog) -> None:
    svc = service_factory()
    # Any backlog is a flood here; the worker is stalled (its first ack waits for the lock)
    # until the broker's in-flight window of the flood waits in the queue behind it.
    svc.health.backlog_seconds = svc.health.report_seconds = 0.0
    base = HOURS.at(DAY, 8.0)
    flood = [reading(base + dt.timedelta(seconds=i), 20 + (i % 7) / 10) for i in range(1500)]
    with caplog.at_level(logging.WARNING):
        with svc._lock:
            sender = threading.Thread(target=send, args=(mosquitto.port, flood, "rel-flood"))
            sender.start()
            wait_for(lambda: svc.health.received >= 10, what="a backlog")
        wait_for(lambda: "flood: behind" in caplog.text, timeout=60, what="flood report")
        sender.join(60)
    ingest = svc.health.snapshot()["ingest"]
    assert ingest["queue_max_seen"] <= svc.queue.maxsize
    assert ingest["received"] > 0


def test_sigterm_stops_while_flooded_and_unacked_are_redelivered(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    cfg = write_config(tmp_path, mosquitto.port, desk_artifact)
    log = tmp_path / "daemon.log"
    d = start_daemon(cfg, log)
    status = Viewer(mosquitto.port, "pt/status")
    try:
        wait_for(lambda: "online" in [b for _, b in status.msgs], what="online")
        base = HOURS.at(DAY, 8.0)
        n = 800
        # Paused while the flood arrives, so a backlog is waiting when it resumes (otherwise
        # a fast machine keeps up with the sender and there is nothing left to abandon).
        d.send_signal(signal.SIGSTOP)
        try:
            send(mosquitto.port, [reading(base + dt.timedelta(seconds=i), 20.0 + i % 5 / 10)
                                  for i in range(n)], "rel-term")
        finally:
            d.send_signal(signal.SIGCONT)
        wait_for(lambda: journal_lines(tmp_path) > 20, what="processing")
        d.send_signal(signal.SIGTERM)
        # wait()'s timeout bounds a hang; `first < n` below shows nothing was drained
        assert d.wait(15) == 0
        first = journal_lines(tmp_path)
        assert first < n  # stopped with work left: nothing was drained
        d = start_daemon(cfg, log)  # the broker redelivers what was not acknowledged
        wait_for(lambda: journaled_readings(tmp_path) == n, timeout=60,
                 what=lambda: f"{journaled_readings(tmp_path)} of {n} journaled")
    finally:
        d.send_signal(signal.SIGTERM)
        d.wait(15)
        status.close()


# -- 7. corrupt artifact -------------------------------------------------------------------
def _poison(d: object) -> bool:
    """Set the first float found under ``d`` to +inf (in place)."""
    items = d.items() if isinstance(d, dict) else enumerate(d) if isinstance(d, list) else []
    for k, v in items:
        if isinstance(v, float):
            d[k] = math.inf  # type: ignore[index]
            return True
        if _poison(v):
            return True
    return False


def test_non_finite_number_in_an_artifact_is_a_configuration_error(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    art = json.loads(desk_artifact.read_text())
    assert _poison(art["models"])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(art))  # writes Infinity, as a corrupted file would hold
    cfg = write_config(tmp_path, mosquitto.port, bad)
    run = subprocess.run([*EXE, "run", "--config", str(cfg)], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 78
    assert "$.models." in run.stderr and "not a finite number" in run.stderr
    check = subprocess.run([*EXE, "check-config", str(cfg)], capture_output=True, text=True,
                           timeout=60)
    assert check.returncode != 0 and "not a finite number" in check.stderr


# -- 8. state from the future --------------------------------------------------------------
def test_state_from_a_day_ahead_does_not_silence_today(service_factory, mosquitto, tmp_path: Path,
                                                      caplog) -> None:
    jdir = tmp_path / "state" / "journal"
    jdir.mkdir(parents=True)
    tomorrow = DAY + dt.timedelta(days=1)
    lines = []
    for b in morning(60):
        o = json.loads(b)
        ts = dt.datetime.fromisoformat(o["ts"]) + dt.timedelta(days=1)
        lines.append(json.dumps({"sensor": REF, "ts": ts.isoformat(), "value": o["value"]}))
    (jdir / f"{tomorrow.isoformat()}.jsonl").write_text("\n".join(lines) + "\n")
    viewer = Viewer(mosquitto.port)
    with caplog.at_level(logging.WARNING):
        svc = service_factory()
    assert "after the daemon's clock" in caplog.text
    send(mosquitto.port, morning(), "rel-future")
    wait_for(lambda: svc.accepted == len(morning()), what="all journaled")
    wait_for(lambda: len(viewer.on("/estimate")) > 0, what="today's estimates")
    viewer.close()


def test_state_from_later_today_stays_out_of_the_window(service_factory, mosquitto,
                                                        tmp_path: Path, caplog) -> None:
    """A replay's state dir run again (or a clock set back within the day): the journal holds
    this afternoon's readings at noon. Replayed, the latest of them would stand in the window
    as the reference's value all morning; they stay on disk."""
    df = day_readings(sml())
    jdir = tmp_path / "state" / "journal"
    jdir.mkdir(parents=True)
    early = df[(df["ts"] >= HOURS.at(DAY, 1.5)) & (df["ts"] < HOURS.at(DAY, 9.0))]
    late = df[df["ts"] >= HOURS.at(DAY, 15.0)]
    (jdir / f"{DAY.isoformat()}.jsonl").write_text("".join(
        json.dumps({"sensor": REF, "ts": ts.isoformat(), "value": float(v)}) + "\n"
        for part in (early, late) for ts, v in zip(part["ts"], part["value"], strict=True)))
    with caplog.at_level(logging.WARNING):
        svc = service_factory()  # clock past noon
    (rt,) = svc.twins.values()
    kept = sorted(p.ts for p in rt.twin.window if p.sensor == REF)
    assert kept and kept[-1] == early["ts"].max()  # the morning's, none of the afternoon's
    assert f"journal holds {len(late)} readings after the daemon's clock" in caplog.text
    on_disk = (jdir / f"{DAY.isoformat()}.jsonl").read_text().splitlines()
    assert len(on_disk) == len(early) + len(late)


# -- 9. operations -------------------------------------------------------------------------
def test_broker_down_at_start_logged_at_once_no_ready_and_sigint_is_prompt(
    desk_artifact, tmp_path: Path
) -> None:
    cfg = write_config(tmp_path, closed_port(), desk_artifact)
    sock_path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.setblocking(False)
    log = tmp_path / "daemon.log"
    d = start_daemon(cfg, log, {"NOTIFY_SOCKET": str(sock_path)})
    try:
        wait_for(lambda: "cannot connect to the broker" in log.read_text(), timeout=10,
                 what="first connection failure logged")
        assert "ConnectionRefusedError" in log.read_text()
        d.send_signal(signal.SIGINT)
        assert d.wait(10) == 0  # prompt: not after the connection retries (a hang bound)
        got = []
        while True:
            try:
                got.append(sock.recv(256).decode())
            except BlockingIOError:
                break
        assert "READY=1" not in got
    finally:
        if d.poll() is None:
            d.kill()
        sock.close()
    text = log.read_text()
    assert "running" not in text[text.index("received SIGINT"):]


def test_wrong_password_exits_with_a_distinct_status(password_broker, desk_artifact,
                                                     tmp_path: Path) -> None:
    cfg = write_config(tmp_path, password_broker, desk_artifact)
    cfg.write_text(cfg.read_text().replace("keepalive = 30", 'keepalive = 30\nusername = "pt"\n'
                                           'password_env = "PT_TEST_PASSWORD"'))
    log = tmp_path / "daemon.log"
    d = start_daemon(cfg, log, {"PT_TEST_PASSWORD": "wrong"})
    try:
        assert d.wait(20) == EX_NOPERM
    finally:
        if d.poll() is None:
            d.kill()
    assert "refused the credentials" in log.read_text()


def test_files_are_private_whatever_the_launcher(mosquitto, desk_artifact,
                                                 tmp_path: Path) -> None:
    cfg = write_config(tmp_path, mosquitto.port, desk_artifact)
    old = os.umask(0o022)  # a permissive launcher
    try:
        d = start_daemon(cfg, tmp_path / "daemon.log")
    finally:
        os.umask(old)
    status = Viewer(mosquitto.port, "pt/status")
    try:
        wait_for(lambda: "online" in [b for _, b in status.msgs], what="online")
        send(mosquitto.port, morning(5), "rel-umask")
        wait_for(lambda: journal_lines(tmp_path) == 5, what="journaled")
    finally:
        d.send_signal(signal.SIGTERM)
        d.wait(15)
        status.close()
    state = tmp_path / "state"
    for p in [state, state / "journal"]:
        assert stat.S_IMODE(p.stat().st_mode) == 0o700, p
    for p in (state / "journal").glob("*.jsonl"):
        assert stat.S_IMODE(p.stat().st_mode) == 0o600, p


def test_replay_that_loses_the_broker_says_where_to_resume(mosquitto, desk_artifact,
                                                           tmp_path: Path, monkeypatch) -> None:
    """It ended in paho's RuntimeError traceback and left the rest unsent without saying so;
    its client id was fixed, so a second replay took the first one's session over."""
    import pseudotwin.edge.replay as replay_module
    from daemon_support import HandClock, config
    from pseudotwin.errors import BrokerError

    monkeypatch.setattr(replay_module, "PUBLISH_TIMEOUT_S", 2.0)
    cfg = config(tmp_path, mosquitto.port, desk_artifact)
    start = HOURS.at(DAY, 8.0)
    readings = day_readings(sml())
    readings = readings[readings["ts"] >= start]
    third = readings["ts"].iloc[2].to_pydatetime()

    class BrokerDiesAtTheThird(HandClock):
        def wait_until(self, instant: dt.datetime, stop: threading.Event) -> bool:
            if instant == third:
                mosquitto.kill()
            return True

    try:
        with pytest.raises(BrokerError) as exc:
            replay_module.replay(cfg, readings, start, HOURS.at(DAY, 19.0), 1.0,
                                 clock=BrokerDiesAtTheThird(start))
    finally:
        mosquitto.start()
    message = str(exc.value)
    assert "after 2 readings" in message and f"--start {third.isoformat()}" in message


def test_a_second_daemon_or_recorder_on_one_state_dir_refuses_to_start(service_factory
                                                                       ) -> None:
    """Two daemons on one configuration knocked each other off the broker every second,
    forever, and wrote one journal; the second now refuses (run exits 75 on it: systemd
    tries again, and starts it once the other has ended)."""
    from pseudotwin.errors import StateInUseError

    first = service_factory()
    with pytest.raises(StateInUseError, match=rf"in use by another pseudotwin daemon \(PID "
                                              rf"{os.getpid()}\)"):
        service_factory()
    recorder = service_factory(kind=Recorder, store="history.db")  # a lock of its own
    with pytest.raises(StateInUseError, match="in use by another pseudotwin recorder"):
        service_factory(kind=Recorder, store="history.db")
    recorder.stop()
    first.stop()
    service_factory().stop()  # the lock went with the first daemon


def test_the_state_lock_is_one_holder_at_a_time_and_says_what_it_cannot_open(
        tmp_path: Path) -> None:
    from pseudotwin.edge.statelock import StateLock
    from pseudotwin.errors import ConfigError, StateInUseError

    a, b = (StateLock(tmp_path / "state" / "daemon.lock", "daemon") for _ in range(2))
    a.acquire()
    with pytest.raises(StateInUseError, match=rf"\(PID {os.getpid()}\)"):
        b.acquire()
    a.release()
    b.acquire()  # released: the next one takes it
    b.release()
    # /proc takes no file, whoever asks (root included): one line naming the file
    with pytest.raises(ConfigError, match="/proc/pseudotwin-lock/daemon.lock: the daemon's "
                                          "lock file cannot be opened"):
        StateLock(Path("/proc/pseudotwin-lock/daemon.lock"), "daemon").acquire()
