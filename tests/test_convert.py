"""Converters of the shared datasets, run on the real data in ``<repo>/../shared/data``."""

from __future__ import annotations

import datetime as dt
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pseudotwin.cli import convert as cc  # the command; cv is the converters
from pseudotwin.core.series import read_history, write_history
from pseudotwin.errors import ConfigError, DataError
from pseudotwin.history import convert as cv

REPO = Path(__file__).resolve().parents[1]
ROOT = cv.shared_data_root()

needs_data = pytest.mark.skipif(not ROOT.is_dir(), reason=f"shared data not found at {ROOT}")

# The sensors the converters wrote before they kept every channel: their ids and values must
# not change (results and artifacts depend on them).
SML_SENSORS = ("dining/temp", "room/temp", "dining/co2", "room/co2", "outdoor/temp")
APPLIANCE_HOUSE = (
    "kitchen/temp",
    "living/temp",
    "laundry/temp",
    "office/temp",
    "bathroom/temp",
    "outside/temp",
    "ironing/temp",
    "teen/temp",
    "parents/temp",
)


APPLIANCE_ROOMS = tuple(s.split("/")[0] for s in APPLIANCE_HOUSE)
APPLIANCE_HOUSE_EXTRA = (*(f"{r}/humidity" for r in APPLIANCE_ROOMS), "house/appliances",
                         "house/lights")
APPLIANCE_WEATHER = ("weather/temp", "weather/humidity", "weather/pressure", "weather/wind",
                     "weather/visibility", "weather/dewpoint")
SML_EXTRA = ("dining/humidity", "room/humidity", "dining/light", "room/light",
             "outdoor/humidity", "outdoor/rain", "outdoor/twilight", "outdoor/wind",
             "outdoor/light_west", "outdoor/light_east", "outdoor/light_south",
             "outdoor/irradiance")

# (rows, sum of values) per original sensor, as the converter wrote them before the other
# channels were kept; sums to 4 decimals.
ORIGINAL = {
    "sml2010": {
        "dining/co2": (4137, 854703.517), "dining/temp": (4137, 84781.7334),
        "outdoor/temp": (4137, 74545.9728), "room/co2": (4137, 867163.285),
        "room/temp": (4137, 83344.2085),
    },
    "room-climate-a": {
        "A/occupancy": (4460, 2748.0), "A1/temp": (4460, 95295.1264),
        "A2/temp": (4460, 96649.8368), "A3/temp": (4460, 95118.3108),
        "A4/temp": (4460, 97291.6865),
    },
    "room-climate-b": {
        "B/occupancy": (3267, 2155.0), "B1/temp": (3266, 74294.4674),
        "B2/temp": (3266, 73181.7708), "B3/temp": (3267, 73597.0427),
    },
    "appliances": {
        "bathroom/temp": (19735, 386650.2184), "ironing/temp": (19735, 399971.3462),
        "kitchen/temp": (19735, 427984.4863), "laundry/temp": (19735, 439451.3028),
        "living/temp": (19735, 401433.9661), "office/temp": (19735, 411580.0307),
        "outside/temp": (19735, 156122.3877), "parents/temp": (19735, 384552.8187),
        "teen/temp": (19735, 434744.4212), "weather/temp": (19729, 146243.3572),
    },
}


Converted = dict[str, tuple[cv.ConvertSummary, pd.DataFrame]]
SHARED = [name for name, spec in cv.DATASETS.items() if spec.shared]


def utc(text: str) -> pd.Timestamp:
    return pd.Timestamp(text, tz="UTC")


def at(df: pd.DataFrame, sensor: str, ts: str) -> float:
    hit = df[(df["sensor"] == sensor) & (df["ts"] == utc(ts))]
    assert len(hit) == 1, f"{sensor} at {ts}: {len(hit)} rows"
    return float(hit["value"].iloc[0])


@pytest.fixture(scope="module")
def converted(tmp_path_factory: pytest.TempPathFactory) -> Converted:
    """Every dataset converted once to CSV and read back through the canonical reader."""
    if not ROOT.is_dir():
        pytest.skip(f"shared data not found at {ROOT}")
    out_dir = tmp_path_factory.mktemp("converted")
    result = {}
    for name in SHARED:
        summary = cv.convert(name, None, out_dir / f"{name}.csv")
        result[name] = (summary, read_history(summary.out))
    return result


def counts(df: pd.DataFrame) -> dict[str, int]:
    return {str(k): int(v) for k, v in df.groupby("sensor").size().items()}


def stamps(df: pd.DataFrame, sensor: str) -> pd.DatetimeIndex:
    return pd.DatetimeIndex(df.loc[df["sensor"] == sensor, "ts"])


def values(df: pd.DataFrame, sensor: str) -> pd.Series:
    return df.loc[df["sensor"] == sensor, "value"]


# ---------------------------------------------------------------------------- resolution


