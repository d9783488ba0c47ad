"""``pseudotwin import FILE --store URL``: load a canonical history file into the history
store (the import itself is :mod:`pseudotwin.history.importer`)."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from pseudotwin.cli.util import Parser, run_reporting
from pseudotwin.core.series import read_history
from pseudotwin.errors import ConfigError
from pseudotwin.history.importer import import_frame
from pseudotwin.history.store import is_memory_url, open_store

PROG = "pseudotwin import"


def _parser() -> argparse.ArgumentParser:
    p = Parser(
        prog=PROG,
        description="Load a canonical history file (CSV or Parquet with columns "
                    "sensor,ts,value; ts ISO 8601 with offset or epoch s/ms) into the "
                    "history store. Idempotent: readings already stored are skipped, so "
                    "importing a file twice adds nothing. A stored reading is never "
                    "overwritten: where the file holds another value for it, the summary "
                    "counts such readings and names the first.",
    )
    p.add_argument("file", type=Path, metavar="FILE", help="canonical history CSV or Parquet")
    p.add_argument("--store", required=True, metavar="URL",
                   help="history store: a SQLite file path, sqlite:///path, "
                        "postgresql://[user@]host/db (password from PGPASSWORD or "
                        "~/.pgpass), or crate://host:4200 (credentials from "
                        "PSEUDOTWIN_CRATE_USER / PSEUDOTWIN_CRATE_PASSWORD)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``pseudotwin import``; returns the exit status (0 ok, 2 error)."""
    def body() -> int:
        args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
        if is_memory_url(args.store):
            raise ConfigError(f"--store {args.store!r} is a store in memory: the imported "
                              "readings would be gone when import ends")
        t0 = time.perf_counter()
        # Validate the file first: a bad file must not create or touch the store.
        df = read_history(args.file)
        with open_store(args.store) as store:
            summary = import_frame(store, df, args.file)
            print(f"{summary.line()} ({time.perf_counter() - t0:.1f} s, into {store.url})")
        return 0

    return run_reporting(PROG, body)
