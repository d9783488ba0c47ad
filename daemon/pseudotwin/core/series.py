"""Canonical history: long rows ``sensor, ts, value`` (ts timezone-aware).

Readers return a DataFrame with columns ``sensor`` (str), ``ts`` (datetime64, UTC) and
``value`` (float), sorted by ``ts``; every malformed input raises :class:`DataError` with a
message that names the file and what is wrong.
"""

from __future__ import annotations

import csv
import datetime as dt
import logging
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from pseudotwin.core.files import write_replacing
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.errors import DataError

COLUMNS = ("sensor", "ts", "value")

#: The oldest reading taken, from a file or live: an older stamp is a device clock never set
#: or an uptime counter sent as epoch seconds (0 is 1970-01-01), not history.
OLDEST = pd.Timestamp("2000-01-01", tz="UTC")
#: How far after the moment a file is read its newest reading may be stamped: further is a
#: device clock far ahead (a reading cannot come from the future), as the recorder rejects it.
AHEAD = pd.Timedelta(days=1)

#: Epoch numbers above this are neither seconds nor milliseconds (ms reach it in year 5138):
#: microseconds or nanoseconds, as some exports write them.
_EPOCH_MS_MAX = 1e14

log = logging.getLogger(__name__)


#: The seconds since 1970 a nanosecond timestamp holds (years 1677–2262), a little inside:
#: a stamp beyond is clamped to it, and dropped as too old or too new (OLDEST, AHEAD).
_NS_SECONDS = 9.2e9
_NS_BOUNDS = (pd.Timestamp(-_NS_SECONDS, unit="s", tz="UTC"),
              pd.Timestamp(_NS_SECONDS, unit="s", tz="UTC"))


def _epoch(num: pd.Series) -> pd.Series:
    # Epoch milliseconds are > 1e11 for any date after 1973; seconds stay below until 5138.
    ms = num.abs() > 1e11
    bound = np.where(ms, 1e3, 1.0) * _NS_SECONDS  # [s] or [ms]
    num = num.clip(-bound, bound)
    out = pd.to_datetime(num.where(~ms) * 1e9, unit="ns", utc=True)
    out = out.where(~ms, pd.to_datetime(num.where(ms) * 1e6, unit="ns", utc=True))
    # A float holds ~16 digits: ms since 1970 times 1e6 lands up to 256 ns off, and the
    # store's millisecond then was often one early (…001 stored as …000, a key another
    # reading had). No epoch number in a file means less than a microsecond.
    return out.dt.round("us")


def _row(mask: pd.Series | np.ndarray) -> int:
    """The 1-based data row (the header not counted) of the first True in ``mask``."""
    return int(np.flatnonzero(np.asarray(mask))[0]) + 1


def _checked_epoch(num: pd.Series, where: str, rows: pd.Series | None = None) -> pd.Series:
    """_epoch of numbers that are epoch seconds or milliseconds; DataError naming the first
    row of another unit. rows: each number's position in the column (default: in order)."""
    huge = num.abs() > _EPOCH_MS_MAX
    if huge.any():
        pos = np.flatnonzero(huge.to_numpy())[0]
        row = int(rows.iloc[pos]) if rows is not None else int(pos)
        raise DataError(f"{where}: epoch value {num.iloc[pos]:.0f} in data row {row + 1} is "
                        "too large for seconds or milliseconds (microseconds or "
                        "nanoseconds? divide by 1e3 or 1e6 first)")
    return _epoch(num)


