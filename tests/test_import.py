"""``pseudotwin import``: the real SML2010 data, converted to canonical CSV, into a store."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from fake_cratedb import FakeCrateDB
from pseudotwin.cli.importer import main
from pseudotwin.core.series import read_history, write_history
from pseudotwin.history import convert as cv
from pseudotwin.history.importer import import_history
from pseudotwin.history.store import open_store

ROOT = cv.shared_data_root()


@pytest.fixture(scope="module")
def sml_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """SML2010 converted by pseudotwin.history.convert and written as canonical CSV."""
    if not ROOT.is_dir():
        pytest.skip(f"shared data not found at {ROOT}")
    path = tmp_path_factory.mktemp("sml") / "sml2010.csv"
    write_history(cv.load("sml2010"), path)
    return path


@pytest.fixture(scope="module")
def sml_frame(sml_csv: Path) -> pd.DataFrame:
    return read_history(sml_csv)


def test_import_twice_adds_nothing_the_second_time(sml_csv: Path, sml_frame: pd.DataFrame,
                                                   tmp_path: Path) -> None:
    progress: list[tuple[int, int]] = []
    with open_store(tmp_path / "history.db") as store:
        first = import_history(store, sml_csv, chunk_rows=6000,
                               progress=lambda done, total: progress.append((done, total)))
        second = import_history(store, sml_csv)
        assert first.rows_read == second.rows_read == len(sml_frame) > 20_000
        assert first.rows_new == len(sml_frame)
        assert second.rows_new == 0
        assert store.count_readings() == len(sml_frame)
        per_sensor = sml_frame["sensor"].value_counts()
        for sensor, n in per_sensor.items():
            assert store.count_readings([sensor]) == n
        assert first.sensors == tuple(sorted(per_sensor.index))
        assert (first.first, first.last) == (sml_frame["ts"].iloc[0], sml_frame["ts"].iloc[-1])
        # What comes back is the file, row for row (CSV values have 6 significant digits,
        # timestamps whole seconds, so nothing is lost at millisecond resolution).
        back = store.read_readings(None)
        pd.testing.assert_frame_equal(back, sml_frame)
    assert progress[-1] == (len(sml_frame), len(sml_frame))
    assert len(progress) == -(-len(sml_frame) // 6000)


def test_import_into_cratedb_fake(sml_csv: Path, sml_frame: pd.DataFrame) -> None:
    with FakeCrateDB() as fake, open_store(fake.url) as store:
        assert import_history(store, sml_csv).rows_new == len(sml_frame)
        assert import_history(store, sml_csv).rows_new == 0
        assert store.count_readings() == len(sml_frame)
        bulk = [r for r in fake.requests if r.bulk_args]
        assert bulk and all(len(r.bulk_args or []) <= 5000 for r in bulk)


def test_cli_import_twice(sml_csv: Path, sml_frame: pd.DataFrame, tmp_path: Path,
                          capsys: pytest.CaptureFixture[str]) -> None:
    db = tmp_path / "history.db"
    assert main([str(sml_csv), "--store", str(db)]) == 0
    out = capsys.readouterr().out
    n = len(sml_frame)
    assert f"{n} readings of {sml_frame['sensor'].nunique()} sensor(s)" in out
    assert f"{n} new, 0 already stored" in out
    assert main([str(sml_csv), "--store", f"sqlite:///{db}"]) == 0
    assert f"0 new, {n} already stored" in capsys.readouterr().out
    with open_store(db) as store:
        assert store.count_readings() == n


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("when,what,how\n1,2,3\n", "missing column(s) sensor, ts, value; expected header "
                                   "sensor,ts,value, found 'when,what,how'"),
        ("sensor;ts;value\na;2016-03-01T00:00:00Z;1\n", "found 'sensor;ts;value' (separated "
                                                     "by ';'? the file must be comma-separated)"),
        ("sensor,ts,value\na,2016-03-01T00:00:00,1.0\n", "has no UTC offset"),
        ("sensor,ts,value\na,2016-03-01T00:00:00Z,warm\n", "is not a number"),
        ("sensor,ts,value\n", "no rows"),
    ],
)
def test_cli_bad_file_is_one_clean_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                        content: str, message: str) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text(content)
    db = tmp_path / "history.db"
    assert main([str(bad), "--store", str(db)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.startswith("pseudotwin import: error: ") and message in err
    assert "\n" not in err and "Traceback" not in captured.err
    assert not db.exists()  # the file is checked before the store is opened


def test_cli_usage_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path / "missing.csv"), "--store", str(tmp_path / "h.db")]) == 2
    assert "missing.csv: no such file" in capsys.readouterr().err
    assert main([str(tmp_path / "x.csv")]) == 2  # --store is required (for now)
    assert "--store" in capsys.readouterr().err
    good = tmp_path / "good.csv"
    good.write_text("sensor,ts,value\na,2016-03-01T00:00:00Z,1.5\n")
    assert main([str(good), "--store", "mysql://db"]) == 2
    assert "unsupported history store" in capsys.readouterr().err
    assert main([str(good), "--store", str(tmp_path / "no" / "such" / "dir.db")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["--help"]) == 0
    assert "idempotent" in capsys.readouterr().out.lower()


@pytest.mark.parametrize("url", ["sqlite:///", ":memory:", "sqlite://"])
def test_cli_import_refuses_a_store_that_keeps_nothing(sml_csv: Path, url: str,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """`--store sqlite:///$DB` with DB unset imported into memory and reported success."""
    assert main([str(sml_csv), "--store", url]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pseudotwin import: error: ") and "Traceback" not in err
    assert ("no file path" if url == "sqlite:///" else "in memory") in err


def test_reimport_with_other_values_names_them_and_keeps_the_stored(
        sml_frame: pd.DataFrame, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    part = sml_frame.iloc[:3000].reset_index(drop=True)
    first, corrected = tmp_path / "first.csv", tmp_path / "corrected.csv"
    write_history(part, first)
    changed = part.copy()
    rows = [500, 2100]  # a corrected export: two values differ, the rest are the same
    changed.loc[rows, "value"] += 1.5
    write_history(changed, corrected)
    db = tmp_path / "history.db"
    assert main([str(first), "--store", str(db)]) == 0
    assert "already stored" in capsys.readouterr().out
    with open_store(db) as store:
        again = import_history(store, first, chunk_rows=1000)
        assert (again.rows_new, again.differing, again.first_differing) == (0, 0, None)
        summary = import_history(store, corrected, chunk_rows=1000)
        assert summary.rows_new == 0 and summary.differing == len(rows)
        sensor, ts, value, stored = summary.first_differing or ("", None, 0.0, 0.0)
        assert (sensor, ts) == (part["sensor"][500], part["ts"][500])
        assert value == pytest.approx(stored + 1.5)
        back = store.read_readings(None)
        pd.testing.assert_frame_equal(back, read_history(first))  # first write wins
    assert main([str(corrected), "--store", str(db)]) == 0
    out = capsys.readouterr().out
    assert f"{len(rows)} of the stored readings hold another value" in out
    assert f"{part['sensor'][500]} at {part['ts'][500].isoformat()}" in out
