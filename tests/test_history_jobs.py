"""Recorder, backfill, training from the store and the daemon's warm start (real SQLite,
real Mosquitto, real twins)."""

from __future__ import annotations

import datetime as dt
import json
import logging
import shutil
from pathlib import Path

import pandas as pd
import pytest

import pseudotwin.edge.recorder as recorder_module
from daemon_support import (
    DAY,
    HOURS,
    REF,
    TARGET,
    Synced,
    config,
    day_readings,
    sml,
    wait_for,
    watch_acks,
    write_config,
)
from fake_cratedb import FakeCrateDB
from pseudotwin.analysis.evaluate import replay_estimates
from pseudotwin.cli import main
from pseudotwin.config import load_config
from pseudotwin.core.series import read_history, write_history
from pseudotwin.edge import readinglines
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.recorder import Recorder
from pseudotwin.edge.service import Service
from pseudotwin.edge.spool import Spool
from pseudotwin.edge.statelock import StateLock
from pseudotwin.errors import StateInUseError
from pseudotwin.history.backfill import backfill
from pseudotwin.history.backfill_pool import backfill_twins
from pseudotwin.history.store import open_store, to_ms
from pseudotwin.live.artifact import Artifact, artifact_hash
from pseudotwin.live.readings import Reading
from test_daemon import publisher, reading


@pytest.fixture(scope="module")
def sml_store(tmp_path_factory) -> Path:
    """SML2010 up to 2012-03-24 in a SQLite store."""
    path = tmp_path_factory.mktemp("db") / "history.db"
    df = sml()
    with open_store(str(path)) as store:
        store.write_readings(df[df["ts"] < "2012-03-24T23:00Z"])
    return path


def test_recorder_writes_every_valid_reading_and_spools_while_the_store_is_away(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    db = tmp_path / "later" / "history.db"  # its folder does not exist yet: store "down"
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(db))
    rec = Recorder(cfg, retry_seconds=0.2)
    rec.start(wait_connected=15)
    pub = publisher(mosquitto.port, "rec-bridge")
    ts = [HOURS.at(DAY, 8 + i / 60) for i in range(40)]
    for i, t in enumerate(ts[:20]):
        pub.publish("house/dining/temp", reading(t, 20 + i / 100), qos=1)
    pub.publish("house/dining/temp", b"{broken", qos=1)
    pub.publish("house/room/temp", reading(ts[0], 99.0), qos=1)  # out of range
    for unset in (0, 12345):  # a device clock never set, an uptime sent as epoch seconds
        pub.publish("house/dining/temp", json.dumps({"ts": unset, "value": 20.0}), qos=1)
    wait_for(lambda: rec.spooled == 20 and rec.rejections.run_total == 4,
             what="first batch spooled while the store is down, bad payloads counted")
    assert rec.written == 0 and rec.rejections.counts[(REF, "too-old")] == 2
    db.parent.mkdir()  # the store comes back
    for i, t in enumerate(ts[20:], start=20):
        pub.publish("house/dining/temp", reading(t, 20 + i / 100), qos=1)
    wait_for(lambda: rec.written == 40, what="spool and new readings written")
    rec.stop()
    pub.loop_stop()
    with open_store(str(db)) as store:
        got = store.read_readings([REF])
    assert len(got) == 40  # count in = count stored
    assert [t.to_pydatetime() for t in got["ts"]] == ts
    assert not rec.spool.path.exists()


def test_rows_the_store_refuses_one_by_one_go_to_a_file_and_block_nothing(
    mosquitto, desk_artifact, tmp_path: Path, monkeypatch
) -> None:
    """CrateDB answers each row of a bulk write: a reading it always refuses must not keep the
    spool, and every reading after it, from the store. It lands in a canonical CSV that
    ``pseudotwin import`` loads once the cause is fixed, synced before it is acknowledged.
    (FakeCrateDB is a fake: no CrateDB server can run here.)"""
    synced = Synced(monkeypatch)
    ts = [HOURS.at(DAY, 8 + i / 60) for i in range(30)]
    bad = {to_ms(ts[3]), to_ms(ts[25])}
    value = {i: 20 + i / 100 + 1e-9 for i in range(30)}  # more digits than %.6g keeps
    with FakeCrateDB() as crate:
        crate.fail_row = lambda stmt, row: ("ColumnValidationException[refused]"
                                            if row[1] in bad else None)
        cfg = config(tmp_path, mosquitto.port, desk_artifact, store=crate.url)
        rec = Recorder(cfg, retry_seconds=0.2)
        unsynced_at_ack = watch_acks(rec.client, monkeypatch,
                                     lambda: synced.unsynced(rec.refused_path))
        rec.start(wait_connected=15)
        pub = publisher(mosquitto.port, "rec-crate")
        for i, t in enumerate(ts[:20]):
            pub.publish("house/dining/temp", reading(t, value[i]), qos=1)
        wait_for(lambda: rec.written == 19 and rec.refused == 1,
                 what=lambda: f"19 written, 1 refused (now {rec.written}, {rec.refused})")
        for i, t in enumerate(ts[20:], start=20):
            pub.publish("house/dining/temp", reading(t, value[i]), qos=1)
        wait_for(lambda: rec.written == 28 and rec.refused == 2, what="later readings stored")
        rec.stop()
        pub.loop_stop()
        assert not rec.spool.path.exists()
        assert len(unsynced_at_ack) == 30 and set(unsynced_at_ack) == {0}
        assert synced.size[rec.refused_path] == rec.refused_path.stat().st_size
        assert rec.refused_path.parent in synced.folders  # its directory entry too
        with open_store(crate.url) as store:
            stored = store.read_readings([REF])
            assert len(stored) == 28
            refused = read_history(rec.refused_path)
            assert [t.to_pydatetime() for t in refused["ts"]] == [ts[3], ts[25]]
            assert refused["value"].tolist() == [value[3], value[25]]
            crate.fail_row = None  # the cause fixed
            assert main(["import", str(rec.refused_path), "--store", crate.url]) == 0
            assert [t.to_pydatetime() for t in store.read_readings([REF])["ts"]] == ts