def parse_timestamps(raw: pd.Series, where: str) -> pd.Series:
    """ISO 8601 with offset, or epoch seconds / milliseconds (row by row) → UTC timestamps;
    a Parquet file's timestamp column must be time-zone aware."""
    if isinstance(raw.dtype, pd.DatetimeTZDtype):
        if raw.isna().any():
            raise DataError(f"{where}: data row {_row(raw.isna())} has no timestamp")
        return raw.dt.tz_convert("UTC")
    if pd.api.types.is_datetime64_dtype(raw):
        raise DataError(f"{where}: the ts column has no time zone (store UTC timestamps)")
    if pd.api.types.is_numeric_dtype(raw):
        if raw.isna().any():
            raise DataError(f"{where}: data row {_row(raw.isna())} has no timestamp")
        return _checked_epoch(raw.astype(float), where)
    text = raw.astype(str).str.strip()
    blank = raw.isna() | (text == "")
    if blank.any():
        raise DataError(f"{where}: data row {_row(blank)} has no timestamp")
    numeric = text.str.fullmatch(r"-?\d+(\.\d+)?")
    out = pd.Series(pd.NaT, index=raw.index, dtype="datetime64[ns, UTC]")
    if numeric.any():
        positions = pd.Series(np.flatnonzero(numeric.to_numpy()))
        out[numeric] = _checked_epoch(text[numeric].astype(float), where, positions)
    iso = text[~numeric]
    if len(iso):
        dated = iso.str.match(r"\d{4}-\d\d-\d\d")
        if not dated.all():
            raise DataError(
                f"{where}: {iso[~dated].iloc[0]!r} in data row {_row(~numeric & ~dated)} is "
                "not a timestamp (use ISO 8601 with a UTC offset, or epoch seconds / ms)"
            )
        # a time, then Z or an offset (±hh, ±hhmm, ±hh:mm): a date alone ends in "-14" too
        aware = iso.str.contains(r"[T ]\d\d:\d\d", regex=True) & iso.str.contains(
            r"(?:Z|[+-]\d\d(?::?\d\d)?)$", regex=True)
        if not aware.all():
            bad = iso[~aware].iloc[0]
            raise DataError(
                f"{where}: timestamp {bad!r} has no UTC offset (use ISO 8601 with offset)"
            )
        parsed = pd.to_datetime(iso, utc=True, format="ISO8601", errors="coerce")
        if parsed.isna().any():
            bad = parsed.isna().reindex(raw.index, fill_value=False)
            raise DataError(f"{where}: {iso[parsed.isna()].iloc[0]!r} in data row {_row(bad)} "
                            "is not a valid ISO 8601 instant")
        out[~numeric] = parsed.clip(*_NS_BOUNDS).dt.as_unit("ns")
    return out


def _sensors(raw: pd.Series, where: str) -> pd.Series:
    """The sensor column as stripped strings; a blank or missing name is an error."""
    names = raw.astype(str).str.strip()
    blank = raw.isna() | (names == "")
    if blank.any():
        raise DataError(f"{where}: data row {_row(blank)} has no sensor name")
    return names


@dataclass(frozen=True)
class Dropped:
    """Rows :func:`normalize` left out: without a finite value (blank, NaN, ±inf), exact
    duplicates of an earlier row, and conflicts: rows repeating an earlier row's sensor and
    time with another value (the first is kept, as the store and the daemon's window keep
    it, so every reader of a file sees the same readings)."""

    rows: int
    not_finite: int
    duplicates: int
    conflicts: int = 0
    too_old: int = 0  # stamped before OLDEST
    too_new: int = 0  # stamped more than AHEAD after the file was read

    def line(self, where: str) -> str | None:
        """One line saying how many rows were dropped and why; None when none was."""
        reasons = [f"{n} {why}" for n, why in (
            (self.not_finite, "with a blank, NaN or infinite value"),
            (self.duplicates, "exact duplicate(s)"),
            (self.conflicts, "repeating a sensor and time with another value: the first is "
                             "used, as the store and the daemon's window keep it"),
            (self.too_old, f"stamped before {OLDEST:%Y-%m-%d}, a device clock never set, as "
                           "the recorder rejects them"),
            (self.too_new, f"stamped more than {AHEAD.days} day after now, a device clock far "
                           "ahead, as the recorder rejects them")) if n]
        if not reasons:
            return None
        dropped = (self.not_finite + self.duplicates + self.conflicts + self.too_old
                   + self.too_new)
        return f"{where}: dropped {dropped} of {self.rows} rows ({', '.join(reasons)})"


def normalize(df: pd.DataFrame, where: str = "history") -> pd.DataFrame:
    """Validate and normalize a long frame; drops non-finite values, exact duplicates and
    later rows of a sensor and time already read (see :class:`Dropped`)."""
    return _normalize(df, where)[0]


def _normalize(df: pd.DataFrame, where: str) -> tuple[pd.DataFrame, Dropped]:
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        found = ",".join(str(c) for c in df.columns)
        other = next((f" (separated by {sep!r}? the file must be comma-separated)"
                      for sep in (";", "\t", "|") if sep in found), "")
        raise DataError(f"{where}: missing column(s) {', '.join(missing)}; expected header "
                        f"sensor,ts,value, found {found[:200]!r}{other}")
    if df.empty:
        raise DataError(f"{where}: no rows")
    out = pd.DataFrame(
        {"sensor": _sensors(df["sensor"], where), "ts": parse_timestamps(df["ts"], where)}
    )
    value = pd.to_numeric(df["value"], errors="coerce")
    bad = value.isna() & df["value"].notna() & (df["value"].astype(str).str.strip() != "")
    if bad.any():
        row = int(np.flatnonzero(bad.values)[0])
        raise DataError(
            f"{where}: value {df['value'].iloc[row]!r} in data row {row + 1} is not a number"
        )
    out["value"] = value.astype(float)
    out = out[np.isfinite(out["value"].values)]
    finite = len(out)
    out = out[out["ts"] >= OLDEST]
    too_old, finite = finite - len(out), len(out)
    out = out[out["ts"] <= pd.Timestamp.now(tz="UTC") + AHEAD]
    too_new, finite = finite - len(out), len(out)
    # One unit everywhere (pandas 3 parses to us), once the stamps beyond ns's years are gone.
    out["ts"] = pd.DatetimeIndex(out["ts"]).as_unit("ns")
    out = out.drop_duplicates()
    unique = len(out)
    out = out[~out.duplicated(["sensor", "ts"])]  # file order: the first stays
    out = out.sort_values(["ts", "sensor"], kind="stable").reset_index(drop=True)
    return out, Dropped(len(df), len(df) - finite - too_old - too_new, finite - unique,
                        unique - len(out), too_old, too_new)


