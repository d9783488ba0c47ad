"""The history store: raw readings, estimates and backfill progress in one database.

One small interface (:class:`Store`), three backends:

* **SQLite** (embedded default): one file, WAL mode so the recorder can write while a
  backfill or the daemon reads, ``busy_timeout`` so concurrent writers wait instead of
  failing. Timestamps are INTEGER epoch milliseconds UTC.
* **CrateDB** through the ``crate`` client (HTTP ``/_sql``): ``TIMESTAMP WITH TIME ZONE``
  columns, tables partitioned by month (a generated column), bulk inserts with per-row
  results. CrateDB stores timestamps at millisecond resolution and transports them as epoch
  milliseconds, which is why every backend stores exactly that.
* **PostgreSQL** (TimescaleDB hypertables when present) through psycopg 3: ``timestamptz``
  columns; in :mod:`pseudotwin.history.postgres`, whose docstring lists its URL forms.

:func:`open_store` picks the backend from a URL:

========================================  ====================================================
``/var/lib/pseudotwin/history.db``         SQLite file (a plain path, relative or absolute)
``sqlite:///history.db``                   SQLite, relative path (SQLAlchemy convention)
``sqlite:////var/lib/pt/history.db``       SQLite, absolute path (note the fourth slash)
``:memory:`` / ``sqlite://``               SQLite in memory (tests)
``crate://host:4200``                      CrateDB over HTTP; several nodes: ``h1:4200,h2:4200``
``crate+https://host:4200``                CrateDB over HTTPS
``crate://host:4200?schema=pt``            tables in schema ``pt`` (default ``pseudotwin``)
``postgresql://host/db?schema=pt``         PostgreSQL (also ``postgres://``); more forms
                                           in :mod:`pseudotwin.history.postgres`
========================================  ====================================================

CrateDB credentials come from the environment, ``PSEUDOTWIN_CRATE_USER`` and
``PSEUDOTWIN_CRATE_PASSWORD``, never from the URL (a URL ends up in configs and logs).

Tables (schema version :data:`SCHEMA_VERSION`, kept in ``meta``):

* ``readings (sensor, ts, value)``, key (sensor, ts). Readings are immutable: writing one
  whose key is stored already changes nothing (first write wins). Only the recorder and
  ``import`` write here; nothing updates or deletes.
* ``estimates (twin, model, ts, value, std, quality, artifact_hash, written_at, source,
  lost)``, key (twin, model, ts): writing the same estimate again replaces the row (one row
  per key), so backfills are idempotent; a backfilled day replaces the twin's rows of that
  day whole (:meth:`Store.replace_estimates`), so none of an earlier artifact's stay.
  ``source`` and ``lost`` say what answered, as the daemon's payload does (its ``model``
  and ``lost``): a failover's kind and the silent references it did without, as a JSON
  list (``[]``: none). Rows written before schema version 2 hold NULL there (read back
  as None): not known.
* ``backfill_progress (twin, day, estimates, finished_at)``, key (twin, day): the days a
  backfill finished, so an interrupted backfill resumes where it stopped.

Every timestamp is stored at millisecond resolution; finer parts are truncated (floor), so
two readings of one sensor within the same millisecond are one reading.

Opening a store of an older schema version brings it up to date in place (version 1 → 2:
``estimates`` gains ``source`` and ``lost``, the rows kept as they are), unless it is opened
only to read readings (``migrate=False``: train, evaluate and the daemon's warm start, so
that an analyst's newer build does not change a store older recorders write to); one of a
newer version is refused.
"""

from __future__ import annotations

import abc
import datetime as dt
import logging
import math
import os
import re
import sqlite3
import threading
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, urlsplit
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import numpy as np
import pandas as pd

from pseudotwin.config.validate import PATHLESS_SQLITE, is_memory_url
from pseudotwin.core.series import COLUMNS, normalize
from pseudotwin.errors import ConfigError, PseudotwinError
from pseudotwin.live.failover import lost_json
from pseudotwin.live.readings import Reading

if TYPE_CHECKING:
    from pseudotwin.live.twin import TwinEstimate

__all__ = [
    "ESTIMATE_COLUMNS",
    "SCHEMA_VERSION",
    "EstimateRow",
    "RowsRejected",
    "Store",
    "StoreError",
    "open_store",
]

log = logging.getLogger(__name__)

#: Version of the table layout. A database written by a newer pseudotwin is refused; an
#: older one is migrated when opened (:data:`MIGRATIONS`).
SCHEMA_VERSION = 2

#: A backfilled day's delete (:meth:`Store.replace_estimates`) finds the twin's rows of the
#: day through it: the primary key (twin, model, ts) narrows it to the twin only, a scan of
#: every row of the twin per day, growing with the twin's history. SQLite and PostgreSQL;
#: made by a writing open (``migrate``), as the columns are.
ESTIMATES_INDEX = "CREATE INDEX IF NOT EXISTS estimates_twin_ts ON estimates (twin, ts)"

#: The columns each version added to a table, with their SQL type (the same in every
#: backend): opening a store of an older version adds those it lacks, in order, the rows
#: kept (NULL there).
MIGRATIONS: dict[int, tuple[tuple[str, str, str], ...]] = {
    2: (("estimates", "source", "TEXT"), ("estimates", "lost", "TEXT")),
}

#: Rows per executemany call: bounds the memory of one bulk request (CrateDB sends the
#: whole batch as one JSON body) while keeping the per-request overhead small.
WRITE_CHUNK = 5000

#: read_readings over a longer span is split into windows of this length, which bounds the
#: size of one result set (CrateDB answers with one JSON document) and lets CrateDB prune
#: monthly partitions.
READ_WINDOW = dt.timedelta(days=31)

#: How long a SQLite writer waits for another writer's lock before failing [ms].
SQLITE_BUSY_TIMEOUT_MS = 10_000

#: Socket timeout of CrateDB HTTP requests [s].
CRATE_TIMEOUT_S = 60.0

ENV_CRATE_USER = "PSEUDOTWIN_CRATE_USER"
ENV_CRATE_PASSWORD = "PSEUDOTWIN_CRATE_PASSWORD"
DEFAULT_CRATE_SCHEMA = "pseudotwin"

