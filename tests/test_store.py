"""History store: the same behaviour tests on every backend, plus backend-specific checks.

Backends: a real SQLite file; the CrateDB backend (real ``crate`` client) against
:mod:`fake_cratedb`, a FAKE of CrateDB's HTTP ``/_sql`` endpoint; a real CrateDB when
``PSEUDOTWIN_TEST_CRATEDB=crate://host:4200`` is set (each run in its own schema, dropped
afterwards); and a real PostgreSQL server started by the ``postgres`` fixture (each test in
a fresh database). PostgreSQL specifics are in test_store_postgres.py.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import sqlite3
import uuid
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from fake_cratedb import FakeCrateDB
from pseudotwin.core.series import normalize
from pseudotwin.errors import ConfigError
from pseudotwin.history import store as store_mod
from pseudotwin.history.store import (
    SCHEMA_VERSION,
    EstimateRow,
    RowsRejected,
    Store,
    StoreError,
    _bulk_count,
    open_store,
)
from pseudotwin.live.readings import Reading

REAL_CRATEDB = os.environ.get("PSEUDOTWIN_TEST_CRATEDB", "").strip()
NO_REAL_CRATEDB = (
    "set PSEUDOTWIN_TEST_CRATEDB=crate://host:4200 to run the CrateDB backend against a "
    "real server (none can be installed on this machine; the fake covers the protocol)"
)
BERLIN = "Europe/Berlin"
UTC = dt.UTC


def utc(text: str) -> pd.Timestamp:
    return pd.Timestamp(text, tz="UTC")


def minute_frame(sensors: list[str], start: str, end: str) -> pd.DataFrame:
    """1-minute readings of every sensor in [start, end): value = minutes since start + k."""
    ts = pd.date_range(utc(start), utc(end), freq="1min", inclusive="left")
    parts = [pd.DataFrame({"sensor": s, "ts": ts, "value": np.arange(len(ts)) + 1000.0 * k})
             for k, s in enumerate(sensors)]
    return normalize(pd.concat(parts, ignore_index=True))


# ------------------------------------------------------------------------------ fixtures


@pytest.fixture
def fake() -> Iterator[FakeCrateDB]:
    with FakeCrateDB() as server:
        yield server


def _drop_real_schema(url: str, schema: str) -> None:
    from crate import client

    servers = url.split("://", 1)[1].split("?")[0].split(",")
    conn = client.connect(servers, username=os.environ.get(store_mod.ENV_CRATE_USER) or None,
                          password=os.environ.get(store_mod.ENV_CRATE_PASSWORD) or None)
    try:
        cur = conn.cursor()
        for table in ("readings", "estimates", "backfill_progress", "meta"):
            cur.execute(f'DROP TABLE IF EXISTS "{schema}"."{table}"')
    finally:
        conn.close()


@pytest.fixture(params=["sqlite", "crate-fake", "crate-real", "postgres"])
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[dict]:
    """How to open the backend under test: ``kind`` and ``url`` (reopenable)."""
    kind = request.param
    if kind == "sqlite":
        yield {"kind": kind, "url": str(tmp_path / "history.db")}
    elif kind == "crate-fake":
        with FakeCrateDB() as server:
            yield {"kind": kind, "url": server.url, "fake": server}
    elif kind == "postgres":
        server = request.getfixturevalue("postgres")  # started only when a test needs it
        db = server.create_database()
        try:
            yield {"kind": kind, "url": server.url(db), "server": server, "db": db}
        finally:
            server.drop_database(db)
    else:
        if not REAL_CRATEDB:
            pytest.skip(NO_REAL_CRATEDB)
        schema = f"pt_test_{uuid.uuid4().hex[:10]}"
        sep = "&" if "?" in REAL_CRATEDB else "?"
        try:
            yield {"kind": kind, "url": f"{REAL_CRATEDB}{sep}schema={schema}", "schema": schema}
        finally:
            _drop_real_schema(REAL_CRATEDB, schema)


@pytest.fixture
def store(backend: dict) -> Iterator[Store]:
    with open_store(backend["url"]) as s:
        yield s


# ---------------------------------------------------------------------- readings (all)


def test_readings_insert_is_idempotent(store: Store) -> None:
    df = minute_frame(["a/temp", "b/temp"], "2016-03-01T00:00", "2016-03-01T06:00")
    assert store.write_readings(df) == len(df)
    assert store.write_readings(df) == 0  # same keys: nothing new
    assert store.count_readings() == len(df)
    assert store.count_readings(["a/temp"]) == len(df) // 2

    # Readings are immutable: a second reading with a stored key changes nothing.
    first = df.iloc[0]
    again = Reading(first["sensor"], first["ts"].to_pydatetime(), -99.0)
    new = Reading("a/temp", dt.datetime(2016, 3, 1, 6, 0, tzinfo=UTC), 7.5)
    assert store.write_readings([again, new, new]) == 1
    got = store.read_readings(["a/temp"], utc("2016-03-01T00:00"), utc("2016-03-01T00:01"))
    assert got["value"].tolist() == [first["value"]]
    assert store.count_readings() == len(df) + 1


def test_read_readings_returns_the_canonical_frame(store: Store) -> None:
    df = minute_frame(["a/temp", "b/co2"], "2016-03-01T00:00", "2016-03-01T03:00")
    store.write_readings(df)
    got = store.read_readings(["a/temp", "b/co2"], utc("2016-03-01T00:00"),
                              utc("2016-03-01T03:00"))
    pd.testing.assert_frame_equal(got, df)  # same columns, dtypes, order (ts, sensor)

    part = store.read_readings("b/co2", utc("2016-03-01T01:00"), utc("2016-03-01T02:00"))
    assert set(part["sensor"]) == {"b/co2"}
    assert len(part) == 60  # half-open: 01:00 included, 02:00 excluded
    assert part["ts"].iloc[0] == utc("2016-03-01T01:00")
    assert part["ts"].iloc[-1] == utc("2016-03-01T01:59")
    assert store.read_readings(["nobody"], utc("2016-03-01"), utc("2016-03-02")).empty
    everything = store.read_readings(None)
    assert len(everything) == len(df)


def test_read_readings_over_windows_matches_one_query(store: Store,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    df = minute_frame(["a/temp"], "2016-01-30T22:00", "2016-02-02T02:00")
    store.write_readings(df)
    monkeypatch.setattr(store_mod, "READ_WINDOW", dt.timedelta(hours=7))
    got = store.read_readings(["a/temp"], utc("2016-01-30"), utc("2016-02-03"))
    pd.testing.assert_frame_equal(got, df)


def test_write_readings_accepts_a_non_canonical_frame(store: Store) -> None:
    raw = pd.DataFrame({"sensor": [" a/temp ", "a/temp", "a/temp"],
                        "ts": ["2016-03-01T00:00:00+01:00", "1456786860", "2016-03-01T00:02Z"],
                        "value": ["21.5", None, 22]})
    assert store.write_readings(raw) == 2  # normalized; the missing value is dropped
    got = store.read_readings("a/temp", utc("2016-02-29"), utc("2016-03-02"))
    assert got["ts"].tolist() == [utc("2016-02-29T23:00"), utc("2016-03-01T00:02")]
    assert got["value"].tolist() == [21.5, 22.0]


def test_timestamps_are_stored_to_the_millisecond(store: Store) -> None:
    ts = dt.datetime(2016, 3, 1, 12, 0, 0, 123999, tzinfo=UTC)
    store.write_readings([Reading("a/temp", ts, 1.0)])
    got = store.read_readings("a/temp", utc("2016-03-01"), utc("2016-03-02"))
    assert got["ts"].iloc[0] == utc("2016-03-01T12:00:00.123")  # floor to ms


def test_iter_days_streams_local_days_across_dst(store: Store) -> None:
    # Europe/Berlin: 2016-03-27 has 23 h (02:00 → 03:00), 2016-10-30 has 25 h.
    spring = minute_frame(["a/temp", "b/temp"], "2016-03-25T00:00", "2016-03-29T00:00")
    autumn = minute_frame(["a/temp"], "2016-10-29T00:00", "2016-10-31T12:00")
    store.write_readings(spring)
    store.write_readings(autumn)

    days = dict(store.iter_days(["a/temp", "b/temp"], dt.date(2016, 3, 26),
                                dt.date(2016, 3, 28), BERLIN))
    assert list(days) == [dt.date(2016, 3, 26), dt.date(2016, 3, 27), dt.date(2016, 3, 28)]
    dst = days[dt.date(2016, 3, 27)]
    assert len(dst) == 2 * 23 * 60
    assert dst["ts"].iloc[0] == utc("2016-03-26T23:00")  # local midnight, CET
    assert dst["ts"].iloc[-1] == utc("2016-03-27T21:59")  # before local midnight, CEST
    local = dst["ts"].dt.tz_convert(BERLIN)
    assert (local.dt.date == dt.date(2016, 3, 27)).all()  # only that day's rows
    assert dst["ts"].is_monotonic_increasing
    assert list(dst.columns) == ["sensor", "ts", "value"]
    assert len(days[dt.date(2016, 3, 26)]) == 2 * 24 * 60

    ((day, fall),) = list(store.iter_days("a/temp", dt.date(2016, 10, 30),
                                          dt.date(2016, 10, 30), BERLIN))
    assert day == dt.date(2016, 10, 30) and len(fall) == 25 * 60
    assert fall["ts"].iloc[0] == utc("2016-10-29T22:00")

    # Days without readings are yielded (empty, canonical columns), so a backfill can
    # mark them done.
    empty = list(store.iter_days(["a/temp"], dt.date(2016, 6, 1), dt.date(2016, 6, 2), BERLIN))
    assert [d for d, _ in empty] == [dt.date(2016, 6, 1), dt.date(2016, 6, 2)]
    assert all(f.empty and list(f.columns) == ["sensor", "ts", "value"] for _, f in empty)


def test_last_readings_before(store: Store) -> None:
    store.write_readings([
        Reading("a/temp", dt.datetime(2016, 3, 1, 7, 0, tzinfo=UTC), 20.0),
        Reading("a/temp", dt.datetime(2016, 3, 1, 7, 20, tzinfo=UTC), 21.0),
        Reading("a/temp", dt.datetime(2016, 3, 1, 7, 30, tzinfo=UTC), 22.0),
        Reading("b/co2", dt.datetime(2016, 2, 20, 12, 0, tzinfo=UTC), 450.0),
    ])
    at = dt.datetime(2016, 3, 1, 7, 30, tzinfo=UTC)
    got = store.last_readings_before(["a/temp", "b/co2", "c/none"], at)
    assert got == {"a/temp": (dt.datetime(2016, 3, 1, 7, 20, tzinfo=UTC), 21.0),  # strictly <
                   "b/co2": (dt.datetime(2016, 2, 20, 12, 0, tzinfo=UTC), 450.0)}
    bounded = store.last_readings_before(["a/temp", "b/co2"], at,
                                         since=at - dt.timedelta(hours=24))
    assert set(bounded) == {"a/temp"}  # b/co2's reading is older than `since`


def test_reading_range(store: Store) -> None:
    assert store.reading_range() is None
    store.write_readings(minute_frame(["a/temp"], "2016-03-01T00:00", "2016-03-01T01:00"))
    assert store.reading_range() == (dt.datetime(2016, 3, 1, tzinfo=UTC),
                                     dt.datetime(2016, 3, 1, 0, 59, tzinfo=UTC))
    assert store.reading_range(["nobody"]) is None


# ------------------------------------------------------------------- estimates, progress


def _estimate(value: float, ts: dt.datetime, model: str = "corrgp-triv",
              std: float = 0.2, artifact: str = "sha256:aa") -> EstimateRow:
    return EstimateRow("desk", model, ts, value, std, "ok", artifact)


def test_estimates_upsert_leaves_one_row_with_the_latest_value(store: Store) -> None:
    t = dt.datetime(2016, 3, 1, 8, 15, tzinfo=UTC)
    assert store.write_estimates([_estimate(21.0, t), _estimate(5.0, t, model="triv")]) == 2
    before = store.read_estimates("desk")
    assert store.write_estimates([_estimate(21.7, t, std=0.3, artifact="sha256:bb")]) == 1
    got = store.read_estimates("desk")
    assert len(got) == 2  # one row per (twin, model, ts)
    row = got[got["model"] == "corrgp-triv"].iloc[0]
    assert (row["value"], row["std"], row["artifact_hash"]) == (21.7, 0.3, "sha256:bb")
    assert row["ts"] == pd.Timestamp(t)
    old = before[before["model"] == "corrgp-triv"].iloc[0]
    assert row["written_at"] >= old["written_at"]
    assert got[got["model"] == "triv"]["value"].tolist() == [5.0]
    assert list(got.columns) == list(store_mod.ESTIMATE_COLUMNS)


def test_estimates_keep_what_answered_and_what_it_lost(store: Store) -> None:
    """source and lost as the payload says them; a rewrite replaces them too; a row that
    does not know them stores None."""
    t = dt.datetime(2016, 3, 1, 8, 15, tzinfo=UTC)
    store.write_estimates([
        EstimateRow("desk", "estimate", t, 21.0, 0.2, "fallback", "h", "triv-cov", ("a", "b")),
        EstimateRow("desk", "triv", t, 21.1, 0.2, "ok", "h", "triv", ()),
        EstimateRow("desk", "varma", t, 21.2, 0.2, "ok", "h"),
    ])
    got = store.read_estimates("desk").set_index("model")
    assert got.loc["estimate", "source"] == "triv-cov"
    assert got.loc["estimate", "lost"] == '["a", "b"]'
    assert (got.loc["triv", "source"], got.loc["triv", "lost"]) == ("triv", "[]")
    assert got.loc["varma", "source"] is None and got.loc["varma", "lost"] is None
    store.write_estimates([EstimateRow("desk", "estimate", t, 21.3, 0.2, "ok", "h",
                                       "corrgp-triv", ())])
    again = store.read_estimates("desk", model="estimate").iloc[0]
    assert (again["source"], again["lost"]) == ("corrgp-triv", "[]")
    with pytest.raises(TypeError, match="tuple of sensor ids"):
        EstimateRow("desk", "estimate", t, 1.0, 0.1, "ok", "h", "triv", "a")  # type: ignore[arg-type]


def test_one_key_twice_in_one_call_first_reading_and_last_estimate_win(store: Store) -> None:
    t = dt.datetime(2016, 3, 1, 8, 15, tzinfo=UTC)
    store.write_readings([Reading("a/temp", t, 1.0), Reading("a/temp", t, 2.0)])
    assert store.read_readings("a/temp")["value"].tolist() == [1.0]  # readings: immutable
    store.write_estimates([_estimate(21.0, t), _estimate(22.0, t)])
    assert store.read_estimates("desk")["value"].tolist() == [22.0]  # as if row by row


def test_replace_estimates_makes_the_span_exactly_the_rows_given(store: Store) -> None:
    """A backfilled day replaces the twin's rows of that day whole: an earlier artifact's
    model and instants go, the twin's other days and other twins stay."""
    day = dt.datetime(2016, 3, 1, tzinfo=UTC)
    at = [day + dt.timedelta(hours=8, minutes=15 * i) for i in range(3)]
    store.write_estimates([
        *(_estimate(20.0 + i, t) for i, t in enumerate(at)),
        _estimate(5.0, at[0], model="varma"),  # a model the new artifact does not run
        _estimate(7.0, day + dt.timedelta(days=1, hours=8)),  # the next day
        EstimateRow("other", "triv", at[0], 1.0, 0.1, "ok", "h"),  # another twin
    ])
    n = store.replace_estimates("desk", day, day + dt.timedelta(days=1),
                                [_estimate(30.0, at[1]), _estimate(31.0, at[2], model="triv")])
    assert n == 2
    got = store.read_estimates("desk")
    assert sorted(zip(got["model"], got["value"], strict=True)) == [
        ("corrgp-triv", 7.0), ("corrgp-triv", 30.0), ("triv", 31.0)]
    assert store.read_estimates("other")["value"].tolist() == [1.0]
    with pytest.raises(ValueError, match="not in it"):
        store.replace_estimates("desk", day, day + dt.timedelta(hours=1), [_estimate(1.0, at[0])])
    assert len(store.read_estimates("desk")) == 3  # refused whole: nothing deleted


