"""Backfill feeds the twin only the readings that can change it (real SML2010 readings from a
real SQLite store, a real trained twin): the rows are those of a twin fed every reading."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pandas as pd
import pytest

from daemon_support import HOURS, REF, config, sml
from pseudotwin.history.backfill import (
    TwinJob,
    day_estimates,
    day_rows,
    grid_instants,
    window_frame,
)
from pseudotwin.history.store import open_store
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin

FIRST, LAST = dt.date(2012, 3, 18), dt.date(2012, 3, 22)
OTHER = "room/temp"  # a second sensor, so "last per sensor" is not "last reading"


@pytest.fixture(scope="module")
def days(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[dt.date, pd.DataFrame]]:
    """The local days FIRST … LAST of REF and OTHER as backfill reads them from the store."""
    path = tmp_path_factory.mktemp("window") / "history.db"
    df = sml()
    with open_store(str(path)) as store:
        store.write_readings(df[df["sensor"].isin([REF, OTHER])])
        return list(store.iter_days([REF, OTHER], FIRST, LAST, HOURS.timezone))


def test_outside_the_window_only_each_sensors_last_reading_per_side_is_kept(
    days: list[tuple[dt.date, pd.DataFrame]]
) -> None:
    for _day, frame in days:
        kept = window_frame(frame, HOURS)
        _, h = HOURS.day_and_hours(frame["ts"])
        inside = (h >= HOURS.init_start) & (h <= HOURS.day_end)
        assert kept.equals(frame.loc[kept.index]) and kept.index.is_monotonic_increasing
        assert frame[inside].index.isin(kept.index).all()
        for side in (h < HOURS.init_start, h > HOURS.day_end):
            outside = frame[side]
            assert outside["sensor"].value_counts().min() > 1  # something to drop
            last = outside.groupby("sensor").tail(1)
            assert kept.index.intersection(outside.index).equals(last.index)
        assert len(kept) < 0.6 * len(frame)


def test_backfill_rows_equal_those_of_a_twin_fed_every_reading(
    desk_artifact: Path, days: list[tuple[dt.date, pd.DataFrame]], tmp_path: Path
) -> None:
    cfg = config(tmp_path, 1883, desk_artifact)
    art = Artifact.load(desk_artifact)
    assert "varma" in art.published  # the lazily refreshed VARMA is among the rows
    job = TwinJob("desk", str(desk_artifact), "sha256:x", tuple(d for d, _ in days), ())
    every = Twin(art, stale_after=cfg.stale_after, thinning=cfg.thinning)
    backfilled = Twin(art, stale_after=cfg.stale_after, thinning=cfg.thinning)
    per_reading = cfg.per_reading_kinds(art.primary)
    for day, frame in days:
        want: dict[tuple[str, dt.datetime], tuple] = {}
        for kind, e in day_estimates(every, frame, grid_instants(cfg, day), per_reading):
            want[(kind, e.ts)] = (e.value, e.std, str(e.quality))
        got = {(r.model, r.ts): (r.value, r.std, str(r.quality))
               for r in day_rows(cfg, job, backfilled, day, frame)}
        assert len(got) > 40
        assert got == want, day  # to the last bit