ESTIMATE_COLUMNS = (
    "twin", "model", "ts", "value", "std", "quality", "artifact_hash", "written_at", "source",
    "lost",
)

_EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
_MS = dt.timedelta(milliseconds=1)
_NS_PER_MS = 1_000_000

Instant = dt.datetime  # timezone-aware; pandas.Timestamp is a datetime subclass


class StoreError(PseudotwinError):
    """The history store cannot be opened, read or written (also: newer schema version)."""


class RowsRejected(StoreError):
    """The database refused some rows of a write and took the others (CrateDB answers each
    row of a bulk request on its own; every row is attempted).

    rows: the refused rows as sent, for readings ``(sensor, ts [ms since the epoch],
    value)``; written: rows the write changed all the same.
    """

    def __init__(self, message: str, rows: list[tuple], written: int) -> None:
        super().__init__(message)
        self.rows = rows
        self.written = written


@dataclass(frozen=True)
class EstimateRow:
    """One estimate to store: the row of ``estimates`` keyed by (twin, model, ts).

    ts: timezone-aware instant the estimate is for. value, std: in the target's unit
    ([°C] or [ppm]); non-finite values are stored as NULL and read back as NaN.
    quality: ok | uncertain | fallback | stale. artifact_hash: identifies the trained
    artifact that produced the estimate (so a backfill with a new artifact is traceable).
    source: what produced the value, the payload's ``model`` (``triv`` on a fallback, the
    failover's kind); lost: the silent references a failover did without (None for both:
    not known, as in rows of schema version 1).
    """

    twin: str
    model: str
    ts: dt.datetime
    value: float
    std: float
    quality: str
    artifact_hash: str
    source: str | None = None
    lost: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.ts.tzinfo is None or self.ts.utcoffset() is None:
            raise ValueError("EstimateRow.ts must be timezone-aware")
        if self.lost is not None and not (isinstance(self.lost, tuple)
                                          and all(isinstance(s, str) for s in self.lost)):
            raise TypeError(f"EstimateRow.lost must be a tuple of sensor ids, not "
                            f"{self.lost!r}")

    @classmethod
    def from_estimate(cls, twin: str, kind: str, estimate: TwinEstimate,
                      artifact_hash: str) -> EstimateRow:
        """The row of one estimate of ``twin``'s model stream ``kind`` (the key: a fallback
        estimate's ``model`` is "triv", but it belongs to the stream it stood in for)."""
        return cls(twin, kind, estimate.ts, estimate.value, estimate.std, estimate.quality,
                   artifact_hash, estimate.model, estimate.lost)


# ------------------------------------------------------------------------------ helpers


def to_ms(ts: dt.datetime) -> int:
    """Epoch milliseconds (UTC, floor) of an aware datetime or pandas Timestamp."""
    if ts.tzinfo is None or ts.utcoffset() is None:
        raise ValueError(f"timestamp {ts!r} must be timezone-aware")
    if isinstance(ts, pd.Timestamp):
        return int(ts.value) // _NS_PER_MS  # .value is always ns, whatever the unit
    return (ts - _EPOCH) // _MS


def from_ms(ms: int) -> dt.datetime:
    """The aware UTC datetime of epoch milliseconds (exact, no float rounding)."""
    return _EPOCH + dt.timedelta(milliseconds=int(ms))


def _ms_to_index(ms: Sequence[int] | np.ndarray) -> pd.DatetimeIndex:
    arr = np.asarray(ms, dtype=np.int64) * _NS_PER_MS
    return pd.DatetimeIndex(arr.view("datetime64[ns]")).tz_localize("UTC")


def _float_or_nan(values: Iterable[Any]) -> np.ndarray:
    return np.array([math.nan if v is None else float(v) for v in values], dtype=float)


def _finite_or_none(x: float | None) -> float | None:
    # NaN has no portable SQL representation (SQLite turns it into NULL anyway, JSON has
    # none): store NULL explicitly and read it back as NaN.
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def empty_readings() -> pd.DataFrame:
    """A canonical frame (sensor, ts, value) with no rows and the canonical dtypes."""
    return pd.DataFrame({
        "sensor": pd.Series([], dtype=object).astype(str),
        "ts": pd.DatetimeIndex([], dtype="datetime64[ns, UTC]"),
        "value": pd.Series([], dtype=float),
    })


def _readings_frame(sensor: list[str], ms: list[int], value: list[float]) -> pd.DataFrame:
    if not sensor:
        return empty_readings()
    return pd.DataFrame({
        # astype(str) as history.normalize does, so frames from files and DB compare equal
        "sensor": pd.Series(sensor, dtype=object).astype(str),
        "ts": _ms_to_index(ms),
        "value": np.asarray(value, dtype=float),
    })


def _tz(tz: str | dt.tzinfo) -> dt.tzinfo:
    if isinstance(tz, dt.tzinfo):
        return tz
    try:
        return ZoneInfo(tz)
    except (ZoneInfoNotFoundError, ValueError):
        raise ConfigError(f"unknown time zone {tz!r} (use an IANA name, e.g. Europe/Berlin)") \
            from None


def _day_bounds(day: dt.date, tz: dt.tzinfo) -> tuple[int, int]:
    """[local midnight, next local midnight) of ``day`` in epoch ms: 23 h or 25 h on DST days."""
    start = dt.datetime.combine(day, dt.time(0), tzinfo=tz)
    end = dt.datetime.combine(day + dt.timedelta(days=1), dt.time(0), tzinfo=tz)
    return to_ms(start), to_ms(end)


def _chunks(items: Iterable[Any], n: int) -> Iterator[list[Any]]:
    it = iter(items)
    while batch := list(islice(it, n)):
        yield batch


def _sensor_list(sensors: Iterable[str] | str | None) -> list[str] | None:
    if sensors is None:
        return None
    if isinstance(sensors, str):  # a lone sensor id is not a list of its characters
        return [sensors]
    return list(dict.fromkeys(sensors))