def test_read_estimates_filters_and_keeps_nan(store: Store) -> None:
    base = dt.datetime(2016, 3, 1, 8, 0, tzinfo=UTC)
    rows = [_estimate(20.0 + i, base + dt.timedelta(minutes=15 * i)) for i in range(4)]
    rows.append(EstimateRow("desk", "varma", base, float("nan"), float("nan"), "fallback", "h"))
    rows.append(EstimateRow("other", "triv", base, 1.0, 0.1, "ok", "h"))
    store.write_estimates(rows)
    window = store.read_estimates("desk", base + dt.timedelta(minutes=15),
                                  base + dt.timedelta(minutes=45), model="corrgp-triv")
    assert window["value"].tolist() == [21.0, 22.0]  # half-open
    varma = store.read_estimates("desk", model="varma")
    assert np.isnan(varma["value"].iloc[0]) and np.isnan(varma["std"].iloc[0])
    assert store.read_estimates("nobody").empty


def test_done_days(store: Store) -> None:
    assert store.done_days("desk") == set()
    store.mark_day_done("desk", dt.date(2016, 3, 1), 44)
    store.mark_day_done("desk", dt.date(2016, 3, 2), 44)
    store.mark_day_done("desk", dt.date(2016, 3, 2), 45)  # re-run of a day: still one
    store.mark_day_done("window", dt.date(2016, 3, 1), 10)
    assert store.done_days("desk") == {dt.date(2016, 3, 1), dt.date(2016, 3, 2)}
    assert store.done_days("window") == {dt.date(2016, 3, 1)}


