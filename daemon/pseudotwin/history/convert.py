"""Converters of the shared datasets into the canonical history (long ``sensor, ts, value``).

``pseudotwin convert DATASET --out FILE.csv`` turns one dataset of ``../shared/data`` into a
canonical CSV (ts ISO 8601 UTC with offset, written by :func:`history.write_history`), so
every experiment and the daemon's backfill read the same thing through
:func:`history.read_history`.

Sensors
-------
Every measured channel is kept as its own sensor (covariate models read them next to the
references); ``Dataset.units`` gives each sensor's unit. Not kept: columns that are not
measurements (SML2010's weather *forecast* ``Weather_Temperature``, the day of week; the
Appliances random ``rv1``/``rv2``), SML2010's enthalpic-motor states (0 throughout both
files) and Room Climate's activity label (a nominal class, not a level).

sensor                          source column                           unit
------------------------------  --------------------------------------  --------
sml2010 (15-min means; column numbers of the ``#`` header)
  dining/temp                   3 Temperature_Comedor_Sensor            °C
  room/temp                     4 Temperature_Habitacion_Sensor         °C
  dining/co2                    6 CO2_Comedor_Sensor                    ppm
  room/co2                      7 CO2_Habitacion_Sensor                 ppm
  outdoor/temp                  22 Temperature_Exterior_Sensor          °C
  dining/humidity               8 Humedad_Comedor_Sensor                %
  room/humidity                 9 Humedad_Habitacion_Sensor             %
  dining/light                  10 Lighting_Comedor_Sensor              lx
  room/light                    11 Lighting_Habitacion_Sensor           lx
  outdoor/humidity              23 Humedad_Exterior_Sensor              %
  outdoor/rain                  12 Precipitacion (share of the 15 min)  fraction
  outdoor/twilight              13 Meteo_Exterior_Crepusculo            lx
  outdoor/wind                  14 Meteo_Exterior_Viento                m/s
  outdoor/light_west            15 Meteo_Exterior_Sol_Oest (façade)     lx
  outdoor/light_east            16 Meteo_Exterior_Sol_Est               lx
  outdoor/light_south           17 Meteo_Exterior_Sol_Sud               lx
  outdoor/irradiance            18 Meteo_Exterior_Piranometro           W/m²
appliances (10 min; ROOM = kitchen, living, laundry, office, bathroom, outside, ironing,
teen, parents for i = 1..9)
  ROOM/temp                     Ti                                      °C
  ROOM/humidity                 RH_i                                    %
  house/appliances              Appliances (energy in the 10 min)       Wh
  house/lights                  lights (energy in the 10 min)           Wh
  weather/temp                  T_out (airport)                         °C
  weather/humidity              RH_out                                  %
  weather/pressure              Press_mm_hg                             mmHg
  weather/wind                  Windspeed                               m/s
  weather/visibility            Visibility                              km
  weather/dewpoint              Tdewpoint                               °C
room-climate-a, -b, -c (X = A, B or C, k = node 1..4, 1..3 or 1..5; 1-min means, ground
truth: maxima; location C is not in the shared data, ``--source`` its folder)
  Xk/temp                       Temp                                    °C
  Xk/humidity                   RelH                                    %
  Xk/light1, Xk/light2          L1, L2                                  a.u.
  X/occupancy                   Occ                                     persons
  X/door, X/window              Door, Win (0 closed, 1 open)            open=1

Units that differ from PROVENANCE: SML2010 columns 15–17 reach 95,000, so they are
illuminance in lux (UCI: "sun light in … facade, in Lux"), not W/m² (the pyranometer, 18,
is). Room Climate's README calls L1/L2 "Wavelength [nm]", but they follow daylight (higher
at midday, both sensors r ≈ 0.98): uncalibrated light levels. Door and window are set per
episode (an experimental condition): A's door is open in episodes 45–60, the window never
(A, B), B's door never, so ``A/window``, ``B/door`` and ``B/window`` are constant 0.

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
* ``appliances``: the house sensors (T, RH, energy) run on a **fixed UTC+1 clock** (Belgian
  winter time, never switched): 2016-03-27 02:00–02:50 are real, varying readings in an unbroken
  10-min grid, and the household's daily routine (appliance load) moves one hour earlier on
  that clock after 27 March. The weather columns were merged from the airport by Belgian
  wall time *with* DST: T_out tracks the façade sensor T6 with ~0 lag before 27 March and
  lags it by ~1 h afterwards. So the ``weather/*`` sensors are read as Europe/Brussels;
  their six stamps 02:00–02:50 on 2016-03-27 do not exist on that clock (they are interpolation
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
Humidity and the light levels are averaged the same way; ``X/occupancy`` is the maximum
ground-truth occupant count (0–2) in that minute and ``X/door``/``X/window`` the maximum state
(open if open at any sample of it).

``--raw`` keeps every sample instead (ts = AbsT to the millisecond; samples of one node at
one instant averaged, of the location the maximum): a real chatty sensor for the window's
thinning (DESIGN §2), its tests and benchmarks. The other datasets have no averaging to
skip; ``--raw`` gives them as they are.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Mapping, Sequence
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
    """One output sensor: the source column it comes from, the clock that column runs on and
    the unit of its values."""

    sensor: str
    column: str | int
    clock: str
    unit: str


@dataclass(frozen=True)
class Dataset:
    """A registered converter: ``read(source)`` returns a canonical long frame.

    units: every sensor it writes → the unit of its values, in the order ``convert`` lists
    them (the original channels first, so summaries keep their order).
    """

    name: str
    folder: str  # relative to the shared data root
    description: str
    units: Mapping[str, str]
    read: Callable[[Path], pd.DataFrame]
    read_raw: Callable[[Path], pd.DataFrame] | None = None  # every sample, where read averages
    # Where the files come from when the shared data does not hold them (``--source`` needed).
    elsewhere: str = ""

    @property
    def shared(self) -> bool:
        """The shared data holds this dataset (``convert`` needs no ``--source``)."""
        return not self.elsewhere

    @property
    def sensors(self) -> tuple[str, ...]:
        return tuple(self.units)

    def unit(self, sensor: str) -> str:
        """The unit of ``sensor``'s values; DataError for a sensor the dataset lacks."""
        try:
            return self.units[sensor]
        except KeyError:
            raise DataError(f"dataset {self.name} has no sensor {sensor!r}") from None


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

