"""Converters of the shared datasets into the canonical history (long ``sensor, ts, value``).

``pseudotwin convert DATASET --out FILE.csv`` turns one dataset of ``../shared/data`` into a
canonical CSV (ts ISO 8601 UTC with offset, written by :func:`history.write_history`), so
every experiment and the daemon's backfill read the same thing through
:func:`history.read_history`.

Clocks
------
The sources store naive wall-clock stamps. Which clock they ran on was checked against the
data itself, because a wrong guess shifts every reading against the twin's local operating
hours (and, on the DST day, stacks readings on one instant):

* ``sml2010`` runs on **UTC**. Both files contain 2012-03-25 02:00–02:45 (times that do not
  exist in Europe/Madrid) in an unbroken 15-min grid, so the logger did not observe DST; and
  the twilight sensor (column 13) crosses 300 lux within ~6 min of the computed UTC
  sunrise/sunset for Valencia on all 42 days, before and after 25 March alike, i.e. the
  clock is UTC, not CET/CEST. Read as Europe/Madrid the data would land 1–2 h late and the
  four 02:xx rows would collide with 03:00.
* ``appliances``: the house sensors (T1–T9) run on a **fixed UTC+1 clock** (Belgian winter
  time, never switched): 2016-03-27 02:00–02:50 are real, varying readings in an unbroken
  10-min grid, and the household's daily routine (appliance load) moves one hour earlier on
  that clock after 27 March. The weather columns were merged from the airport by Belgian
  wall time *with* DST: T_out tracks the façade sensor T6 with ~0 lag before 27 March and
  lags it by ~1 h afterwards. So ``weather/temp`` is read as Europe/Brussels; its six
  stamps 02:00–02:50 on 2016-03-27 do not exist on that clock (they are interpolation
  fillers) and are dropped rather than shifted forward onto 03:00. Fixed UTC+1 rather than
  UTC for the house follows from T_out (Belgian wall time) lining up with the house clock
  in winter.
* ``room-climate-*`` stamps are Unix epoch milliseconds, i.e. already UTC.

For a DST-observing clock, wall times in the spring-forward gap or the autumn fold become
NaT and are dropped: a DST-aware logger never writes the former, and the latter cannot be
placed without guessing.

Room climate: 1-minute means
----------------------------
The FAU nodes sample every ~4 s. A live twin conditions on change-of-value-rate readings,
not on a 4-s stream, and the PROVENANCE verification (correlations, offsets) was done on
1-minute means, so the converter emits per node the mean Temp of each UTC minute (bucket =
floor of AbsT to the minute, ts = bucket start; only minutes with at least one sample).
``X/occupancy`` is the maximum ground-truth occupant count (0–2) in that minute.

``--raw`` keeps every sample instead (ts = AbsT to the millisecond; samples of one node at
one instant averaged): a real chatty sensor for the window's thinning (DESIGN §2), its tests
and benchmarks. The other datasets have no averaging to skip; ``--raw`` gives them as they
are.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from pseudotwin.core.series import COLUMNS, write_history
from pseudotwin.errors import ConfigError, DataError

SHARED_DATA_ENV = "PSEUDOTWIN_SHARED_DATA"

# Fixed UTC+1; the POSIX-style name inverts the sign.
_UTC_PLUS_1 = "Etc/GMT-1"


@dataclass(frozen=True)
class Channel:
    """One output sensor: the source column it comes from and the clock that column runs on."""

    sensor: str
    column: str | int
    clock: str


@dataclass(frozen=True)
class Dataset:
    """A registered converter: ``read(source)`` returns a canonical long frame."""

    name: str
    folder: str  # relative to the shared data root
    description: str
    sensors: tuple[str, ...]
    read: Callable[[Path], pd.DataFrame]
    read_raw: Callable[[Path], pd.DataFrame] | None = None  # every sample, where read averages


@dataclass(frozen=True)
class ConvertSummary:
    """What one conversion wrote; ``first``/``last`` are UTC timestamps."""

    dataset: str
    rows: int
    sensors: tuple[str, ...]
    first: pd.Timestamp
    last: pd.Timestamp
    out: Path

    def line(self) -> str:
        return (
            f"{self.dataset}: {self.rows} rows, {len(self.sensors)} sensors "
            f"({', '.join(self.sensors)}), {self.first.isoformat()} .. {self.last.isoformat()}"
            f" -> {self.out}"
        )


# ---------------------------------------------------------------------------- helpers


def shared_data_root() -> Path:
    """``$PSEUDOTWIN_SHARED_DATA`` if set, else ``<repo>/../shared/data``."""
    env = os.environ.get(SHARED_DATA_ENV)
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parents[3]
    return repo.parent / "shared" / "data"


def _localize(naive: pd.Series, clock: str) -> pd.Series:
    """Naive wall-clock stamps on ``clock`` → UTC; gap and fold times become NaT."""
    idx = pd.DatetimeIndex(naive).tz_localize(clock, nonexistent="NaT", ambiguous="NaT")
    return pd.Series(idx.tz_convert("UTC"), index=naive.index)


def _numeric(raw: pd.Series, path: Path, what: str, line_offset: int) -> pd.Series:
    """Column → float; a token that is present but not a number is a malformed file."""
    if pd.api.types.is_numeric_dtype(raw):
        return raw.astype(float)
    num = pd.to_numeric(raw, errors="coerce")
    bad = num.isna() & raw.notna() & (raw.astype(str).str.strip() != "")
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        raise DataError(
            f"{path}: {what} value {raw.iloc[i]!r} on line {i + line_offset} is not a number"
        )
    return num.astype(float)


def _parse_naive(
    text: pd.Series, formats: Sequence[str], path: Path, line_offset: int
) -> pd.Series:
    """Parse wall-clock stamps with the first format that reads every row."""
    best: pd.Series | None = None
    for fmt in formats:
        parsed = pd.to_datetime(text, format=fmt, errors="coerce")
        if parsed.notna().all():
            return parsed
        if best is None or parsed.notna().sum() > best.notna().sum():
            best = parsed
    assert best is not None
    i = int(np.flatnonzero(best.isna().to_numpy())[0])
    raise DataError(
        f"{path}: unparseable date/time {text.iloc[i]!r} on line {i + line_offset} "
        f"(expected {' or '.join(formats)})"
    )


def _long(sensor: str, ts: pd.Series, value: pd.Series) -> pd.DataFrame:
    return pd.DataFrame(
        {"sensor": sensor, "ts": ts.reset_index(drop=True), "value": value.reset_index(drop=True)}
    )


def _finish(parts: list[pd.DataFrame], where: Path) -> pd.DataFrame:
    """Concatenate per-sensor parts into the canonical frame (same order as history.normalize)."""
    df = pd.concat(parts, ignore_index=True)
    df["ts"] = pd.to_datetime(df["ts"], utc=True).astype("datetime64[ns, UTC]")
    df["value"] = df["value"].astype(float)
    df = df[df["ts"].notna() & np.isfinite(df["value"].to_numpy())].drop_duplicates()
    # Two different values for one sensor and instant means the clock handling is wrong
    # (or files overlap); silently keeping one would hide that.
    clash = df.duplicated(["sensor", "ts"], keep=False)
    if clash.any():
        row = df[clash].iloc[0]
        n = int(clash.sum())
        raise DataError(
            f"{where}: {n} conflicting readings share a timestamp, e.g. {row['sensor']} at "
            f"{row['ts'].isoformat()}"
        )
    if df.empty:
        raise DataError(f"{where}: no readings")
    df = df.sort_values(["ts", "sensor"], kind="stable").reset_index(drop=True)
    return df.loc[:, list(COLUMNS)]


def _files(source: Path, pattern: str) -> list[Path]:
    """``source`` may be the dataset folder or a single file (handy for one-off checks)."""
    if source.is_file():
        return [source]
    if not source.is_dir():
        raise DataError(f"{source}: no such file or directory")
    files = sorted(p for p in source.glob(pattern) if p.is_file())
    if not files:
        raise DataError(f"{source / pattern}: no such file")
    return files


# ---------------------------------------------------------------------------- SML2010

_SML_HEADER = {
    1: "Date",
    2: "Time",
    3: "Temperature_Comedor_Sensor",
    4: "Temperature_Habitacion_Sensor",
    6: "CO2_Comedor_Sensor",
    7: "CO2_Habitacion_Sensor",
    22: "Temperature_Exterior_Sensor",
}
_SML_NCOLS = 24
# Column numbers are the 1-based ones of the file header.
_SML_CHANNELS = (
    Channel("dining/temp", 3, "UTC"),
    Channel("room/temp", 4, "UTC"),
    Channel("dining/co2", 6, "UTC"),
    Channel("room/co2", 7, "UTC"),
    Channel("outdoor/temp", 22, "UTC"),
)


def _read_sml2010_file(path: Path) -> list[pd.DataFrame]:
    try:
        with path.open(encoding="utf-8", errors="replace") as fh:
            header = fh.readline()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
    if not header.startswith("#"):
        raise DataError(f"{path}: first line is not the '#' column header of SML2010")
    names = {int(k): v for k, v in re.findall(r"(\d+):(\S+)", header)}
    missing = [f"{k}:{v}" for k, v in _SML_HEADER.items() if names.get(k) != v]
    if missing:
        raise DataError(f"{path}: header lacks column(s) {', '.join(missing)}")
    try:
        raw = pd.read_csv(path, sep=r"\s+", header=None, comment="#", dtype={0: str, 1: str})
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not readable as SML2010 text ({exc})") from None
    if raw.shape[1] != _SML_NCOLS:
        raise DataError(f"{path}: expected {_SML_NCOLS} columns, found {raw.shape[1]}")
    # Line numbers for messages: the header is line 1.
    naive = _parse_naive(raw[0] + " " + raw[1], ["%d/%m/%Y %H:%M"], path, 2)
    parts = []
    for ch in _SML_CHANNELS:
        assert isinstance(ch.column, int)
        value = _numeric(raw[ch.column - 1], path, _SML_HEADER[ch.column], 2)
        parts.append(_long(ch.sensor, _localize(naive, ch.clock), value))
    return parts


def read_sml2010(source: Path) -> pd.DataFrame:
    parts: list[pd.DataFrame] = []
    for path in _files(source, "NEW-DATA-*.T15.txt"):
        parts.extend(_read_sml2010_file(path))
    return _finish(parts, source)


# ---------------------------------------------------------------------------- appliances

_APPLIANCES_FILE = "energydata_complete.csv"
_APPLIANCES_CHANNELS = (
    Channel("kitchen/temp", "T1", _UTC_PLUS_1),
    Channel("living/temp", "T2", _UTC_PLUS_1),
    Channel("laundry/temp", "T3", _UTC_PLUS_1),
    Channel("office/temp", "T4", _UTC_PLUS_1),
    Channel("bathroom/temp", "T5", _UTC_PLUS_1),
    Channel("outside/temp", "T6", _UTC_PLUS_1),
    Channel("ironing/temp", "T7", _UTC_PLUS_1),
    Channel("teen/temp", "T8", _UTC_PLUS_1),
    Channel("parents/temp", "T9", _UTC_PLUS_1),
    Channel("weather/temp", "T_out", "Europe/Brussels"),
)
# The shared copy was re-saved by a spreadsheet (day-first); the UCI original is ISO-like.
_APPLIANCES_DATE_FORMATS = ("%d-%m-%Y %H:%M", "%Y-%m-%d %H:%M:%S")


def read_appliances(source: Path) -> pd.DataFrame:
    path = source / _APPLIANCES_FILE if source.is_dir() else source
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    try:
        raw = pd.read_csv(path, dtype={"date": str})
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not readable as CSV ({exc})") from None
    need = ["date"] + [str(ch.column) for ch in _APPLIANCES_CHANNELS]
    missing = [c for c in need if c not in raw.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}")
    naive = _parse_naive(raw["date"].astype(str).str.strip(), _APPLIANCES_DATE_FORMATS, path, 2)
    parts = []
    for ch in _APPLIANCES_CHANNELS:
        value = _numeric(raw[ch.column], path, str(ch.column), 2)
        parts.append(_long(ch.sensor, _localize(naive, ch.clock), value))
    return _finish(parts, path)


# ---------------------------------------------------------------------------- room climate

_RC_NCOLS = 12
_RC_ABST, _RC_NID, _RC_TEMP, _RC_OCC = 1, 3, 4, 8
_RC_NODES = {"A": (1, 2, 3, 4), "B": (1, 2, 3)}


def _read_room_climate_file(path: Path, location: str) -> pd.DataFrame:
    try:
        raw = pd.read_csv(path, header=None, skipinitialspace=True)
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not readable as room-climate CSV ({exc})") from None
    if raw.shape[1] != _RC_NCOLS:
        raise DataError(
            f"{path}: expected {_RC_NCOLS} columns (EID, AbsT, RelT, NID, Temp, RelH, L1, L2, "
            f"Occ, Act, Door, Win), found {raw.shape[1]}"
        )
    out = pd.DataFrame(
        {
            "abst": _numeric(raw[_RC_ABST], path, "AbsT", 1),
            "nid": _numeric(raw[_RC_NID], path, "NID", 1),
            "temp": _numeric(raw[_RC_TEMP], path, "Temp", 1),
            "occ": _numeric(raw[_RC_OCC], path, "Occ", 1),
        }
    )
    if out["abst"].isna().any():
        i = int(np.flatnonzero(out["abst"].isna().to_numpy())[0])
        raise DataError(f"{path}: AbsT missing on line {i + 1}")
    unknown = sorted(set(out["nid"].dropna().unique()) - set(_RC_NODES[location]))
    if unknown:
        raise DataError(
            f"{path}: node id(s) {', '.join(f'{n:g}' for n in unknown)} are not nodes of "
            f"location {location} ({', '.join(map(str, _RC_NODES[location]))})"
        )
    return out


def _room_climate_samples(source: Path, location: str) -> pd.DataFrame:
    return pd.concat(
        [_read_room_climate_file(p, location) for p in _files(source, "*.csv")],
        ignore_index=True,
    )


def _room_climate_frame(raw: pd.DataFrame, key: str, source: Path, location: str) -> pd.DataFrame:
    """Per node the mean Temp, and the maximum occupancy, of each value of column ``key``
    (epoch ms: the sample's own time, or its minute)."""
    temp = raw.dropna(subset=["nid", "temp"]).groupby(["nid", key])["temp"].mean()
    parts = []
    for nid, series in temp.groupby(level="nid"):
        ts = pd.Series(pd.to_datetime(series.index.get_level_values(key), unit="ms", utc=True))
        parts.append(_long(f"{location}{int(nid)}/temp", ts, series.reset_index(drop=True)))
    occ = raw.dropna(subset=["occ"]).groupby(key)["occ"].max()
    if len(occ):
        ts = pd.Series(pd.to_datetime(occ.index, unit="ms", utc=True))
        parts.append(_long(f"{location}/occupancy", ts, occ.reset_index(drop=True)))
    return _finish(parts, source)


def read_room_climate_raw(source: Path, location: str) -> pd.DataFrame:
    """Every sample of every node (the sensors' own ~4 s rate; one instant's samples of a
    node averaged)."""
    return _room_climate_frame(_room_climate_samples(source, location), "abst", source,
                               location)


def read_room_climate(source: Path, location: str) -> pd.DataFrame:
    raw = _room_climate_samples(source, location)
    raw["minute"] = (raw["abst"].to_numpy(dtype=np.int64) // 60_000) * 60_000
    return _room_climate_frame(raw, "minute", source, location)


# ---------------------------------------------------------------------------- registry

DATASETS: dict[str, Dataset] = {
    "sml2010": Dataset(
        "sml2010",
        "sml2010",
        "UCI SML2010 house, Valencia 2012: dining/room temp + CO2, outdoor temp (15 min, UTC)",
        tuple(ch.sensor for ch in _SML_CHANNELS),
        read_sml2010,
    ),
    "room-climate-a": Dataset(
        "room-climate-a",
        "room_climate/datasets-location_A",
        "FAU office A 2016: 4 temp nodes in one room, A4 above the desk (1-min means)",
        ("A1/temp", "A2/temp", "A3/temp", "A4/temp", "A/occupancy"),
        partial(read_room_climate, location="A"),
        partial(read_room_climate_raw, location="A"),
    ),
    "room-climate-b": Dataset(
        "room-climate-b",
        "room_climate/datasets-location_B",
        "FAU office B 2016: 3 temp nodes in one room, B2 between the desks (1-min means)",
        ("B1/temp", "B2/temp", "B3/temp", "B/occupancy"),
        partial(read_room_climate, location="B"),
        partial(read_room_climate_raw, location="B"),
    ),
    "appliances": Dataset(
        "appliances",
        "appliances",
        "UCI appliances house, Belgium 2016: 9 room/outside temps + airport T_out (10 min)",
        tuple(ch.sensor for ch in _APPLIANCES_CHANNELS),
        read_appliances,
    ),
}


def find_dataset(name: str) -> Dataset:
    """The registered dataset ``name``; ConfigError naming the choices otherwise."""
    try:
        return DATASETS[name]
    except KeyError:
        raise ConfigError(
            f"unknown dataset {name!r} (choose from {', '.join(sorted(DATASETS))})"
        ) from None


def default_source(dataset: str) -> Path:
    return shared_data_root() / find_dataset(dataset).folder


def load(dataset: str, source: Path | None = None, raw: bool = False) -> pd.DataFrame:
    """Convert ``dataset`` into a canonical frame without writing it; ``raw``: every sample
    where the converter would average."""
    spec = find_dataset(dataset)
    src = Path(source) if source is not None else shared_data_root() / spec.folder
    if not src.exists():
        raise DataError(f"{src}: no such file or directory")
    read = spec.read_raw if raw and spec.read_raw is not None else spec.read
    return read(src)


def convert(dataset: str, source: Path | None, out: Path, raw: bool = False) -> ConvertSummary:
    """Convert ``dataset`` (``source`` or its shared-data folder) into canonical CSV ``out``."""
    df = load(dataset, source, raw)
    out = Path(out)
    write_history(df, out)
    present = set(df["sensor"].unique())
    spec = DATASETS[dataset]
    sensors = tuple(s for s in spec.sensors if s in present)
    sensors += tuple(sorted(present - set(sensors)))
    return ConvertSummary(
        dataset=dataset,
        rows=len(df),
        sensors=sensors,
        first=df["ts"].iloc[0],
        last=df["ts"].iloc[-1],
        out=out,
    )