def test_reopen_keeps_data_and_schema_version(backend: dict) -> None:
    with open_store(backend["url"]) as s:
        assert s.schema_version == SCHEMA_VERSION
        s.write_readings(minute_frame(["a/temp"], "2016-03-01T00:00", "2016-03-01T00:10"))
    with open_store(backend["url"]) as s:
        assert s.count_readings() == 10
        assert s.schema_version == SCHEMA_VERSION


def test_newer_schema_version_is_refused(backend: dict) -> None:
    with open_store(backend["url"]) as s:
        if backend["kind"] == "crate-real":
            s._run("UPDATE meta SET value = ? WHERE name = ?",  # type: ignore[attr-defined]
                   [str(SCHEMA_VERSION + 1), "schema_version"])
            s._run("REFRESH TABLE meta")  # type: ignore[attr-defined]
    if backend["kind"] == "sqlite":
        with sqlite3.connect(backend["url"]) as conn:
            conn.execute("UPDATE meta SET value = ? WHERE name = 'schema_version'",
                         (str(SCHEMA_VERSION + 1),))
    elif backend["kind"] == "crate-fake":
        backend["fake"].sql("UPDATE meta SET value = ? WHERE name = 'schema_version'",
                            [str(SCHEMA_VERSION + 1)])
    elif backend["kind"] == "postgres":
        import psycopg

        with psycopg.connect(backend["url"], autocommit=True) as conn:
            conn.execute("UPDATE pseudotwin.meta SET value = %s WHERE name = 'schema_version'",
                         [str(SCHEMA_VERSION + 1)])
    with pytest.raises(StoreError, match=rf"schema version {SCHEMA_VERSION + 1}, newer .* "
                       rf"supports \({SCHEMA_VERSION}\)"):
        open_store(backend["url"])