# Column numbers are the 1-based ones of the file header; every kept column's header name is
# checked, so a reordered file cannot put lux under a temperature id.
_SML_HEADER = {
    1: "Date",
    2: "Time",
    3: "Temperature_Comedor_Sensor",
    4: "Temperature_Habitacion_Sensor",
    6: "CO2_Comedor_Sensor",
    7: "CO2_Habitacion_Sensor",
    8: "Humedad_Comedor_Sensor",
    9: "Humedad_Habitacion_Sensor",
    10: "Lighting_Comedor_Sensor",
    11: "Lighting_Habitacion_Sensor",
    12: "Precipitacion",
    13: "Meteo_Exterior_Crepusculo",
    14: "Meteo_Exterior_Viento",
    15: "Meteo_Exterior_Sol_Oest",
    16: "Meteo_Exterior_Sol_Est",
    17: "Meteo_Exterior_Sol_Sud",
    18: "Meteo_Exterior_Piranometro",
    22: "Temperature_Exterior_Sensor",
    23: "Humedad_Exterior_Sensor",
}
_SML_NCOLS = 24
_SML_CHANNELS = (
    Channel("dining/temp", 3, "UTC", "°C"),
    Channel("room/temp", 4, "UTC", "°C"),
    Channel("dining/co2", 6, "UTC", "ppm"),
    Channel("room/co2", 7, "UTC", "ppm"),
    Channel("outdoor/temp", 22, "UTC", "°C"),
    Channel("dining/humidity", 8, "UTC", "%"),
    Channel("room/humidity", 9, "UTC", "%"),
    Channel("dining/light", 10, "UTC", "lx"),
    Channel("room/light", 11, "UTC", "lx"),
    Channel("outdoor/humidity", 23, "UTC", "%"),
    Channel("outdoor/rain", 12, "UTC", "fraction"),
    Channel("outdoor/twilight", 13, "UTC", "lx"),
    Channel("outdoor/wind", 14, "UTC", "m/s"),
    Channel("outdoor/light_west", 15, "UTC", "lx"),
    Channel("outdoor/light_east", 16, "UTC", "lx"),
    Channel("outdoor/light_south", 17, "UTC", "lx"),
    Channel("outdoor/irradiance", 18, "UTC", "W/m²"),
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
_APPLIANCES_ROOMS = ("kitchen", "living", "laundry", "office", "bathroom", "outside", "ironing",
                     "teen", "parents")  # T1..T9 and RH_1..RH_9, in that order
_WEATHER = "Europe/Brussels"
_APPLIANCES_CHANNELS = (
    *(Channel(f"{room}/temp", f"T{i}", _UTC_PLUS_1, "°C")
      for i, room in enumerate(_APPLIANCES_ROOMS, start=1)),
    Channel("weather/temp", "T_out", _WEATHER, "°C"),
    *(Channel(f"{room}/humidity", f"RH_{i}", _UTC_PLUS_1, "%")
      for i, room in enumerate(_APPLIANCES_ROOMS, start=1)),
    # Metered by the house, so on the house's clock; energy used in the 10 minutes.
    Channel("house/appliances", "Appliances", _UTC_PLUS_1, "Wh"),
    Channel("house/lights", "lights", _UTC_PLUS_1, "Wh"),
    # The airport columns were merged like T_out, so they share its clock.
    Channel("weather/humidity", "RH_out", _WEATHER, "%"),
    Channel("weather/pressure", "Press_mm_hg", _WEATHER, "mmHg"),
    Channel("weather/wind", "Windspeed", _WEATHER, "m/s"),
    Channel("weather/visibility", "Visibility", _WEATHER, "km"),
    Channel("weather/dewpoint", "Tdewpoint", _WEATHER, "°C"),
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
_RC_ABST, _RC_NID = 1, 3
# Location C (5 nodes, early 2017) is not in the shared data; its files have the same format.
_RC_NODES = {"A": (1, 2, 3, 4), "B": (1, 2, 3), "C": (1, 2, 3, 4, 5)}
# Per node, averaged over the bucket: output name (``A1/humidity``) → (column, its README
# name, unit). L1/L2 are documented as "Light Sensor (Wavelength) [nm]", but their values
# rise and fall with the room's light; they are uncalibrated light levels, hence "a.u.".
_RC_NODE_VALUES = {
    "temp": (4, "Temp", "°C"),
    "humidity": (5, "RelH", "%"),
    "light1": (6, "L1", "a.u."),
    "light2": (7, "L2", "a.u."),
}
# Per location, the maximum over the bucket (ground truth: any open moment counts as open).
# Act (activity class 0–4) is a nominal label, not a level, and is not kept.
_RC_LOCATION_VALUES = {
    "occupancy": (8, "Occ", "persons"),
    "door": (10, "Door", "open=1"),
    "window": (11, "Win", "open=1"),
}


def _room_climate_units(location: str) -> dict[str, str]:
    """The sensors of one location in output order (the original temp/occupancy first)."""
    nodes = _RC_NODES[location]
    units = {f"{location}{n}/temp": _RC_NODE_VALUES["temp"][2] for n in nodes}
    units[f"{location}/occupancy"] = _RC_LOCATION_VALUES["occupancy"][2]
    for name, (_, _, unit) in _RC_NODE_VALUES.items():
        if name != "temp":
            units.update({f"{location}{n}/{name}": unit for n in nodes})
    for name, (_, _, unit) in _RC_LOCATION_VALUES.items():
        if name != "occupancy":
            units[f"{location}/{name}"] = unit
    return units


def _read_room_climate_file(path: Path, location: str) -> pd.DataFrame:
    # The files name their location; node ids alone do not tell A's 1–4 from C's 1–5.
    named = re.search(r"location_([A-Za-z])(?![A-Za-z])", path.name)
    if named and (other := named.group(1).upper()) != location:
        instead = (f" (convert room-climate-{other.lower()} instead)" if other in _RC_NODES
                   else "")
        raise DataError(f"{path}: a file of location {other}, not {location}{instead}")
    try:
        raw = pd.read_csv(path, header=None, skipinitialspace=True)
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not readable as room-climate CSV ({exc})") from None
    if raw.shape[1] != _RC_NCOLS:
        raise DataError(
            f"{path}: expected {_RC_NCOLS} columns (EID, AbsT, RelT, NID, Temp, RelH, L1, L2, "
            f"Occ, Act, Door, Win), found {raw.shape[1]}"
        )
    columns = {"abst": (_RC_ABST, "AbsT"), "nid": (_RC_NID, "NID")}
    columns.update({k: (col, what) for k, (col, what, _) in _RC_NODE_VALUES.items()})
    columns.update({k: (col, what) for k, (col, what, _) in _RC_LOCATION_VALUES.items()})
    out = pd.DataFrame({k: _numeric(raw[col], path, what, 1) for k, (col, what) in columns.items()})
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


def _epoch_ms(values: pd.Index) -> pd.Series:
    return pd.Series(pd.to_datetime(values, unit="ms", utc=True))


def _room_climate_frame(raw: pd.DataFrame, key: str, source: Path, location: str) -> pd.DataFrame:
    """Per node the mean of each node value, and per location the maximum of each ground
    truth, of each value of column ``key`` (epoch ms: the sample's own time, or its minute)."""
    parts = []
    for name in _RC_NODE_VALUES:
        mean = raw.dropna(subset=["nid", name]).groupby(["nid", key])[name].mean()
        for nid, series in mean.groupby(level="nid"):
            ts = _epoch_ms(pd.Index(series.index.get_level_values(key)))
            parts.append(_long(f"{location}{int(nid)}/{name}", ts, series.reset_index(drop=True)))
    for name in _RC_LOCATION_VALUES:
        peak = raw.dropna(subset=[name]).groupby(key)[name].max()
        if len(peak):
            parts.append(_long(f"{location}/{name}", _epoch_ms(peak.index),
                               peak.reset_index(drop=True)))
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


def _room_climate_dataset(location: str, about: str, elsewhere: str = "") -> Dataset:
    """The converter of one Room Climate location (``about``: its nodes and room)."""
    return Dataset(
        f"room-climate-{location.lower()}",
        f"room_climate/datasets-location_{location}",
        f"{about}; occupancy, door, window (1-min means)"
        + ("; not in the shared data: --source DIR" if elsewhere else ""),
        _room_climate_units(location),
        partial(read_room_climate, location=location),
        partial(read_room_climate_raw, location=location),
        elsewhere=elsewhere,
    )


def _channel_units(channels: Sequence[Channel]) -> dict[str, str]:
    return {ch.sensor: ch.unit for ch in channels}


DATASETS: dict[str, Dataset] = {
    "sml2010": Dataset(
        "sml2010",
        "sml2010",
        "UCI SML2010 house, Valencia 2012: dining/room temp, CO2, humidity, light; outdoor "
        "temp, humidity, wind, rain, sun (15 min, UTC)",
        _channel_units(_SML_CHANNELS),
        read_sml2010,
    ),
    "room-climate-a": _room_climate_dataset(
        "A", "FAU office A 2016: 4 temp/humidity/light nodes in one room, A4 above the desk"),
    "room-climate-b": _room_climate_dataset(
        "B", "FAU office B 2016: 3 temp/humidity/light nodes in one room, B2 between the desks"),
    "room-climate-c": _room_climate_dataset(
        "C", "FAU location C 2017: 5 temp/humidity/light nodes in one room",
        elsewhere="the datasets-location_C folder of github.com/IoTsec/Room-Climate-Datasets"),
    "appliances": Dataset(
        "appliances",
        "appliances",
        "UCI appliances house, Belgium 2016: 9 room/outside temps + humidities, appliance and "
        "light energy, airport weather (10 min)",
        _channel_units(_APPLIANCES_CHANNELS),
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
    """Where ``dataset`` lies in the shared data; DataError for one that is not there."""
    spec = find_dataset(dataset)
    if not spec.shared:
        raise DataError(f"{dataset} is not part of the shared data: give --source DIR "
                        f"({spec.elsewhere})")
    return shared_data_root() / spec.folder


def load(dataset: str, source: Path | None = None, raw: bool = False) -> pd.DataFrame:
    """Convert ``dataset`` into a canonical frame without writing it; ``raw``: every sample
    where the converter would average."""
    spec = find_dataset(dataset)
    src = _source(dataset, source)
    read = spec.read_raw if raw and spec.read_raw is not None else spec.read
    return read(src)


def _source(dataset: str, source: Path | None) -> Path:
    """The dataset's file or folder: ``source``, else its shared-data folder."""
    src = Path(source) if source is not None else default_source(dataset)
    if not src.exists():
        raise DataError(f"{src}: no such file or directory")
    return src


def convert(dataset: str, source: Path | None, out: Path, raw: bool = False) -> ConvertSummary:
    """Convert ``dataset`` (``source`` or its shared-data folder) into canonical CSV ``out``."""
    src, out = _source(dataset, source).resolve(), Path(out)
    # Not even a new file in its folder: a converter that reads the folder's files (Room
    # Climate's *.csv) would take it for data the next time.
    if out.resolve() == src or src in out.resolve().parents:
        raise DataError(f"{out}: the output would be written into the dataset ({src}); "
                        "give a path outside it")
    df = load(dataset, src, raw)
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
