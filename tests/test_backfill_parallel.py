"""Backfill of several twins in parallel worker processes (real SQLite files, real SML2010
readings, real trained twins): the same rows as one process, resume, idempotence, failures
and Ctrl-C."""

from __future__ import annotations

import datetime as dt
import fcntl
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
from contextlib import closing
from pathlib import Path

import pandas as pd
import pytest

from daemon_support import HOURS, sml, wait_for, write_config
from pseudotwin.analysis.training import train_twin
from pseudotwin.cli import main
from pseudotwin.config import ServiceConfig, load_config
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.backfill_pool import backfill_twins
from pseudotwin.history.store import open_store

FIRST, LAST = dt.date(2012, 3, 19), dt.date(2012, 3, 26)  # the 25th and 26th have no data
TWINS = ["desk", "air"]
EXE = str(Path(sys.executable).parent / "pseudotwin")

AIR_TWIN = """
[[sensors]]
id = "dining/co2"
topic = "house/dining/co2"
unit = "ppm"
min = 0
max = 5000

[[sensors]]
id = "room/co2"
topic = "house/room/co2"
unit = "ppm"
min = 0
max = 5000

[[twins]]
id = "air"
references = ["dining/co2"]
quantity = "co2"
artifact = "{artifact}"
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory, desk_artifact: Path) -> Path:
    """A folder with a two-twin configuration (desk temperature, CO2 "air") and
    ``base.db``: SML2010 readings up to 2012-03-24."""
    folder = tmp_path_factory.mktemp("site")
    df = sml()
    # The CO2 twin is TRIV only: a second, different twin that trains in a second.
    spec = TwinSpec(("dining/co2",), "room/co2", Quantity.CO2, HOURS)
    air = train_twin(df, spec, dt.date(2012, 3, 14), 5, models=("triv",), validate=False)
    air_path = air.save(folder / "air.json")
    cfg = write_config(folder, 1883, desk_artifact, store="history.db")
    cfg.write_text(cfg.read_text() + AIR_TWIN.format(artifact=air_path))
    with open_store(str(folder / "base.db")) as store:
        store.write_readings(df[df["ts"] < "2012-03-24T23:00Z"])
    return folder


def fresh_store(site: Path, name: str) -> Path:
    """A copy of the readings-only base store (the base store is closed: no WAL left)."""
    path = site / f"{name}.db"
    for suffix in ("", "-wal", "-shm"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)
    shutil.copy(site / "base.db", path)
    return path


def site_config(site: Path, db: Path) -> ServiceConfig:
    text = (site / "config.toml").read_text()
    cfg_path = site / f"config-{db.stem}.toml"
    cfg_path.write_text(text.replace('store = "history.db"', f'store = "{db}"'))
    return load_config(cfg_path)


def rows(db: Path, twin: str, with_written_at: bool = False) -> pd.DataFrame:
    with open_store(str(db)) as store:
        est = store.read_estimates(twin)
    return est if with_written_at else est.drop(columns="written_at")


def progress(db: Path) -> dict[tuple[str, str], int]:
    """(twin@artifact, day) → estimates recorded for every finished day."""
    with closing(sqlite3.connect(db)) as con:
        got = con.execute("SELECT twin, day, estimates FROM backfill_progress").fetchall()
    return {(t, d): n for t, d, n in got}


@pytest.fixture(scope="module")
def serial(site: Path) -> Path:
    """The reference: both twins, one process, each twin's days as one run."""
    db = fresh_store(site, "serial")
    with open_store(str(db)) as store:
        run = backfill_twins(site_config(site, db), TWINS, FIRST, LAST, store, jobs=1,
                             progress=False, chunk_days=100)
    assert not run.failures and run.workers == 1
    assert {t: s.days for t, s in run.twins.items()} == {"desk": 6, "air": 6}
    return db


def test_parallel_backfill_writes_exactly_the_serial_rows(site: Path, serial: Path,
                                                          capsys) -> None:
    db = fresh_store(site, "parallel")
    cfg = site_config(site, db)
    # One day per chunk: every day starts from a fresh twin seeded from the store.
    with open_store(str(db)) as store:
        run = backfill_twins(cfg, TWINS, FIRST, LAST, store, jobs=2, chunk_days=1)
    assert run.workers == 2 and not run.failures and not run.interrupted
    for twin in TWINS:
        want = rows(serial, twin)
        assert len(want) > 6 * 40
        pd.testing.assert_frame_equal(rows(db, twin), want, check_exact=True)
        assert run.twins[twin].skipped == {"no reference readings": ["2012-03-25",
                                                                     "2012-03-26"]}
    assert progress(db) == progress(serial)
    # One progress line per chunk, each whole (never two interleaved on one line).
    lines = capsys.readouterr().err.splitlines()
    chunk_lines = [ln for ln in lines if ln.startswith("backfill ")]
    assert len(chunk_lines) == 2 * 8
    assert all(ln.endswith("days/s]") for ln in chunk_lines)


