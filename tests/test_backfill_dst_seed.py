"""Backfill's carry-over seed on a spring DST day: the same 24 hours as the twin's."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pandas as pd

from daemon_support import HOURS, REF, config
from pseudotwin.history.backfill import _seed
from pseudotwin.history.store import open_store
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin

SPRING = dt.date(2012, 3, 25)  # Madrid: 02:00 CET → 03:00 CEST


def test_a_wild_last_reading_leaves_the_seed_24_hours_not_23(tmp_path: Path,
                                                             desk_artifact: Path) -> None:
    cfg = config(tmp_path, 1883, desk_artifact)
    init = HOURS.at(SPRING, HOURS.init_start)  # 07:30 CEST = 05:30 UTC
    kept = init.astimezone(dt.UTC) - dt.timedelta(hours=23, minutes=30)  # 06:00 UTC the day before
    rows = pd.DataFrame({"sensor": [REF, REF], "value": [21.0, 99.0],  # 99 °C: out of range
                         "ts": pd.to_datetime([kept, kept + dt.timedelta(hours=6)], utc=True)})
    with open_store(str(tmp_path / "history.db")) as store:
        store.write_readings(rows)
        seeded = _seed(cfg, store, [REF], init)
    # the daemon rejects the 99 °C reading; its twin carries the one before, 23.5 h old
    twin = Twin(Artifact.load(desk_artifact))
    twin.observe(REF, kept, 21.0)
    twin.observe(REF, init, 21.5)  # opens the spring day's window
    assert [(r.ts, r.value) for r in twin.window][0] == (kept, 21.0)
    assert seeded == {REF: (kept, 21.0)}