def read_history(path: str | Path) -> pd.DataFrame:
    """Read a canonical CSV (or Parquet) history file: the one place history files are
    read (import, train, evaluate, replay). The rows :class:`Dropped` names are dropped, with
    one warning saying how many; a file left without a valid reading, a row without a sensor
    name or timestamp, a value that is no number, a row with more fields than the header:
    DataError."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: no such file")
    if p.is_dir():
        raise DataError(f"{p}: is a directory, not a history file")
    try:
        if p.suffix.lower() in (".parquet", ".pq"):
            df = pd.read_parquet(p)
        else:
            # index_col=False: pandas would take a row's extra field for an index and shift
            # the others into the wrong columns; it then warns instead, and that is an error.
            with warnings.catch_warnings():
                warnings.simplefilter("error", pd.errors.ParserWarning)
                try:
                    df = pd.read_csv(p, dtype={"sensor": str, "ts": str}, comment="#",
                                     index_col=False)
                except (pd.errors.ParserWarning, pd.errors.ParserError) as exc:
                    # the warning for an extra field in the first row, the error in others
                    if (overlong := _overlong_row(p)) is not None:
                        raise DataError(f"{p}: {overlong}") from None
                    raise pd.errors.ParserError(str(exc)) from None
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError, ImportError) as exc:
        raise DataError(f"{p}: not a readable canonical history file "
                        f"({' '.join(str(exc).split())})") from None
    out, dropped = _normalize(df, str(p))
    if out.empty:
        raise DataError(f"{p}: no valid readings: "
                        f"{(dropped.line('') or '').removeprefix(': ')}")
    if (line := dropped.line(str(p))) is not None:
        log.warning("%s", line)
    return out


def _overlong_row(path: Path) -> str | None:
    """Which data row has more (non-empty) fields than the header, said for a DataError;
    None when none has."""
    with open(path, encoding="utf-8", newline="") as fh:
        rows = (r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#"))
        header = next(rows, [])
        for n, row in enumerate(rows, 1):
            if len(row) > len(header) and any(f.strip() for f in row[len(header):]):
                return (f"data row {n} has {len(row)} fields, the header {len(header)} "
                        f"({','.join(header)}): an extra column, or a value with a comma?")
    return None


def iso_utc(ts: pd.Series | pd.DatetimeIndex) -> pd.Index:
    """ISO 8601 UTC texts of aware timestamps, fractions of a second kept as far as they go
    (``2012-03-14T10:00:00+00:00``, ``2012-03-14T10:00:00.5+00:00``)."""
    text = pd.DatetimeIndex(ts).tz_convert("UTC").strftime("%Y-%m-%dT%H:%M:%S.%f")
    return text.str.replace(r"\.?0+$", "", regex=True).str.rstrip(".") + "+00:00"


def write_history(df: pd.DataFrame, path: str | Path, append: bool = False,
                  exact: bool = False) -> None:
    """Write a long frame as canonical CSV (ISO 8601 UTC timestamps), or as Parquet (aware
    UTC timestamps) when ``path`` ends in .parquet or .pq, as :func:`read_history` reads.
    append: add the rows to the CSV at ``path`` (its header written when it is new).
    exact: every value as it is (else 6 significant digits, which a converted dataset's
    sensors never exceed): for raw readings that are to be imported later."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() in (".parquet", ".pq"):
        if append:
            raise ValueError("write_history: append is for CSV files only")
        frame = df.loc[:, list(COLUMNS)].reset_index(drop=True)
        frame["ts"] = pd.DatetimeIndex(frame["ts"]).tz_convert("UTC")
        try:
            write_replacing(path, lambda tmp: frame.to_parquet(tmp, index=False))
        except ImportError as exc:  # pandas' Parquet engine is pyarrow
            raise DataError(f"{path}: cannot write Parquet ({' '.join(str(exc).split())}); "
                            "write .csv instead") from None
        return
    out = df.loc[:, list(COLUMNS)].copy()
    out["ts"] = iso_utc(out["ts"])
    fmt = None if exact else "%.6g"
    if append:
        fresh = not path.exists() or path.stat().st_size == 0
        out.to_csv(path, index=False, float_format=fmt, mode="a", header=fresh)
    else:
        write_replacing(path, lambda tmp: out.to_csv(tmp, index=False, float_format=fmt))