# The estimates table and meta as pseudotwin wrote them at schema version 1, per backend's
# SQL dialect, with one estimate: the database an upgrade finds.
_V1_ESTIMATES = {
    "sqlite": "CREATE TABLE estimates (twin TEXT NOT NULL, model TEXT NOT NULL, "
              "ts INTEGER NOT NULL, value REAL, std REAL, quality TEXT NOT NULL, "
              "artifact_hash TEXT NOT NULL, written_at INTEGER NOT NULL, "
              "PRIMARY KEY (twin, model, ts)) WITHOUT ROWID",
    "crate": "CREATE TABLE estimates (twin TEXT NOT NULL, model TEXT NOT NULL, "
             "ts TIMESTAMP WITH TIME ZONE NOT NULL, value DOUBLE PRECISION, "
             "std DOUBLE PRECISION, quality TEXT NOT NULL, artifact_hash TEXT NOT NULL, "
             "written_at TIMESTAMP WITH TIME ZONE NOT NULL, "
             "month TIMESTAMP WITH TIME ZONE GENERATED ALWAYS AS date_trunc('month', ts), "
             "PRIMARY KEY (twin, model, ts, month)) PARTITIONED BY (month)",
    "postgres": 'CREATE TABLE estimates (twin TEXT COLLATE "C" NOT NULL, '
                'model TEXT COLLATE "C" NOT NULL, ts TIMESTAMPTZ NOT NULL, '
                "value DOUBLE PRECISION, std DOUBLE PRECISION, quality TEXT NOT NULL, "
                "artifact_hash TEXT NOT NULL, written_at TIMESTAMPTZ NOT NULL, "
                "PRIMARY KEY (twin, model, ts))",
}
_V1_ROW = ("desk", "estimate", 1456819200000, 21.5, 0.2, "ok", "sha256:aa", 1456819200000)


