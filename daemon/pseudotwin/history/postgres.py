"""The PostgreSQL backend of the history store (TimescaleDB hypertables when present).

Through psycopg 3 (libpq). Timestamps are ``timestamptz`` columns, so Grafana, Home
Assistant's tools and plain SQL see real times; they hold the same millisecond instants as
the other backends (written exactly, read back as epoch milliseconds by a binary loader).
Text keys use ``COLLATE "C"``: rows come back in the order Python sorts strings, whatever
the database's locale.

URL forms (:func:`pseudotwin.history.store.open_store`):

============================================================  ================================
``postgresql://host/dbname``                                  port 5432, the OS user's name
``postgres://pt@db.example:5433/history``                     user ``pt`` (no password!)
``postgresql://host/db?schema=building7``                     tables in schema ``building7``
                                                              (default ``pseudotwin``)
``postgresql://host/db?timescaledb=no``                       plain tables even where
                                                              TimescaleDB is installed
``postgresql://host/db?sslmode=verify-full&connect_timeout=5``  any other libpq parameter
``postgresql:///history?host=/run/postgresql``                over a Unix socket
============================================================  ================================

A password never goes into the URL (a URL ends up in configs and logs): libpq takes it from
``PGPASSWORD`` or the password file (``~/.pgpass``, ``PGPASSFILE``); the other ``PG*``
variables (``PGUSER``, ``PGHOST``, ``PGSSLMODE`` …) work as for ``psql``.

``timescaledb=auto`` (default): when the store creates its tables and the TimescaleDB
extension is installed in the database (or can be created there), ``readings`` and
``estimates`` become hypertables partitioned by ``ts``; otherwise plain tables with a
``ts`` index. ``yes``: refuse to create plain tables. ``no``: plain tables. An existing
store keeps the layout it was created with.

Outage: every driver error is a :class:`StoreError` (the recorder then spools to disk and
retries), and a store whose connection broke reconnects on its next call.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from typing import Any, Literal
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import psycopg
from psycopg import sql
from psycopg.adapt import Buffer, Loader
from psycopg.conninfo import conninfo_to_dict
from psycopg.pq import Format

from pseudotwin.errors import ConfigError
from pseudotwin.history.store import (
    ESTIMATES_INDEX,
    SCHEMA_VERSION,
    Store,
    StoreError,
    from_ms,
)

__all__ = ["PostgresStore", "open_postgres"]

log = logging.getLogger(__name__)

DEFAULT_SCHEMA = "pseudotwin"
#: Used unless the URL sets connect_timeout: an unreachable server must turn into a
#: StoreError (and the recorder's spool) within seconds, not the OS's TCP timeout.
CONNECT_TIMEOUT_S = 10
#: Used unless the URL sets them: a server cut off mid-write (a network partition, a
#: rebooted router) must fail the write within a minute, so that the recorder spools, not
#: block its worker until the OS gives up on the connection (~15 min).
TCP_DEFAULTS = (("keepalives", "1"), ("keepalives_idle", "30"), ("keepalives_interval", "10"),
                ("keepalives_count", "3"), ("tcp_user_timeout", "60000"))

Timescale = Literal["auto", "yes", "no"]
TIMESCALE_CHOICES: tuple[Timescale, ...] = ("auto", "yes", "no")

#: Epoch ms of PostgreSQL's own epoch 2000-01-01 UTC, where binary timestamps count from.
_PG_EPOCH_MS = 946_684_800_000

#: Per table: the key's positions in the rows Store hands to _write, and whether the last
#: of two rows with one key wins (upserts) or the first (readings are immutable).
_KEYS = {"readings": ((0, 1), False), "estimates": ((0, 1, 2), True),
         "backfill_progress": ((0, 1), True)}


def _tstz(col: str) -> str:
    """SQL: epoch ms (bigint) → timestamptz, exactly (to_timestamp of whole seconds is
    exact; float arithmetic on the milliseconds could be off by a microsecond)."""
    return f"(to_timestamp({col} / 1000) + ({col} % 1000) * interval '1 millisecond')"


class _EpochMsLoader(Loader):
    """timestamptz (binary: int64 µs since 2000-01-01 UTC) → epoch ms, floor, as Store's
    base class expects from every backend."""

    format = Format.BINARY

    def load(self, data: Buffer) -> int:
        return int.from_bytes(data, "big", signed=True) // 1000 + _PG_EPOCH_MS


def hypertables_wanted(option: Timescale, installed: bool, available: bool) -> bool | None:
    """Whether new tables become hypertables: True, False, or None (try creating the
    extension first; keep plain tables if that fails, unless ``option`` is "yes")."""
    if option == "no":
        return False
    if installed:
        return True
    if available:
        return None
    if option == "yes":
        raise StoreError("timescaledb=yes, but the TimescaleDB extension is not installed "
                         "on this PostgreSQL server (use timescaledb=auto for plain tables)")
    return False


class PostgresStore(Store):
    """PostgreSQL (optionally TimescaleDB) through one psycopg connection in autocommit
    mode; each write call is one transaction."""

    # One statement per chunk with one array per column (unnest): a round trip per chunk,
    # not per row, and no staging table. Timestamps travel as epoch-ms bigints.
    INSERT_READING = (
        f"INSERT INTO readings (sensor, ts, value) SELECT s, {_tstz('t')}, v "
        "FROM unnest(?::text[], ?::bigint[], ?::float8[]) AS u(s, t, v) "
        "ON CONFLICT (sensor, ts) DO NOTHING"
    )
    UPSERT_ESTIMATE = (
        "INSERT INTO estimates (twin, model, ts, value, std, quality, artifact_hash, "
        f"written_at, source, lost) SELECT tw, m, {_tstz('t')}, v, sd, q, h, {_tstz('w')}, "
        "src, l FROM unnest(?::text[], ?::text[], ?::bigint[], ?::float8[], ?::float8[], "
        "?::text[], ?::text[], ?::bigint[], ?::text[], ?::text[]) "
        "AS u(tw, m, t, v, sd, q, h, w, src, l) "
        "ON CONFLICT (twin, model, ts) DO UPDATE "
        "SET value = excluded.value, std = excluded.std, quality = excluded.quality, "
        "artifact_hash = excluded.artifact_hash, written_at = excluded.written_at, "
        "source = excluded.source, lost = excluded.lost"
    )
    UPSERT_PROGRESS = (
        f"INSERT INTO backfill_progress (twin, day, estimates, finished_at) "
        f"SELECT tw, d, e, {_tstz('f')} "
        "FROM unnest(?::text[], ?::text[], ?::int[], ?::bigint[]) AS u(tw, d, e, f) "
        "ON CONFLICT (twin, day) DO UPDATE SET estimates = excluded.estimates, "
        "finished_at = excluded.finished_at"
    )
    DDL = (
        'CREATE TABLE IF NOT EXISTS readings (sensor TEXT COLLATE "C" NOT NULL, '
        "ts TIMESTAMPTZ NOT NULL, value DOUBLE PRECISION NOT NULL, PRIMARY KEY (sensor, ts))",
        'CREATE TABLE IF NOT EXISTS estimates (twin TEXT COLLATE "C" NOT NULL, '
        'model TEXT COLLATE "C" NOT NULL, ts TIMESTAMPTZ NOT NULL, value DOUBLE PRECISION, '
        "std DOUBLE PRECISION, quality TEXT NOT NULL, artifact_hash TEXT NOT NULL, "
        "written_at TIMESTAMPTZ NOT NULL, source TEXT, lost TEXT, "
        "PRIMARY KEY (twin, model, ts))",
        'CREATE TABLE IF NOT EXISTS backfill_progress (twin TEXT COLLATE "C" NOT NULL, '
        "day TEXT NOT NULL, estimates INTEGER NOT NULL, finished_at TIMESTAMPTZ NOT NULL, "
        "PRIMARY KEY (twin, day))",
    )
    #: Plain tables only: TimescaleDB indexes a hypertable's time column itself.
    PLAIN_DDL = ("CREATE INDEX IF NOT EXISTS readings_ts ON readings (ts)",)
    HYPERTABLES = ("readings", "estimates")

    def __init__(self, conninfo: str, schema: str, timescaledb: Timescale, url: str,
                 migrate: bool = True) -> None:
        super().__init__(url, migrate)
        self.schema = schema
        self.timescaledb = timescaledb
        self.hypertables = False
        self._conninfo = conninfo
        self._conn = self._connect()
        try:
            self._setup()
        except BaseException:
            self._conn.close()
            raise

    # --- connection ----------------------------------------------------------------
    def _connect(self) -> psycopg.Connection[Any]:
        try:
            conn = psycopg.connect(self._conninfo, autocommit=True,
                                   application_name="pseudotwin")
        except psycopg.Error as exc:
            raise StoreError(f"{self.url}: cannot connect to PostgreSQL ({_first_line(exc)})") \
                from None
        conn.adapters.register_loader("timestamptz", _EpochMsLoader)
        try:
            # Unqualified names are this store's tables (schema created in _setup).
            conn.execute(sql.SQL("SET search_path TO {}").format(sql.Identifier(self.schema)))
        except psycopg.Error as exc:
            conn.close()
            raise StoreError(f"{self.url}: {_first_line(exc)}") from None
        log.info("history store: PostgreSQL %s, database %s, schema %s",
                 conn.info.host or "(socket)", conn.info.dbname, self.schema)
        return conn

    def _live_conn(self) -> psycopg.Connection[Any]:
        if self._conn.closed:  # broken by an outage: the server may be back
            self._conn = self._connect()
        return self._conn

    def _ts_arg(self, ms: int) -> Any:
        return from_ms(ms)  # psycopg sends a datetime as timestamptz, exact to the µs

    # --- setup ---------------------------------------------------------------------
    def _setup(self) -> None:
        conn = self._conn
        try:
            with conn.transaction():
                # Two processes opening a new store at once (recorder and backfill) would
                # race on CREATE TABLE: serialize them per schema.
                conn.execute("SELECT pg_advisory_xact_lock(hashtext(%s))",
                             [f"pseudotwin store {self.schema}"])
                if not conn.execute("SELECT 1 FROM pg_namespace WHERE nspname = %s",
                                    [self.schema]).fetchone():
                    conn.execute(sql.SQL("CREATE SCHEMA {}").format(
                        sql.Identifier(self.schema)))
                conn.execute("CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, "
                             "value TEXT NOT NULL)")
                row = conn.execute("SELECT value FROM meta WHERE name = 'schema_version'"
                                   ).fetchone()
                version = self._check_version(None if row is None else row[0])
                added = self._added_since(version)
                if version == 0:
                    self._create_tables(conn)
                    conn.execute(ESTIMATES_INDEX)
                    conn.execute("INSERT INTO meta (name, value) VALUES ('schema_version', "
                                 "%s) ON CONFLICT (name) DO NOTHING", [str(SCHEMA_VERSION)])
                else:
                    self.hypertables = self._is_hypertable(conn, "readings")
                    for table, column, kind in added:
                        conn.execute(sql.SQL("ALTER TABLE {} ADD COLUMN IF NOT EXISTS {} {}")
                                     .format(sql.Identifier(table), sql.Identifier(column),
                                             sql.SQL(kind)))
                    if self.migrate:
                        conn.execute(ESTIMATES_INDEX)
                    if version < SCHEMA_VERSION and self.migrate:
                        conn.execute("UPDATE meta SET value = %s WHERE name = "
                                     "'schema_version'", [str(SCHEMA_VERSION)])
        except psycopg.Error as exc:
            raise StoreError(f"{self.url}: cannot set up the history tables "
                             f"({_first_line(exc)})") from None
        self._migrated(version, added)
        log.info("history store %s: %s", self.url,
                 "TimescaleDB hypertables" if self.hypertables else "plain tables")

    def _create_tables(self, conn: psycopg.Connection[Any]) -> None:
        installed = self._timescale_schema(conn) is not None
        available = bool(conn.execute("SELECT 1 FROM pg_available_extensions WHERE name = "
                                      "'timescaledb'").fetchone())
        wanted = hypertables_wanted(self.timescaledb, installed, available)
        if wanted is None:
            wanted = self._try_create_extension(conn)
        for stmt in self.DDL:
            conn.execute(stmt)
        if not wanted:
            for stmt in self.PLAIN_DDL:
                conn.execute(stmt)
            return
        ns = self._timescale_schema(conn)
        for table in self.HYPERTABLES:
            conn.execute(sql.SQL("SELECT {}.create_hypertable(%s, 'ts', if_not_exists => TRUE)")
                         .format(sql.Identifier(ns or "public")),
                         [f'"{self.schema}".{table}'])  # quoted as CREATE SCHEMA did
        self.hypertables = True

    def _try_create_extension(self, conn: psycopg.Connection[Any]) -> bool:
        try:
            with conn.transaction():  # a savepoint: a refusal must not abort the setup
                conn.execute("CREATE EXTENSION IF NOT EXISTS timescaledb")
            return True
        except psycopg.Error as exc:
            if self.timescaledb == "yes":
                raise StoreError(f"{self.url}: timescaledb=yes, but the extension cannot be "
                                 f"created ({_first_line(exc)})") from None
            log.warning("%s: TimescaleDB is available but could not be enabled (%s); using "
                        "plain tables", self.url, _first_line(exc))
            return False

    @staticmethod
    def _timescale_schema(conn: psycopg.Connection[Any]) -> str | None:
        row = conn.execute("SELECT extnamespace::regnamespace::text FROM pg_extension "
                           "WHERE extname = 'timescaledb'").fetchone()
        return None if row is None else str(row[0])

    def _is_hypertable(self, conn: psycopg.Connection[Any], table: str) -> bool:
        if self._timescale_schema(conn) is None:
            return False
        return bool(conn.execute(
            "SELECT 1 FROM timescaledb_information.hypertables WHERE hypertable_schema = %s "
            "AND hypertable_name = %s", [self.schema, table]).fetchone())

    # --- Store primitives ------------------------------------------------------------
    def _query(self, sql_text: str, args: Sequence[Any] = ()) -> list[Sequence[Any]]:
        try:
            cur = self._live_conn().execute(_pyformat(sql_text), list(args), binary=True)
            return cur.fetchall()
        except psycopg.Error as exc:
            raise StoreError(f"{self.url}: query failed ({_first_line(exc)})") from None

    def _write(self, table: str, sql_text: str, batches: Iterable[list[tuple]],
               before: tuple[str, list[Any]] | None = None) -> int:
        key, keep_last = _KEYS[table]
        stmt = _pyformat(sql_text)
        n = 0
        try:
            conn = self._live_conn()
            # One transaction per call, as in SQLite: a write_* call lands completely or not
            # at all.
            with conn.transaction(), conn.cursor() as cur:
                if before is not None:
                    cur.execute(_pyformat(before[0]), before[1])
                for batch in batches:
                    rows = _unique(batch, key, keep_last)
                    if rows:
                        cur.execute(stmt, [list(col) for col in zip(*rows, strict=True)])
                        n += max(cur.rowcount, 0)  # DO NOTHING: skipped rows count 0
        except psycopg.Error as exc:
            raise StoreError(f"{self.url}: writing {table} failed ({_first_line(exc)})") \
                from None
        return n

    def _close(self) -> None:
        self._conn.close()


def _unique(rows: list[tuple], key: tuple[int, ...], keep_last: bool) -> list[tuple]:
    """One row per key: one INSERT cannot touch a row twice (DO UPDATE raises), and the row
    kept must be the one that row-by-row writing would leave (SQLite's semantics)."""
    out: dict[tuple, tuple] = {}
    for row in rows:
        k = tuple(row[i] for i in key)
        if keep_last or k not in out:
            out[k] = row
    return list(out.values())


def _pyformat(sql_text: str) -> str:
    # Store's SQL uses "?" (SQLite, CrateDB) and never contains "?" otherwise; "%" is
    # psycopg's placeholder mark, so the modulo operator must be doubled.
    return sql_text.replace("%", "%%").replace("?", "%s")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


# ------------------------------------------------------------------------------ URL


def open_postgres(text: str, migrate: bool = True) -> PostgresStore:
    """The store at a ``postgresql://`` or ``postgres://`` URL (module docstring)."""
    parts = urlsplit(text)
    try:
        password = parts.password
    except ValueError:
        raise ConfigError(f"{text!r}: malformed PostgreSQL URL") from None
    query = parse_qsl(parts.query, keep_blank_values=True)
    if password is not None or any(k == "password" for k, _ in query):
        # Credentials in a URL leak into configs, logs and process lists.
        raise ConfigError("postgresql URL must not contain a password; set PGPASSWORD or "
                          "use a password file (~/.pgpass, PGPASSFILE) instead")
    ours = {k: v for k, v in query if k in ("schema", "timescaledb")}
    rest = [(k, v) for k, v in query if k not in ours]
    schema = ours.get("schema", DEFAULT_SCHEMA).strip()
    if not schema.isidentifier():
        raise ConfigError(f"{text!r}: schema {schema!r} is not a plain identifier")
    option = ours.get("timescaledb", "auto").strip().lower()
    if option not in TIMESCALE_CHOICES:
        raise ConfigError(f"{text!r}: timescaledb={option!r}; expected one of "
                          f"{', '.join(TIMESCALE_CHOICES)}")
    given = {k for k, _ in rest}
    rest += [(k, v) for k, v in (("connect_timeout", str(CONNECT_TIMEOUT_S)), *TCP_DEFAULTS)
             if k not in given]
    conninfo = urlunsplit(("postgresql", parts.netloc, parts.path, urlencode(rest), ""))
    try:
        conninfo_to_dict(conninfo)  # libpq's own check: unknown parameters, bad syntax
    except psycopg.Error as exc:
        raise ConfigError(f"{text!r}: not a valid PostgreSQL URL ({_first_line(exc)})") \
            from None
    option_t: Timescale = "yes" if option == "yes" else "no" if option == "no" else "auto"
    return PostgresStore(conninfo, schema, option_t, url=text, migrate=migrate)
