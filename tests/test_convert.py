"""Converters of the shared datasets, run on the real data in ``<repo>/../shared/data``."""

from __future__ import annotations

import datetime as dt
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pseudotwin.cli import convert as cc  # the command; cv is the converters
from pseudotwin.core.series import read_history
from pseudotwin.errors import ConfigError, DataError
from pseudotwin.history import convert as cv

REPO = Path(__file__).resolve().parents[1]
ROOT = cv.shared_data_root()

needs_data = pytest.mark.skipif(not ROOT.is_dir(), reason=f"shared data not found at {ROOT}")

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


Converted = dict[str, tuple[cv.ConvertSummary, pd.DataFrame]]


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
    for name in cv.DATASETS:
        summary = cv.convert(name, None, out_dir / f"{name}.csv")
        result[name] = (summary, read_history(summary.out))
    return result


def counts(df: pd.DataFrame) -> dict[str, int]:
    return {str(k): int(v) for k, v in df.groupby("sensor").size().items()}


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
@pytest.mark.parametrize("name", list(cv.DATASETS))
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


# ---------------------------------------------------------------------------- SML2010


@needs_data
def test_sml2010_counts_and_span(converted: Converted) -> None:
    summary, df = converted["sml2010"]
    # PROVENANCE: 2,764 + 1,373 = 4,137 timestamps. None is dropped: the logger clock is UTC,
    # so the night of 2012-03-25 has no nonexistent or repeated times to lose.
    assert counts(df) == {s: 4137 for s in SML_SENSORS}
    assert summary.rows == 5 * 4137
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
    for sensor in SML_SENSORS:
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


# ---------------------------------------------------------------------------- appliances


@needs_data
def test_appliances_counts(converted: Converted) -> None:
    summary, df = converted["appliances"]
    expected = {s: 19735 for s in APPLIANCE_HOUSE}
    # 2016-03-27 02:00–02:50 do not exist on Belgian wall time, the clock of the merged
    # airport weather: those six interpolated T_out rows are dropped.
    expected["weather/temp"] = 19735 - 6
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
    indoor = df[~df["sensor"].isin(["outside/temp", "weather/temp"])]["value"]
    assert indoor.between(14.0, 30.0).all()
    assert df[df["sensor"] == "outside/temp"]["value"].between(-7.0, 29.0).all()
    # E-notation T_out ("6.60E+00") parsed as numbers.
    assert at(df, "weather/temp", "2016-01-11 16:00") == pytest.approx(6.6)
    assert df[df["sensor"] == "weather/temp"]["value"].between(-5.0, 26.2).all()


# ---------------------------------------------------------------------------- room climate


@needs_data
def test_room_climate_minutes(converted: Converted) -> None:
    _, a = converted["room-climate-a"]
    _, b = converted["room-climate-b"]
    # 73.5 h (A) / 54.0 h (B) of episodes in PROVENANCE → one row per node per covered minute
    # (episode edges add partial minutes). B3 has one minute with no B1/B2 sample.
    assert counts(a) == {"A1/temp": 4460, "A2/temp": 4460, "A3/temp": 4460, "A4/temp": 4460,
                         "A/occupancy": 4460}
    assert counts(b) == {"B1/temp": 3266, "B2/temp": 3266, "B3/temp": 3267, "B/occupancy": 3267}
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
         "CO2_Comedor_Sensor", "CO2_Habitacion_Sensor"] + [f"c{i}" for i in range(8, 22)]
        + ["Temperature_Exterior_Sensor", "H", "Day_Of_Week"],
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
    assert counts(df) == {s: 1 for s in SML_SENSORS}
    assert at(df, "outdoor/temp", "2012-03-25 02:15") == 15.0


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


def test_sml2010_headerless_or_short_rows(tmp_path: Path) -> None:
    path = tmp_path / "NEW-DATA-1.T15.txt"
    path.write_text(sml_row("13/03/2012", "11:45") + "\n")
    with pytest.raises(DataError, match="column header"):
        cv.load("sml2010", path)
    path.write_text(SML_HEADER + "\n13/03/2012 11:45 20.1 19.9\n")
    with pytest.raises(DataError, match="expected 24 columns, found 4"):
        cv.load("sml2010", path)


def test_appliances_malformed(tmp_path: Path) -> None:
    path = tmp_path / "energydata_complete.csv"
    cols = ["date"] + [f"T{i}" for i in range(1, 10)] + ["T_out"]
    path.write_text(",".join(c for c in cols if c != "T5") + "\n")
    with pytest.raises(DataError, match=re.escape(f"{path}: missing column(s) T5")):
        cv.load("appliances", tmp_path)
    path.write_text(",".join(cols) + "\n" + ",".join(["2016-13-45 25:00"] + ["20"] * 10) + "\n")
    with pytest.raises(DataError, match=re.escape(f"{path}: unparseable date/time")):
        cv.load("appliances", tmp_path)
    row = ["11-01-2016 17:00", "warm"] + ["20"] * 9
    path.write_text(",".join(cols) + "\n" + ",".join(row) + "\n")
    msg = f"{path}: T1 value 'warm' on line 2 is not a number"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("appliances", tmp_path)


def test_room_climate_malformed(tmp_path: Path) -> None:
    path = tmp_path / "room_climate-location_B-measurement01.csv"
    path.write_text("1, 1458031648545, 1, 1, 20.48, 42.3\n")
    with pytest.raises(DataError, match=re.escape(f"{path}: expected 12 columns")):
        cv.load("room-climate-b", tmp_path)
    path.write_text("1, 1458031648545, 1, 4, 20.48, 42.3, 185.7, 492.2, 0, 0, 0, 0\n")
    msg = f"{path}: node id(s) 4 are not nodes of location B"
    with pytest.raises(DataError, match=re.escape(msg)):
        cv.load("room-climate-b", tmp_path)


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
    assert "\n" not in line and line.startswith("sml2010: 20685 rows, 5 sensors")
    assert len(read_history(out)) == 20685


def test_main_missing_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope"
    code = cc.main(["appliances", "--source", str(missing), "--out", str(tmp_path / "o.csv")])
    assert code == 2
    assert str(missing) in one_error_line(capsys)


def test_main_malformed_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "energydata_complete.csv").write_text("date,T1\n11-01-2016 17:00,20\n")
    assert cc.main(["appliances", "--source", str(tmp_path), "--out", str(tmp_path / "o.csv")]) == 2
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
    converted: Converted, tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    _, minutes = converted["room-climate-a"]
    out = tmp_path / "raw.csv"
    assert cc.main(["room-climate-a", "--raw", "--out", str(out)]) == 0
    assert "room-climate-a:" in capsys.readouterr().out
    raw = read_history(out)
    assert counts(raw)["A1/temp"] > 10 * counts(minutes)["A1/temp"]  # ~4-s samples
    a1 = raw[raw["sensor"] == "A1/temp"]
    assert (a1["ts"].dt.microsecond != 0).any()  # the samples' own milliseconds
    by_minute = a1.groupby(a1["ts"].dt.floor("min"))["value"].mean()
    want = minutes[minutes["sensor"] == "A1/temp"].set_index("ts")["value"]
    np.testing.assert_allclose(by_minute.loc[want.index].to_numpy(), want.to_numpy(),
                               atol=1e-4)  # both written as CSV with four decimals
    # datasets without averaging give the same rows either way
    pd.testing.assert_frame_equal(cv.load("sml2010", raw=True), cv.load("sml2010"))