def test_a_retained_reading_without_a_timestamp_is_not_taken_again_at_each_subscribe(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    """A bare number published with retain comes again at every subscribe: stamped on
    arrival it was an old value taken in as new at each reconnect, and a dead sensor never
    turned stale. Daemon and recorder reject it as `retained`; unretained ones are readings."""
    cfg_path = write_config(tmp_path, mosquitto.port, desk_artifact,
                            store=str(tmp_path / "history.db"))
    text = cfg_path.read_text(encoding="utf-8").replace(
        'topic = "house/dining/temp"', 'topic = "house/dining/temp"\nformat = "number"')
    cfg_path.write_text(text, encoding="utf-8")
    cfg = load_config(cfg_path)
    pub = publisher(mosquitto.port, "retaining-panel")
    pub.publish("house/dining/temp", b"17.0", qos=1, retain=True).wait_for_publish(10)
    for _ in range(2):  # a start, and a restart on the same state
        svc = Service(cfg, ReplayClock(HOURS.at(DAY, 9.0), 1.0))
        svc.start(wait_connected=15)
        rec = Recorder(cfg, retry_seconds=0.2)
        rec.start(wait_connected=15)
        wait_for(lambda s=svc, r=rec: s.rejections.counts.get((REF, "retained")) == 1
                 and r.rejections.counts.get((REF, "retained")) == 1,
                 what="the retained value rejected by both")
        assert not [p for p in svc.twins["desk"].twin.window if p.sensor == REF]
        rec.stop()
        svc.stop()
    svc = Service(cfg, ReplayClock(HOURS.at(DAY, 9.0), 1.0))
    svc.start(wait_connected=15)
    try:
        pub.publish("house/dining/temp", b"17.2", qos=1).wait_for_publish(10)
        wait_for(lambda: [p.value for p in svc.twins["desk"].twin.window
                          if p.sensor == REF] == [17.2], what="an unretained bare number taken")
    finally:
        svc.stop()
        pub.publish("house/dining/temp", b"", qos=1, retain=True).wait_for_publish(10)
        pub.loop_stop()


def test_the_recorder_unsubscribes_a_sensor_removed_from_the_configuration_once(
    mosquitto, desk_artifact, tmp_path: Path, caplog
) -> None:
    """As the daemon: the persistent session kept a removed sensor's subscription, and the
    recorder took every reading of it in and dropped it without a word, for good."""
    path = write_config(tmp_path, mosquitto.port, desk_artifact,
                        store=str(tmp_path / "history.db"))
    base = path.read_text(encoding="utf-8")
    path.write_text(base + '\n[[sensors]]\nid = "hall/temp"\ntopic = "house/hall/temp"\n'
                           'unit = "°C"\nmin = -10\nmax = 50\n', encoding="utf-8")
    first = Recorder(load_config(path), retry_seconds=0.2)
    first.start(wait_connected=15)
    first.stop()
    path.write_text(base, encoding="utf-8")  # the hall sensor removed
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.mqttconn")
    said = lambda: [r for r in caplog.records if "house/hall/temp" in r.getMessage()]  # noqa: E731
    pub = publisher(mosquitto.port, "hall-panel")
    for n in (1, 2):  # the restart after the change, then the next
        for k in range(2):  # the first restart's session keeps them; the next has none
            pub.publish("house/hall/temp", reading(HOURS.at(DAY, 8.9), 20.0 + k),
                        qos=1).wait_for_publish(10)
        rec = Recorder(load_config(path), retry_seconds=0.2, flush_seconds=0.05)
        rec.start(wait_connected=15)
        try:
            # one publisher's messages arrive in order: the hall's came before this one
            pub.publish("house/dining/temp", reading(HOURS.at(DAY, 8.9 + n / 100), 20.0),
                        qos=1).wait_for_publish(10)
            wait_for(lambda r=rec: r.written == 1, what="the dining reading stored")
        finally:
            rec.stop()
        assert len(said()) == 1 and "recorder" in said()[0].getMessage() \
            and "unsubscribed" in said()[0].getMessage()  # said once, and gone at the next
    pub.loop_stop()


def test_a_spool_line_cut_short_costs_no_later_reading(tmp_path: Path) -> None:
    """A crash or a full disk mid-write leaves the spool's last line torn: the readings spooled
    after it (acknowledged, the store being away) must not be glued onto it and lost."""
    spool = Spool(tmp_path / "spool.jsonl")
    at = [HOURS.at(DAY, h) for h in (8.0, 8.1, 8.2)]
    first, *later = [Reading(REF, t, 17.0 + k) for k, t in enumerate(at)]
    spool.add([first])
    with open(spool.path, "ab") as fh:
        fh.write(b'{"sensor": "dining/temp", "ts": "2012-03-20T0')  # the crash
    spool.add(later)
    assert spool.load() == [first, *later]


def test_a_long_spool_goes_to_the_store_a_piece_at_a_time(
    mosquitto, desk_artifact, tmp_path: Path, monkeypatch, caplog
) -> None:
    """The recorder read its whole spool into memory at every retry while the store was
    away (days of readings: seconds of CPU and hundreds of MB every few seconds), and wrote
    it in one piece when the store came back."""
    monkeypatch.setattr(recorder_module, "SPOOL_CHUNK", 10)
    monkeypatch.setattr(recorder_module, "SPOOL_CHUNKS_PER_FLUSH", 2)  # 3 pieces: 2 flushes
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.recorder")
    db = tmp_path / "later" / "history.db"  # its folder does not exist yet: store "down"
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(db))
    spooled = [Reading(REF, HOURS.at(DAY, 8 + i / 60), 20 + i / 100) for i in range(25)]
    Spool(Path(cfg.state_dir) / "recorder-spool.jsonl").add(spooled)  # a run before's
    rec = Recorder(cfg, retry_seconds=0.2)
    rec.start(wait_connected=15)
    try:
        wait_for(lambda: rec.metrics.store_errors._value.get() >= 2,
                 what="two retries while the store is away")
        tried = [r.getMessage() for r in caplog.records if "history store unavailable" in
                 r.getMessage()]
        assert tried and all("; 10 readings: they and the rest of the spool stay in it" in t
                             for t in tried)
        assert rec.spool.load() == spooled
        db.parent.mkdir()  # the store comes back
        wait_for(lambda: not rec.spool.path.exists(), what="the spool written")
    finally:
        rec.stop()
    with open_store(str(db)) as store:
        got = store.read_readings([REF])
    assert [t.to_pydatetime() for t in got["ts"]] == [r.ts for r in spooled]
    assert "wrote 25 spooled readings to the history store" in caplog.text