def _estimate_batches(rows: Iterable[EstimateRow]) -> Iterator[list[tuple]]:
    """The rows of ``estimates`` in chunks of WRITE_CHUNK, written_at now."""
    now = to_ms(dt.datetime.now(dt.UTC))
    for batch in _chunks(rows, WRITE_CHUNK):
        yield [(r.twin, r.model, to_ms(r.ts), _finite_or_none(r.value), _finite_or_none(r.std),
                r.quality, r.artifact_hash, now, r.source,
                None if r.lost is None else lost_json(r.lost)) for r in batch]


def _reading_rows(readings: Iterable[Reading] | pd.DataFrame) -> Iterator[list[tuple]]:
    """(sensor, ts_ms, value) rows in chunks of WRITE_CHUNK; non-finite values dropped."""
    if isinstance(readings, pd.DataFrame):
        df = readings
        if df.empty:
            return
        canonical = (
            all(c in df.columns for c in COLUMNS)
            and isinstance(df["ts"].dtype, pd.DatetimeTZDtype)
            and pd.api.types.is_float_dtype(df["value"].dtype)
        )
        if not canonical:  # strings, naive times, ...: the file reader's rules apply
            df = normalize(df, "readings")
        ts = pd.DatetimeIndex(df["ts"]).as_unit("ns").asi8 // _NS_PER_MS
        value = df["value"].to_numpy(dtype=float)
        ok = np.isfinite(value)
        sensor = df["sensor"].astype(str).to_numpy()[ok]
        ts, value = ts[ok], value[ok]
        for i in range(0, len(sensor), WRITE_CHUNK):
            j = i + WRITE_CHUNK
            yield list(zip(sensor[i:j].tolist(), ts[i:j].tolist(), value[i:j].tolist(),
                           strict=True))
        return
    for batch in _chunks(readings, WRITE_CHUNK):
        rows = [(r.sensor, to_ms(r.ts), float(r.value)) for r in batch
                if math.isfinite(r.value)]
        if rows:
            yield rows


# -------------------------------------------------------------------------- interface


