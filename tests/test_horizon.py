"""Operating hours, wall-clock time on DST days, the slot grid, day windows and carry-over."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np
import pandas as pd
import pytest

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import normalize, read_history, split_days, write_history
from pseudotwin.errors import ConfigError, DataError

BERLIN = "Europe/Berlin"


def frame(rows: list[tuple[str, str, float]]) -> pd.DataFrame:
    return normalize(pd.DataFrame(rows, columns=["sensor", "ts", "value"]))


def test_defaults_and_window_slots() -> None:
    h = OperatingHours()
    assert (h.day_start, h.day_end, h.init_start) == (8.0, 19.0, 7.5)
    slots = h.window_slots()
    assert slots[0] * h.slot_hours == 7.5 and (slots[-1] + 1) * h.slot_hours == 19.0
    assert len(slots) == 46


@pytest.mark.parametrize(
    "kwargs",
    [
        {"day_start": "19:00", "day_end": "08:00"},
        {"day_start": "8am"},
        {"timezone": "Mars/Olympus"},
        {"slot_minutes": 7},
        {"init_minutes": 600, "day_start": "06:00"},
    ],
)
def test_bad_hours_are_config_errors(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        OperatingHours.from_strings(**kwargs)


EXAMPLE = ("(an IANA name such as 'Europe/Berlin' or 'UTC', not an abbreviation or a UTC "
           "offset: a zone's offset changes with daylight saving time)")


@pytest.mark.parametrize("name,hint", [
    ("utc", "(did you mean 'UTC'?)"),  # the default is shown as UTC; zone names are cased
    ("europe/berlin", "(did you mean 'Europe/Berlin'?)"),
    ("Europe/Berln", "(did you mean 'Europe/Berlin'?)"),
    ("Mars/Olympus", EXAMPLE),
    ("CEST", EXAMPLE),  # not 'EST', seven hours off
    ("UTC+1", EXAMPLE),  # not 'UTC'
])
def test_an_unknown_time_zone_says_the_zone_meant(name: str, hint: str) -> None:
    with pytest.raises(ConfigError) as exc:
        OperatingHours.from_strings(timezone=name)
    assert str(exc.value) == f"unknown time zone {name!r} {hint}"


@pytest.mark.parametrize(
    "day,expected_utc",
    [
        (dt.date(2016, 3, 27), dt.datetime(2016, 3, 27, 6, 0, tzinfo=dt.UTC)),  # spring forward
        (dt.date(2016, 10, 30), dt.datetime(2016, 10, 30, 7, 0, tzinfo=dt.UTC)),  # fall back
        (dt.date(2016, 3, 26), dt.datetime(2016, 3, 26, 7, 0, tzinfo=dt.UTC)),
    ],
)
def test_wall_clock_is_kept_on_dst_days(day: dt.date, expected_utc: dt.datetime) -> None:
    h = OperatingHours(timezone=BERLIN)
    at8 = h.at(day, 8.0)
    assert at8 == expected_utc
    assert h.hours_of(at8) == pytest.approx(8.0)
    assert h.day_of(at8) == day
    # hours of the day along a 15-min grid of local wall clock never jump inside the window
    ts = pd.date_range(h.at(day, 7.5), h.at(day, 19.0), freq="15min")
    _, hours = h.day_and_hours(ts)
    assert np.allclose(np.diff(hours), 0.25)


@pytest.mark.parametrize(("start", "end", "step_min", "first", "last", "n"), [
    ("08:00", "19:00", 15, "08:00", "19:00", 45),
    ("08:10", "19:00", 15, "08:15", "19:00", 44),  # on the quarter hours, not 08:10, 08:25, …
    ("07:50", "18:50", 30, "08:00", "18:30", 22),
    ("08:00", "24:00", 60, "08:00", "23:00", 16),  # midnight is the next day's, outside its window
])
def test_the_publish_grid_is_anchored_at_local_midnight(
        start: str, end: str, step_min: int, first: str, last: str, n: int) -> None:
    h = OperatingHours.from_strings(day_start=start, day_end=end, timezone=BERLIN)
    day = dt.date(2016, 3, 28)
    grid = h.grid(day, step_min / 60)
    local = [t.astimezone(ZoneInfo(BERLIN)) for t in grid]
    assert [f"{t:%H:%M}" for t in (local[0], local[-1])] == [first, last] and len(grid) == n
    assert all(t.date() == day and (t.hour * 60 + t.minute) % step_min == 0 for t in local)
    assert all(h.day_start <= h.hours_of(t) <= h.day_end for t in grid)


def test_nonexistent_wall_time_steps_over_the_gap() -> None:
    h = OperatingHours(timezone=BERLIN)
    t = h.at(dt.date(2016, 3, 27), 2.5)  # 02:30 does not exist that night
    # the gap's end, not 03:30: a window opening at 02:30 opens at 03:00, where its
    # readings begin
    assert t.astimezone(ZoneInfo(BERLIN)).replace(tzinfo=None) == dt.datetime(2016, 3, 27, 3)


def test_a_grid_over_a_dst_gap_skips_the_lost_instants_in_order() -> None:
    """Hours 01:00–23:00 on the spring-forward day: the grid held 03:00–03:45 twice, out of
    order, so backfill estimated those instants after the 03:45 reading and the daemon's
    ticker skipped 03:00 and 03:15."""
    h = OperatingHours.from_strings("01:00", "23:00", timezone=BERLIN)
    grid = h.grid(dt.date(2016, 3, 27), 0.25)
    assert grid == sorted(set(grid)) and len(grid) == 89 - 4
    walls = [t.astimezone(ZoneInfo(BERLIN)).strftime("%H:%M") for t in grid]
    assert walls[3:6] == ["01:45", "03:00", "03:15"]
    fall = h.grid(dt.date(2016, 10, 30), 0.25)  # 02:00–02:59 twice: both passes, in order
    assert fall == sorted(set(fall)) and len(fall) == 89 + 4


def test_split_days_carries_last_value_and_keeps_silent_cov_sensor() -> None:
    h = OperatingHours(timezone=BERLIN)
    df = frame([
        ("ref", "2016-03-14T17:00:00+01:00", 20.0),  # last value of the day before
        ("ref", "2016-03-15T06:00:00+01:00", 20.5),  # before the init phase: carried
        ("ref", "2016-03-15T09:00:00+01:00", 21.0),
        ("tgt", "2016-03-15T08:30:00+01:00", 22.0),
        ("cov", "2016-03-14T12:00:00+01:00", 19.0),  # silent all of the 15th (COV)
    ])
    days = split_days(df, ["ref", "tgt", "cov"], h, [dt.date(2016, 3, 15)])
    d = days[0]
    hr, vr = d.series["ref"]
    assert list(hr) == [7.5, 9.0] and list(vr) == [20.5, 21.0]
    hc, vc = d.series["cov"]
    assert list(hc) == [7.5] and list(vc) == [19.0]  # carried though silent for 20 h
    assert "tgt" in d.series and d.series["tgt"][0][0] == 7.5 or d.series["tgt"][1][0] == 22.0
    slots = d.slot_values("cov", h)
    assert np.all(slots == 19.0)  # sample-and-hold all day
    ref_slots = d.slot_values("ref", h)
    assert ref_slots[0] == 20.5 and ref_slots[-1] == 21.0
    # the value at 09:00 appears at the 09:00 slot exactly (held from its own timestamp)
    nine = int(np.flatnonzero(h.window_slots() * h.slot_hours == 9.0)[0])
    assert ref_slots[nine - 1] == 20.5 and ref_slots[nine] == 21.0


def test_carry_over_is_limited_in_age() -> None:
    h = OperatingHours()
    df = frame([
        ("ref", "2020-01-01T12:00:00+00:00", 1.0),
        ("ref", "2020-01-05T09:00:00+00:00", 2.0),
    ])
    d = split_days(df, ["ref"], h, [dt.date(2020, 1, 5)])[0]
    assert list(d.series["ref"][0]) == [9.0]  # 4 days old: not carried


def test_split_days_on_dst_day_uses_local_wall_clock() -> None:
    h = OperatingHours(timezone=BERLIN)
    ts = pd.date_range("2016-03-27T07:30:00+02:00", "2016-03-27T19:00:00+02:00", freq="30min")
    df = normalize(pd.DataFrame({"sensor": "s", "ts": ts.astype(str), "value": 1.0}))
    d = split_days(df, ["s"], h, [dt.date(2016, 3, 27)])[0]
    assert d.series["s"][0][0] == 7.5 and d.series["s"][0][-1] == 19.0
    assert len(d.series["s"][0]) == len(ts)


def test_history_round_trip_and_errors(tmp_path) -> None:
    df = frame([("a", "2020-01-01T08:00:00+01:00", 1.5), ("b", "1577865600", 2.0)])
    p = tmp_path / "h.csv"
    write_history(df, p)
    back = read_history(p)
    pd.testing.assert_frame_equal(back, df)
    with pytest.raises(DataError, match="no such file"):
        read_history(tmp_path / "missing.csv")
    (tmp_path / "bad.csv").write_text("sensor,time,value\na,1,2\n")
    with pytest.raises(DataError, match="missing column"):
        read_history(tmp_path / "bad.csv")
    (tmp_path / "naive.csv").write_text("sensor,ts,value\na,2020-01-01 08:00,2\n")
    with pytest.raises(DataError, match="no UTC offset"):
        read_history(tmp_path / "naive.csv")
    (tmp_path / "nan.csv").write_text("sensor,ts,value\na,2020-01-01T08:00Z,warm\n")
    with pytest.raises(DataError, match="not a number"):
        read_history(tmp_path / "nan.csv")


def test_epoch_milliseconds_read_as_the_same_instant_as_iso(tmp_path: Path) -> None:
    """1704880800001 ms was read 256 ns early and stored at …000: a key of another reading,
    and an import of the same readings in ISO form added them a second time."""
    millis = [1704880800000 + k for k in range(0, 2000, 7)]
    epoch = tmp_path / "epoch.csv"
    epoch.write_text("sensor,ts,value\n" + "".join(f"v/t,{m},{i}\n"
                                                    for i, m in enumerate(millis)))
    seconds = tmp_path / "seconds.csv"
    seconds.write_text("sensor,ts,value\n" + "".join(f"v/t,{m / 1000:.3f},{i}\n"
                                                      for i, m in enumerate(millis)))
    iso = tmp_path / "iso.csv"
    iso.write_text("sensor,ts,value\n" + "".join(
        f"v/t,{pd.Timestamp(m, unit='ms', tz='UTC').isoformat()},{i}\n"
        for i, m in enumerate(millis)))
    want = read_history(iso)["ts"]
    assert list(want) == [pd.Timestamp(m, unit="ms", tz="UTC") for m in millis]
    pd.testing.assert_series_equal(read_history(epoch)["ts"], want)
    pd.testing.assert_series_equal(read_history(seconds)["ts"], want)