def test_resume_writes_only_the_missing_days_and_a_rerun_nothing(site: Path,
                                                                 serial: Path) -> None:
    db = fresh_store(site, "resume")
    cfg = site_config(site, db)
    first_days = [dt.date(2012, 3, 20), dt.date(2012, 3, 22)]
    with open_store(str(db)) as store:  # an earlier, interrupted run finished two days
        for d in first_days:
            backfill_twins(cfg, ["desk"], d, d, store, jobs=1, progress=False)
    before = rows(db, "desk", with_written_at=True)
    with open_store(str(db)) as store:
        run = backfill_twins(cfg, TWINS, FIRST, LAST, store, jobs=2, progress=False)
    assert run.twins["desk"].skipped["already backfilled"] == [str(d) for d in first_days]
    assert run.twins["desk"].days == 4 and run.twins["air"].days == 6
    after = rows(db, "desk", with_written_at=True)
    # the days done before were not rewritten: their rows keep their written_at
    kept = after.merge(before, on=["model", "ts"], suffixes=("", "_before"))
    assert len(kept) == len(before)
    assert (kept["written_at"] == kept["written_at_before"]).all()
    for twin in TWINS:
        pd.testing.assert_frame_equal(rows(db, twin), rows(serial, twin), check_exact=True)
    assert progress(db).keys() == progress(serial).keys()
    # idempotent: a rerun of the finished range computes and writes nothing
    with open_store(str(db)) as store:
        again = backfill_twins(cfg, TWINS, FIRST, LAST, store, jobs=2, progress=False)
    assert sum(s.days + s.estimates for s in again.twins.values()) == 0
    # the days without readings are not recorded: skipped again, for readings to come
    assert again.twins["air"].skipped == {
        "already backfilled": [str(FIRST + dt.timedelta(days=i)) for i in range(6)],
        "no reference readings": ["2012-03-25", "2012-03-26"]}
    pd.testing.assert_frame_equal(rows(db, "desk", with_written_at=True), after)