def test_a_recorder_that_can_neither_store_nor_spool_says_degraded_sparingly(
    mosquitto, desk_artifact, tmp_path: Path, mqtt_client, caplog
) -> None:
    """With the store away and the disk refusing the spool, the recorder logged an error at
    every flush (~86,000 a day) while its status stayed `online`."""
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.recorder")
    db = tmp_path / "later" / "history.db"  # the store away
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(db))
    rec = Recorder(cfg, retry_seconds=0.05, flush_seconds=0.05)
    rec.spool.path.mkdir()  # the spool cannot be written (as on a full disk)
    status = mqtt_client()
    status.subscribe("pt/recorder/status")
    said: list[bytes] = []

    def last_status() -> bytes | None:
        while not status.messages.empty():
            said.append(status.messages.get_nowait().payload)
        return said[-1] if said else None

    rec.start(wait_connected=15)
    pub = publisher(mosquitto.port, "stuck-bridge")
    try:
        pub.publish("house/dining/temp", reading(HOURS.at(DAY, 8.0), 20.0), qos=1)
        wait_for(lambda: rec._stuck >= 20, what="twenty failed flushes")
        wait_for(lambda: last_status() == b"degraded", what="status degraded")
        for what in ("cannot spool", "cannot read the spool"):  # append, and retry
            said = [r for r in caplog.records if what in r.getMessage()]
            assert 1 <= len(said) <= 6, what  # 1, 2, 4, 8, 16, (32) of 20 and more
        rec.spool.path.rmdir()  # space again
        wait_for(lambda: rec.spooled == 1, what="the reading spooled")
        wait_for(lambda: last_status() == b"online", what="status online again")
        assert "spooling again after" in caplog.text
    finally:
        rec.stop()
        pub.loop_stop()


def test_a_recorder_whose_state_dir_is_deleted_spools_and_locks_it_again(
    mosquitto, desk_artifact, tmp_path: Path, caplog
) -> None:
    """The recorder alone on its state dir: deleted, the spool failed every second until an
    administrator made the folder again, and the lock was gone (a second recorder could
    start there)."""
    caplog.set_level(logging.WARNING, logger="pseudotwin")
    db = tmp_path / "later" / "history.db"  # the store away: readings go to the spool
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(db))
    rec = Recorder(cfg, retry_seconds=0.2)
    rec.start(wait_connected=15)
    pub = publisher(mosquitto.port, "deleted-state-bridge")
    try:
        pub.publish("house/dining/temp", reading(HOURS.at(DAY, 8.0), 20.0), qos=1)
        wait_for(lambda: rec.spooled == 1, what="the first reading spooled")
        shutil.rmtree(cfg.state_dir)
        pub.publish("house/dining/temp", reading(HOURS.at(DAY, 8.1), 20.1), qos=1)
        wait_for(lambda: rec.spooled == 2, what="the second reading spooled")
        assert rec.spool.load()[-1].value == 20.1
        assert "was deleted while recording" in caplog.text
        with pytest.raises(StateInUseError):  # locked again: no second recorder here
            StateLock(Path(cfg.state_dir) / "recorder.lock", "recorder").acquire()
    finally:
        rec.stop()
        pub.loop_stop()


