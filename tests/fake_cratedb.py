"""A FAKE of CrateDB's HTTP ``/_sql`` endpoint — NOT CrateDB — for testing the CrateDB store.

No CrateDB server can be installed on the development machines, so the CrateDB backend of
:mod:`pseudotwin.history.store` is exercised through the real ``crate`` client against this thin
stand-in. It is deliberately small: it checks the *wire protocol* (request and response
shapes, bulk requests and their per-row results, errors) and records every statement so
tests can assert the SQL the backend sends. It does not check CrateDB semantics beyond the
few rules listed below; the real-server tests (``PSEUDOTWIN_TEST_CRATEDB``) do that.

What it serves (``http.server`` on 127.0.0.1, a free port, in a thread):

* ``GET /`` — the node info the client reads on connect (``name``, ``version.number``).
* ``POST /_sql`` (any query string, e.g. the client's ``?types=true``; gzip bodies
  accepted) with JSON ``{"stmt", "args"}`` → ``{"cols", "rows", "rowcount", "duration"}``,
  or ``{"stmt", "bulk_args"}`` → ``{"cols": [], "duration", "results": [{"rowcount": n},
  ...]}`` where a failed row is ``{"rowcount": -2, "error_message": ...}`` (HTTP 200, as
  CrateDB does: every row of a bulk request is attempted). Errors of a whole statement:
  HTTP 4xx ``{"error": {"message", "code"}, "error_trace"}``.

Statements run on an in-memory SQLite database after this translation — of exactly the SQL
the store emits, nothing more:

1. ``REFRESH TABLE ...`` is a no-op (SQLite reads its own writes).
2. ``CREATE TABLE``: ``TIMESTAMP WITH TIME ZONE`` → ``INTEGER`` (CrateDB transports
   timestamps as epoch milliseconds, which is what the store sends and expects back),
   ``DOUBLE PRECISION`` → ``REAL``; a column ``<name> TIMESTAMP WITH TIME ZONE GENERATED
   ALWAYS AS date_trunc('month', <col>)`` is dropped (and remembered as generated),
   ``PARTITIONED BY (...)`` is dropped, generated columns are dropped from the primary key;
   the table is created ``STRICT`` so a wrongly typed value is an error, as in CrateDB.
3. ``INSERT ... ON CONFLICT (cols)``: generated columns are dropped from the target.

CrateDB rules it enforces, because the store must get them right:

* a partition column must be part of the primary key;
* an ``ON CONFLICT (...)`` target must name exactly the primary-key columns (generated
  ones included);
* bulk requests are only allowed for INSERT/UPDATE/DELETE.

The ``Default-Schema`` header is recorded but ignored: there is one namespace.
"""

from __future__ import annotations

import base64
import gzip
import json
import re
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

FAKE_VERSION = "5.10.0"  # what GET / claims; the client only parses it

_GENERATED = re.compile(
    r",\s*(\w+)\s+TIMESTAMP WITH TIME ZONE\s+GENERATED ALWAYS AS\s+"
    r"date_trunc\('month',\s*\w+\)",
    re.IGNORECASE,
)
_PARTITIONED = re.compile(r"\s*PARTITIONED BY\s*\(([^)]*)\)", re.IGNORECASE)
_PRIMARY_KEY = re.compile(r"PRIMARY KEY\s*\(([^)]*)\)", re.IGNORECASE)
_CREATE = re.compile(r"^\s*CREATE TABLE (?:IF NOT EXISTS )?(\w+)", re.IGNORECASE)
_INSERT = re.compile(r"^\s*INSERT INTO (\w+)", re.IGNORECASE)
_ON_CONFLICT = re.compile(r"ON CONFLICT\s*\(([^)]*)\)", re.IGNORECASE)
_REFRESH = re.compile(r"^\s*REFRESH TABLE\s+[\w\s,]+$", re.IGNORECASE)
_INLINE_PK = re.compile(r"\(\s*(\w+)\s+\w+\s+PRIMARY KEY", re.IGNORECASE)


class FakeSQLError(Exception):
    """A statement error answered as CrateDB would: HTTP status and CrateDB error code."""

    def __init__(self, message: str, code: int = 4000, status: int = 400) -> None:
        super().__init__(message)
        self.code = code
        self.status = status


@dataclass(frozen=True)
class Recorded:
    """One POST /_sql as received: the statement, its args or bulk_args, and headers."""

    stmt: str
    args: list[Any] | None
    bulk_args: list[list[Any]] | None
    schema: str | None
    user: str | None
    has_password: bool


def _names(text: str) -> list[str]:
    return [c.strip().strip('"').lower() for c in text.split(",") if c.strip()]


