"""Which days backfill records as finished (real SQLite files, real SML2010 readings, a real
trained twin): only a day with reference readings that has ended in the twin's time zone. A
day without readings, or one not over yet, is left for a later run, which then writes the
rows a backfill with every reading there from the start writes."""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import pandas as pd
import pytest

from daemon_support import HOURS, config, sml
from pseudotwin.config import ServiceConfig
from pseudotwin.history.backfill import backfill
from pseudotwin.history.store import open_store
from pseudotwin.live.artifact import artifact_hash

DAY = dt.date(2012, 3, 24)  # a whole day of readings in the base store
NEXT = DAY + dt.timedelta(days=1)  # the readings that "arrive later"
NOON = HOURS.at(DAY, 12.0)


@pytest.fixture(scope="module")
def base_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """SML2010 readings up to the start of DAY, in a readings-only store."""
    path = tmp_path_factory.mktemp("progress") / "base.db"
    df = sml()
    with open_store(str(path)) as store:
        store.write_readings(df[df["ts"] < HOURS.at(DAY, 0.0)])
    return path


def readings(start: dt.date | dt.datetime, end: dt.date) -> pd.DataFrame:
    """SML2010 readings from ``start`` (a local day's midnight, or an instant) up to the end
    of local day ``end``."""
    first = HOURS.at(start, 0.0) if not isinstance(start, dt.datetime) else start
    df = sml()
    return df[(df["ts"] >= first) & (df["ts"] < HOURS.at(end + dt.timedelta(days=1), 0.0))]


def site(tmp: Path, name: str, base: Path, artifact: Path) -> tuple[Path, ServiceConfig]:
    folder = tmp / name
    folder.mkdir()
    db = folder / "history.db"
    shutil.copy(base, db)
    return db, config(folder, 1883, artifact, store=str(db))


def rows(db: Path) -> pd.DataFrame:
    with open_store(str(db)) as store:
        return store.read_estimates("desk").drop(columns="written_at")


def done(db: Path, artifact: Path) -> set[dt.date]:
    with open_store(str(db)) as store:
        return store.done_days(f"desk@{artifact_hash(artifact)[:16]}")


def reference(tmp: Path, base: Path, artifact: Path, last: dt.date) -> pd.DataFrame:
    """The rows of a backfill of DAY … last with every reading of those days there."""
    db, cfg = site(tmp, "reference", base, artifact)
    with open_store(str(db)) as store:
        store.write_readings(readings(DAY, last))
        s = backfill(cfg, "desk", DAY, last, store, progress=False)
    assert s.days == (last - DAY).days + 1 and not s.skipped and not s.unended
    return rows(db)


def test_a_day_without_readings_is_not_recorded_and_a_rerun_fills_it(
    desk_artifact: Path, base_db: Path, tmp_path: Path
) -> None:
    db, cfg = site(tmp_path, "late", base_db, desk_artifact)
    with open_store(str(db)) as store:
        store.write_readings(readings(DAY, DAY))
        first = backfill(cfg, "desk", DAY, NEXT, store, progress=False)
    assert first.days == 1
    assert first.skipped == {"no reference readings": [str(NEXT)]}
    assert done(db, desk_artifact) == {DAY}  # the empty day is not recorded
    with open_store(str(db)) as store:  # the readings of NEXT arrive (an import)
        store.write_readings(readings(NEXT, NEXT))
        again = backfill(cfg, "desk", DAY, NEXT, store, progress=False)
    assert again.days == 1 and again.estimates > 40
    assert again.skipped == {"already backfilled": [str(DAY)]}
    assert done(db, desk_artifact) == {DAY, NEXT}
    pd.testing.assert_frame_equal(rows(db), reference(tmp_path, base_db, desk_artifact, NEXT),
                                  check_exact=True)