def require_sensors(df: pd.DataFrame, sensors: list[str], where: str = "history") -> None:
    have = set(df["sensor"].unique())
    missing = [s for s in sensors if s not in have]
    if missing and not have:
        raise DataError(f"{where}: sensor(s) {', '.join(missing)} not found; it has no valid "
                        "readings")
    if missing:
        known = ", ".join(sorted(have)[:20])
        raise DataError(f"{where}: sensor(s) {', '.join(missing)} not found; file has: {known}")


@dataclass(frozen=True)
class DayReadings:
    """One local day's window of readings, per sensor, in time order.

    series: sensor → (hours [n] wall clock, values [n]); the first point of a sensor may be
    the value carried over from before the init phase, placed at ``hours.init_start``.
    """

    day: dt.date
    series: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def has(self, sensor: str) -> bool:
        return sensor in self.series and len(self.series[sensor][0]) > 0

    def slot_values(self, sensor: str, hours: OperatingHours) -> np.ndarray:
        """Sample-and-hold values at the start of every window slot: [S] (NaN before any)."""
        slots = hours.window_slots()
        starts = slots * hours.slot_hours
        if not self.has(sensor):
            return np.full(len(slots), np.nan)
        h, v = self.series[sensor]
        idx = np.searchsorted(h, starts + 1e-9, side="right") - 1
        out = np.where(idx >= 0, v[np.clip(idx, 0, None)], np.nan)
        return out

    def slot_means(self, sensor: str, hours: OperatingHours) -> np.ndarray:
        """The slot's level: the time-weighted mean of the sample-and-hold signal over every
        window slot [start, start + slot): [S] (over its part after the first reading; NaN
        for a slot wholly before it). One reading per slot at its start (15-min means) gives
        :meth:`slot_values`; 1-minute readings give the slot's mean, not one minute of it;
        a COV sensor's value counts for as long as it held."""
        starts = hours.window_slots() * hours.slot_hours
        if not self.has(sensor):
            return np.full(len(starts), np.nan)
        h, v = self.series[sensor]
        # integral of the held signal from the first reading up to each reading
        at_reading = np.concatenate([[0.0], np.cumsum(v[:-1] * np.diff(h))])

        def integral(x: np.ndarray) -> np.ndarray:  # from the first reading to x ≥ h[0]
            i = np.clip(np.searchsorted(h, x, side="right") - 1, 0, None)
            return at_reading[i] + v[i] * (x - h[i])

        lo = np.maximum(starts, h[0])
        ends = starts + hours.slot_hours
        covered = ends - lo
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (integral(ends) - integral(lo)) / covered
        return np.where(covered > 0, mean, np.nan)


def split_days(
    df: pd.DataFrame,
    sensors: list[str],
    hours: OperatingHours,
    days: list[dt.date] | None = None,
    max_carry_hours: float = 24.0,
) -> list[DayReadings]:
    """Cut a long frame into per-day windows (init start … day end), with carry-over.

    The last reading of each sensor before the init phase (at most ``max_carry_hours`` old) is
    carried into the window as one point at the init start, as the daemon does.
    """
    sub = df[df["sensor"].isin(sensors)]
    if sub.empty:
        return []
    dayv, hrs = hours.day_and_clock(sub["ts"])  # the twin's hours, in time order
    ts_ns = pd.DatetimeIndex(sub["ts"]).as_unit("ns").asi8
    sens = sub["sensor"].values
    vals = sub["value"].values.astype(float)
    all_days = sorted({d.astype(object) for d in np.unique(dayv)})
    wanted = all_days if days is None else list(days)
    out: list[DayReadings] = []
    for day in wanted:
        init_ts = pd.Timestamp(hours.at(day, hours.init_start)).value
        carry_from = init_ts - int(max_carry_hours * 3.6e12)
        in_day = dayv == np.datetime64(day)
        series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for s in sensors:
            ms = sens == s
            w = ms & in_day & hours.in_window(hrs)
            h, v = hrs[w], vals[w]
            before = np.flatnonzero(ms & (ts_ns < init_ts) & (ts_ns >= carry_from))
            if len(before):
                h = np.concatenate([[hours.init_start], h])
                v = np.concatenate([[vals[before[-1]]], v])
            if len(h):
                order = np.argsort(h, kind="stable")
                series[s] = (h[order], v[order])
        out.append(DayReadings(day, series))
    return out