class FakeCrateDB:
    """The fake server. ``start()``/``stop()`` or use as a context manager.

    url: ``crate://127.0.0.1:<port>`` for :func:`pseudotwin.history.store.open_store`.
    requests: every POST /_sql received, in order; ``statements`` just their SQL.
    fail_row: optional hook ``(stmt, row_args) -> error message | None``; a message makes
        that row of a bulk request fail with rowcount -2 (to test per-row error handling).
    """

    def __init__(self) -> None:
        self._db = sqlite3.connect(":memory:", check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        self.requests: list[Recorded] = []
        self.fail_row: Callable[[str, list[Any]], str | None] | None = None
        self._generated: dict[str, set[str]] = {}  # table → its generated columns
        self._full_pk: dict[str, list[str]] = {}  # table → primary key as declared
        self._server: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None

    # --- lifecycle -----------------------------------------------------------------
    def start(self) -> FakeCrateDB:
        fake = self

        class Handler(_Handler):
            server_fake = fake

        self._server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self._server.daemon_threads = True
        # A short poll interval keeps stop() (and so every test's teardown) fast.
        self._thread = threading.Thread(target=self._server.serve_forever, args=(0.02,),
                                        name="fake-cratedb", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._db.close()

    def __enter__(self) -> FakeCrateDB:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def port(self) -> int:
        assert self._server is not None, "FakeCrateDB not started"
        return int(self._server.server_address[1])

    @property
    def url(self) -> str:
        return f"crate://127.0.0.1:{self.port}"

    @property
    def statements(self) -> list[str]:
        return [r.stmt for r in self.requests]

    def sql(self, stmt: str, args: list[Any] | None = None) -> list[tuple]:
        """Run SQL directly on the backing SQLite (test setup/inspection, not recorded)."""
        with self._lock:
            return self._db.execute(stmt, args or []).fetchall()

    # --- translation -----------------------------------------------------------------
    def translate(self, stmt: str) -> str | None:
        """The SQLite statement for a CrateDB one; None for a no-op (REFRESH TABLE)."""
        if _REFRESH.match(stmt):
            return None
        if m := _CREATE.match(stmt):
            return self._translate_create(m.group(1).lower(), stmt)
        if "GENERATED" in stmt.upper() or "PARTITIONED" in stmt.upper():
            raise FakeSQLError(f"fake cannot translate: {stmt}")
        if (m := _INSERT.match(stmt)) and (c := _ON_CONFLICT.search(stmt)):
            table = m.group(1).lower()
            if table not in self._full_pk:
                raise FakeSQLError(f"RelationUnknown[Relation '{table}' unknown]", 4041, 404)
            target = _names(c.group(1))
            if sorted(target) != sorted(self._full_pk[table]):
                raise FakeSQLError(
                    f"SQLParseException[Number of conflict targets ({target}) did not match "
                    f"the number of primary key columns ({self._full_pk[table]})]"
                )
            kept = [col for col in target if col not in self._generated.get(table, set())]
            return stmt[: c.start()] + f"ON CONFLICT ({', '.join(kept)})" + stmt[c.end():]
        return stmt

    def _translate_create(self, table: str, stmt: str) -> str:
        generated = {m.group(1).lower() for m in _GENERATED.finditer(stmt)}
        out = _GENERATED.sub("", stmt)
        if "GENERATED" in out.upper():
            raise FakeSQLError(f"fake cannot translate generated column in: {stmt}")
        partitioned: list[str] = []
        if m := _PARTITIONED.search(out):
            partitioned = _names(m.group(1))
            out = out[: m.start()] + out[m.end():]
        pk_match = _PRIMARY_KEY.search(out)
        if pk_match:
            full_pk = _names(pk_match.group(1))
        elif m := _INLINE_PK.search(out):
            full_pk = [m.group(1).lower()]
        else:
            full_pk = []
        missing = [c for c in partitioned if c not in full_pk]
        if full_pk and missing:
            raise FakeSQLError(
                f"SQLParseException[Cannot use non primary key column '{missing[0]}' in "
                "PARTITIONED BY clause if primary key is set on table]"
            )
        if pk_match:
            kept = [c for c in full_pk if c not in generated]
            out = out[: pk_match.start()] + f"PRIMARY KEY ({', '.join(kept)})" \
                + out[pk_match.end():]
        out = re.sub(r"TIMESTAMP WITH TIME ZONE", "INTEGER", out, flags=re.IGNORECASE)
        out = re.sub(r"DOUBLE PRECISION", "REAL", out, flags=re.IGNORECASE)
        # IF NOT EXISTS: the first definition stays, as in the database.
        self._generated.setdefault(table, generated)
        self._full_pk.setdefault(table, full_pk)
        return out.rstrip().rstrip(";") + " STRICT"

    # --- execution -------------------------------------------------------------------
    def execute(self, body: dict[str, Any], headers: dict[str, str]) -> dict[str, Any]:
        """Answer one /_sql request body (raises FakeSQLError for a failed statement)."""
        stmt = body.get("stmt")
        if not isinstance(stmt, str):
            raise FakeSQLError("SQLParseException[Missing stmt]")
        args, bulk = body.get("args"), body.get("bulk_args")
        user, has_password = _auth(headers.get("authorization"))
        with self._lock:
            self.requests.append(Recorded(stmt, args, bulk, headers.get("default-schema"),
                                          user, has_password))
            t0 = time.perf_counter()
            if args is not None and bulk is not None:
                raise FakeSQLError("SQLParseException[request body contains args and "
                                   "bulk_args. It's forbidden to provide both]")
            sql = self.translate(stmt)
            if bulk is not None:
                if not re.match(r"^\s*(INSERT|UPDATE|DELETE)\b", stmt, re.IGNORECASE):
                    raise FakeSQLError("UnsupportedFeatureException[Bulk operations for "
                                       "statements that return result sets is not supported]",
                                       4004)
                results = [self._bulk_row(stmt, sql, row) for row in bulk]
                return {"cols": [], "duration": _ms_since(t0), "results": results}
            if sql is None:  # REFRESH TABLE
                return {"cols": [], "rows": [], "rowcount": 1, "duration": _ms_since(t0)}
            cur = self._run(sql, args or [])
            if cur.description is not None:
                rows = [list(r) for r in cur.fetchall()]
                cols = [d[0] for d in cur.description]
                return {"cols": cols, "rows": rows, "rowcount": len(rows),
                        "duration": _ms_since(t0)}
            rowcount = cur.rowcount if cur.rowcount >= 0 else 1  # DDL: "1 row affected"
            return {"cols": [], "rows": [], "rowcount": rowcount, "duration": _ms_since(t0)}

    def _bulk_row(self, stmt: str, sql: str | None, row: list[Any]) -> dict[str, Any]:
        if self.fail_row is not None and (msg := self.fail_row(stmt, row)):
            return {"rowcount": -2, "error_message": msg}
        try:
            cur = self._run(sql or "", row)
        except FakeSQLError as exc:
            return {"rowcount": -2, "error_message": str(exc)}
        return {"rowcount": max(cur.rowcount, 0)}

    def _run(self, sql: str, args: list[Any]) -> sqlite3.Cursor:
        try:
            return self._db.execute(sql, args)
        except sqlite3.IntegrityError as exc:
            if "UNIQUE" in str(exc) or "PRIMARY KEY" in str(exc):
                raise FakeSQLError("DuplicateKeyException[A document with the same primary "
                                   "key exists already]", 4091, 409) from None
            raise FakeSQLError(f"ColumnValidationException[{exc}]", 4003) from None
        except sqlite3.OperationalError as exc:
            if "no such table" in str(exc):
                raise FakeSQLError(f"RelationUnknown[{exc}]", 4041, 404) from None
            raise FakeSQLError(f"SQLParseException[{exc}]") from None
        except sqlite3.Error as exc:
            raise FakeSQLError(f"SQLParseException[{exc}]") from None


def _ms_since(t0: float) -> float:
    return round((time.perf_counter() - t0) * 1000, 3)


def _auth(header: str | None) -> tuple[str | None, bool]:
    """(user, whether a password was sent) of a Basic Authorization header."""
    if not header or not header.startswith("Basic "):
        return None, False
    user, _, password = base64.b64decode(header[6:]).decode().partition(":")
    return user, bool(password)


class _Handler(BaseHTTPRequestHandler):
    server_fake: FakeCrateDB
    protocol_version = "HTTP/1.1"  # keep-alive, as urllib3's pool expects
    # Headers and body go out in two writes; with Nagle on, a keep-alive client waits for
    # the delayed ACK (~40 ms) on every request.
    disable_nagle_algorithm = True

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - base signature
        pass  # quiet: tests assert on recorded requests, not on an access log

    def _reply(self, status: int, doc: dict[str, Any]) -> None:
        data = json.dumps(doc).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json; charset=UTF-8")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def do_GET(self) -> None:  # noqa: N802 - http.server naming
        if self.path.split("?")[0] != "/":
            self._reply(404, {"error": {"message": "not found", "code": 4040}})
            return
        self._reply(200, {
            "ok": True, "status": 200, "name": "fake-cratedb", "cluster_name": "fake",
            "version": {"number": FAKE_VERSION, "build_hash": "fake", "build_snapshot": False,
                        "lucene_version": "fake"},
        })

    def do_POST(self) -> None:  # noqa: N802 - http.server naming
        if self.path.split("?")[0] != "/_sql":
            self._reply(404, {"error": {"message": "not found", "code": 4040}})
            return
        raw = self.rfile.read(int(self.headers.get("Content-Length") or 0))
        if self.headers.get("Content-Encoding", "").lower() == "gzip":
            raw = gzip.decompress(raw)  # the client gzips bodies above 8 KiB
        headers = {k.lower(): v for k, v in self.headers.items()}
        try:
            body = json.loads(raw)
            self._reply(200, self.server_fake.execute(body, headers))
        except FakeSQLError as exc:
            self._reply(exc.status, {"error": {"message": str(exc), "code": exc.code},
                                     "error_trace": "(fake CrateDB: no trace)"})
        except ValueError as exc:
            self._reply(400, {"error": {"message": f"SQLParseException[bad JSON: {exc}]",
                                        "code": 4000}})

