"""Loading a canonical history file into the history store (``pseudotwin import``).

The file is read and validated by :func:`pseudotwin.core.series.read_history` (CSV or
Parquet) and written in chunks. Importing is idempotent: readings are keyed by (sensor, ts)
and a key already stored is left alone, so importing a file twice adds nothing the second
time and an interrupted import can simply be re-run. A key stored with another value than
the file's (a corrected export, two sources under one sensor id) keeps the stored value
(first write wins); such readings are counted and the first one named, never passed over in
silence.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
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
    #: readings whose key was stored with another value (the stored one is kept)
    differing: int = 0
    #: the first of them: (sensor, ts, the file's value, the stored value)
    first_differing: tuple[str, pd.Timestamp, float, float] | None = None

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
            + self._differing_text()
        )

    def _differing_text(self) -> str:
        if self.first_differing is None:
            return ""
        sensor, ts, value, stored = self.first_differing
        return (f"; {self.differing} of the stored readings hold another value than the "
                f"file's and were kept (first write wins), the first: {sensor} at "
                f"{ts.isoformat()} stored {stored:g}, file {value:g}")


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
    # The store keys readings on (sensor, ms): rows of the file within one ms are one reading.
    repeated = pd.DataFrame({"sensor": df["sensor"], "ms": df["ts"].dt.floor("ms")}).duplicated()
    new = 0
    differing: list[pd.DataFrame] = []
    for i in range(0, total, chunk_rows):
        chunk = df.iloc[i:i + chunk_rows]
        keys = chunk[~repeated.iloc[i:i + chunk_rows].to_numpy()]
        written = store.write_readings(chunk)
        new += written
        if written < len(keys):  # some keys were stored already: with the same value?
            differing.append(_differing(store, keys))
        if progress is not None:
            progress(min(i + chunk_rows, total), total)
    diff = pd.concat(differing, ignore_index=True) if differing else None
    return ImportSummary(
        path=path,
        rows_read=total,
        rows_new=new,
        repeats=int(repeated.sum()),
        differing=0 if diff is None else len(diff),
        first_differing=None if diff is None or diff.empty else (
            str(diff["sensor"].iloc[0]), diff["ts"].iloc[0], float(diff["value"].iloc[0]),
            float(diff["stored"].iloc[0])),
        sensors=tuple(sorted(df["sensor"].unique())),
        first=df["ts"].iloc[0],
        last=df["ts"].iloc[-1],
    )


def _differing(store: Store, keys: pd.DataFrame) -> pd.DataFrame:
    """The readings of ``keys`` (one row per stored key) that the store now holds with
    another value: columns sensor, ts, value (the file's), stored; in the file's order."""
    stored = store.read_readings(sorted(keys["sensor"].unique()), keys["ts"].min(),
                                 keys["ts"].max() + pd.Timedelta(milliseconds=1))
    mine = keys.assign(ms=keys["ts"].dt.floor("ms"))
    both = mine.merge(stored.rename(columns={"ts": "ms", "value": "stored"}),
                      on=["sensor", "ms"], how="inner")
    # A file's decimal text and the stored double may differ in the last bit, not more.
    same = np.isclose(both["value"], both["stored"], rtol=1e-12, atol=0.0)
    return both.loc[~same, ["sensor", "ts", "value", "stored"]].reset_index(drop=True)