@pytest.mark.parametrize("fsync", [True, False])
def test_a_recorder_acknowledges_a_reading_only_once_it_is_on_disk(
    mosquitto, desk_artifact, tmp_path: Path, monkeypatch, fsync: bool
) -> None:
    """The broker forgets a reading once the recorder acknowledges it: with `journal_fsync`
    (the default) the reading must then survive a power cut. Its spool line was only
    flushed to the kernel, and SQLite's commits (synchronous NORMAL) could roll back."""
    synced = Synced(monkeypatch)
    db = tmp_path / "later" / "history.db"  # the store away: readings go to the spool
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(db), journal_fsync=fsync)
    rec = Recorder(cfg, retry_seconds=0.2)
    # the spool's bytes not on disk, and the directory entries synced, at each ack
    at_ack = watch_acks(rec.client, monkeypatch,
                        lambda: (synced.unsynced(rec.spool.path), len(synced.folders)))
    rec.start(wait_connected=15)
    pub = publisher(mosquitto.port, f"durable-bridge-{fsync}")
    try:
        for i in range(6):
            pub.publish("house/dining/temp", reading(HOURS.at(DAY, 8 + i / 60), 20.0 + i),
                        qos=1)
            if i == 2:  # two flushes: a new spool file, then one that exists
                wait_for(lambda: len(at_ack) == 3, what="three readings acked")
        wait_for(lambda: len(at_ack) == 6, what="six readings acknowledged")
        assert rec.spooled == 6
        if fsync:  # the file's directory entry and the state dir's, once, before any ack
            assert at_ack == [(0, 2)] * 6
            assert synced.folders == [rec.spool.path.parent, rec.spool.path.parent.parent]
        else:
            assert synced.size == {} and synced.folders == []
            assert max(unsynced for unsynced, _ in at_ack) > 0  # type: ignore[misc]
        db.parent.mkdir()  # the store comes back
        wait_for(lambda: rec.written == 6, what="the spool written to the store")
        store = rec.store
        assert store is not None
        full, normal = 2, 1
        assert store._conn.execute("PRAGMA synchronous").fetchone()[0] == (
            full if fsync else normal)
    finally:
        rec.stop()
        pub.loop_stop()


def test_a_durable_spool_syncs_every_directory_entry_it_hangs_on_until_a_sync_worked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Synced lines in a file whose directory entry is not on disk are lost with it: the
    state dir made again under a running recorder had only its own folder synced (not at
    all when its mark made it again first), and an entry whose sync failed once was never
    tried again. A mark left without its file skipped a new spool's lines."""
    synced = Synced(monkeypatch)
    state = tmp_path / "state"
    spool = Spool(state / "spool.jsonl", durable=True)
    readings = [Reading(REF, HOURS.at(DAY, 8 + i / 60), 20.0 + i) for i in range(9)]
    assert spool.add(readings[:1])[0] is False
    assert synced.folders == [state, tmp_path] and synced.unsynced(spool.path) == 0
    spool.add(readings[1:2])
    assert synced.folders == [state, tmp_path] and synced.unsynced(spool.path) == 0
    shutil.rmtree(state)  # deleted under a running recorder, made again by the spool
    assert spool.add(readings[2:3])[0] is True
    assert synced.folders[2:] == [state, tmp_path]
    shutil.rmtree(state)
    spool.consume(0)  # the recorder's mark of what it stored makes the folder again first
    assert spool.add(readings[3:4])[0] is True
    assert synced.folders[4:] == [state, tmp_path]

    counted = readinglines.sync_folder
    failing = {tmp_path}  # the state dir's entry: its sync fails once

    def sync_folder(folder: Path) -> None:
        if folder in failing:
            failing.remove(folder)
            raise OSError(5, "Input/output error")
        counted(folder)

    monkeypatch.setattr(readinglines, "sync_folder", sync_folder)
    shutil.rmtree(state)
    del synced.folders[:]
    with pytest.raises(OSError):  # not acknowledged: the recorder retries the batch
        spool.add(readings[4:5])
    assert synced.folders == [state]
    spool.add(readings[4:5])
    assert synced.folders == [state, tmp_path]  # the one that failed, tried again

    # A cut (the bridge's spool) whose entry sync fails is done all the same, once: the
    # next add syncs the entry.
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.spool")
    failing.add(state)
    first_line = spool.path.read_bytes().index(b"\n") + 1
    spool.keep_from(first_line)
    assert "not synced yet" in caplog.text
    assert spool.load() == readings[4:5]  # of the two copies of the retried batch
    spool.add(readings[5:6])
    assert synced.folders[-1] == state and spool.load() == readings[4:6]

    spool.clear()
    spool.consume(10_000)  # a mark left behind without its spool
    spool.add(readings[6:9])
    assert spool.load() == readings[6:9]