def _write_version_1(backend: dict) -> None:
    kind = backend["kind"]
    if kind == "sqlite":
        with sqlite3.connect(backend["url"]) as conn:
            conn.execute("CREATE TABLE meta (name TEXT PRIMARY KEY, value TEXT NOT NULL) "
                         "WITHOUT ROWID")
            conn.execute("INSERT INTO meta VALUES ('schema_version', '1')")
            conn.execute(_V1_ESTIMATES["sqlite"])
            conn.execute("INSERT INTO estimates VALUES (?, ?, ?, ?, ?, ?, ?, ?)", _V1_ROW)
    elif kind == "postgres":
        import psycopg

        with psycopg.connect(backend["url"], autocommit=True) as conn:
            conn.execute("CREATE SCHEMA pseudotwin; SET search_path TO pseudotwin")
            conn.execute("CREATE TABLE meta (name TEXT PRIMARY KEY, value TEXT NOT NULL)")
            conn.execute("INSERT INTO meta VALUES ('schema_version', '1')")
            conn.execute(_V1_ESTIMATES["postgres"])
            conn.execute('CREATE TABLE readings (sensor TEXT COLLATE "C" NOT NULL, '
                         "ts TIMESTAMPTZ NOT NULL, value DOUBLE PRECISION NOT NULL, "
                         "PRIMARY KEY (sensor, ts))")  # (PostgreSQL makes tables only new)
            conn.execute("INSERT INTO estimates VALUES (%s, %s, to_timestamp(%s / 1000.0), %s, "
                         "%s, %s, %s, to_timestamp(%s / 1000.0))", _V1_ROW)
    else:  # through the crate client, as the store of version 1 sent it
        from crate import client

        servers = backend["url"].split("://", 1)[1].split("?")[0].split(",")
        conn = client.connect([f"http://{h}" for h in servers],
                              schema=backend.get("schema", store_mod.DEFAULT_CRATE_SCHEMA))
        try:
            cur = conn.cursor()
            cur.execute("CREATE TABLE meta (name TEXT PRIMARY KEY, value TEXT NOT NULL)")
            cur.execute("INSERT INTO meta (name, value) VALUES ('schema_version', '1')")
            cur.execute(_V1_ESTIMATES["crate"])
            cur.execute("INSERT INTO estimates (twin, model, ts, value, std, quality, "
                        "artifact_hash, written_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                        list(_V1_ROW))
            if kind == "crate-real":
                cur.execute("REFRESH TABLE meta, estimates")
        finally:
            conn.close()


def test_a_version_1_store_is_migrated_in_place_keeping_its_rows(
        backend: dict, caplog: pytest.LogCaptureFixture) -> None:
    """An upgrade opens a store of schema version 1: ``estimates`` gains source and lost (the
    old row kept, with both not known), the version becomes 2, and the new columns take
    what a failover answered; opening it again changes nothing."""
    _write_version_1(backend)
    t = dt.datetime(2016, 3, 1, 8, 15, tzinfo=UTC)
    with caplog.at_level(logging.WARNING, logger="pseudotwin.history.store"), \
            open_store(backend["url"]) as s:
        assert s.schema_version == SCHEMA_VERSION == 2
        old = s.read_estimates("desk")
        assert len(old) == 1 and old["value"].iloc[0] == 21.5
        assert old["source"].iloc[0] is None and old["lost"].iloc[0] is None
        s.write_estimates([EstimateRow("desk", "estimate", t, 21.9, 0.3, "fallback", "h",
                                       "triv", ("room/wall, left",))])
    said = [r.getMessage() for r in caplog.records]
    assert any("schema version 1 → 2 (added estimates.source, estimates.lost)" in m
               for m in said), said
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pseudotwin.history.store"), \
            open_store(backend["url"]) as s:
        assert s.schema_version == SCHEMA_VERSION
        got = s.read_estimates("desk")
    assert not caplog.records  # up to date: nothing migrated twice
    assert got["value"].tolist() == [21.5, 21.9]
    assert got["source"].tolist() == [None, "triv"]
    assert got["lost"].tolist() == [None, '["room/wall, left"]']


def test_closed_store_raises(store: Store) -> None:
    store.close()
    store.close()  # idempotent
    with pytest.raises(StoreError, match="closed"):
        store.count_readings()


# ---------------------------------------------------------------------- SQLite specifics


def test_sqlite_file_is_wal_with_integer_ms_timestamps(tmp_path: Path) -> None:
    path = tmp_path / "h.db"
    with open_store(path) as s:
        s.write_readings([Reading("a/temp", dt.datetime(2016, 3, 1, tzinfo=UTC), 21.0)])
    with sqlite3.connect(path) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert conn.execute("SELECT sensor, ts, value FROM readings").fetchall() == [
            ("a/temp", 1456790400000, 21.0)]
        assert conn.execute("SELECT value FROM meta WHERE name = 'schema_version'"
                            ).fetchone()[0] == str(SCHEMA_VERSION)


def test_two_sqlite_stores_share_one_file(tmp_path: Path) -> None:
    path = tmp_path / "h.db"
    with open_store(path) as recorder, open_store(path) as backfill:
        recorder.write_readings(minute_frame(["a/temp"], "2016-03-01T00:00", "2016-03-01T01:00"))
        backfill.write_estimates([_estimate(1.0, dt.datetime(2016, 3, 1, tzinfo=UTC))])
        recorder.write_readings(minute_frame(["b/temp"], "2016-03-01T00:00", "2016-03-01T01:00"))
        assert backfill.count_readings() == 120
        assert len(recorder.read_estimates("desk")) == 1


def test_sqlite_write_call_is_one_transaction(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(store_mod, "WRITE_CHUNK", 1)  # the good row is written first
    good = Reading("a/temp", dt.datetime(2016, 3, 1, tzinfo=UTC), 1.0)
    naive = SimpleNamespace(sensor="a/temp", ts=dt.datetime(2016, 3, 1, 1), value=2.0)
    with open_store(tmp_path / "h.db") as s:
        with pytest.raises(ValueError, match="timezone-aware"):
            s.write_readings(iter([good, naive]))  # type: ignore[list-item]
        assert s.count_readings() == 0  # the first batch was rolled back


def test_open_store_urls(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with open_store("sqlite:///rel.db") as s:
        assert s.url == "sqlite:///rel.db"
    assert (tmp_path / "rel.db").exists()
    with open_store(f"sqlite:///{tmp_path}/abs.db") as s:  # four slashes: absolute
        assert s.count_readings() == 0
    assert (tmp_path / "abs.db").exists()
    with open_store(tmp_path / "plain.db") as s:
        assert s.url == f"sqlite:///{tmp_path}/plain.db"
    for memory in (":memory:", "sqlite://", "sqlite:///:memory:"):
        with open_store(memory) as s:
            assert s.count_readings() == 0
        with pytest.raises(ConfigError, match="holds nothing to read"):
            open_store(memory, existing=True)
    with pytest.raises(ConfigError, match="no file path"):  # sqlite:///$DB with DB unset
        open_store("sqlite:///")
    with pytest.raises(StoreError, match="does not exist"):
        open_store(tmp_path / "missing" / "h.db")
    (tmp_path / "junk.db").write_bytes(b"this is not a database file, just some bytes" * 50)
    with pytest.raises(StoreError, match="not a usable SQLite history DB"):
        open_store(tmp_path / "junk.db")
    with pytest.raises(ConfigError, match="unsupported"):
        open_store("mysql://db/x")
    with pytest.raises(ConfigError, match="must not contain credentials"):
        open_store("crate://admin:secret@localhost:4200")
    with pytest.raises(ConfigError, match="unknown option"):
        open_store("crate://localhost:4200?ssl=1")
    with pytest.raises(ConfigError, match="empty"):
        open_store("  ")


def test_crate_hosts_get_the_default_port() -> None:
    assert [store_mod._with_port(h) for h in ("db", "db:4300", "[::1]", "[::1]:4201")] == [
        "db:4200", "db:4300", "[::1]:4200", "[::1]:4201"]


# ------------------------------------------------------ CrateDB backend against the FAKE


def _stmts(fake: FakeCrateDB, prefix: str) -> list[str]:
    return [s for s in fake.statements if s.lstrip().upper().startswith(prefix.upper())]


def test_crate_ddl_uses_cratedb_types_and_monthly_partitions(fake: FakeCrateDB) -> None:
    with open_store(fake.url):
        pass
    ddl = {s.split()[5]: s for s in _stmts(fake, "CREATE TABLE IF NOT EXISTS")}
    assert set(ddl) == {"meta", "readings", "estimates", "backfill_progress"}
    for table in ("readings", "estimates"):
        sql = ddl[table]
        assert "ts TIMESTAMP WITH TIME ZONE NOT NULL" in sql
        assert "DOUBLE PRECISION" in sql
        assert ("month TIMESTAMP WITH TIME ZONE GENERATED ALWAYS AS "
                "date_trunc('month', ts)") in sql
        assert sql.endswith("PARTITIONED BY (month)")
    assert "PRIMARY KEY (sensor, ts, month)" in ddl["readings"]
    assert "PRIMARY KEY (twin, model, ts, month)" in ddl["estimates"]
    assert "written_at TIMESTAMP WITH TIME ZONE" in ddl["estimates"]
    assert "finished_at TIMESTAMP WITH TIME ZONE" in ddl["backfill_progress"]
    # The schema version is written once, without clobbering an existing one.
    assert any("INSERT INTO meta" in s and "ON CONFLICT (name) DO NOTHING" in s
               for s in fake.statements)
    assert fake.sql("SELECT value FROM meta") == [(str(SCHEMA_VERSION),)]
    assert {r.schema for r in fake.requests} == {store_mod.DEFAULT_CRATE_SCHEMA}


def test_crate_writes_are_bulk_requests_with_on_conflict(fake: FakeCrateDB,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(store_mod, "WRITE_CHUNK", 100)
    df = minute_frame(["a/temp"], "2016-03-01T00:00", "2016-03-01T04:10")  # 250 rows
    with open_store(fake.url) as s:
        assert s.write_readings(df) == 250
        assert s.write_readings(df) == 0  # every row answered rowcount 0 (DO NOTHING)
        s.write_estimates([_estimate(21.0, dt.datetime(2016, 3, 1, 8, tzinfo=UTC))])
    inserts = [r for r in fake.requests if r.stmt.startswith("INSERT INTO readings")]
    assert [len(r.bulk_args or []) for r in inserts] == [100, 100, 50, 100, 100, 50]
    assert all(r.args is None for r in inserts)  # bulk_args, never one request per row
    assert inserts[0].stmt.endswith("ON CONFLICT (sensor, ts, month) DO NOTHING")
    # Timestamps travel as epoch milliseconds, values as floats; month is never sent.
    assert inserts[0].bulk_args[0] == ["a/temp", 1456790400000, 0.0]
    (upsert,) = [r for r in fake.requests if r.stmt.startswith("INSERT INTO estimates")]
    assert "ON CONFLICT (twin, model, ts, month) DO UPDATE SET value = excluded.value" \
        in upsert.stmt
    assert "lost = excluded.lost" in upsert.stmt
    assert upsert.bulk_args is not None and len(upsert.bulk_args[0]) == 10


def test_crate_refreshes_written_tables_before_reading(fake: FakeCrateDB) -> None:
    with open_store(fake.url) as s:
        s.write_readings(minute_frame(["a/temp"], "2016-03-01T00:00", "2016-03-01T00:10"))
        n0 = len(fake.statements)
        s.count_readings()
        s.count_readings()
    after = fake.statements[n0:]
    assert after[0] == "REFRESH TABLE readings"  # once, right after the write
    assert [a.split()[0] for a in after] == ["REFRESH", "SELECT", "SELECT"]


def test_crate_iter_days_is_one_query_per_day(fake: FakeCrateDB) -> None:
    with open_store(fake.url) as s:
        s.write_readings(minute_frame(["a/temp"], "2016-03-25T00:00", "2016-03-29T00:00"))
        days = s.iter_days(["a/temp"], dt.date(2016, 3, 26), dt.date(2016, 3, 28), BERLIN)
        n0 = len(_stmts(fake, "SELECT"))
        next(days)
        assert len(_stmts(fake, "SELECT")) == n0 + 1  # lazily: nothing read ahead
        _, dst = next(days)
        sel = fake.requests[-1]
        assert sel.args == [to_ms("2016-03-26T23:00"), to_ms("2016-03-27T22:00"), "a/temp"]
        assert len(dst) == 23 * 60


def to_ms(text: str) -> int:
    return int(utc(text).value // 1_000_000)


def test_crate_bulk_row_failure_raises_with_the_first_error(fake: FakeCrateDB) -> None:
    df = minute_frame(["a/temp", "b/temp"], "2016-03-01T00:00", "2016-03-01T00:05")
    fake.fail_row = lambda stmt, row: ("ColumnValidationException[b is read-only]"
                                       if row[0] == "b/temp" else None)
    with open_store(fake.url) as s:
        with pytest.raises(RowsRejected, match=r"rejected 5 of 10 rows of readings; first: "
                                               r"row 1 \(ColumnValidationException\[b is") as e:
            s.write_readings(df)
        assert e.value.written == 5
        assert sorted(r[0] for r in e.value.rows) == ["b/temp"] * 5
        assert s.read_readings("a/temp")["ts"].tolist() == list(df[df.sensor == "a/temp"].ts)


def test_crate_rows_after_a_refused_batch_are_written_all_the_same(
        fake: FakeCrateDB, monkeypatch: pytest.MonkeyPatch) -> None:
    """A row CrateDB always refuses must not keep the rows of later bulk requests out: the
    recorder would retry the same spool forever and store nothing after it."""
    monkeypatch.setattr(store_mod, "WRITE_CHUNK", 4)
    df = minute_frame(["a/temp"], "2016-03-01T00:00", "2016-03-01T00:10")
    first = int(df.ts.iloc[0].value // 1_000_000)
    fake.fail_row = lambda stmt, row: "SQLParseException[refused]" if row[1] == first else None
    with open_store(fake.url) as s:
        with pytest.raises(RowsRejected, match="rejected 1 of 10 rows") as e:
            s.write_readings(df)
        assert e.value.written == 9 and [r[1] for r in e.value.rows] == [first]
        assert s.read_readings("a/temp")["ts"].tolist() == df.ts.tolist()[1:]


def test_bulk_count_understands_both_error_shapes() -> None:
    assert _bulk_count([{"rowcount": 1}, {"rowcount": 0}, {"rowcount": -1}], 3) == (2, [])
    assert _bulk_count([], 7) == (7, [])  # no per-row results: rows sent
    assert _bulk_count([{"rowcount": 1},
                        {"rowcount": -2, "error": {"code": 5000, "message": "IOException[disk]"}}],
                       2) == (1, [(1, "IOException[disk]")])
    assert _bulk_count([{"rowcount": -2}], 1) == (0, [(0, None)])


def test_crate_statement_error_is_a_store_error(fake: FakeCrateDB) -> None:
    with open_store(fake.url) as s:
        fake.sql("DROP TABLE readings")
        with pytest.raises(StoreError, match="RelationUnknown"):
            s.count_readings()


def test_crate_fake_enforces_the_primary_key_rules(fake: FakeCrateDB) -> None:
    # The fake rejects what CrateDB rejects, so the checks above are meaningful.
    from fake_cratedb import FakeSQLError

    with pytest.raises(FakeSQLError, match="PARTITIONED BY"):
        fake.translate("CREATE TABLE t (a TEXT, ts TIMESTAMP WITH TIME ZONE, month TIMESTAMP "
                       "WITH TIME ZONE GENERATED ALWAYS AS date_trunc('month', ts), "
                       "PRIMARY KEY (a, ts)) PARTITIONED BY (month)")
    with open_store(fake.url):
        pass
    with pytest.raises(FakeSQLError, match="conflict targets"):
        fake.translate("INSERT INTO readings (sensor, ts, value) VALUES (?, ?, ?) "
                       "ON CONFLICT (sensor, ts) DO NOTHING")


def test_crate_credentials_and_schema(fake: FakeCrateDB, monkeypatch: pytest.MonkeyPatch,
                                      caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setenv(store_mod.ENV_CRATE_USER, "pt_writer")
    monkeypatch.setenv(store_mod.ENV_CRATE_PASSWORD, "s3cr3t-pw")
    caplog.set_level(logging.DEBUG)
    with open_store(f"{fake.url}?schema=building7") as s:
        s.write_readings(minute_frame(["a/temp"], "2016-03-01T00:00", "2016-03-01T00:05"))
        assert "s3cr3t" not in repr(s)
    assert {(r.user, r.has_password, r.schema) for r in fake.requests} == {
        ("pt_writer", True, "building7")}
    assert "s3cr3t-pw" not in caplog.text


def test_crate_unreachable_is_a_store_error() -> None:
    with FakeCrateDB() as server:
        url = server.url
    with pytest.raises(StoreError, match="cannot connect to CrateDB"):
        open_store(url)


def test_a_sqlite_store_held_by_another_writer_is_busy_not_broken(tmp_path: Path,
                                                                  monkeypatch) -> None:
    """An import or backfill holding the file's lock past the busy timeout: the message says
    busy and what to do, not that the file is no usable history DB."""
    url = f"sqlite:///{tmp_path / 'history.db'}"
    open_store(url).close()
    monkeypatch.setattr(store_mod, "SQLITE_BUSY_TIMEOUT_MS", 200)
    holder = sqlite3.connect(tmp_path / "history.db", isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        with pytest.raises(StoreError, match="busy: another process held its lock") as err:
            open_store(url)
        assert "not a usable" not in str(err.value)
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    open_store(url).close()  # free again


def test_a_crate_migration_cut_short_is_finished(fake: FakeCrateDB) -> None:
    """CrateDB has no transactions: a migration stopped after its first ALTER left the
    version at 1 and one column added; the next open adds only the other."""
    _write_version_1({"kind": "crate-fake", "url": fake.url})
    fake.sql("ALTER TABLE estimates ADD COLUMN source TEXT")
    with open_store(fake.url) as s:
        assert s.schema_version == SCHEMA_VERSION
        assert s.read_estimates("desk")["lost"].tolist() == [None]
    alters = [st for st in fake.statements if st.startswith("ALTER")]
    assert alters == ["ALTER TABLE estimates ADD COLUMN lost TEXT"]
    assert fake.sql("SELECT value FROM meta") == [(str(SCHEMA_VERSION),)]


def test_a_crate_migration_racing_another_process_takes_its_column(
        fake: FakeCrateDB, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two processes open a version-1 CrateDB store at once (the daemon and the recorder
    after an upgrade): both find a column missing, the other adds it first, and this one's
    ALTER is refused. It goes on, since the column is there now."""
    _write_version_1({"kind": "crate-fake", "url": fake.url})
    fake.sql("ALTER TABLE estimates ADD COLUMN source TEXT")  # the other process's ALTER
    looked: list[str] = []
    real = store_mod.CrateStore._has_column

    def has_column(self: store_mod.CrateStore, table: str, column: str) -> bool:
        looked.append(column)
        if looked.count(column) == 1:  # looked before the other process added it
            return False
        return real(self, table, column)

    monkeypatch.setattr(store_mod.CrateStore, "_has_column", has_column)
    with open_store(fake.url) as s:
        assert s.schema_version == SCHEMA_VERSION
        assert s.read_estimates("desk")["source"].tolist() == [None]
    refused = [st for st in fake.statements if st.startswith("ALTER")]
    assert refused == ["ALTER TABLE estimates ADD COLUMN source TEXT",
                       "ALTER TABLE estimates ADD COLUMN lost TEXT"]
    assert looked == ["source", "source", "lost"]  # the refused ALTER looked again


def test_a_crate_setup_cut_short_before_its_version_gets_the_new_columns(
        fake: FakeCrateDB) -> None:
    """A version-1 setup that stopped after its tables, before the meta row: no version
    recorded, old tables. Opening it adds the columns and records version 2."""
    _write_version_1({"kind": "crate-fake", "url": fake.url})
    fake.sql("DELETE FROM meta")
    with open_store(fake.url) as s:
        s.write_estimates([EstimateRow("desk", "estimate", dt.datetime(2016, 3, 1, 9, tzinfo=UTC),
                                       21.0, 0.2, "ok", "h", "triv", ())])
        assert s.read_estimates("desk")["source"].tolist() == [None, "triv"]
    assert fake.sql("SELECT value FROM meta") == [(str(SCHEMA_VERSION),)]


def test_a_store_opened_only_to_read_readings_is_not_migrated(backend: dict) -> None:
    """train, evaluate and the daemon's warm start read readings only: a version-1 store
    (older recorders still write to it) stays at version 1, its readings readable, its
    estimates refused with a clear error; a writing open migrates it."""
    _write_version_1(backend)
    reading = Reading("a/temp", dt.datetime(2016, 3, 1, 8, tzinfo=UTC), 20.5)
    with open_store(backend["url"], migrate=False) as s:
        assert s.schema_version == 1
        s.write_readings([reading])  # (readings: the same table in both versions)
        with pytest.raises(StoreError, match="schema version 1.*record, import, backfill"):
            s.read_estimates("desk")
        with pytest.raises(StoreError, match="schema version 1"):
            s.write_estimates([_estimate(1.0, reading.ts)])
    with open_store(backend["url"], existing=True, migrate=False) as s:  # still 1
        assert s.schema_version == 1
        assert s.read_readings("a/temp")["value"].tolist() == [20.5]
    with open_store(backend["url"]) as s:
        assert s.schema_version == SCHEMA_VERSION
        assert s.read_estimates("desk")["value"].tolist() == [21.5]


def test_a_days_delete_finds_its_rows_through_an_index(tmp_path: Path) -> None:
    """SQLite: the replace's delete of a twin's day uses the (twin, ts) index a writing
    open makes, not a scan of every row of the twin; an open only to read readings does
    not make it."""
    _write_version_1({"kind": "sqlite", "url": str(tmp_path / "h.db")})
    plan = "EXPLAIN QUERY PLAN DELETE FROM estimates WHERE twin = ? AND ts >= ? AND ts < ?"
    with open_store(str(tmp_path / "h.db"), migrate=False):
        pass
    with sqlite3.connect(tmp_path / "h.db") as conn:
        assert "estimates_twin_ts" not in str(conn.execute(plan, ("d", 0, 1)).fetchall())
    with open_store(str(tmp_path / "h.db")):
        pass
    with sqlite3.connect(tmp_path / "h.db") as conn:
        assert "estimates_twin_ts" in str(conn.execute(plan, ("d", 0, 1)).fetchall())


def test_a_crate_replace_refreshes_before_its_delete(fake: FakeCrateDB) -> None:
    """CrateDB's DELETE sees only refreshed rows: the replace refreshes the table first,
    so rows written in the last second (here, by this store) go too."""
    day = dt.datetime(2016, 3, 1, tzinfo=UTC)
    with open_store(fake.url) as s:
        s.write_estimates([_estimate(1.0, day + dt.timedelta(hours=8))])
        s.replace_estimates("desk", day, day + dt.timedelta(days=1), [])
    sent = fake.statements
    delete = next(i for i, st in enumerate(sent) if st.startswith("DELETE FROM estimates"))
    assert sent[delete - 1] == "REFRESH TABLE estimates"
    assert fake.sql("SELECT count(*) FROM estimates") == [(0,)]
