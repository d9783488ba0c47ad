"""What backfill stores at a reading and at a grid instant follows what the daemon publishes
(``[service] baselines``), with the same numbers either way (real SQLite files, real SML2010
readings, a real trained twin)."""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import pandas as pd
import pytest

from daemon_support import config, sml
from pseudotwin.history.backfill import backfill, grid_instants
from pseudotwin.history.store import open_store
from pseudotwin.live.artifact import Artifact

FIRST, LAST = dt.date(2012, 3, 20), dt.date(2012, 3, 21)
# Hourly: SML2010's readings (every 15 min) fall on the grid and off it.
GRID_MINUTES = 60


@pytest.fixture(scope="module")
def base_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """SML2010 readings up to 2012-03-22 in a readings-only store."""
    path = tmp_path_factory.mktemp("cadence") / "base.db"
    df = sml()
    with open_store(str(path)) as store:
        store.write_readings(df[df["ts"] < "2012-03-22T23:00Z"])
    return path


def backfilled(tmp: Path, artifact: Path, base: Path, baselines: str) -> pd.DataFrame:
    folder = tmp / baselines
    folder.mkdir()
    db = folder / "history.db"
    shutil.copy(base, db)
    cfg = config(folder, 1883, artifact, store=str(db), baselines=baselines,
                 publish_every_minutes=GRID_MINUTES)
    with open_store(str(db)) as store:
        summary = backfill(cfg, "desk", FIRST, LAST, store, progress=False)
        assert summary.days == 2
        est = store.read_estimates("desk").drop(columns="written_at")
    est["ts"] = pd.DatetimeIndex(est["ts"]).tz_convert("UTC")
    return est


def test_baselines_on_the_grid_by_default_with_the_numbers_of_every_reading(
    desk_artifact: Path, base_db: Path, tmp_path: Path
) -> None:
    on_grid = backfilled(tmp_path, desk_artifact, base_db, "grid")
    every = backfilled(tmp_path, desk_artifact, base_db, "reading")
    art = Artifact.load(desk_artifact)
    baselines = sorted(k for k in art.published if k != art.primary)
    assert baselines and set(every["model"]) == set(art.published) == set(on_grid["model"])
    cfg = config(tmp_path, 1883, desk_artifact, publish_every_minutes=GRID_MINUTES)
    grid = {pd.Timestamp(g).tz_convert("UTC") for d in (FIRST, LAST)
            for g in grid_instants(cfg, d)}

    def instants(est: pd.DataFrame, kind: str) -> set[pd.Timestamp]:
        return set(est.loc[est["model"] == kind, "ts"])

    # The primary: at every reading that moved the twin and every grid instant, both ways.
    primary = instants(every, art.primary)
    assert instants(on_grid, art.primary) == primary
    assert len(primary - grid) > 2 * 30 and len(primary & grid) > 2 * 10
    for kind in baselines:
        # the baselines: on the grid only by default, at every reading with "reading"
        assert instants(on_grid, kind) == instants(every, kind) & grid, kind
        assert instants(every, kind) == primary, kind
    # Wherever both stored a row it is the same row, to the last bit.
    both = on_grid.merge(every, on=["twin", "model", "ts"], suffixes=("", "_every"))
    assert len(both) == len(on_grid)
    for col in ("value", "std", "quality", "artifact_hash"):
        assert (both[col] == both[f"{col}_every"]).all(), col


def test_without_baselines_backfill_stores_the_primary_alone_with_the_same_numbers(
    desk_artifact: Path, base_db: Path, tmp_path: Path
) -> None:
    """``baselines = "none"``: the twin runs its primary only (and what it needs); the rows
    it stores are exactly the primary's rows of a twin that runs every published model."""
    on_grid = backfilled(tmp_path, desk_artifact, base_db, "grid")
    alone = backfilled(tmp_path, desk_artifact, base_db, "none")
    art = Artifact.load(desk_artifact)
    assert len(art.published) > 1  # there were baselines to leave out
    assert set(alone["model"]) == {art.primary}
    primary = on_grid[on_grid["model"] == art.primary].reset_index(drop=True)
    pd.testing.assert_frame_equal(alone.reset_index(drop=True), primary)
