"""A DST fold inside the operating hours (an autumn night of a site working round the clock):
the twin's hours go forward through both passes of the repeated wall-clock hour, so a reading
of the second pass is the newest, not one older than the first pass's last."""

from __future__ import annotations

import datetime as dt

import pandas as pd
import pytest

from daemon_support import REF, TARGET, TZ, sml
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin

ROUND_THE_CLOCK = OperatingHours(0.0, 24.0, 0.0, 15.0, TZ)
FOLD_DAY = dt.date(2012, 10, 28)  # Madrid: 03:00 CEST → 02:00 CET, at 01:00 UTC


def utc(h: int, m: int) -> dt.datetime:
    return dt.datetime(2012, 10, 28, h, m, tzinfo=dt.UTC)


@pytest.fixture(scope="module")
def art() -> Artifact:
    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, ROUND_THE_CLOCK)
    return train_twin(sml(), spec, dt.date(2012, 3, 14), 5, models=("triv",))


def test_a_reading_in_the_second_pass_of_the_fold_moves_the_estimate(art) -> None:
    t = Twin(art)
    t.observe(REF, utc(0, 50), 20.0)  # 02:50 CEST, the first pass
    before = t.estimate(utc(0, 50))["triv"].value
    t.observe(REF, utc(1, 10), 25.0)  # 02:10 CET, the second pass: 20 min later
    after = t.estimate(utc(1, 10))["triv"].value
    # TRIV is the reference plus a time-of-day offset: the new value is held
    assert after - before == pytest.approx(5.0, abs=1.0)
    hours = [r.hours for r in t.window]
    assert hours == sorted(hours) and len(set(hours)) == len(hours)


def test_the_twins_hours_go_forward_through_folds_and_equal_the_wall_clock_elsewhere() -> None:
    for zone, day in (("Europe/Berlin", dt.date(2016, 10, 30)),
                      ("Australia/Lord_Howe", dt.date(2016, 4, 3)),  # a 30-min fold
                      ("America/Santiago", dt.date(2016, 5, 14))):  # 23:00–24:00 twice
        hours = OperatingHours(0.0, 24.0, 0.0, 15.0, zone)
        tz = hours.tz
        start = dt.datetime.combine(day, dt.time(0), tzinfo=tz).astimezone(dt.UTC)
        end = dt.datetime.combine(day + dt.timedelta(days=1), dt.time(0), tzinfo=tz)
        stamps = pd.date_range(start, end.astimezone(dt.UTC), freq="5min", inclusive="left")
        days, vec = hours.day_and_clock(stamps)
        scalar = [hours.clock_of(t) for t in stamps.to_pydatetime()]
        assert (pd.Series(vec).diff().dropna() > 0).all(), zone
        assert list(vec) == pytest.approx(scalar) and {str(d) for d in days} == {str(day)}
        wall = [hours.hours_of(t) for t in stamps.to_pydatetime()]
        differ = sum(abs(a - b) > 1e-9 for a, b in zip(scalar, wall, strict=True))
        fold_min = 60 if zone != "Australia/Lord_Howe" else 30
        assert 0 < differ < 2 * fold_min / 5  # only inside the fold


def test_days_without_a_fold_keep_the_wall_clock() -> None:
    hours = OperatingHours(0.0, 24.0, 0.0, 15.0, "Europe/Berlin")
    for t in (dt.datetime(2016, 3, 27, 1, 30, tzinfo=dt.UTC),  # the spring day
              dt.datetime(2016, 7, 1, 12, 7, tzinfo=dt.UTC)):
        assert hours.clock_of(t) == hours.hours_of(t)


def test_the_grid_goes_through_both_passes_of_a_fold_and_skips_a_gap() -> None:
    """Every 15 min of the 25-h day in time order (the second pass had no instant: 75 min
    without baselines and monitor), and of the 23-h one, where the gap's instants are
    not on the clock."""
    hours = OperatingHours(0.0, 24.0, 0.0, 15.0, "Europe/Berlin")
    for day, n in ((dt.date(2016, 10, 30), 100), (dt.date(2016, 3, 27), 92)):
        grid = hours.grid(day, 0.25)
        utc = [t.astimezone(dt.UTC) for t in grid]
        assert len(grid) == n
        steps = {b - a for a, b in zip(utc[:-1], utc[1:], strict=True)}
        assert steps == {dt.timedelta(minutes=15)}
        assert all(grid[i] < grid[i + 1] for i in range(len(grid) - 1))  # as compared
        assert all(hours.day_of(t) == day for t in grid)
    assert len(hours.grid(dt.date(2016, 7, 1), 0.25)) == 96