def test_default_root_is_repo_sibling_shared_data(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(cv.SHARED_DATA_ENV, raising=False)
    assert cv.shared_data_root() == REPO.parent / "shared" / "data"
    assert cv.default_source("room-climate-b") == (
        REPO.parent / "shared" / "data" / "room_climate" / "datasets-location_B"
    )


def test_env_var_overrides_root(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(cv.SHARED_DATA_ENV, str(tmp_path))
    assert cv.default_source("appliances") == tmp_path / "appliances"
    with pytest.raises(DataError, match=re.escape(str(tmp_path / "appliances"))):
        cv.load("appliances")


# ---------------------------------------------------------------------------- all datasets


@needs_data
@pytest.mark.parametrize("name", SHARED)
def test_canonical_shape_and_round_trip(
    converted: Converted, name: str
) -> None:
    summary, back = converted[name]
    assert summary.sensors == cv.DATASETS[name].sensors
    assert set(back["sensor"]) == set(cv.DATASETS[name].sensors)
    assert summary.rows == len(back)
    assert (summary.first, summary.last) == (back["ts"].iloc[0], back["ts"].iloc[-1])

    header, first = summary.out.read_text().splitlines()[:2]
    assert header == "sensor,ts,value"
    assert first.split(",")[1].endswith("+00:00")

    assert str(back["ts"].dt.tz) == "UTC"
    assert not back.duplicated(["sensor", "ts"]).any()
    for sensor, g in back.groupby("sensor"):
        assert g["ts"].is_monotonic_increasing and g["ts"].is_unique, sensor

    # The CSV keeps 6 significant digits; nothing else may change on the way through disk.
    direct = cv.load(name)
    both = direct.merge(back, on=["sensor", "ts"], how="outer", indicator=True)
    assert (both["_merge"] == "both").all()
    np.testing.assert_allclose(both["value_y"], both["value_x"], rtol=1e-5)


@needs_data
@pytest.mark.parametrize("name", SHARED)
def test_original_sensors_unchanged(name: str) -> None:
    """Keeping more channels adds sensors only: the original ones keep their ids, rows and
    values, and come first in the dataset's listing."""
    df = cv.load(name)
    original = ORIGINAL[name]
    kept = df[df["sensor"].isin(list(original))]
    got = {str(s): (len(g), round(float(g["value"].sum()), 4)) for s, g in kept.groupby("sensor")}
    assert got.keys() == original.keys()
    for sensor, (n, total) in original.items():
        assert got[sensor][0] == n, sensor
        assert got[sensor][1] == pytest.approx(total, abs=1e-3), sensor
    assert set(cv.DATASETS[name].sensors[: len(original)]) == set(original)


@pytest.mark.parametrize("name", list(cv.DATASETS))
def test_every_sensor_has_a_unit(name: str) -> None:
    spec = cv.DATASETS[name]
    assert len(spec.sensors) == len(set(spec.sensors)) > len(ORIGINAL.get(name, ()))
    for sensor in spec.sensors:
        assert spec.unit(sensor).strip(), sensor
    assert spec.unit(spec.sensors[0]) == "°C"
    with pytest.raises(DataError, match=f"dataset {name} has no sensor 'nope/temp'"):
        spec.unit("nope/temp")


def test_units_of_the_kept_channels() -> None:
    sml, app = cv.DATASETS["sml2010"], cv.DATASETS["appliances"]
    a, b = cv.DATASETS["room-climate-a"], cv.DATASETS["room-climate-b"]
    assert [sml.unit(s) for s in ("dining/co2", "room/humidity", "room/light",
                                  "outdoor/irradiance", "outdoor/light_south")] == [
        "ppm", "%", "lx", "W/m²", "lx"]
    assert [app.unit(s) for s in ("teen/humidity", "house/lights", "weather/pressure",
                                  "weather/dewpoint")] == ["%", "Wh", "mmHg", "°C"]
    assert [a.unit(s) for s in ("A4/humidity", "A2/light1", "A/door", "A/occupancy")] == [
        "%", "a.u.", "open=1", "persons"]
    assert set(b.sensors) == {
        *(f"B{k}/{q}" for k in (1, 2, 3) for q in ("temp", "humidity", "light1", "light2")),
        "B/occupancy", "B/door", "B/window"}
    assert set(cv.DATASETS["room-climate-c"].sensors) == {
        *(f"C{k}/{q}" for k in range(1, 6) for q in ("temp", "humidity", "light1", "light2")),
        "C/occupancy", "C/door", "C/window"}


# ---------------------------------------------------------------------------- SML2010


@needs_data
def test_sml2010_counts_and_span(converted: Converted) -> None:
    summary, df = converted["sml2010"]
    # PROVENANCE: 2,764 + 1,373 = 4,137 timestamps. None is dropped: the logger clock is UTC,
    # so the night of 2012-03-25 has no nonexistent or repeated times to lose.
    assert counts(df) == {s: 4137 for s in (*SML_SENSORS, *SML_EXTRA)}
    assert summary.rows == 17 * 4137
    assert summary.first == utc("2012-03-13 11:45")
    assert summary.last == utc("2012-05-02 07:30")
    assert at(df, "dining/temp", "2012-03-13 11:45") == pytest.approx(18.1875)
    assert at(df, "outdoor/temp", "2012-03-13 11:45") == pytest.approx(18.115)


@needs_data
def test_sml2010_gaps_match_provenance(
    converted: Converted,
) -> None:
    _, df = converted["sml2010"]
    ts = df.loc[df["sensor"] == "room/temp", "ts"]
    step = ts.diff().dropna()
    gaps = step[step > pd.Timedelta("15min")]
    assert sorted(gaps.tolist()) == [
        pd.Timedelta("30min"),
        pd.Timedelta("30min"),
        pd.Timedelta("6D17h30min"),  # between the two files: 04-11 06:30 → 04-18 00:00
    ]


@needs_data
def test_sml2010_dst_night_is_continuous(
    converted: Converted,
) -> None:
    _, df = converted["sml2010"]
    # 02:15 on 2012-03-25 does not exist in Europe/Madrid (02:00 → 03:00) yet the file has
    # it: the clock ignores DST. It must land at 02:15 UTC, not be shifted onto 03:00.
    with pytest.raises(ValueError, match="nonexistent"):
        pd.DatetimeIndex(["2012-03-25 02:15"]).tz_localize("Europe/Madrid", nonexistent="raise")
    assert at(df, "dining/temp", "2012-03-25 02:15") == pytest.approx(16.99)
    assert at(df, "room/temp", "2012-03-25 02:15") == pytest.approx(16.4827)
    for sensor in (*SML_SENSORS, *SML_EXTRA):
        day = df[(df["sensor"] == sensor) & (df["ts"].dt.date == dt.date(2012, 3, 25))]
        assert len(day) == 96
        assert (day["ts"].diff().dropna() == pd.Timedelta("15min")).all()


def _sunrise_sunset_utc(day: dt.date, lat: float, lon: float) -> tuple[float, float]:
    """NOAA approximation, hours UTC (good to a few minutes)."""
    g = 2 * np.pi / 365 * (day.timetuple().tm_yday - 1)
    eot = 229.18 * (
        0.000075 + 0.001868 * np.cos(g) - 0.032077 * np.sin(g)
        - 0.014615 * np.cos(2 * g) - 0.040849 * np.sin(2 * g)
    )
    decl = (
        0.006918 - 0.399912 * np.cos(g) + 0.070257 * np.sin(g) - 0.006758 * np.cos(2 * g)
        + 0.000907 * np.sin(2 * g) - 0.002697 * np.cos(3 * g) + 0.00148 * np.sin(3 * g)
    )
    la = np.radians(lat)
    ha = np.degrees(
        np.arccos(
            np.cos(np.radians(90.833)) / (np.cos(la) * np.cos(decl)) - np.tan(la) * np.tan(decl)
        )
    )
    noon = 720 - 4 * lon - eot
    return (noon - 4 * ha) / 60, (noon + 4 * ha) / 60


@needs_data
def test_sml2010_clock_is_utc_by_the_sun() -> None:
    """Why the converter reads SML2010 as UTC: dawn/dusk on the twilight sensor fall at the
    UTC sunrise/sunset of Valencia both before and after the DST change (CET would put
    them ~1 h late, CEST ~2 h)."""
    raw = pd.concat(
        pd.read_csv(p, sep=r"\s+", header=None, comment="#", dtype={0: str, 1: str})
        for p in sorted((ROOT / "sml2010").glob("NEW-DATA-*.T15.txt"))
    )
    stamp = pd.to_datetime(raw[0] + " " + raw[1], format="%d/%m/%Y %H:%M")
    hours = (stamp.dt.hour + stamp.dt.minute / 60).to_numpy()
    twilight = raw[12].to_numpy()  # column 13 Meteo_Exterior_Crepusculo
    offsets = {"before": [], "after": []}
    for day in sorted(set(stamp.dt.date)):
        on = (stamp.dt.date == day).to_numpy()
        h, tw = hours[on], twilight[on]
        if len(h) < 90:
            continue
        up = np.flatnonzero((tw[1:] > 300) & (tw[:-1] <= 300))
        down = np.flatnonzero((tw[1:] < 300) & (tw[:-1] >= 300))
        rise, sset = _sunrise_sunset_utc(day, 39.47, -0.38)
        side = "before" if day < dt.date(2012, 3, 25) else "after"
        offsets[side] += [h[up[0] + 1] - rise, h[down[-1]] - sset]
    for side, off in offsets.items():
        assert len(off) > 20, side
        assert abs(np.median(off)) < 0.35, (side, np.median(off))


@needs_data
def test_sml2010_plausible_values(converted: Converted) -> None:
    _, df = converted["sml2010"]
    temp = df[df["sensor"].isin(["dining/temp", "room/temp"])]["value"]
    co2 = df[df["sensor"].str.endswith("/co2")]["value"]
    # PROVENANCE ranges: temps 11.08–28.92 °C; CO2 187–609 ppm (offset, uncalibrated sensors).
    assert temp.between(11.0, 29.0).all()
    assert co2.between(187.0, 610.0).all()
    assert df.loc[df["sensor"] == "outdoor/temp", "value"].between(5.0, 35.0).all()


@needs_data
def test_sml2010_kept_channels(converted: Converted) -> None:
    _, df = converted["sml2010"]
    # Every channel comes from the same rows, on the same (UTC) clock as the temperatures.
    for sensor in SML_EXTRA:
        assert stamps(df, sensor).equals(stamps(df, "dining/temp")), sensor
    for sensor in ("dining/humidity", "room/humidity", "outdoor/humidity"):
        assert values(df, sensor).between(0.0, 100.0).all(), sensor
        assert values(df, sensor).std() > 5.0, sensor  # a real, varying humidity
    for sensor in ("dining/light", "room/light", "outdoor/twilight", "outdoor/light_west",
                   "outdoor/light_east", "outdoor/light_south", "outdoor/wind"):
        assert (values(df, sensor) >= 0.0).all(), sensor
    assert values(df, "outdoor/rain").between(0.0, 1.0).all()
    # The pyranometer reads a few W/m² below zero at night (its offset), ~1100 at noon.
    assert values(df, "outdoor/irradiance").between(-5.0, 1200.0).all()
    # First row of NEW-DATA-1: columns 8, 10, 17, 18 and 23 of the file.
    first = "2012-03-13 11:45"
    assert at(df, "dining/humidity", first) == pytest.approx(39.9125)
    assert at(df, "dining/light", first) == pytest.approx(81.665)
    assert at(df, "outdoor/light_south", first) == pytest.approx(95436.8)
    assert at(df, "outdoor/irradiance", first) == pytest.approx(758.88)
    assert at(df, "outdoor/humidity", first) == pytest.approx(48.375)
    # Daylight: façade light and irradiance are ~0 at 00:00 UTC and high at 12:00 UTC.
    wide = df.pivot(index="ts", columns="sensor", values="value")
    hour = pd.DatetimeIndex(wide.index).hour
    for sensor in ("outdoor/irradiance", "outdoor/light_south"):
        night, noon = wide.loc[hour == 0, sensor].median(), wide.loc[hour == 12, sensor].median()
        assert noon > 20 * max(night, 1.0), sensor


# ---------------------------------------------------------------------------- appliances


@needs_data
def test_appliances_counts(converted: Converted) -> None:
    summary, df = converted["appliances"]
    expected = {s: 19735 for s in (*APPLIANCE_HOUSE, *APPLIANCE_HOUSE_EXTRA)}
    # 2016-03-27 02:00–02:50 do not exist on Belgian wall time, the clock of the merged
    # airport weather: those six interpolated rows of every weather column are dropped.
    expected.update({s: 19735 - 6 for s in APPLIANCE_WEATHER})
    assert counts(df) == expected
    # The house clock is fixed UTC+1: 2016-01-11 17:00 → 16:00Z, 2016-05-27 18:00 → 17:00Z.
    assert summary.first == utc("2016-01-11 16:00")
    assert summary.last == utc("2016-05-27 17:00")
    for sensor in APPLIANCE_HOUSE:
        ts = df.loc[df["sensor"] == sensor, "ts"]
        assert (ts.diff().dropna() == pd.Timedelta("10min")).all(), sensor


@needs_data
def test_appliances_dst_day(converted: Converted) -> None:
    _, df = converted["appliances"]
    # House sensors: real readings at 02:xx on the clock that never switched.
    assert at(df, "kitchen/temp", "2016-03-27 00:50") == pytest.approx(22.89)  # 01:50 label
    assert at(df, "kitchen/temp", "2016-03-27 02:00") == pytest.approx(22.79)  # 03:00 label
    assert at(df, "kitchen/temp", "2016-03-27 10:00") == pytest.approx(22.6)  # 11:00 label
    # Weather: Belgian wall time, so the 12:00 label after the change is CEST = 10:00Z and
    # the 01:50 CET label is 00:50Z; nothing between 01:00Z and 00:50Z+1h is invented.
    assert at(df, "weather/temp", "2016-03-27 10:00") == pytest.approx(9.5)
    assert at(df, "weather/temp", "2016-03-27 00:50") == pytest.approx(7.55)
    assert at(df, "weather/temp", "2016-03-27 01:00") == pytest.approx(7.20)  # 03:00 CEST
    weather = df[df["sensor"] == "weather/temp"].set_index("ts")["value"]
    assert weather.loc[utc("2016-03-27 00:51") : utc("2016-03-27 00:59")].empty


def _best_lag(a: pd.Series, b: pd.Series, max_steps: int = 12) -> int:
    """Lag (10-min steps) at which b's changes correlate best with a's; > 0: b is late."""
    x, y = a.diff().to_numpy()[1:], b.diff().to_numpy()[1:]
    lags = list(range(-max_steps, max_steps + 1))
    r = [
        np.corrcoef(x[max(0, -k) : len(x) - max(0, k)], y[max(0, k) : len(y) - max(0, -k)])[0, 1]
        for k in lags
    ]
    return lags[int(np.argmax(r))]


@needs_data
def test_appliances_weather_aligned_with_house_both_sides_of_dst(
    converted: Converted,
) -> None:
    """In the raw file T_out lags the façade sensor T6 by ~1 h after 27 March; with the
    per-column clocks the two agree within 20 min before and after."""
    _, df = converted["appliances"]
    wide = df.pivot(index="ts", columns="sensor", values="value")[["outside/temp", "weather/temp"]]
    wide = wide.asfreq("10min").interpolate(limit=6)
    for lo, hi in [("2016-01-12", "2016-03-26"), ("2016-03-28", "2016-05-27")]:
        part = wide.loc[lo:hi].dropna()
        assert abs(_best_lag(part["outside/temp"], part["weather/temp"])) <= 2, (lo, hi)


@needs_data
def test_appliances_plausible_values(
    converted: Converted,
) -> None:
    _, df = converted["appliances"]
    indoor = df[df["sensor"].isin([s for s in APPLIANCE_HOUSE if s != "outside/temp"])]["value"]
    assert indoor.between(14.0, 30.0).all()
    assert df[df["sensor"] == "outside/temp"]["value"].between(-7.0, 29.0).all()
    # E-notation T_out ("6.60E+00") parsed as numbers.
    assert at(df, "weather/temp", "2016-01-11 16:00") == pytest.approx(6.6)
    assert df[df["sensor"] == "weather/temp"]["value"].between(-5.0, 26.2).all()


@needs_data
def test_appliances_kept_channels(converted: Converted) -> None:
    _, df = converted["appliances"]
    # House channels on the house clock, airport channels on the weather clock: the same
    # instants as the temperatures of the same rows.
    for sensor in APPLIANCE_HOUSE_EXTRA:
        assert stamps(df, sensor).equals(stamps(df, "kitchen/temp")), sensor
    for sensor in APPLIANCE_WEATHER:
        assert stamps(df, sensor).equals(stamps(df, "weather/temp")), sensor
    for sensor in (*(f"{r}/humidity" for r in APPLIANCE_ROOMS), "weather/humidity"):
        assert values(df, sensor).between(0.0, 100.0).all(), sensor
    assert values(df, "house/appliances").between(10.0, 1080.0).all()
    assert set(values(df, "house/lights").unique()) <= set(range(0, 80, 10))  # Wh, 10-Wh steps
    assert values(df, "weather/pressure").between(720.0, 780.0).all()  # mm Hg
    assert (values(df, "weather/wind") >= 0).all() and (values(df, "weather/visibility") > 0).all()
    assert (values(df, "weather/dewpoint") <= values(df, "weather/temp").to_numpy() + 0.5).all()
    # The first row of the file (11-01-2016 17:00, house clock UTC+1; weather CET = UTC+1).
    assert at(df, "kitchen/humidity", "2016-01-11 16:00") == pytest.approx(47.59666667)
    assert at(df, "house/appliances", "2016-01-11 16:00") == 60.0
    assert at(df, "house/lights", "2016-01-11 16:00") == 30.0
    assert at(df, "weather/pressure", "2016-01-11 16:00") == pytest.approx(733.5)
    assert at(df, "weather/dewpoint", "2016-01-11 16:00") == pytest.approx(5.3)
    # After the DST change the weather's 12:00 label is CEST (10:00Z), as for T_out.
    raw = pd.read_csv(ROOT / "appliances/energydata_complete.csv", dtype={"date": str})
    row = raw[raw["date"].str.strip() == "27-03-2016 12:00"].iloc[0]
    assert at(df, "weather/humidity", "2016-03-27 10:00") == pytest.approx(row["RH_out"])
    assert at(df, "bathroom/humidity", "2016-03-27 11:00") == pytest.approx(row["RH_5"])


# ---------------------------------------------------------------------------- room climate


@needs_data
def test_room_climate_minutes(converted: Converted) -> None:
    _, a = converted["room-climate-a"]
    _, b = converted["room-climate-b"]
    # 73.5 h (A) / 54.0 h (B) of episodes in PROVENANCE → one row per node per covered minute
    # (episode edges add partial minutes). B3 has one minute with no B1/B2 sample.
    node = ("temp", "humidity", "light1", "light2")
    assert counts(a) == {**{f"A{k}/{q}": 4460 for k in (1, 2, 3, 4) for q in node},
                         "A/occupancy": 4460, "A/door": 4460, "A/window": 4460}
    assert counts(b) == {**{f"B{k}/{q}": 3266 for k in (1, 2) for q in node},
                         **{f"B3/{q}": 3267 for q in node},
                         "B/occupancy": 3267, "B/door": 3267, "B/window": 3267}
    for df in (a, b):
        assert (df["ts"].dt.second == 0).all() and (df["ts"].dt.microsecond == 0).all()
    assert a["ts"].iloc[0] == utc("2016-03-15 08:47")  # AbsT 1458031648545 ms
    assert b["ts"].iloc[-1] == utc("2016-04-27 12:34")


@needs_data
def test_room_climate_value_is_mean_of_the_minute(
    converted: Converted,
) -> None:
    _, a = converted["room-climate-a"]
    raw = pd.read_csv(
        ROOT / "room_climate/datasets-location_A/room_climate-location_A-measurement07.csv",
        header=None,
        skipinitialspace=True,
    )
    stamp = pd.to_datetime(raw[1], unit="ms", utc=True).dt.floor("min")
    minute = stamp.iloc[len(raw) // 2]
    for nid in (1, 4):
        sel = (stamp == minute) & (raw[3] == nid)
        assert sel.sum() >= 10  # ~4 s sampling
        assert at(a, f"A{nid}/temp", str(minute.tz_localize(None))) == pytest.approx(
            raw.loc[sel, 4].mean(), abs=1e-4
        )
    occ = raw.loc[stamp == minute, 8].max()
    assert at(a, "A/occupancy", str(minute.tz_localize(None))) == occ


@needs_data
def test_room_climate_kept_channels_are_minute_means_and_maxima(
    converted: Converted,
) -> None:
    _, a = converted["room-climate-a"]
    _, b = converted["room-climate-b"]
    frames = {}
    for loc in "AB":
        frames[loc] = pd.concat(
            pd.read_csv(p, header=None, skipinitialspace=True)
            for p in sorted((ROOT / f"room_climate/datasets-location_{loc}").glob("*.csv"))
        )
    raw = frames["A"]
    raw["minute"] = pd.to_datetime(raw[1], unit="ms", utc=True).dt.floor("min")
    # A minute with the door open (in the shared files the state never changes within a
    # minute; the maximum over mixed samples is tested on a synthetic file).
    per_minute = raw.groupby("minute")[10].max()
    minute = per_minute.index[per_minute == 1][len(per_minute[per_minute == 1]) // 2]
    label = str(minute.tz_localize(None))
    assert at(a, "A/door", label) == 1.0
    for nid in (2, 4):
        sel = (raw["minute"] == minute) & (raw[3] == nid)
        for col, q in ((5, "humidity"), (6, "light1"), (7, "light2")):
            assert at(a, f"A{nid}/{q}", label) == pytest.approx(raw.loc[sel, col].mean(),
                                                                abs=1e-3), (nid, q)
    # Node channels share the node's temperature minutes, ground truth the occupancy's.
    for df, loc, nodes in ((a, "A", (1, 2, 3, 4)), (b, "B", (1, 2, 3))):
        for k in nodes:
            for q in ("humidity", "light1", "light2"):
                assert stamps(df, f"{loc}{k}/{q}").equals(stamps(df, f"{loc}{k}/temp"))
        for q in ("door", "window"):
            assert stamps(df, f"{loc}/{q}").equals(stamps(df, f"{loc}/occupancy"))
    for df in (a, b):
        hum = df[df["sensor"].str.endswith("/humidity")]["value"]
        assert hum.between(30.0, 70.0).all()  # PROVENANCE-era offices: 36–65 % RH raw
        light = df[df["sensor"].str.contains("/light")]["value"]
        assert (light > 0).all()
        state = df[df["sensor"].str.endswith(("/door", "/window"))]["value"]
        assert set(state.unique()) <= {0.0, 1.0}
    # The ground truth as the source has it: A's door opens (≈23 % of samples), no window is
    # ever open, B's door never.
    door_share = float((frames["A"][10] == 1).mean())
    assert 0.1 < door_share < 0.4
    assert values(a, "A/door").mean() == pytest.approx(door_share, abs=0.1)
    for df, loc in ((a, "A"), (b, "B")):
        assert (values(df, f"{loc}/window") == 0).all()
        assert values(df, f"{loc}/window").size == values(df, f"{loc}/occupancy").size
    assert (values(b, "B/door") == 0).all() and not (frames["B"][10] == 1).any()
    # Light follows daylight: brighter in the early afternoon than at 9:00 (local time).
    wide = a.pivot(index="ts", columns="sensor", values="value")
    hour = pd.DatetimeIndex(wide.index).tz_convert("Europe/Berlin").hour
    for q in ("A1/light1", "A4/light2"):
        assert wide.loc[hour == 14, q].mean() > 1.1 * wide.loc[hour == 9, q].mean(), q


@needs_data
def test_room_climate_plausible_values(
    converted: Converted,
) -> None:
    _, a = converted["room-climate-a"]
    _, b = converted["room-climate-b"]
    # PROVENANCE raw ranges A 20.4–24.1, B 21.0–25.5 °C; means cannot leave them.
    assert a[a["sensor"].str.endswith("/temp")]["value"].between(20.4, 24.1).all()
    assert b[b["sensor"].str.endswith("/temp")]["value"].between(20.9, 25.5).all()
    for df in (a, b):
        occ = df[df["sensor"].str.endswith("/occupancy")]["value"]
        assert set(occ.unique()) == {0.0, 1.0, 2.0}
    # Same room: the desk node follows the ceiling node (PROVENANCE pooled r ≈ 0.95).
    wide = a.pivot(index="ts", columns="sensor", values="value")
    assert wide["A1/temp"].corr(wide["A4/temp"]) > 0.9


# ---------------------------------------------------------------------------- errors


def test_missing_file_names_the_path(tmp_path: Path) -> None:
    with pytest.raises(DataError, match=re.escape(str(tmp_path / "energydata_complete.csv"))):
        cv.load("appliances", tmp_path)
    with pytest.raises(DataError, match=r"NEW-DATA-\*\.T15\.txt"):
        cv.load("sml2010", tmp_path)
    missing = tmp_path / "nowhere"
    with pytest.raises(DataError, match=re.escape(str(missing))):
        cv.convert("room-climate-a", missing, tmp_path / "out.csv")
    assert not (tmp_path / "out.csv").exists()


SML_HEADER = "#  " + " ".join(
    f"{i}:{n}"
    for i, n in enumerate(
        ["Date", "Time", "Temperature_Comedor_Sensor", "Temperature_Habitacion_Sensor", "W",
         "CO2_Comedor_Sensor", "CO2_Habitacion_Sensor", "Humedad_Comedor_Sensor",
         "Humedad_Habitacion_Sensor", "Lighting_Comedor_Sensor", "Lighting_Habitacion_Sensor",
         "Precipitacion", "Meteo_Exterior_Crepusculo", "Meteo_Exterior_Viento",
         "Meteo_Exterior_Sol_Oest", "Meteo_Exterior_Sol_Est", "Meteo_Exterior_Sol_Sud",
         "Meteo_Exterior_Piranometro", "c19", "c20", "c21", "Temperature_Exterior_Sensor",
         "Humedad_Exterior_Sensor", "Day_Of_Week"],
        start=1,
    )
)


def sml_row(date: str, clock: str) -> str:
    values = ["20.1", "19.9", "0", "200", "210"] + ["1"] * 14 + ["15", "50", "2"]
    return " ".join([date, clock, *values])


def test_sml2010_synthetic_file_converts(tmp_path: Path) -> None:
    path = tmp_path / "NEW-DATA-9.T15.txt"
    path.write_text("\n".join([SML_HEADER, sml_row("25/03/2012", "02:15")]) + "\n")
    df = cv.load("sml2010", tmp_path)
    assert counts(df) == {s: 1 for s in (*SML_SENSORS, *SML_EXTRA)}
    assert at(df, "outdoor/temp", "2012-03-25 02:15") == 15.0
    assert at(df, "outdoor/humidity", "2012-03-25 02:15") == 50.0
    assert at(df, "dining/humidity", "2012-03-25 02:15") == 1.0


def test_sml2010_bad_date_is_data_error(tmp_path: Path) -> None:
    path = tmp_path / "NEW-DATA-1.T15.txt"
    path.write_text("\n".join([SML_HEADER, sml_row("13/03/2012", "11:45"),
                               sml_row("32/03/2012", "12:00")]) + "\n")
    msg = f"{path}: unparseable date/time '32/03/2012 12:00' on line 3"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("sml2010", tmp_path)


def test_sml2010_missing_column_is_data_error(tmp_path: Path) -> None:
    path = tmp_path / "NEW-DATA-1.T15.txt"
    path.write_text(SML_HEADER.replace("7:CO2_Habitacion_Sensor", "7:X") + "\n"
                    + sml_row("13/03/2012", "11:45") + "\n")
    msg = f"{path}: header lacks column(s) 7:CO2_Habitacion_Sensor"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("sml2010", path)
    # A kept channel's column is checked as well: humidity must not be read from column 23
    # of a file whose column 23 is something else.
    path.write_text(SML_HEADER.replace("23:Humedad_Exterior_Sensor", "23:Otra") + "\n"
                    + sml_row("13/03/2012", "11:45") + "\n")
    msg = f"{path}: header lacks column(s) 23:Humedad_Exterior_Sensor"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("sml2010", path)


def test_sml2010_headerless_or_short_rows(tmp_path: Path) -> None:
    path = tmp_path / "NEW-DATA-1.T15.txt"
    path.write_text(sml_row("13/03/2012", "11:45") + "\n")
    with pytest.raises(DataError, match="column header"):
        cv.load("sml2010", path)
    path.write_text(SML_HEADER + "\n13/03/2012 11:45 20.1 19.9\n")
    with pytest.raises(DataError, match="expected 24 columns, found 4"):
        cv.load("sml2010", path)


APPLIANCE_COLUMNS = (["date", "Appliances", "lights"]
                     + [c for i in range(1, 10) for c in (f"T{i}", f"RH_{i}")]
                     + ["T_out", "Press_mm_hg", "RH_out", "Windspeed", "Visibility",
                        "Tdewpoint", "rv1", "rv2"])


def test_appliances_malformed(tmp_path: Path) -> None:
    path = tmp_path / "energydata_complete.csv"
    cols = APPLIANCE_COLUMNS
    n = len(cols) - 1
    path.write_text(",".join(c for c in cols if c != "T5") + "\n")
    with pytest.raises(DataError, match=re.escape(f"{path}: missing column(s) T5")):
        cv.load("appliances", tmp_path)
    path.write_text(",".join(c for c in cols if c not in ("RH_out", "lights")) + "\n")
    with pytest.raises(DataError, match=re.escape(f"{path}: missing column(s) lights, RH_out")):
        cv.load("appliances", tmp_path)
    path.write_text(",".join(cols) + "\n" + ",".join(["2016-13-45 25:00"] + ["20"] * n) + "\n")
    with pytest.raises(DataError, match=re.escape(f"{path}: unparseable date/time")):
        cv.load("appliances", tmp_path)
    row = ["11-01-2016 17:00"] + ["20"] * n
    row[cols.index("T1")] = "warm"
    path.write_text(",".join(cols) + "\n" + ",".join(row) + "\n")
    msg = f"{path}: T1 value 'warm' on line 2 is not a number"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("appliances", tmp_path)
    row = ["11-01-2016 17:00"] + ["20"] * n
    row[cols.index("Press_mm_hg")] = "high"
    path.write_text(",".join(cols) + "\n" + ",".join(row) + "\n")
    msg = f"{path}: Press_mm_hg value 'high' on line 2 is not a number"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("appliances", tmp_path)
    # Only the random columns may go: they are not measurements and are not read.
    path.write_text(",".join(c for c in cols if c not in ("rv1", "rv2")) + "\n"
                    + ",".join(["11-01-2016 17:00"] + ["20"] * (n - 2)) + "\n")
    df = cv.load("appliances", tmp_path)
    assert len(df) == len(cv.DATASETS["appliances"].sensors)
    assert at(df, "house/lights", "2016-01-11 16:00") == 20.0


def test_room_climate_malformed(tmp_path: Path) -> None:
    path = tmp_path / "room_climate-location_B-measurement01.csv"
    path.write_text("1, 1458031648545, 1, 1, 20.48, 42.3\n")
    with pytest.raises(DataError, match=re.escape(f"{path}: expected 12 columns")):
        cv.load("room-climate-b", tmp_path)
    path.write_text("1, 1458031648545, 1, 4, 20.48, 42.3, 185.7, 492.2, 0, 0, 0, 0\n")
    msg = f"{path}: node id(s) 4 are not nodes of location B"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("room-climate-b", tmp_path)


def test_room_climate_synthetic_minute(tmp_path: Path) -> None:
    """Node values are the minute's means per node; occupancy, door and window its maxima
    over every node's samples (open if open at any sample)."""
    rows = [  # EID, AbsT, RelT, NID, Temp, RelH, L1, L2, Occ, Act, Door, Win
        (1, 1458031620000, 0, 1, 20.0, 40.0, 100.0, 500.0, 0, 0, 0, 0),
        (2, 1458031624000, 4, 1, 21.0, 42.0, 110.0, 520.0, 1, 1, 1, 0),
        (3, 1458031628000, 8, 2, 22.0, 50.0, 200.0, 900.0, 0, 0, 0, 1),
        (4, 1458031680000, 60, 1, 20.5, 41.0, 105.0, 510.0, 0, 0, 0, 0),
    ]
    path = tmp_path / "room_climate-location_B-measurement01.csv"
    path.write_text("".join(", ".join(map(str, r)) + "\n" for r in rows))
    df = cv.load("room-climate-b", tmp_path)
    first, second = "2016-03-15 08:47", "2016-03-15 08:48"
    assert at(df, "B1/humidity", first) == 41.0
    assert at(df, "B1/light1", first) == 105.0 and at(df, "B1/light2", first) == 510.0
    assert at(df, "B2/humidity", first) == 50.0 and at(df, "B2/light2", first) == 900.0
    assert (at(df, "B/occupancy", first), at(df, "B/door", first),
            at(df, "B/window", first)) == (1.0, 1.0, 1.0)
    assert (at(df, "B/door", second), at(df, "B/window", second)) == (0.0, 0.0)
    assert at(df, "B1/humidity", second) == 41.0
    assert counts(df)["B2/humidity"] == 1 and counts(df)["B/door"] == 2
    raw = cv.load("room-climate-b", tmp_path, raw=True)
    assert counts(raw)["B/door"] == 4  # every sample's own instant
    assert at(raw, "B1/light2", "2016-03-15 08:47:04") == 520.0


def test_room_climate_location_c(tmp_path: Path) -> None:
    """Location C (not in the shared data) has five nodes and the same file format; without
    --source the error says where its files come from."""
    with pytest.raises(DataError, match=r"room-climate-c is not part of the shared data: give "
                                        r"--source DIR \(the datasets-location_C folder"):
        cv.load("room-climate-c")
    with pytest.raises(DataError, match="room-climate-c is not part of the shared data"):
        cv.default_source("room-climate-c")
    assert not cv.DATASETS["room-climate-c"].shared and cv.DATASETS["room-climate-b"].shared
    rows = [  # EID, AbsT, RelT, NID, Temp, RelH, L1, L2, Occ, Act, Door, Win; 2017-01-25
        (k, 1485353109917 + 700 * k, 1, k, 22.0 + k / 10, 40.0, 150.0, 550.0, 0, 0, 0, 0)
        for k in (1, 2, 3, 4, 5)
    ]
    path = tmp_path / "room_climate-location_C-measurement01.csv"
    path.write_text("".join(", ".join(map(str, r)) + "\n" for r in rows))
    df = cv.load("room-climate-c", tmp_path)
    assert {f"C{k}/temp" for k in range(1, 6)} <= set(df["sensor"])
    assert at(df, "C5/temp", "2017-01-25 14:05") == pytest.approx(22.5)
    assert set(df["sensor"]) <= set(cv.DATASETS["room-climate-c"].sensors)
    # Location A's converter on C's files: their names say whose they are.
    with pytest.raises(DataError, match="a file of location C, not A"):
        cv.load("room-climate-a", tmp_path)
    # A's files, whose node ids 1–4 are also C's, are not taken for C's either.
    a_files = tmp_path / "a"
    a_files.mkdir()
    (a_files / "room_climate-location_A-measurement01.csv").write_text(
        "".join(", ".join(map(str, r)) + "\n" for r in rows[:4]))
    with pytest.raises(DataError, match=r"a file of location A, not C \(convert room-climate-a"):
        cv.load("room-climate-c", a_files)
    # A file whose name does not say: the node it does not know.
    unnamed = tmp_path / "unnamed"
    unnamed.mkdir()
    (unnamed / "measurement01.csv").write_text(path.read_text())
    with pytest.raises(DataError, match=re.escape("node id(s) 5 are not nodes of location A")):
        cv.load("room-climate-a", unnamed)


def test_unknown_dataset_api() -> None:
    with pytest.raises(ConfigError, match="unknown dataset 'nope'"):
        cv.load("nope")


# ---------------------------------------------------------------------------- CLI


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("pseudotwin convert: error: ")
    return lines[0]


def test_main_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert cc.main(["--list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out] == list(cv.DATASETS)


@needs_data
def test_main_converts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sml.csv"
    assert cc.main(["sml2010", "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert "\n" not in line and line.startswith(
        "sml2010: 70329 rows, 17 sensors (dining/temp, room/temp, dining/co2, room/co2, "
        "outdoor/temp, dining/humidity")
    assert len(read_history(out)) == 70329


def test_main_dataset_outside_shared(tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    assert cc.main(["room-climate-c", "--out", str(tmp_path / "c.csv")]) == 2
    assert "give --source DIR" in one_error_line(capsys)
    assert not (tmp_path / "c.csv").exists()


def test_main_missing_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope"
    code = cc.main(["appliances", "--source", str(missing), "--out", str(tmp_path / "o.csv")])
    assert code == 2
    assert str(missing) in one_error_line(capsys)


def test_main_malformed_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "src"
    src.mkdir()
    (src / "energydata_complete.csv").write_text("date,T1\n11-01-2016 17:00,20\n")
    assert cc.main(["appliances", "--source", str(src), "--out", str(tmp_path / "o.csv")]) == 2
    assert "missing column(s) T2" in one_error_line(capsys)


def test_main_unknown_dataset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cc.main(["nope", "--out", str(tmp_path / "o.csv")]) == 2
    assert "unknown dataset 'nope'" in one_error_line(capsys)


@pytest.mark.parametrize(
    "argv, message",
    [([], "dataset name is required"), (["sml2010"], "--out"), (["sml2010", "--bogus"], "--bogus")],
)
def test_main_usage_errors(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cc.main(argv) == 2
    assert message in one_error_line(capsys)


@needs_data
def test_room_climate_raw_keeps_every_sample_and_its_minute_means_are_the_default(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    # Two episodes, the door closed in the first and open in the second (the whole dataset
    # as raw CSV takes ~1 min to write and read back).
    source = tmp_path / "episodes"
    source.mkdir()
    for n in (44, 45):
        name = f"room_climate-location_A-measurement{n}.csv"
        (source / name).symlink_to(ROOT / "room_climate/datasets-location_A" / name)
    minutes = cv.load("room-climate-a", source)
    out = tmp_path / "raw.csv"
    assert cc.main(["room-climate-a", "--raw", "--source", str(source), "--out", str(out)]) == 0
    assert "room-climate-a:" in capsys.readouterr().out
    raw = read_history(out)
    assert counts(raw)["A1/temp"] > 10 * counts(minutes)["A1/temp"]  # ~4-s samples
    for q in ("temp", "humidity", "light2"):
        a1 = raw[raw["sensor"] == f"A1/{q}"]
        assert (a1["ts"].dt.microsecond != 0).any()  # the samples' own milliseconds
        by_minute = a1.groupby(a1["ts"].dt.floor("min"))["value"].mean()
        want = minutes[minutes["sensor"] == f"A1/{q}"].set_index("ts")["value"]
        assert by_minute.index.equals(want.index), q
        np.testing.assert_allclose(by_minute.to_numpy(), want.to_numpy(),
                                   rtol=1e-5, atol=1e-4)  # the CSV's 6 significant digits
    # Node channels at their node's sample instants, ground truth at the occupancy's.
    for q in ("humidity", "light2"):
        assert stamps(raw, f"A1/{q}").equals(stamps(raw, "A1/temp")), q
    assert stamps(raw, "A/door").equals(stamps(raw, "A/occupancy"))
    assert set(values(raw, "A/door").unique()) == {0.0, 1.0}
    # datasets without averaging give the same rows either way
    pd.testing.assert_frame_equal(cv.load("sml2010", raw=True), cv.load("sml2010"))


def test_convert_to_parquet_reads_back_as_the_csv(tmp_path: Path) -> None:
    """--out x.parquet wrote CSV text into a .parquet file that read_history then refused."""
    (tmp_path / "src").mkdir()
    src = tmp_path / "src" / "NEW-DATA-9.T15.txt"
    src.write_text("\n".join([SML_HEADER, *(sml_row("13/03/2012", f"{h:02d}:00")
                                             for h in range(6))]) + "\n")
    for out in ("h.csv", "h.parquet"):
        assert cc.main(["sml2010", "--source", str(src.parent),
                        "--out", str(tmp_path / out)]) == 0
    csv, parquet = read_history(tmp_path / "h.csv"), read_history(tmp_path / "h.parquet")
    assert len(parquet) == len(csv) > 0
    pd.testing.assert_frame_equal(parquet[["sensor", "ts"]], csv[["sensor", "ts"]])
    np.testing.assert_allclose(parquet["value"], csv["value"], rtol=1e-5)


def test_raw_is_refused_where_nothing_is_averaged(tmp_path: Path, capsys) -> None:
    assert cc.main(["sml2010", "--raw", "--out", str(tmp_path / "h.csv")]) == 2
    assert "--raw: sml2010 has no samples to keep" in capsys.readouterr().err
    assert not (tmp_path / "h.csv").exists()


@needs_data
def test_main_never_writes_into_its_own_dataset(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """``--out`` the source file replaced the raw dataset by the converted one."""
    src = tmp_path / "sml"
    shutil.copytree(cv.default_source("sml2010"), src)
    before = {p.name: p.read_bytes() for p in src.iterdir()}
    # a new file in its folder too: a converter reading the folder's *.csv (Room Climate)
    # would take it for data the next time
    for out in (*(src / name for name in before), src / "converted.csv"):
        assert cc.main(["sml2010", "--source", str(src), "--out", str(out)]) == 2
        assert "would be written into the dataset" in one_error_line(capsys)
    assert cc.main(["sml2010", "--source", str(src / "NEW-DATA-1.T15.txt"),
                    "--out", str(src / "NEW-DATA-1.T15.txt")]) == 2
    assert "would be written into the dataset" in one_error_line(capsys)
    assert {p.name: p.read_bytes() for p in src.iterdir()} == before


def test_an_interrupted_write_leaves_the_earlier_file_whole(tmp_path: Path) -> None:
    """A converted file overwritten by a run that failed (or was interrupted) part-way was
    left truncated at a whole row: shorter history that read and imported without a word."""
    class Unwritable:
        def __str__(self) -> str:
            raise RuntimeError("the write fails here")

    path = tmp_path / "h.csv"
    earlier = pd.DataFrame({"sensor": "a", "value": [1.0, 2.0],
                            "ts": pd.to_datetime(["2012-03-14T10:00Z", "2012-03-14T10:01Z"])})
    write_history(earlier, path)
    kept = path.read_bytes()
    n = 300_000  # more rows than pandas writes in one chunk: the first chunks reach the file
    later = pd.DataFrame({"sensor": "a", "ts": pd.date_range("2012-03-15", periods=n,
                                                              freq="s", tz="UTC"),
                          "value": np.r_[np.ones(n - 1), np.nan].astype(object)})
    later.loc[n - 1, "value"] = Unwritable()
    with pytest.raises(RuntimeError, match="fails here"):
        write_history(later, path)
    assert path.read_bytes() == kept
    assert [p.name for p in tmp_path.iterdir()] == ["h.csv"]  # no temporary file left


@needs_data
def test_parquet_without_its_engine_is_one_error_line(tmp_path: Path) -> None:
    """pandas' Parquet engine missing (pyarrow; here a stand-in module that fails to import,
    as a broken or absent install does): convert printed pandas' traceback."""
    stub = tmp_path / "stub"
    stub.mkdir()
    (stub / "pyarrow.py").write_text('raise ImportError("no pyarrow here")\n')
    out = tmp_path / "sml.parquet"
    p = subprocess.run([sys.executable, "-m", "pseudotwin.cli", "convert", "sml2010",
                        "--out", str(out)], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(stub)})
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and "cannot write Parquet" in p.stderr
    assert not out.exists()


def test_a_history_archive_holds_the_file_under_its_own_name(tmp_path: Path) -> None:
    """Written through a temporary file, a .csv.zip held a member named after it."""
    df = pd.DataFrame({"sensor": "a", "value": [1.0, 2.0],
                       "ts": pd.to_datetime(["2012-03-14T10:00Z", "2012-03-14T10:01Z"])})
    write_history(df, tmp_path / "h.csv.zip")
    with zipfile.ZipFile(tmp_path / "h.csv.zip") as z:
        assert z.namelist() == ["h.csv"]
    assert len(read_history(tmp_path / "h.csv.zip")) == 2
    link = tmp_path / "link.csv"
    link.symlink_to(tmp_path / "real.csv")
    write_history(df, link)
    assert link.is_symlink() and len(read_history(tmp_path / "real.csv")) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["h.csv.zip", "link.csv", "real.csv"]