def test_a_day_with_readings_of_the_night_before_only_is_estimated_not_recorded(
    desk_artifact: Path, base_db: Path, tmp_path: Path
) -> None:
    """A store filled up to 01:00 of NEXT (an import cut there): NEXT has reference
    readings, but none from its init phase on, so its estimates are stale. Written, said, not
    recorded: the rest of NEXT imported later makes a rerun write what a backfill with every
    reading there from the start writes."""
    db, cfg = site(tmp_path, "night", base_db, desk_artifact)
    one_am = HOURS.at(NEXT, 1.0)
    with open_store(str(db)) as store:
        store.write_readings(readings(DAY, NEXT).loc[lambda f: f["ts"] < one_am])
        first = backfill(cfg, "desk", DAY, NEXT, store, progress=False)
    assert first.days == 2 and first.silent == [str(NEXT)] and not first.skipped
    assert (f"not marked done 1 day(s), no reference reading from the init phase on, its "
            f"estimates stale or held (a run after more readings are stored redoes it): "
            f"{NEXT}") in first.lines()
    assert done(db, desk_artifact) == {DAY}
    with open_store(str(db)) as store:
        assert set(store.read_estimates("desk").query("ts >= @one_am")["quality"]) <= {
            "stale", "init"}
        store.write_readings(readings(one_am, NEXT))
        again = backfill(cfg, "desk", DAY, NEXT, store, progress=False)
    assert again.days == 1 and not again.silent
    assert done(db, desk_artifact) == {DAY, NEXT}
    pd.testing.assert_frame_equal(rows(db), reference(tmp_path, base_db, desk_artifact, NEXT),
                                  check_exact=True)


def test_a_reference_the_store_never_held_is_named(
    desk_artifact: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Every day without reference readings is skipped quietly, as a store not filled yet
    would be; a reference with no reading at all (a misspelt id, a sensor never recorded)
    is named once."""
    folder = tmp_path / "never"
    folder.mkdir()
    db = folder / "history.db"
    with open_store(str(db)) as store:
        desk = readings(DAY, DAY)
        store.write_readings(desk[desk["sensor"] != "dining/temp"])
    cfg = config(folder, 1883, desk_artifact, store=str(db))
    with caplog.at_level("WARNING", logger="pseudotwin.history.backfill"), \
            open_store(str(db)) as store:
        s = backfill(cfg, "desk", DAY, DAY, store, progress=False)
    assert s.skipped == {"no reference readings": [str(DAY)]}
    assert [r.getMessage() for r in caplog.records if "no reading at all" in r.getMessage()] == [
        "twin desk: the store holds no reading at all of dining/temp (not recorded yet, or "
        "under another name?): every day is skipped as without reference readings"]


def test_a_day_not_ended_is_estimated_not_recorded_and_a_later_run_completes_it(
    desk_artifact: Path, base_db: Path, tmp_path: Path
) -> None:
    db, cfg = site(tmp_path, "today", base_db, desk_artifact)
    later = NEXT + dt.timedelta(days=1)
    with open_store(str(db)) as store:  # "now" is noon of DAY: its morning is stored
        store.write_readings(readings(DAY, DAY).loc[lambda f: f["ts"] < NOON])
        first = backfill(cfg, "desk", DAY, later, store, progress=False, now=NOON)
    assert first.days == 1 and first.estimates > 0
    assert first.unended == [str(DAY)]
    assert first.skipped == {"no reference readings": [str(NEXT), str(later)]}
    assert done(db, desk_artifact) == set()
    assert (f"not marked done 1 day(s), the day has not ended (a run after its end completes "
            f"it): {DAY}") in first.lines()
    partial = rows(db)
    # nothing of the afternoon to come: the daemon has not published it either
    assert not partial.empty and partial["ts"].max() <= NOON
    # The next morning: the afternoon's readings are stored, DAY has ended, NEXT has not.
    morning = HOURS.at(NEXT, 9.0)
    with open_store(str(db)) as store:
        store.write_readings(readings(NOON, NEXT).loc[lambda f: f["ts"] < morning])
        second = backfill(cfg, "desk", DAY, later, store, progress=False, now=morning)
    assert second.days == 2 and second.unended == [str(NEXT)]
    assert done(db, desk_artifact) == {DAY}
    complete = rows(db)
    assert len(complete) > len(partial)
    # DAY's rows (the morning's rewritten) are those of a backfill with the whole day stored
    want = reference(tmp_path, base_db, desk_artifact, DAY)
    got = complete[complete["ts"] < HOURS.at(NEXT, 0.0)].reset_index(drop=True)
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    # a rerun on the clock: DAY is finished, NEXT (long over, readings of its morning only)
    # is recorded now
    with open_store(str(db)) as store:
        third = backfill(cfg, "desk", DAY, NEXT, store, progress=False)
    assert third.skipped == {"already backfilled": [str(DAY)]}
    assert third.days == 1 and not third.unended
    assert done(db, desk_artifact) == {DAY, NEXT}


def test_now_must_be_aware(desk_artifact: Path, base_db: Path, tmp_path: Path) -> None:
    db, cfg = site(tmp_path, "naive", base_db, desk_artifact)
    with open_store(str(db)) as store, pytest.raises(ValueError, match="timezone-aware"):
        backfill(cfg, "desk", DAY, DAY, store, progress=False, now=dt.datetime(2012, 3, 24))
