"""PostgreSQL backend specifics, against the real server of the ``postgres`` fixture.

The behaviour every backend shares is in test_store.py (its ``postgres`` param); here:
the table layout (timestamptz, "C" collation, plain tables without TimescaleDB), exact
millisecond instants on both sides of PostgreSQL's 2000 epoch, URL handling, concurrent
first opens, and an outage of the real server (the store reconnects; the recorder spools
and then drains its spool).
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import pandas as pd
import psycopg
import pytest

from conftest import MosquittoBroker
from daemon_support import DAY, HOURS, REF, config, wait_for
from postgres_server import PostgresServer
from pseudotwin.config.loader import load_config
from pseudotwin.edge.recorder import Recorder
from pseudotwin.errors import ConfigError
from pseudotwin.history.postgres import PostgresStore, Timescale, hypertables_wanted
from pseudotwin.history.store import SCHEMA_VERSION, Store, StoreError, open_store
from pseudotwin.live.readings import Reading
from test_daemon import publisher, reading

UTC = dt.UTC


@pytest.fixture
def db(postgres: PostgresServer) -> Iterator[str]:
    """A fresh database on the test server, dropped afterwards; yields its name."""
    if not postgres.running:  # an outage test that failed half-way
        postgres.start()
    name = postgres.create_database()
    try:
        yield name
    finally:
        postgres.drop_database(name)


def sql_rows(url: str, query: str, args: list | None = None) -> list[tuple]:
    with psycopg.connect(url, autocommit=True) as conn:
        return conn.execute(query, args).fetchall()


def test_tables_are_timestamptz_with_c_collation_and_plain_without_timescaledb(
    postgres: PostgresServer, db: str
) -> None:
    url = postgres.url(db)
    with open_store(url) as s:
        assert isinstance(s, PostgresStore)
        assert s.schema == "pseudotwin" and s.schema_version == SCHEMA_VERSION
        assert s.hypertables is False  # Debian's server has no TimescaleDB
    cols = dict(((t, c), (typ, coll)) for t, c, typ, coll in sql_rows(
        url, "SELECT table_name, column_name, data_type, collation_name FROM "
             "information_schema.columns WHERE table_schema = 'pseudotwin'"))
    for key in (("readings", "ts"), ("estimates", "ts"), ("estimates", "written_at"),
                ("backfill_progress", "finished_at")):
        assert cols[key][0] == "timestamp with time zone"
    assert cols[("readings", "value")][0] == "double precision"
    assert cols[("readings", "sensor")][1] == "C"
    assert cols[("estimates", "model")][1] == "C"
    indexes = {r[0] for r in sql_rows(url, "SELECT indexname FROM pg_indexes WHERE "
                                           "schemaname = 'pseudotwin'")}
    assert "readings_ts" in indexes  # the plain layout's time index
    assert sql_rows(url, "SELECT value FROM pseudotwin.meta") == [(str(SCHEMA_VERSION),)]


def test_timescaledb_yes_without_the_extension_fails_and_creates_nothing(
    postgres: PostgresServer, db: str
) -> None:
    with pytest.raises(StoreError, match="TimescaleDB extension is not installed"):
        open_store(postgres.url(db, timescaledb="yes"))
    # One transaction: the refusal leaves no half-made schema behind.
    assert sql_rows(postgres.url(db), "SELECT 1 FROM pg_namespace WHERE nspname = "
                                      "'pseudotwin'") == []
    with open_store(postgres.url(db, timescaledb="no")) as s:
        assert s.hypertables is False


@pytest.mark.parametrize(("option", "installed", "available", "expected"), [
    ("auto", True, True, True),
    ("auto", False, True, None),  # try CREATE EXTENSION, plain tables if refused
    ("auto", False, False, False),
    ("yes", True, True, True),
    ("yes", False, True, None),
    ("no", True, True, False),
    ("no", False, False, False),
])
def test_hypertable_decision(option: Timescale, installed: bool, available: bool,
                             expected: bool | None) -> None:
    assert hypertables_wanted(option, installed, available) is expected


def test_hypertable_decision_refuses_yes_without_timescaledb() -> None:
    with pytest.raises(StoreError, match="timescaledb=yes"):
        hypertables_wanted("yes", False, False)


@pytest.mark.parametrize("text", [
    "1969-12-31T23:59:59.999999+00:00",  # before 1970: floor, not toward zero
    "1999-12-31T23:59:59.999500+00:00",  # just before PostgreSQL's own epoch
    "2000-01-01T00:00:00.000999+00:00",
    "2016-03-27T02:30:00.123999+02:00",  # an offset: the instant counts, not the wall time
    "2099-06-30T12:00:00.001+00:00",
])
def test_instants_are_exact_to_the_millisecond_in_the_database(
    postgres: PostgresServer, db: str, text: str
) -> None:
    ts = dt.datetime.fromisoformat(text)
    floor = ts.replace(microsecond=ts.microsecond // 1000 * 1000)
    url = postgres.url(db)
    with open_store(url) as s:
        s.write_readings([Reading("a/temp", ts, 1.0)])
        got = s.read_readings("a/temp")
        assert got["ts"].tolist() == [pd.Timestamp(floor)]
        assert s.reading_range() == (floor, floor)
        assert s.last_readings_before("a/temp", floor + dt.timedelta(milliseconds=1)) == {
            "a/temp": (floor, 1.0)}
        assert s.last_readings_before("a/temp", floor) == {}  # strictly before
    # What SQL users (Grafana) see is the same instant as a timestamptz.
    assert sql_rows(url, "SELECT ts FROM pseudotwin.readings") == [(floor,)]


def test_schema_option_and_postgres_alias(postgres: PostgresServer, db: str) -> None:
    url = postgres.url(db, schema="building7").replace("postgresql://", "postgres://")
    with open_store(url) as s:
        s.write_readings([Reading("a/temp", dt.datetime(2016, 3, 1, tzinfo=UTC), 1.0)])
    assert sql_rows(postgres.url(db), "SELECT count(*) FROM building7.readings") == [(1,)]
    with open_store(postgres.url(db)) as default:  # another schema: another store
        assert default.count_readings() == 0


def test_a_cut_off_server_fails_a_write_in_a_minute_not_the_os_s_fifteen(
        postgres: PostgresServer, db: str) -> None:
    """Only connect_timeout was set: a server cut off mid-write (a partition) blocked the
    recorder's worker until the OS gave up on the socket, and nothing spooled meanwhile.
    The connection's own libpq parameters (what psycopg reports it was opened with)."""
    with open_store(postgres.url(db, keepalives_idle="5")) as s:
        params = s._conn.info.get_parameters()  # the live connection, not a parsed URL
    assert params["tcp_user_timeout"] == "60000" and params["keepalives"] == "1"
    assert params["keepalives_idle"] == "5"  # the URL's own value wins