class Store(abc.ABC):
    """The history DB. Thread-safe (one lock per store); use as a context manager.

    Instants passed in must be timezone-aware; instants returned are UTC. Read methods
    return canonical frames: columns sensor (str), ts (datetime64[ns, UTC]), value (float),
    sorted by ts then sensor.
    """

    #: SQL of the backend, set by subclasses (``?`` parameters in all).
    INSERT_READING: str
    UPSERT_ESTIMATE: str
    UPSERT_PROGRESS: str

    def __init__(self, url: str, migrate: bool = True) -> None:
        self.url = url  # never contains credentials (see open_store)
        self._lock = threading.RLock()
        self._closed = False
        self.migrate = migrate  # bring an older schema up to date on open
        self.schema_version = 0  # the tables' version once open (older: not migrated)

    # --- backend primitives -------------------------------------------------------
    def _ts_arg(self, ms: int) -> Any:
        """A timestamp query parameter (epoch ms) as the backend's driver takes it: SQLite
        and CrateDB compare epoch milliseconds; PostgreSQL's columns are timestamptz."""
        return ms

    @abc.abstractmethod
    def _query(self, sql: str, args: Sequence[Any] = ()) -> list[Sequence[Any]]:
        """Rows of a SELECT (after making the tables' latest writes visible)."""

    @abc.abstractmethod
    def _write(self, table: str, sql: str, batches: Iterable[list[tuple]],
               before: tuple[str, list[Any]] | None = None) -> int:
        """Run ``sql`` for every row of every batch; the number of rows changed (or sent,
        where the backend cannot tell). before: (SQL, arguments) run first, in the same
        transaction where the backend has them."""

    @abc.abstractmethod
    def _close(self) -> None: ...

    # --- lifecycle -----------------------------------------------------------------
    def close(self) -> None:
        """Close the connection; later calls raise :class:`StoreError`. Idempotent."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url}>"

    def _check_open(self) -> None:
        if self._closed:
            raise StoreError(f"{self.url}: store is closed")

    def _check_version(self, found: str | None) -> int:
        """The schema version stored in ``meta`` (None: a new database)."""
        if found is None:
            return 0
        try:
            version = int(found)
        except ValueError:
            raise StoreError(f"{self.url}: unreadable schema version {found!r} in table meta") \
                from None
        if version > SCHEMA_VERSION:
            raise StoreError(
                f"{self.url}: history DB has schema version {version}, newer than this "
                f"pseudotwin supports ({SCHEMA_VERSION}); upgrade pseudotwin"
            )
        return version

    def _added_since(self, version: int) -> list[tuple[str, str, str]]:
        """(table, column, SQL type) of every column added after schema ``version``, in
        order (none for a new database, whose tables are created whole, nor for a store
        opened without ``migrate``)."""
        if version == 0 or not self.migrate:
            return []
        return [c for v in range(version + 1, SCHEMA_VERSION + 1) for c in MIGRATIONS.get(v, ())]

    def _migrated(self, version: int, added: Sequence[tuple[str, str, str]]) -> None:
        """Log a migration: from ``version`` (0: no version recorded, as after a CrateDB
        setup cut short before its meta row) with the columns ``added``; set the version
        the tables are at."""
        if version and version < SCHEMA_VERSION and not self.migrate:
            self.schema_version = version
            log.info("history store %s: schema version %d, read as it is (this build's is "
                     "%d; record, import or backfill of this build migrates it)", self.url,
                     version, SCHEMA_VERSION)
            return
        self.schema_version = SCHEMA_VERSION
        if (version and version < SCHEMA_VERSION) or added:
            cols = ", ".join(f"{t}.{c}" for t, c, _ in added) or "nothing to add"
            log.warning("history store %s: schema version %s → %d (added %s); an older "
                        "pseudotwin now refuses this database", self.url,
                        version or "unrecorded", SCHEMA_VERSION, cols)

    # --- readings ------------------------------------------------------------------
    def write_readings(self, readings: Iterable[Reading] | pd.DataFrame) -> int:
        """Store readings (Reading objects or a canonical frame); idempotent on (sensor, ts).

        A reading whose key is stored already is left as it is (readings are immutable);
        non-finite values are skipped. Returns the number of rows newly inserted (CrateDB:
        rows sent where the server does not report a count).
        """
        with self._lock:
            self._check_open()
            return self._write("readings", self.INSERT_READING, _reading_rows(readings))

    def read_readings(
        self,
        sensors: Iterable[str] | str | None,
        start: Instant | None = None,
        end: Instant | None = None,
    ) -> pd.DataFrame:
        """Readings of ``sensors`` (None: all) with start <= ts < end, as a canonical frame.

        Long spans are read in windows of :data:`READ_WINDOW` and concatenated.
        """
        names = _sensor_list(sensors)
        if names == []:
            return empty_readings()
        lo = to_ms(start) if start is not None else None
        hi = to_ms(end) if end is not None else None
        if lo is None or hi is None:
            span = self._span_ms(names)
            if span is None:
                return empty_readings()
            lo = span[0] if lo is None else lo
            hi = span[1] + 1 if hi is None else hi
        step = READ_WINDOW // _MS
        parts = [self._readings_between(names, a, min(a + step, hi)) for a in range(lo, hi, step)]
        parts = [p for p in parts if not p.empty]
        if not parts:
            return empty_readings()
        return parts[0] if len(parts) == 1 else pd.concat(parts, ignore_index=True)

    def iter_days(
        self,
        sensors: Iterable[str] | str | None,
        start_day: dt.date,
        end_day: dt.date,
        tz: str | dt.tzinfo,
    ) -> Iterator[tuple[dt.date, pd.DataFrame]]:
        """Every local day from ``start_day`` to ``end_day`` (both included) with its readings.

        One query per day, so memory stays bounded by one day's rows. A day runs from local
        midnight to the next local midnight in ``tz`` (23 h or 25 h on DST days); days
        without readings are yielded with an empty frame, so a backfill can mark them done.
        """
        zone = _tz(tz)
        names = _sensor_list(sensors)
        day = start_day
        while day <= end_day:
            if names == []:
                yield day, empty_readings()
            else:
                yield day, self._readings_between(names, *_day_bounds(day, zone))
            day += dt.timedelta(days=1)

    def last_readings_before(
        self, sensors: Iterable[str] | str, ts: Instant, since: Instant | None = None
    ) -> dict[str, tuple[dt.datetime, float]]:
        """sensor → (ts, value) of its last reading strictly before ``ts`` (for carry-over).

        since: ignore readings before this instant (bounds the search; CrateDB then scans
        only the relevant partitions). Sensors without such a reading are absent.
        """
        hi = to_ms(ts)
        lo = to_ms(since) if since is not None else None
        where = "sensor = ? AND ts < ?" + (" AND ts >= ?" if lo is not None else "")
        sql = f"SELECT ts, value FROM readings WHERE {where} ORDER BY ts DESC LIMIT 1"
        out: dict[str, tuple[dt.datetime, float]] = {}
        for sensor in _sensor_list(sensors) or []:
            args = [sensor, self._ts_arg(hi)] + ([self._ts_arg(lo)] if lo is not None else [])
            rows = self._locked_query(sql, args)
            if rows:
                out[sensor] = (from_ms(rows[0][0]), float(rows[0][1]))
        return out

    def count_readings(self, sensors: Iterable[str] | str | None = None) -> int:
        """Number of stored readings (of ``sensors``, or all)."""
        names = _sensor_list(sensors)
        if names == []:
            return 0
        where, args = self._sensor_clause(names)
        rows = self._locked_query(f"SELECT count(*) FROM readings{where}", args)
        return int(rows[0][0])

    def reading_range(
        self, sensors: Iterable[str] | str | None = None
    ) -> tuple[dt.datetime, dt.datetime] | None:
        """(first, last) reading time of ``sensors`` (or all), None if there is none."""
        span = self._span_ms(_sensor_list(sensors))
        return None if span is None else (from_ms(span[0]), from_ms(span[1]))

    def _span_ms(self, names: list[str] | None) -> tuple[int, int] | None:
        if names == []:
            return None
        where, args = self._sensor_clause(names)
        rows = self._locked_query(f"SELECT min(ts), max(ts) FROM readings{where}", args)
        if not rows or rows[0][0] is None:
            return None
        return int(rows[0][0]), int(rows[0][1])

    @staticmethod
    def _sensor_clause(names: list[str] | None, joiner: str = " WHERE ") -> tuple[str, list]:
        if names is None:
            return "", []
        # IN (?, ?, ...) rather than = ANY(?): the same SQL works in SQLite and CrateDB.
        return f"{joiner}sensor IN ({', '.join('?' * len(names))})", list(names)

    def _readings_between(self, names: list[str] | None, lo: int, hi: int) -> pd.DataFrame:
        where, args = self._sensor_clause(names, joiner=" AND ")
        rows = self._locked_query(
            f"SELECT sensor, ts, value FROM readings WHERE ts >= ? AND ts < ?{where} "
            "ORDER BY ts, sensor",
            [self._ts_arg(lo), self._ts_arg(hi), *args],
        )
        if not rows:
            return empty_readings()
        sensor, ms, value = (list(c) for c in zip(*rows, strict=True))
        return _readings_frame(sensor, ms, value)

    def _locked_query(self, sql: str, args: Sequence[Any] = ()) -> list[Sequence[Any]]:
        with self._lock:
            self._check_open()
            return self._query(sql, args)

    # --- estimates -----------------------------------------------------------------
    def write_estimates(self, rows: Iterable[EstimateRow]) -> int:
        """Upsert estimates on (twin, model, ts): writing one again leaves one row, the latest.

        ``written_at`` is set to now (UTC) by the store. Returns the rows written.
        """
        self._check_estimates()
        with self._lock:
            self._check_open()
            return self._write("estimates", self.UPSERT_ESTIMATE, _estimate_batches(rows))

    def replace_estimates(self, twin: str, start: Instant, end: Instant,
                          rows: Iterable[EstimateRow]) -> int:
        """Make ``twin``'s estimates with start <= ts < end exactly ``rows``: what a
        backfilled day does, so that none of an earlier artifact's rows of the day stay (a
        model it no longer runs, instants it no longer estimates). One transaction where
        the backend has them (CrateDB: the delete, then the writes). Returns the rows
        written; ValueError for a row of another twin or outside the span."""
        self._check_estimates()
        lo, hi = to_ms(start), to_ms(end)
        rows = list(rows)
        if stray := [r for r in rows if r.twin != twin or not lo <= to_ms(r.ts) < hi]:
            raise ValueError(f"replace_estimates({twin!r}, {start}, {end}): a row of "
                             f"{stray[0].twin!r} at {stray[0].ts} is not in it")
        delete = ("DELETE FROM estimates WHERE twin = ? AND ts >= ? AND ts < ?",
                  [twin, self._ts_arg(lo), self._ts_arg(hi)])
        with self._lock:
            self._check_open()
            return self._write("estimates", self.UPSERT_ESTIMATE, _estimate_batches(rows),
                               before=delete)

    def read_estimates(
        self,
        twin: str,
        start: Instant | None = None,
        end: Instant | None = None,
        model: str | None = None,
    ) -> pd.DataFrame:
        """Estimates of ``twin`` (optionally one model) with start <= ts < end.

        Columns :data:`ESTIMATE_COLUMNS`; ts and written_at datetime64[ns, UTC]; value and
        std float (NaN where not finite); source and lost str (lost a JSON list), None where
        not known (rows of schema version 1); sorted by ts, then model.
        """
        self._check_estimates()
        where = "twin = ?"
        args: list[Any] = [twin]
        if model is not None:
            where, args = where + " AND model = ?", [*args, model]
        if start is not None:
            where, args = where + " AND ts >= ?", [*args, self._ts_arg(to_ms(start))]
        if end is not None:
            where, args = where + " AND ts < ?", [*args, self._ts_arg(to_ms(end))]
        rows = self._locked_query(
            f"SELECT {', '.join(ESTIMATE_COLUMNS)} FROM estimates WHERE {where} "
            "ORDER BY ts, model",
            args,
        )
        cols = list(zip(*rows, strict=True)) if rows else [()] * len(ESTIMATE_COLUMNS)
        c = dict(zip(ESTIMATE_COLUMNS, cols, strict=True))
        return pd.DataFrame({
            "twin": pd.Series(list(c["twin"]), dtype=object).astype(str),
            "model": pd.Series(list(c["model"]), dtype=object).astype(str),
            "ts": _ms_to_index(list(c["ts"])),
            "value": _float_or_nan(c["value"]),
            "std": _float_or_nan(c["std"]),
            "quality": pd.Series(list(c["quality"]), dtype=object).astype(str),
            "artifact_hash": pd.Series(list(c["artifact_hash"]), dtype=object).astype(str),
            "written_at": _ms_to_index(list(c["written_at"])),
            "source": pd.Series(list(c["source"]), dtype=object),
            "lost": pd.Series(list(c["lost"]), dtype=object),
        })

    def _check_estimates(self) -> None:
        if self.schema_version < SCHEMA_VERSION:
            raise StoreError(f"{self.url}: the estimates table is at schema version "
                             f"{self.schema_version}, without source and lost; a writing "
                             "command of this build (record, import, backfill) migrates it")

    # --- backfill progress -----------------------------------------------------------
    def mark_day_done(self, twin: str, day: dt.date, n_estimates: int) -> None:
        """Record that the backfill of ``twin`` finished local ``day`` with n estimates."""
        row = (twin, day.isoformat(), int(n_estimates), to_ms(dt.datetime.now(dt.UTC)))
        with self._lock:
            self._check_open()
            self._write("backfill_progress", self.UPSERT_PROGRESS, [[row]])

    def done_days(self, twin: str) -> set[dt.date]:
        """The local days the backfill of ``twin`` finished."""
        rows = self._locked_query("SELECT day FROM backfill_progress WHERE twin = ?", [twin])
        return {dt.date.fromisoformat(r[0]) for r in rows}


# ------------------------------------------------------------------------------ SQLite


class SQLiteStore(Store):
    """SQLite file (or ``:memory:``): WAL mode, busy timeout, one transaction per write call."""

    DDL = (
        # WITHOUT ROWID: the primary key *is* the table's b-tree, so the (sensor, ts) index
        # the queries need costs no second copy of every row.
        "CREATE TABLE IF NOT EXISTS readings (sensor TEXT NOT NULL, ts INTEGER NOT NULL, "
        "value REAL NOT NULL, PRIMARY KEY (sensor, ts)) WITHOUT ROWID",
        # Time-range queries over all sensors (reading_range, read_readings(None, ...)).
        "CREATE INDEX IF NOT EXISTS readings_ts ON readings (ts)",
        "CREATE TABLE IF NOT EXISTS estimates (twin TEXT NOT NULL, model TEXT NOT NULL, "
        "ts INTEGER NOT NULL, value REAL, std REAL, quality TEXT NOT NULL, "
        "artifact_hash TEXT NOT NULL, written_at INTEGER NOT NULL, source TEXT, lost TEXT, "
        "PRIMARY KEY (twin, model, ts)) WITHOUT ROWID",
        "CREATE TABLE IF NOT EXISTS backfill_progress (twin TEXT NOT NULL, day TEXT NOT NULL, "
        "estimates INTEGER NOT NULL, finished_at INTEGER NOT NULL, "
        "PRIMARY KEY (twin, day)) WITHOUT ROWID",
    )
    INSERT_READING = "INSERT OR IGNORE INTO readings (sensor, ts, value) VALUES (?, ?, ?)"
    UPSERT_ESTIMATE = (
        "INSERT INTO estimates (twin, model, ts, value, std, quality, artifact_hash, "
        "written_at, source, lost) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) "
        "ON CONFLICT (twin, model, ts) DO UPDATE "
        "SET value = excluded.value, std = excluded.std, quality = excluded.quality, "
        "artifact_hash = excluded.artifact_hash, written_at = excluded.written_at, "
        "source = excluded.source, lost = excluded.lost"
    )
    UPSERT_PROGRESS = (
        "INSERT INTO backfill_progress (twin, day, estimates, finished_at) VALUES (?, ?, ?, ?) "
        "ON CONFLICT (twin, day) DO UPDATE SET estimates = excluded.estimates, "
        "finished_at = excluded.finished_at"
    )

    def __init__(self, path: str, url: str | None = None, existing: bool = False,
                 migrate: bool = True, durable: bool = False) -> None:
        super().__init__(url or (path if path == ":memory:" else f"sqlite:///{path}"), migrate)
        self.path = path
        self.durable = durable
        if path != ":memory:":
            parent = Path(path).parent
            # No silent mkdir: a mistyped sqlite:/// URL (relative vs. absolute) must fail
            # loudly instead of creating a fresh, empty DB somewhere else.
            if not parent.is_dir():
                raise StoreError(f"{self.url}: directory {parent} does not exist")
            if existing and not Path(path).is_file():
                raise StoreError(f"{self.url}: no such database file (nothing to read: "
                                 "import or record readings into it first)")
        try:
            # isolation_level=None: no implicit transactions; writes use BEGIN IMMEDIATE
            # so a writer takes the lock up front and busy_timeout applies (a deferred
            # transaction upgrading to a write lock can fail with SQLITE_BUSY at once).
            self._conn = sqlite3.connect(
                path, timeout=SQLITE_BUSY_TIMEOUT_MS / 1000, isolation_level=None,
                check_same_thread=False,  # the RLock serializes use across threads
            )
        except sqlite3.Error as exc:
            raise StoreError(f"{self.url}: cannot open ({exc})") from None
        try:
            self._setup()
        except BaseException:
            self._conn.close()
            raise

    def _setup(self) -> None:
        try:
            self._conn.execute(f"PRAGMA busy_timeout = {SQLITE_BUSY_TIMEOUT_MS}")
            if self.path != ":memory:":
                mode = self._conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
                if str(mode).lower() != "wal":  # e.g. some network file systems
                    log.warning("%s: WAL mode unavailable (journal_mode=%s); concurrent "
                                "readers may wait for writers", self.url, mode)
            # NORMAL in WAL mode: a power loss may drop the last transactions, never
            # corrupt the file, and no fsync per write. FULL syncs the WAL at each commit:
            # for the recorder, which tells the broker a reading is safe once committed.
            self._conn.execute(f"PRAGMA synchronous = {'FULL' if self.durable else 'NORMAL'}")
            self._conn.execute("CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, "
                               "value TEXT NOT NULL) WITHOUT ROWID")
            row = self._conn.execute(
                "SELECT value FROM meta WHERE name = 'schema_version'").fetchone()
            version = self._check_version(None if row is None else row[0])
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                if version:  # another process may have migrated it since: read it again
                    row = self._conn.execute(
                        "SELECT value FROM meta WHERE name = 'schema_version'").fetchone()
                    version = self._check_version(row[0])
                for stmt in self.DDL:
                    self._conn.execute(stmt)
                added = self._added_since(version)
                for table, column, kind in added:
                    have = {r[1] for r in self._conn.execute(f"PRAGMA table_info({table})")}
                    if column not in have:
                        self._conn.execute(f"ALTER TABLE {table} ADD COLUMN {column} {kind}")
                if self.migrate or version == 0:
                    self._conn.execute(ESTIMATES_INDEX)
                if version == 0:
                    self._conn.execute("INSERT OR IGNORE INTO meta (name, value) VALUES "
                                       "('schema_version', ?)", (str(SCHEMA_VERSION),))
                elif version < SCHEMA_VERSION and self.migrate:
                    self._conn.execute("UPDATE meta SET value = ? WHERE name = "
                                       "'schema_version'", (str(SCHEMA_VERSION),))
                self._conn.execute("COMMIT")
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            self._migrated(version, added)
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) and "busy" not in str(exc):
                raise StoreError(f"{self.url}: not a usable SQLite history DB ({exc})") \
                    from None
            # Another process held the file's write lock past the busy timeout (an import, a
            # backfill, the recorder's write): busy, not broken.
            wait = SQLITE_BUSY_TIMEOUT_MS / 1000
            raise StoreError(f"{self.url}: busy: another process held its lock for more than "
                             f"{wait:g} s ({exc}); try again once it is done") from None
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.url}: not a usable SQLite history DB ({exc})") from None

    def _query(self, sql: str, args: Sequence[Any] = ()) -> list[Sequence[Any]]:
        try:
            return self._conn.execute(sql, tuple(args)).fetchall()
        except sqlite3.Error as exc:
            raise StoreError(f"{self.url}: query failed ({exc})") from None

    def _write(self, table: str, sql: str, batches: Iterable[list[tuple]],
               before: tuple[str, list[Any]] | None = None) -> int:
        # One transaction per call: a write_* call lands completely or not at all.
        n = 0
        try:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                if before is not None:
                    self._conn.execute(before[0], before[1])
                for batch in batches:
                    cur = self._conn.executemany(sql, batch)
                    n += max(cur.rowcount, 0)  # INSERT OR IGNORE: ignored rows count 0
                self._conn.execute("COMMIT")
            except BaseException:
                # SQLite may have rolled back already (SQLITE_FULL, SQLITE_IOERR): a second
                # ROLLBACK would replace the real error with "no transaction is active".
                if self._conn.in_transaction:
                    self._conn.execute("ROLLBACK")
                raise
        except sqlite3.Error as exc:
            raise StoreError(f"{self.url}: writing {table} failed ({exc})") from None
        return n

    def _close(self) -> None:
        self._conn.close()


# ------------------------------------------------------------------------------ CrateDB


class CrateStore(Store):
    """CrateDB through the ``crate`` DB-API client (HTTP), monthly partitions.

    CrateDB is eventually visible: a write shows up in SELECTs after the table's next
    refresh (default every second). This store runs ``REFRESH TABLE`` before reading a
    table it wrote since its last read, so a store reads its own writes; writes of other
    processes show up within the refresh interval.

    Writes are chunked bulk requests (``bulk_args``); there are no transactions, so a failed
    call may have stored some rows — harmless, since every write here is idempotent.
    """

    DDL = (
        "CREATE TABLE IF NOT EXISTS readings (sensor TEXT NOT NULL, "
        "ts TIMESTAMP WITH TIME ZONE NOT NULL, value DOUBLE PRECISION NOT NULL, "
        "month TIMESTAMP WITH TIME ZONE GENERATED ALWAYS AS date_trunc('month', ts), "
        # CrateDB requires the partition column in the primary key.
        "PRIMARY KEY (sensor, ts, month)) PARTITIONED BY (month)",
        "CREATE TABLE IF NOT EXISTS estimates (twin TEXT NOT NULL, model TEXT NOT NULL, "
        "ts TIMESTAMP WITH TIME ZONE NOT NULL, value DOUBLE PRECISION, "
        "std DOUBLE PRECISION, quality TEXT NOT NULL, artifact_hash TEXT NOT NULL, "
        "written_at TIMESTAMP WITH TIME ZONE NOT NULL, source TEXT, lost TEXT, "
        "month TIMESTAMP WITH TIME ZONE GENERATED ALWAYS AS date_trunc('month', ts), "
        "PRIMARY KEY (twin, model, ts, month)) PARTITIONED BY (month)",
        "CREATE TABLE IF NOT EXISTS backfill_progress (twin TEXT NOT NULL, day TEXT NOT NULL, "
        "estimates INTEGER NOT NULL, finished_at TIMESTAMP WITH TIME ZONE NOT NULL, "
        "PRIMARY KEY (twin, day))",
    )
    META_DDL = "CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT NOT NULL)"
    # The conflict target must match the whole primary key, generated month included;
    # month itself is computed by CrateDB from ts and never sent.
    INSERT_READING = (
        "INSERT INTO readings (sensor, ts, value) VALUES (?, ?, ?) "
        "ON CONFLICT (sensor, ts, month) DO NOTHING"
    )
    UPSERT_ESTIMATE = (
        "INSERT INTO estimates (twin, model, ts, value, std, quality, artifact_hash, "
        "written_at, source, lost) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) "
        "ON CONFLICT (twin, model, ts, month) "
        "DO UPDATE SET value = excluded.value, std = excluded.std, "
        "quality = excluded.quality, artifact_hash = excluded.artifact_hash, "
        "written_at = excluded.written_at, source = excluded.source, lost = excluded.lost"
    )
    UPSERT_PROGRESS = (
        "INSERT INTO backfill_progress (twin, day, estimates, finished_at) VALUES (?, ?, ?, ?) "
        "ON CONFLICT (twin, day) DO UPDATE SET estimates = excluded.estimates, "
        "finished_at = excluded.finished_at"
    )

    def __init__(self, servers: list[str], schema: str, url: str, migrate: bool = True) -> None:
        super().__init__(url, migrate)
        try:
            from crate import client as crate_client
            from crate.client import exceptions as crate_exceptions
        except ImportError:
            raise StoreError(f"{url}: the CrateDB store needs the 'crate' package "
                             "(pip install crate)") from None
        self._db_error: type[Exception] = crate_exceptions.Error
        self.servers = servers
        self.schema = schema
        self._dirty: set[str] = set()
        user = os.environ.get(ENV_CRATE_USER) or None
        password = os.environ.get(ENV_CRATE_PASSWORD) or None
        log.info("history store: CrateDB %s, schema %s, %s", ", ".join(servers), schema,
                 f"user {user}" if user else "no user")  # never the password
        try:
            self._conn = crate_client.connect(
                servers, username=user, password=password, schema=schema,
                timeout=CRATE_TIMEOUT_S,
            )
        except self._db_error as exc:
            raise StoreError(f"{url}: cannot connect to CrateDB ({exc})") from None
        try:
            self._setup()
        except BaseException:
            self._conn.close()
            raise

    def _run(self, sql: str, args: Sequence[Any] | None = None) -> list[Sequence[Any]]:
        cur = self._conn.cursor()
        try:
            cur.execute(sql, list(args) if args else None)
        except self._db_error as exc:
            cur.close()
            raise StoreError(f"{self.url}: {_first_line(exc)}") from None
        try:
            return cur.fetchall()
        except self._db_error:  # a response without a result set (some DDL)
            return []
        finally:
            cur.close()

    def _setup(self) -> None:
        self._run(self.META_DDL)
        rows = self._run("SELECT value FROM meta WHERE name = ?", ["schema_version"])
        version = self._check_version(rows[0][0] if rows else None)
        for stmt in self.DDL:
            self._run(stmt)
        # No transactions in CrateDB: a migration cut short, or a version-1 setup cut short
        # before its meta row (version 0 with old tables), has some columns already, and
        # another process may be adding them at this very moment (the daemon and the
        # recorder started together after an upgrade): each column is looked for first,
        # and an ALTER that fails is forgiven once the column is there.
        added: list[tuple[str, str, str]] = []
        if version < SCHEMA_VERSION and (self.migrate or version == 0):
            for table, column, kind in (c for v in sorted(MIGRATIONS) for c in MIGRATIONS[v]):
                if self._has_column(table, column):
                    continue
                try:
                    self._run(f"ALTER TABLE {table} ADD COLUMN {column} {kind}")
                except StoreError:
                    if not self._has_column(table, column):
                        raise
                added.append((table, column, kind))
        if version == 0:
            self._run("INSERT INTO meta (name, value) VALUES (?, ?) ON CONFLICT (name) "
                      "DO NOTHING", ["schema_version", str(SCHEMA_VERSION)])
        elif version < SCHEMA_VERSION and self.migrate:
            self._run("UPDATE meta SET value = ? WHERE name = ?",
                      [str(SCHEMA_VERSION), "schema_version"])
        self._migrated(version, added)

    def _has_column(self, table: str, column: str) -> bool:
        try:
            self._run(f"SELECT {column} FROM {table} LIMIT 1")
        except StoreError:  # ColumnUnknownException
            return False
        return True

    def _query(self, sql: str, args: Sequence[Any] = ()) -> list[Sequence[Any]]:
        stale = [t for t in _FROM.findall(sql) if t in self._dirty]
        if stale:
            self._run(f"REFRESH TABLE {', '.join(stale)}")
            self._dirty.difference_update(stale)
        return self._run(sql, args)

    def _write(self, table: str, sql: str, batches: Iterable[list[tuple]],
               before: tuple[str, list[Any]] | None = None) -> int:
        """Every batch is sent, even after one with refused rows: a row CrateDB always
        refuses must not keep the rows after it out (RowsRejected names them all).
        ``before`` runs first, on its own (CrateDB has no transactions: between the two,
        and after a failure, readers see it done and the rows not yet written; a backfill
        marks the day done only after both, so a rerun completes it)."""
        n, sent = 0, 0
        if before is not None:
            # A DELETE sees only refreshed rows (CrateDB's refresh): this store's writes
            # and other processes' of the last second too.
            self._run(f"REFRESH TABLE {table}")
            self._dirty.discard(table)
            self._run(*before)
            self._dirty.add(table)
        refused: list[tuple[int, tuple, str | None]] = []
        for batch in batches:
            cur = self._conn.cursor()
            try:
                results = cur.executemany(sql, batch)
            except self._db_error as exc:
                raise StoreError(f"{self.url}: writing {table} failed ({_first_line(exc)})") \
                    from None
            finally:
                cur.close()
            self._dirty.add(table)
            written, failed = _bulk_count(results, len(batch))
            n += written
            refused += [(sent + i, batch[i], msg) for i, msg in failed]
            sent += len(batch)
        if refused:
            i, _, msg = refused[0]
            raise RowsRejected(
                f"{self.url}: CrateDB rejected {len(refused)} of {sent} rows of {table}; "
                f"first: row {i} ({msg or 'no error message given'})",
                [row for _, row, _ in refused], n)
        return n

    def _close(self) -> None:
        self._conn.close()


_FROM = re.compile(r"\bFROM\s+(\w+)", re.IGNORECASE)


def _first_line(exc: BaseException) -> str:
    text = str(getattr(exc, "message", None) or exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _bulk_count(results: list[dict] | None, sent: int) -> tuple[int, list[tuple[int, str | None]]]:
    """(rows changed, [(index, error message) of each failed row]) of one bulk request.

    Per-row results: rowcount 1 (written), 0 (ON CONFLICT DO NOTHING skipped it),
    -1 (unknown: counted as sent), -2 (failed, with ``error_message`` or, in newer
    CrateDB releases, ``error: {code, message}``).
    """
    if not results:
        return sent, []
    failed = []
    written = 0
    for i, r in enumerate(results):
        rc = r.get("rowcount")
        if isinstance(rc, int) and rc <= -2:
            err = r.get("error")
            msg = r.get("error_message") or (err.get("message") if isinstance(err, dict)
                                             else err)
            failed.append((i, str(msg) if msg else None))
        else:
            written += rc if isinstance(rc, int) and rc >= 0 else 1
    return written, failed


# ------------------------------------------------------------------------------ factory


def open_store(url: str | os.PathLike[str], existing: bool = False,
               migrate: bool = True, durable: bool = False) -> Store:
    """Open (creating tables on first use) the store at ``url``; see the module docstring.

    existing: the caller only reads what is there (train, evaluate, backfill): a SQLite file
    that does not exist is an error, not a new empty database (a mistyped path).
    migrate: bring a store of an older schema version up to date; False for callers that
    only read readings (its estimates then cannot be read or written).
    durable: a write that returned survives a power cut (SQLite: synchronous FULL, an fsync
    per write; PostgreSQL and CrateDB commit to disk by default, their servers' settings).
    Raises ConfigError for a malformed URL, StoreError when the database cannot be used.
    """
    text = os.fspath(url).strip()
    if not text:
        raise ConfigError("empty history store URL")
    scheme = text.split("://", 1)[0].lower() if "://" in text else ""
    if scheme in ("crate", "crate+http", "crate+https"):
        return _open_crate(text, "https" if scheme == "crate+https" else "http", migrate)
    if scheme in ("postgresql", "postgres"):
        from pseudotwin.history.postgres import open_postgres  # psycopg only when used

        return open_postgres(text, migrate)
    if is_memory_url(text):
        if existing:
            raise ConfigError(f"{text!r} is a store in memory: it holds nothing to read "
                              "(give the history database's file path or URL)")
        return SQLiteStore(":memory:", migrate=migrate)
    if scheme == "sqlite":
        rest = text[len("sqlite://"):]
        if text == PATHLESS_SQLITE:
            raise ConfigError(f"{text!r}: no file path after sqlite:/// (a store in memory "
                              "is sqlite:// or :memory:)")
        if not rest.startswith("/"):
            raise ConfigError(f"{text!r}: expected sqlite:///relative.db or "
                              "sqlite:////absolute/path.db")
        return SQLiteStore(rest[1:], url=text, existing=existing, migrate=migrate,
                           durable=durable)
    if scheme:
        raise ConfigError(f"{text!r}: unsupported history store (use a SQLite file path, "
                          "sqlite:///path, postgresql://host/db or crate://host:4200)")
    return SQLiteStore(text, existing=existing, migrate=migrate, durable=durable)


def _with_port(host: str) -> str:
    """``host`` with CrateDB's HTTP port 4200 added when it names none (the client would
    otherwise use the scheme's 80/443); IPv6 hosts are bracketed, ``[::1]:4200``."""
    after_ipv6 = host.rsplit("]", 1)[-1]
    return host if ":" in after_ipv6 else f"{host}:4200"


def _open_crate(text: str, http: str, migrate: bool = True) -> CrateStore:
    parts = urlsplit(text)
    netloc = parts.netloc
    if "@" in netloc:
        # Credentials in a URL leak into configs, logs and process lists.
        raise ConfigError(f"crate URL must not contain credentials; set {ENV_CRATE_USER} "
                          f"and {ENV_CRATE_PASSWORD} instead")
    hosts = [h.strip() for h in netloc.split(",") if h.strip()]
    if not hosts:
        raise ConfigError(f"{text!r}: no CrateDB host (expected crate://host:4200)")
    if parts.path not in ("", "/"):
        raise ConfigError(f"{text!r}: unexpected path {parts.path!r} "
                          "(choose the schema with ?schema=NAME)")
    query = parse_qs(parts.query, keep_blank_values=True)
    unknown = sorted(set(query) - {"schema"})
    if unknown:
        raise ConfigError(f"{text!r}: unknown option(s) {', '.join(unknown)} (known: schema)")
    schema = query.get("schema", [DEFAULT_CRATE_SCHEMA])[-1].strip()
    if not schema.isidentifier():
        raise ConfigError(f"{text!r}: schema {schema!r} is not a plain identifier")
    servers = [f"{http}://{_with_port(h)}" for h in hosts]
    return CrateStore(servers, schema, url=text, migrate=migrate)
