"""Loading a canonical history file into the history store (``pseudotwin import``).

The file is read and validated by :func:`pseudotwin.core.series.read_history` (CSV or
Parquet) and written in chunks. Importing is idempotent: readings are keyed by (sensor, ts)
and a key already stored is left alone, so importing a file twice adds nothing the second
time and an interrupted import can simply be re-run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from pseudotwin.core.series import read_history
from pseudotwin.history.store import Store

#: Readings per write_readings call: one SQLite transaction / a few CrateDB bulk requests.
#: Bounds the work lost when an import is interrupted (it is re-runnable anyway).
IMPORT_CHUNK = 50_000


@dataclass(frozen=True)
class ImportSummary:
    """What one import did.

    rows_read: valid readings in the file (after dropping non-finite values and exact
    duplicates); rows_new: readings the store did not have before (0 on a re-import);
    sensors: the file's sensor ids, sorted; first, last: its first and last reading (UTC).
    """

    path: Path
    rows_read: int
    rows_new: int
    sensors: tuple[str, ...]
    first: pd.Timestamp
    last: pd.Timestamp
    repeats: int = 0  # rows whose sensor and millisecond an earlier row of the file has

    def line(self) -> str:
        """A one-line human summary."""
        shown = ", ".join(self.sensors[:8]) + (", ..." if len(self.sensors) > 8 else "")
        # (≥ 0: a store that reports rows sent, not rows written, counts repeats as new)
        stored = max(0, self.rows_read - self.rows_new - self.repeats)
        return (
            f"{self.path}: {self.rows_read} readings of {len(self.sensors)} sensor(s) "
            f"({shown}) from {self.first.isoformat()} to {self.last.isoformat()}; "
            f"{self.rows_new} new, {stored} already stored"
            + (f", {self.repeats} repeating an earlier row's sensor and millisecond "
               "(the store keeps the first)" if self.repeats else "")
        )


def import_history(
    store: Store,
    path: str | Path,
    chunk_rows: int = IMPORT_CHUNK,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Import the canonical history file ``path`` into ``store``.

    progress: called as ``progress(rows_done, rows_total)`` after every chunk.
    Raises DataError for a malformed file, StoreError when the store cannot be written.
    """
    p = Path(path)
    return import_frame(store, read_history(p), p, chunk_rows, progress)


def import_frame(
    store: Store,
    df: pd.DataFrame,
    path: Path,
    chunk_rows: int = IMPORT_CHUNK,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Write an already validated canonical frame (read from ``path``) in chunks."""
    total = len(df)
    new = 0
    for i in range(0, total, chunk_rows):
        new += store.write_readings(df.iloc[i:i + chunk_rows])
        if progress is not None:
            progress(min(i + chunk_rows, total), total)
    # The store keys readings on (sensor, ms): rows of the file within one ms are one reading.
    ms = df["ts"].dt.floor("ms")
    return ImportSummary(
        path=path,
        rows_read=total,
        rows_new=new,
        repeats=int(pd.DataFrame({"sensor": df["sensor"], "ms": ms}).duplicated().sum()),
        sensors=tuple(sorted(df["sensor"].unique())),
        first=df["ts"].iloc[0],
        last=df["ts"].iloc[-1],
    )