def test_a_spool_written_in_part_keeps_the_rest_in_order(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "state" / "spool.jsonl")
    readings = [Reading(REF, HOURS.at(DAY, 8 + i / 60), 20.0 + i) for i in range(25)]
    spool.add(readings)
    pieces = list(spool.chunks(10))
    assert [len(p) for p, _ in pieces] == [10, 10, 5]
    assert pieces[-1][1] == spool.path.stat().st_size
    spool.consume(pieces[0][1])  # the first piece stored
    assert spool.load() == readings[10:]
    assert [len(p) for p, _ in spool.chunks(10)] == [10, 5]
    spool.add(readings[:1])  # spooled after: behind the rest
    assert spool.load() == [*readings[10:], readings[0]]
    spool.clear()
    assert spool.load() == [] and not spool.offset_path.exists()
    (tmp_path / "state").rmdir()  # the state dir deleted under a running recorder
    spool.add(readings[:1])
    assert spool.load() == readings[:1]


def test_backfill_equals_evaluate_and_is_idempotent_and_resumable(
    mosquitto, desk_artifact, sml_store: Path, tmp_path: Path
) -> None:
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(sml_store))
    d1, d3 = dt.date(2012, 3, 20), dt.date(2012, 3, 22)
    with open_store(str(sml_store)) as store:
        s1 = backfill(cfg, "desk", d1, d1, store, progress=False)
        assert (s1.days, s1.skipped) == (1, {})
        s2 = backfill(cfg, "desk", d1, d3, store, progress=False)  # resumes after day 1
        assert s2.days == 2 and s2.skipped == {"already backfilled": [str(d1)]}
        est = store.read_estimates("desk")
        key = f"desk@{artifact_hash(desk_artifact)[:16]}"  # progress per artifact version
        assert store.done_days(key) == {d1, d1 + dt.timedelta(days=1), d3}
        # a rerun of a finished range writes nothing
        s3 = backfill(cfg, "desk", d1, d3, store, progress=False)
        assert s3.days == 0 and s3.estimates == 0
        assert len(store.read_estimates("desk")) == len(est)
    published = set(Artifact.load(desk_artifact).published)  # every model validation kept
    assert {"corrgp-triv", "corrgp-lcm", "triv"} <= published
    assert set(est["model"]) == published
    assert len(est) == s1.estimates + s2.estimates
    # the same numbers as evaluate at the same instants (SML2010: refs and target share ts)
    art = Artifact.load(desk_artifact)
    df = sml()
    ev = replay_estimates(art, df[df["ts"] < "2012-03-22T23:00Z"], d1)
    ev = ev[ev["model"] == "corrgp-triv"].set_index("ts")["value"]
    bf = est[est["model"] == "corrgp-triv"].copy()
    bf["ts"] = pd.DatetimeIndex(bf["ts"]).tz_convert("UTC")
    bf = bf.set_index("ts")["value"]
    common = ev.index.intersection(bf.index)
    assert len(common) > 3 * 40
    pd.testing.assert_series_equal(bf[common], ev[common], check_names=False,
                                   check_index_type=False, rtol=1e-12)


def test_a_day_backfilled_again_keeps_none_of_the_earlier_rows(
    mosquitto, desk_artifact, sml_store: Path, tmp_path: Path
) -> None:
    """A day backfilled again (--redo, here with the twin now running its primary only)
    holds only what the new run estimates: the baselines' rows of the first run are gone
    from that day, and stay on the day not redone."""
    db = tmp_path / "history.db"
    shutil.copy(sml_store, db)
    d1, d2 = dt.date(2012, 3, 20), dt.date(2012, 3, 21)
    primary = Artifact.load(desk_artifact).primary
    with open_store(str(db)) as store:
        backfill(config(tmp_path, mosquitto.port, desk_artifact, store=str(db)), "desk", d1, d2,
                 store, progress=False)
        first = store.read_estimates("desk")
        assert set(first["model"]) > {primary}  # the baselines on the grid too
        lean = config(tmp_path, mosquitto.port, desk_artifact, store=str(db), baselines="none")
        run = backfill_twins(lean, ["desk"], d1, d1, store, jobs=1, progress=False, redo=True)
        assert run.twins["desk"].days == 1
        again = store.read_estimates("desk")
    day = HOURS.day_of
    redone = again[[day(t) == d1 for t in again["ts"]]]
    kept = again[[day(t) == d2 for t in again["ts"]]]
    assert set(redone["model"]) == {primary} and len(redone) > 40
    was = first[[day(t) == d2 for t in first["ts"]]]
    pd.testing.assert_frame_equal(kept.reset_index(drop=True), was.reset_index(drop=True))