@pytest.mark.parametrize(("url", "message"), [
    ("postgresql://pt:secret@db/history", "must not contain a password"),
    ("postgresql://db/history?password=secret", "must not contain a password"),
    ("postgresql://db/history?timescaledb=maybe", "expected one of auto, yes, no"),
    ("postgresql://db/history?schema=a;drop", "not a plain identifier"),
    ("postgresql://db/history?no_such_option=1", "not a valid PostgreSQL URL"),
])
def test_bad_urls_are_config_errors(url: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        open_store(url)
    assert "secret" not in str(err.value)


def test_config_accepts_a_postgresql_store_but_no_password(tmp_path: Path,
                                                           desk_artifact: Path) -> None:
    from daemon_support import write_config

    ok = load_config(write_config(tmp_path, 1883, desk_artifact,
                                  store="postgresql://pt@db.example/history?schema=b7"))
    assert ok.store == "postgresql://pt@db.example/history?schema=b7"
    bad = write_config(tmp_path, 1883, desk_artifact, store="postgres://pt:pw@db/history")
    with pytest.raises(ConfigError, match="password does not belong in the store URL"):
        load_config(bad)


def test_unreachable_server_is_a_store_error(postgres: PostgresServer) -> None:
    from postgres_server import _free_port

    with pytest.raises(StoreError, match="cannot connect to PostgreSQL"):
        open_store(f"postgresql://pt@127.0.0.1:{_free_port()}/x")


def test_two_processes_creating_the_store_at_once_both_succeed(postgres: PostgresServer,
                                                               db: str) -> None:
    url = postgres.url(db)
    opened: list[Store] = []
    errors: list[BaseException] = []
    gate = threading.Barrier(4)

    def open_one() -> None:
        gate.wait()
        try:
            opened.append(open_store(url))
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=open_one) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    for s in opened:
        s.close()
    assert errors == [] and len(opened) == 4
    assert sql_rows(url, "SELECT count(*) FROM pseudotwin.meta") == [(1,)]