def test_a_failing_day_names_twin_and_day_and_the_others_stay_written(
    site: Path, serial: Path, capsys
) -> None:
    db = fresh_store(site, "failing")
    site_config(site, db)
    # The database itself refuses one day of one twin (as a full disk or a constraint would).
    bad = HOURS.at(dt.date(2012, 3, 21), 0.0)
    with sqlite3.connect(db) as con:
        con.execute(
            "CREATE TRIGGER refuse BEFORE INSERT ON estimates WHEN NEW.twin = 'air' AND "
            f"NEW.ts >= {int(bad.timestamp() * 1000)} AND "
            f"NEW.ts < {int((bad + dt.timedelta(days=1)).timestamp() * 1000)} "
            "BEGIN SELECT RAISE(ABORT, 'quota exceeded'); END")
    args = ["--log-level", "WARNING", "backfill", "--config", str(site / "config-failing.toml"),
            "--twin", "desk,air", "--from", str(FIRST), "--to", str(LAST), "--jobs", "2",
            "--quiet"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "error: twin air, day 2012-03-21: StoreError:" in err and "quota exceeded" in err
    assert "Traceback" not in err
    done = progress(db)
    # the other twin: all days with readings (the 25th and 26th have none: not recorded)
    assert sum(1 for t, _ in done if t.startswith("desk@")) == 6
    air_days = {d for t, d in done if t.startswith("air@")}
    assert "2012-03-21" not in air_days and "2012-03-19" in air_days
    pd.testing.assert_frame_equal(rows(db, "desk"), rows(serial, "desk"), check_exact=True)
    # the cause removed, the same command finishes the missing days only
    with sqlite3.connect(db) as con:
        con.execute("DROP TRIGGER refuse")
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "air: skipped" in out and "desk: backfilled 0 day(s)" in out
    pd.testing.assert_frame_equal(rows(db, "air"), rows(serial, "air"), check_exact=True)


def test_ctrl_c_stops_the_workers_and_keeps_finished_days(site: Path, tmp_path: Path) -> None:
    """Ctrl-C in the middle of a run, made certain without timing: stderr is a pipe of one
    page that the test does not read until after the Ctrl-C, and every finished day logs a
    DEBUG line to it. Workers block on that pipe after ~40 days of the 76 with readings, so
    the run cannot end before the Ctrl-C; the test waits for a first finished day only."""
    db = fresh_store(site, "interrupted")
    with open_store(str(db)) as store:  # readings up to the end of April: a long run
        df = sml()
        store.write_readings(df[df["ts"] < "2012-04-30T22:00Z"])
    site_config(site, db)
    read_end, write_end = os.pipe()
    fcntl.fcntl(write_end, fcntl.F_SETPIPE_SZ, 4096)  # Linux rounds it to one page
    # Its own process group, as a terminal's foreground job: Ctrl-C reaches every process.
    proc = subprocess.Popen(
        [EXE, "--log-level", "DEBUG", "backfill", "--config",
         str(site / "config-interrupted.toml"), "--twin", "desk,air", "--from", "2012-03-19",
         "--to", "2012-04-29", "--jobs", "2"],
        stdout=subprocess.PIPE, stderr=write_end, text=True, start_new_session=True,
        preexec_fn=_ctrl_c_as_in_a_terminal)
    os.close(write_end)
    chunks: list[bytes] = []
    reader = threading.Thread(target=_drain, args=(read_end, chunks), daemon=True)
    try:
        wait_for(lambda: bool(progress(db)), timeout=120, what="a first finished day")
        os.killpg(proc.pid, signal.SIGINT)
        reader.start()  # only now: the workers go on to their current day's end
        out, _ = proc.communicate(timeout=120)
        reader.join(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        if not reader.is_alive() and not chunks:
            os.close(read_end)  # the reader never ran: nobody else closes it
    err = b"".join(chunks).decode()
    assert proc.returncode == 130, err
    assert "interrupted; finished days stay written" in err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    # no worker outlives the run
    wait_for(lambda: not _group_alive(proc.pid), timeout=30, what="worker processes gone")
    done = progress(db)
    assert 0 < len(done) < 84
    for twin in TWINS:
        est = rows(db, twin)
        per_day = est["ts"].dt.tz_convert(HOURS.timezone).dt.date.astype(str).value_counts()
        twin_done = {d: n for (t, d), n in done.items() if t.startswith(f"{twin}@")}
        for day, n in twin_done.items():  # every day marked done has all its rows
            assert per_day.get(day, 0) == n
        assert set(per_day.index) <= set(twin_done)  # and no half-written day


def _ctrl_c_as_in_a_terminal() -> None:
    """A shell starts background jobs (``cmd &``) with SIGINT ignored, and the test suite's
    children inherit that: the backfill would then rightly ignore Ctrl-C. A terminal's
    foreground job, what these tests stand for, has the default."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _drain(fd: int, into: list[bytes]) -> None:
    with os.fdopen(fd, "rb") as f:
        into.append(f.read())


def test_ctrl_c_while_the_workers_start(site: Path) -> None:
    """The moment a worker is still importing (the last stop's CI failure): no traceback
    from it, the run ends as interrupted, and no day is half written."""
    db = fresh_store(site, "early")
    site_config(site, db)
    proc = subprocess.Popen(
        [EXE, "--log-level", "WARNING", "backfill", "--config", str(site / "config-early.toml"),
         "--twin", "desk,air", "--from", str(FIRST), "--to", str(LAST), "--jobs", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=_ctrl_c_as_in_a_terminal)
    try:
        # the parent, its resource tracker and a first worker: workers are starting
        wait_for(lambda: len(_group(proc.pid)) >= 3, timeout=60, what="a worker process")
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode in (0, 130), err  # 0: the run was already over (a fast machine)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    wait_for(lambda: not _group_alive(proc.pid), timeout=30, what="worker processes gone")
    with open_store(str(db)) as store:
        est = store.read_estimates("desk")
    per_day = est["ts"].dt.tz_convert(HOURS.timezone).dt.date.astype(str).value_counts()
    done = progress(db)
    for (twin, day), n in done.items():
        if twin.startswith("desk@"):
            assert per_day.get(day, 0) == n
    assert set(per_day.index) <= {d for t, d in done if t.startswith("desk@")}


def _group(pgid: int) -> list[int]:
    members = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                if os.getpgid(int(pid)) == pgid:
                    members.append(int(pid))
            except ProcessLookupError:
                continue
    return members


def _group_alive(pgid: int) -> bool:
    return bool(_group(pgid))


def test_cli_twin_lists_and_bad_arguments(site: Path, capsys) -> None:
    db = fresh_store(site, "cli")
    site_config(site, db)
    cfg = str(site / "config-cli.toml")
    rc = main(["backfill", "--config", cfg, "--twin", "desk,nope", "--twin", "air",
               "--from", "2012-03-25", "--to", "2012-03-25"])
    assert rc == 2 and "no twin 'nope'" in capsys.readouterr().err
    rc = main(["backfill", "--config", cfg, "--all-twins", "--from", "2012-03-25",
               "--to", "2012-03-26", "--jobs", "2", "--quiet"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "desk: skipped 2 day(s), no reference readings" in out
    assert "air: skipped 2 day(s), no reference readings" in out
    with pytest.raises(SystemExit):
        main(["backfill", "--config", cfg, "--all-twins", "--from", "2012-03-25",
              "--to", "2012-03-26", "--jobs", "0"])
    assert "argument --jobs/-j: must be at least 1, not 0" in capsys.readouterr().err