def test_backfill_reports_days_without_readings(
    mosquitto, desk_artifact, sml_store: Path, tmp_path: Path, capsys
) -> None:
    cfg_path = write_config(tmp_path, mosquitto.port, desk_artifact, store=str(sml_store))
    rc = main(["backfill", "--config", str(cfg_path), "--twin", "desk", "--from", "2012-03-24",
               "--to", "2012-03-26", "--quiet"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "skipped 2 day(s), no reference readings: 2012-03-25, 2012-03-26" in out
    rc = main(["backfill", "--config", str(cfg_path), "--twin", "nope", "--from", "2012-03-24",
               "--to", "2012-03-24"])
    assert rc == 2 and "no twin 'nope'" in capsys.readouterr().err


def _backfilled_day(folder: Path, readings: pd.DataFrame, port: int, artifact: Path
                    ) -> pd.DataFrame:
    """``readings`` in a new store in ``folder``, DAY backfilled for the desk twin by the CLI:
    the stored estimates (without their written_at)."""
    folder.mkdir()
    db = folder / "history.db"
    with open_store(str(db)) as store:
        store.write_readings(readings)
    cfg = write_config(folder, port, artifact, store=str(db))
    assert main(["backfill", "--config", str(cfg), "--twin", "desk", "--from", str(DAY),
                 "--to", str(DAY), "--quiet"]) == 0
    with open_store(str(db)) as store:
        return store.read_estimates("desk").drop(columns="written_at")


def test_backfill_and_warm_start_leave_out_stored_readings_the_daemon_would_reject(
    mosquitto, desk_artifact, tmp_path: Path, capsys
) -> None:
    """``import`` knows no configuration: a stored 85 °C (the sensor's max is 50) must not
    become an `ok` estimate of 85 °C in a backfill, nor a warm-started window. Both take the
    day as the daemon would have: without it."""
    df = day_readings(sml())
    wild = (df["sensor"] == REF) & (df["ts"] == HOURS.at(DAY, 10.0))
    assert wild.sum() == 1
    stores = {"wild": df.assign(value=df["value"].where(~wild, 85.0)), "clean": df[~wild]}
    rows = {}
    for name, frame in stores.items():
        rows[name] = _backfilled_day(tmp_path / name, frame, mosquitto.port, desk_artifact)
        out = capsys.readouterr().out
        assert ("left out 1 stored reading(s) outside their sensor's configured min..max"
                in out) == (name == "wild")
        db = tmp_path / name / "history.db"
        svc = Service(config(tmp_path / name, mosquitto.port, desk_artifact, store=str(db)),
                      ReplayClock(HOURS.at(DAY, 12.0), 1.0))
        svc.restore()
        assert max(p.value for p in svc.twins["desk"].twin.window if p.sensor == REF) < 50
        svc.journal.close()
    assert len(rows["clean"]) > 0
    pd.testing.assert_frame_equal(rows["wild"], rows["clean"])


def test_backfill_seeds_the_carry_over_with_the_last_reading_in_range(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    """A reference silent overnight: a fresh backfill twin takes its carry-over from the day
    before. When that last stored reading lies outside the sensor's range, the daemon would
    hold the one before it; the backfill held none, and had nothing to publish until then."""
    df = sml()
    before = day_readings(df, DAY - dt.timedelta(days=1))
    today = day_readings(df)
    today = today[today["ts"] >= HOURS.at(DAY, 9.0)]  # silent until 09:00
    last = before["ts"] == before["ts"].max()
    stores = {"wild": pd.concat([before.assign(value=before["value"].where(~last, 85.0)),
                                 today]),
              "clean": pd.concat([before[~last], today])}
    rows = {name: _backfilled_day(tmp_path / name, frame, mosquitto.port, desk_artifact)
            for name, frame in stores.items()}
    # before the day's first reading the carry-over answers (stale, with a value)
    assert (rows["clean"]["ts"] < HOURS.at(DAY, 9.0)).any()
    pd.testing.assert_frame_equal(rows["wild"], rows["clean"])


def test_backfill_redo_estimates_a_day_again_once_its_readings_are_imported(
    mosquitto, desk_artifact, tmp_path: Path, capsys
) -> None:
    """A day imported in part (up to 10:00) is backfilled and marked done; importing the
    rest does not make it due again (a rerun skips it), ``--redo`` does: its rows become
    those of a backfill from the whole day. (A day imported up to its init phase only is
    not marked done: tests/test_backfill_progress.py.)"""
    df = sml()
    day = dt.date(2012, 3, 20)
    upto = df[df["ts"] < HOURS.at(day + dt.timedelta(days=1), 0.0)]
    stores = {name: f"sqlite:///{tmp_path / name}.db" for name in ("partial", "whole")}
    with open_store(stores["partial"]) as s:
        s.write_readings(upto[upto["ts"] < HOURS.at(day, 10.0)])
    with open_store(stores["whole"]) as s:
        s.write_readings(upto)

    def backfilled(name: str, *extra: str) -> pd.DataFrame:
        (tmp_path / name).mkdir(exist_ok=True)
        cfg = write_config(tmp_path / name, mosquitto.port, desk_artifact, store=stores[name])
        rc = main(["backfill", "--config", str(cfg), "--twin", "desk", "--from", str(day),
                   "--to", str(day), "--quiet", *extra])
        assert rc == 0
        with open_store(stores[name]) as s:
            return s.read_estimates("desk").drop(columns="written_at")

    morning = backfilled("partial")
    with open_store(stores["partial"]) as s:
        s.write_readings(upto)  # the rest of the day arrives
    assert backfilled("partial").equals(morning)  # done already: skipped
    assert "already backfilled" in capsys.readouterr().out
    redone, whole = backfilled("partial", "--redo"), backfilled("whole")
    assert not redone.equals(morning)
    pd.testing.assert_frame_equal(redone, whole)


def test_train_from_the_store_equals_train_from_a_file_of_the_same_readings(
        tmp_path: Path) -> None:
    """The first training day's carry-over (a reference silent overnight, its last evening
    reading held) and covariates that miss whole days: from the store as from the file
    (the store's first day started without a carry-over, and it required covariates on a
    training day that a file does not)."""
    df = sml()
    df = df[df["ts"] < "2012-03-24T23:00Z"]
    local = df["ts"].dt.tz_convert("Europe/Madrid")
    silent = (df["sensor"] == REF) & (local.dt.hour < 9)  # a COV sensor quiet overnight
    co2_gone = (df["sensor"] == "dining/co2") & local.dt.day.isin([15, 16])
    df = df[~silent & ~co2_gone]
    csv, db = tmp_path / "h.csv", tmp_path / "h.db"
    write_history(df, csv)
    with open_store(str(db)) as store:
        store.write_readings(read_history(csv))
    arts = {}
    for source in (["--history", str(csv)], ["--store", str(db)]):
        out = tmp_path / f"{source[0][2:]}.json"
        assert main(["--log-level", "WARNING", "train", *source, "--references", REF,
                     "--target", TARGET, "--covariates", "dining/co2", "--quantity",
                     "temperature", "--timezone", "Europe/Madrid", "--train-start",
                     "2012-03-15", "--models", "ref,triv,triv-cov", "--out", str(out)]) == 0
        arts[source[0]] = json.loads(out.read_text())
    a, b = arts["--history"], arts["--store"]
    assert a["training"]["days"] == b["training"]["days"]
    assert a["training"]["days"][:2] == ["2012-03-15", "2012-03-16"]  # without their CO2
    assert a["models"] == b["models"]
    assert a["validation"]["scores"] == b["validation"]["scores"]


def test_a_file_whose_other_sensors_begin_earlier_skips_the_twins_partial_first_day(
        tmp_path: Path, capsys) -> None:
    """Without --train-start the first full day was judged on every sensor of the file: an
    export whose outdoor sensor began the day before made the twin's partly covered first
    day (2012-03-13 from 11:45) a training day, which the store skips."""
    df = sml()
    df = df[df["ts"] < "2012-03-24T23:00Z"]
    early = pd.DataFrame({"sensor": "outdoor/else", "ts": pd.date_range(
        "2012-03-12T00:00Z", "2012-03-13T00:00Z", freq="1h"), "value": 10.0})
    csv = tmp_path / "h.csv"
    write_history(pd.concat([df, early], ignore_index=True), csv)
    out = tmp_path / "a.json"
    assert main(["--log-level", "WARNING", "train", "--history", str(csv), "--references",
                 REF, "--target", TARGET, "--quantity", "temperature", "--timezone",
                 "Europe/Madrid", "--models", "ref,triv", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["training"]["days"][0] == "2012-03-14"


def test_train_from_the_store_picks_full_days_itself(sml_store: Path, tmp_path: Path,
                                                      capsys) -> None:
    out = tmp_path / "a.json"
    rc = main(["--log-level", "WARNING", "train", "--store", str(sml_store), "--references",
               REF, "--target", TARGET, "--quantity", "temperature", "--timezone",
               "Europe/Madrid", "--models", "corrgp-triv,triv", "--out", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    # the data begins 2012-03-13 11:45: the first full day is the 14th
    assert "2012-03-14, 2012-03-15, 2012-03-16, 2012-03-17, 2012-03-18" in printed
    art = json.loads(out.read_text())
    assert art["training"]["days"][0] == "2012-03-14"
    # a day left out is passed over while streaming the store, and the next one taken
    rc = main(["--log-level", "WARNING", "train", "--store", str(sml_store), "--references",
               REF, "--target", TARGET, "--quantity", "temperature", "--timezone",
               "Europe/Madrid", "--models", "triv", "--skip-days", "2012-03-16",
               "--out", str(out)])
    assert rc == 0
    art = json.loads(out.read_text())
    assert art["training"]["days"] == ["2012-03-14", "2012-03-15", "2012-03-17", "2012-03-18",
                                       "2012-03-19"]
    assert art["training"]["skipped"] == ["2012-03-16"]
    # the first usable day left out too (a commissioning day): still recorded, still shown
    rc = main(["--log-level", "WARNING", "train", "--store", str(sml_store), "--references",
               REF, "--target", TARGET, "--quantity", "temperature", "--timezone",
               "Europe/Madrid", "--models", "ref,triv", "--skip-days", "2012-03-14,2012-03-16",
               "--out", str(out), "--report", str(tmp_path / "r")])
    assert rc == 0
    art = json.loads(out.read_text())
    assert art["training"]["days"] == ["2012-03-15", "2012-03-17", "2012-03-18", "2012-03-19",
                                       "2012-03-20"]
    assert art["training"]["skipped"] == ["2012-03-14", "2012-03-16"]
    page = (tmp_path / "r" / "a.html").read_text(encoding="utf-8")
    assert page.count("left out (--skip-days)") == 2 * 2  # two days, a row per sensor


def test_train_from_the_store_names_the_sensor_it_lacks(desk_artifact, sml_store: Path,
                                                         tmp_path: Path, capsys) -> None:
    """A mistyped reference: named, against the store and against the configuration, not
    counted as too few usable days."""
    base = ("--log-level", "WARNING", "train", "--target", TARGET, "--quantity", "temperature",
            "--timezone", "Europe/Madrid", "--models", "ref,triv",
            "--out", str(tmp_path / "a.json"))
    assert main([*base, "--store", str(sml_store), "--references", "dinning/temp"]) == 2
    assert "the history store has no readings of dinning/temp" in capsys.readouterr().err
    cfg = write_config(tmp_path, 1883, desk_artifact, store=str(sml_store))
    assert main([*base, "--config", str(cfg), "--references", "dinning/temp"]) == 2
    err = capsys.readouterr().err
    assert f"--references: dinning/temp not a sensor of {cfg}" in err
    assert "(did you mean 'dining/temp'?)" in err
    # a covariate the store has, but the configuration does not feed
    assert main([*base, "--config", str(cfg), "--references", REF, "--models",
                 "ref,triv,triv-cov", "--covariates", "dining/co2"]) == 2
    assert "--covariates: dining/co2 not a sensor of" in capsys.readouterr().err
    assert not (tmp_path / "a.json").exists()


def test_daemon_warm_starts_from_the_store_without_a_checkpoint(
    mosquitto, desk_artifact, sml_store: Path, tmp_path: Path
) -> None:
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(sml_store))
    now = HOURS.at(DAY, 12.0)
    svc = Service(cfg, ReplayClock(now, 1.0))
    n = svc.restore()
    assert n > 0
    window = [r for r in svc.twins["desk"].twin.window if r.sensor == REF]
    assert window and max(r.ts for r in window) <= now + cfg.max_skew
    assert min(r.hours for r in window) == HOURS.init_start  # the carried value
    # A live reading after the warm start is journaled, as the daemon journals each one.
    live = Reading(REF, now + dt.timedelta(minutes=5), 21.5)  # a window point of its own
    svc.journal.append(live)
    svc.journal.close()
    # A restart later today finds a journal of today and restores from it alone: it must
    # still hold the morning the store gave (it held only the live reading, so the window
    # shrank to it).
    again = Service(cfg, ReplayClock(now + dt.timedelta(minutes=6), 1.0))
    assert again.restore() == n + 1
    restored = [r for r in again.twins["desk"].twin.window if r.sensor == REF]
    assert restored[:-1] == window and (restored[-1].ts, restored[-1].value) == (live.ts, 21.5)
    again.journal.close()


def test_a_warm_start_from_a_store_not_there_says_where_it_looked_and_makes_none(
    mosquitto, desk_artifact, tmp_path: Path, caplog
) -> None:
    """The daemon only reads the store: a mistyped (or, after an upgrade, differently
    resolved) path made an empty database there, and the log said "0 stored readings"."""
    db = tmp_path / "history.db"
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(db))
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.service")
    svc = Service(cfg, ReplayClock(HOURS.at(DAY, 12.0), 1.0))
    assert svc.restore() == 0
    svc.journal.close()
    assert not db.exists()
    assert f"no history store at {db} yet" in caplog.text


def test_a_warm_start_takes_a_reading_stamped_ahead_within_max_skew(
    mosquitto, desk_artifact, tmp_path: Path
) -> None:
    """A sensor whose clock runs 2 min ahead: the recorder stored its latest reading at its
    stamp, after the daemon's clock; the warm start takes it, as a journal restore would,
    instead of starting from the reading before."""
    now = HOURS.at(DAY, 9.0)
    df = day_readings(sml())
    ahead = Reading(REF, now + dt.timedelta(minutes=2), 18.5)
    db = tmp_path / "history.db"
    with open_store(str(db)) as store:
        store.write_readings(df[df["ts"] < now])
        store.write_readings([ahead])
    svc = Service(config(tmp_path, mosquitto.port, desk_artifact, store=str(db)),
                  ReplayClock(now, 1.0))
    assert svc.restore() > 0
    assert max(p.ts for p in svc.twins["desk"].twin.window if p.sensor == REF) == ahead.ts
    svc.journal.close()


def test_backfill_refuses_an_artifact_that_does_not_fit_its_twin(
    desk_artifact, sml_store: Path, tmp_path: Path, capsys
) -> None:
    """Other operating hours than the artifact's: `run` refuses the config, and so does
    backfill, before it replaces any stored estimate with ones of the wrong hours."""
    path = write_config(tmp_path, 1883, desk_artifact, store=str(sml_store), day_start="07:00")
    with open_store(str(sml_store)) as store:
        before = len(store.read_estimates("desk"))
    code = main(["backfill", "--config", str(path), "--twin", "desk", "--from", "2012-03-23",
                 "--to", "2012-03-23", "--jobs", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "twins.desk.artifact: operating hours" in err
    assert "Traceback" not in err
    with open_store(str(sml_store)) as store:
        assert len(store.read_estimates("desk")) == before