def test_store_survives_a_server_restart(postgres: PostgresServer, db: str) -> None:
    t0 = dt.datetime(2016, 3, 1, tzinfo=UTC)
    with open_store(postgres.url(db)) as s:
        s.write_readings([Reading("a/temp", t0, 1.0)])
        postgres.stop()
        try:
            with pytest.raises(StoreError):
                s.write_readings([Reading("a/temp", t0 + dt.timedelta(minutes=1), 2.0)])
            with pytest.raises(StoreError, match="cannot connect to PostgreSQL"):
                s.count_readings()  # still down: the reconnect fails cleanly
        finally:
            postgres.start()
        # Back: the same store object reconnects by itself; nothing half-written.
        assert s.count_readings() == 1
        assert s.write_readings([Reading("a/temp", t0 + dt.timedelta(minutes=1), 2.0)]) == 1


def test_recorder_spools_during_an_outage_and_drains_after(
    postgres: PostgresServer, db: str, mosquitto: MosquittoBroker, desk_artifact: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    url = postgres.url(db)
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=url)
    rec = Recorder(cfg, retry_seconds=0.2)
    rec.start(wait_connected=15)
    pub = publisher(mosquitto.port, "rec-pg-bridge")
    ts = [HOURS.at(DAY, 8 + i / 60) for i in range(30)]
    try:
        # start() returns once the broker's SUBACK is back (mqttconn.Subscription): what is
        # published from here reaches the recorder
        assert rec.connected.is_set()
        for i, t in enumerate(ts[:10]):
            pub.publish("house/dining/temp", reading(t, 20 + i / 100), qos=1)
        wait_for(lambda: rec.written == 10, what="first readings in PostgreSQL")
        postgres.stop()
        try:
            for i, t in enumerate(ts[10:20], start=10):
                pub.publish("house/dining/temp", reading(t, 20 + i / 100), qos=1)
            wait_for(lambda: rec.spooled == 10, what="readings spooled while the server is down")
            assert rec.written == 10 and rec.spool.path.exists()
        finally:
            postgres.start()
        for i, t in enumerate(ts[20:], start=20):
            pub.publish("house/dining/temp", reading(t, 20 + i / 100), qos=1)
        wait_for(lambda: rec.written == 30,
                 what="spool drained and new readings written")
    finally:
        rec.stop()
        pub.disconnect()
        pub.loop_stop()
    assert not rec.spool.path.exists()
    with open_store(url) as store:
        got = store.read_readings([REF])
    assert [t.to_pydatetime() for t in got["ts"]] == ts  # count in = count stored, in order
    assert got["value"].tolist() == [20 + i / 100 for i in range(30)]
    assert "spooling" in caplog.text and "wrote 10 spooled readings" in caplog.text


def test_backfill_into_postgres_equals_backfill_into_sqlite(
    postgres: PostgresServer, db: str, desk_artifact: Path, tmp_path: Path
) -> None:
    from daemon_support import sml
    from pseudotwin.history.backfill import backfill

    df = sml()
    df = df[df["ts"] < "2012-03-20T23:00Z"]
    day = dt.date(2012, 3, 20)
    got = {}
    for name, url in (("sqlite", str(tmp_path / "h.db")), ("postgres", postgres.url(db))):
        (tmp_path / name).mkdir()
        cfg = config(tmp_path / name, 1883, desk_artifact, store=url)  # no broker needed
        with open_store(url) as store:
            store.write_readings(df)
            first = backfill(cfg, "desk", day, day, store, progress=False)
            again = backfill(cfg, "desk", day, day, store, progress=False)
            assert first.days == 1 and first.estimates > 100
            assert again.days == 0 and again.estimates == 0  # resumable: day already done
            got[name] = store.read_estimates("desk").drop(columns=["written_at"])
    pd.testing.assert_frame_equal(got["postgres"], got["sqlite"])
