"""One training day unlike the others (analysis/commissioning/oddday.py) and --skip-days:
Grubbs' test on synthetic offsets, and on SML2010's CO2 days through the real CLI."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from daemon_support import sml_csv
from pseudotwin.analysis.commissioning.oddday import odd_day, odd_training_day
from pseudotwin.cli import main

DAY0 = dt.date(2012, 3, 14)


def offsets(values: list[float]) -> dict[dt.date, float]:
    return {DAY0 + dt.timedelta(days=i): v for i, v in enumerate(values)}


def test_a_day_far_from_the_others_is_named_with_the_spread_without_it() -> None:
    found = odd_day(offsets([0.1, -0.1, 3.0, 0.0, 0.05]))
    assert found is not None and found.day == DAY0 + dt.timedelta(days=2)
    assert found.offset == 3.0 and sorted(found.others) == [-0.1, 0.0, 0.05, 0.1]
    assert found.spread == pytest.approx(np.std([0.1, -0.1, 3.0, 0.0, 0.05], ddof=1))
    assert found.spread_without == pytest.approx(np.std([0.1, -0.1, 0.0, 0.05], ddof=1))
    text = found.advice("°C")
    assert "on 2012-03-16" in text and "--skip-days 2012-03-16" in text and "+3.00 °C" in text
    assert "+3.00 °C from the reference on average" in text
    assert "+3.00 °C from the mean of the 2 references on average" in found.advice("°C", 2)


def test_ordinary_alike_and_too_few_days_are_not_flagged() -> None:
    assert odd_day(offsets([0.1, -0.1, 0.3, 0.0, 0.2])) is None
    assert odd_day(offsets([0.5] * 5)) is None  # no spread at all
    assert odd_day(offsets([0.0, 5.0])) is None  # two days: nothing to compare
    assert odd_day(offsets([0.1, -0.1, float("nan"), 0.0, 3.0])) is not None  # NaN ignored


@pytest.mark.parametrize("n", [5, 10])
def test_ordinary_normal_days_are_flagged_one_time_in_twenty(n: int) -> None:
    rng = np.random.default_rng(7)
    flagged = sum(odd_day(offsets(list(rng.normal(0.0, 1.0, n)))) is not None
                  for _ in range(4000))
    assert 0.04 <= flagged / 4000 <= 0.06


def test_for_five_days_a_day_is_flagged_exactly_below_0_328_of_the_spread() -> None:
    # four ordinary days and a fifth moved ever further away: flagged once the spread without
    # it falls below 0.328 of the spread with it (the docstring's figure), not before
    others = [0.1, -0.1, 0.05, -0.02]
    seen = set()
    for x in np.linspace(0.0, 3.0, 600):
        ratio = np.std(others, ddof=1) / np.std([*others, x], ddof=1)
        if abs(ratio - 0.3283) < 0.001:
            continue  # the edge itself, to three figures
        flagged = odd_day(offsets([*others, float(x)])) is not None
        assert flagged == (ratio < 0.3283), (x, ratio)
        seen.add(flagged)
    assert seen == {True, False}


def test_an_artifact_without_daily_offsets_has_no_odd_day() -> None:
    assert odd_training_day({}) is None  # saved before validation recorded them
    assert odd_training_day({"offset_by_day": {}}) is None
    saved = {"2012-03-14": 3.0, "2012-03-15": 0.1, "2012-03-16": -0.1, "2012-03-17": 0.0,
             "2012-03-18": 0.05}
    found = odd_training_day({"offset_by_day": saved})
    assert found is not None and found.day == DAY0
    # JSON writes NaN as null: a day without an offset is not a day
    assert odd_training_day({"offset_by_day": {**saved, "2012-03-14": None}}) is None


def co2_csv(folder: Path) -> Path:
    """SML2010's CO2 readings of its first training days, as a canonical CSV."""
    import pandas as pd

    path = sml_csv(folder, DAY0 + dt.timedelta(days=6))
    df = pd.read_csv(path)
    df[df["sensor"].isin(["dining/co2", "room/co2"])].to_csv(path, index=False)
    return path


def test_train_names_the_odd_co2_day_and_skip_days_leaves_it_out(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    history = co2_csv(tmp_path)
    args = ["--log-level", "WARNING", "train", "--history", str(history),
            "--references", "dining/co2", "--target", "room/co2", "--quantity", "co2",
            "--train-start", str(DAY0), "--timezone", "Europe/Madrid", "--models", "ref,triv"]
    assert main([*args, "--out", str(tmp_path / "all.json"),
                 "--report", str(tmp_path / "r")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    # SML2010's first day: the desk ~18 ppm above the reference, the others within 2 ppm
    assert "One training day is unlike the others: on 2012-03-14" in out
    assert "--skip-days 2012-03-14" in out
    page = (tmp_path / "r" / "all.html").read_text(encoding="utf-8")
    assert "One training day is unlike the others." in page
    saved = json.loads((tmp_path / "all.json").read_text())
    assert saved["validation"]["offset_by_day"]["2012-03-14"] > 10.0
    assert "skipped" not in saved["training"]

    assert main([*args, "--skip-days", "2012-03-14", "--out", str(tmp_path / "skip.json"),
                 "--report", str(tmp_path / "r")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    saved = json.loads((tmp_path / "skip.json").read_text())
    assert saved["training"]["days"][0] == "2012-03-15" and len(saved["training"]["days"]) == 5
    assert saved["training"]["skipped"] == ["2012-03-14"]
    assert "2012-03-14" not in saved["validation"]["offset_by_day"]
    assert "unlike the others" not in out  # the other days' offsets: +0.48 … +1.91 ppm
    assert "left out (--skip-days)" in (tmp_path / "r" / "skip.html").read_text(encoding="utf-8")


def test_evaluate_says_it_too(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    history = co2_csv(tmp_path)
    rc = main(["--log-level", "WARNING", "evaluate", "--history", str(history),
               "--references", "dining/co2", "--target", "room/co2", "--quantity", "co2",
               "--train-start", str(DAY0), "--timezone", "Europe/Madrid", "--models", "ref,triv",
               "--out", str(tmp_path / "ev")])
    assert rc == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "training days: One training day is unlike the others: on 2012-03-14" in out


def test_skip_days_that_leave_too_few_days_say_so(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    history = co2_csv(tmp_path)
    skip = ",".join(str(DAY0 + dt.timedelta(days=i)) for i in range(3))
    rc = main(["--log-level", "WARNING", "train", "--history", str(history),
               "--references", "dining/co2", "--target", "room/co2", "--quantity", "co2",
               "--train-start", str(DAY0), "--timezone", "Europe/Madrid", "--models", "ref,triv",
               "--skip-days", skip, "--out", str(tmp_path / "x.json")])
    assert rc != 0
    err = capsys.readouterr().err
    assert "not counting 3 left out by --skip-days, 5 needed" in err


def test_a_bad_skip_day_is_argparse_s_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["train", "--history", "x.csv", "--references", "a", "--target", "b",
              "--quantity", "co2", "--skip-days", "2012-03-32", "--out", "x.json"])
    assert exc.value.code == 2
    assert "'2012-03-32' is not a date YYYY-MM-DD" in capsys.readouterr().err


def test_a_skip_day_that_would_not_have_been_trained_on_is_named(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    history = co2_csv(tmp_path)
    rc = main(["--log-level", "WARNING", "train", "--history", str(history),
               "--references", "dining/co2", "--target", "room/co2", "--quantity", "co2",
               "--train-start", str(DAY0), "--timezone", "Europe/Madrid", "--models", "ref,triv",
               "--skip-days", "2012-03-16,2012-04-30", "--out", str(tmp_path / "x.json")])
    assert rc == 0
    warned = [r.getMessage() for r in caplog.records if "--skip-days" in r.getMessage()]
    assert len(warned) == 1  # the twin's name first (core/twinlog.py)
    assert "twin x: --skip-days 2012-04-30: would not have been a training day" in warned[0]
    saved = json.loads((tmp_path / "x.json").read_text())
    assert saved["training"]["skipped"] == ["2012-03-16"]
    assert saved["training"]["days"] == ["2012-03-14", "2012-03-15", "2012-03-17",
                                         "2012-03-18", "2012-03-19"]


def skipped_warning(caplog: pytest.LogCaptureFixture, source: str, history: Path,
                    start: str, out: Path) -> str:
    """Train SML2010's temperature twin from ``start``; the warning about days passed over."""
    rc = main(["--log-level", "WARNING", "train", source, str(history),
               "--references", "dining/temp", "--target", "room/temp", "--quantity",
               "temperature", "--train-start", start, "--timezone", "Europe/Madrid",
               "--models", "ref,triv", "--out", str(out)])
    assert rc == 0
    return " ".join(r.getMessage() for r in caplog.records if "skips" in r.getMessage())


@pytest.mark.parametrize("source", ["--history", "--store"])
def test_every_day_training_passes_over_is_named_with_its_reason(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, source: str) -> None:
    """SML2010 from Apr 9: the warning named Apr 11 "without data of every sensor" (both
    had a few readings) and left out Apr 12–17, which had none at all; from the store it
    would have called Apr 11 a day without readings (only usable days were loaded)."""
    history = sml_csv(tmp_path, dt.date(2012, 4, 21))
    if source == "--store":
        assert main(["import", str(history), "--store", str(tmp_path / "h.db")]) == 0
        history = tmp_path / "h.db"
    warned = skipped_warning(caplog, source, history, "2012-04-09", tmp_path / "x.json")
    assert "2012-04-11 (dining/temp 3, room/temp 3 reading(s) in operating hours)" in warned
    assert "2012-04-12 … 2012-04-17 (no readings)" in warned
    saved = json.loads((tmp_path / "x.json").read_text())
    assert saved["training"]["days"] == ["2012-04-09", "2012-04-10", "2012-04-18",
                                         "2012-04-19", "2012-04-20"]


def test_days_passed_over_for_one_reason_are_one_range(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """References recorded for weeks before the desk sensor came: each of those days was
    named on its own, one line of dozens of days."""
    history = sml_csv(tmp_path, dt.date(2012, 4, 10))
    df = pd.read_csv(history)
    early = pd.to_datetime(df["ts"], utc=True) < pd.Timestamp("2012-03-31T22:00Z")
    df[~(early & (df["sensor"] == "room/temp"))].to_csv(history, index=False)
    warned = skipped_warning(caplog, "--history", history, "2012-03-14", tmp_path / "x.json")
    assert "2012-03-14 … 2012-03-31 (room/temp 0 reading(s) in operating hours)" in warned
    assert warned.count("2012-03-2") == 0  # no day of the range named on its own


def test_a_first_day_cut_short_and_a_missing_time_zone_are_said(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Data beginning mid-morning: training began the next day without a word (the day was
    often the richest); and without --timezone the hours were silently UTC."""
    history = sml_csv(tmp_path, dt.date(2012, 3, 21))
    df = pd.read_csv(history)
    df[pd.to_datetime(df["ts"], utc=True) >= pd.Timestamp("2012-03-14T09:00Z")].to_csv(
        history, index=False)
    with caplog.at_level("INFO"):
        rc = main(["train", "--history", str(history), "--references", "dining/temp",
                   "--target", "room/temp", "--quantity", "temperature", "--models",
                   "ref,triv", "--out", str(tmp_path / "x.json")])
    assert rc == 0
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "no --timezone: the operating hours and the days are in UTC" in said
    assert ("training begins on 2012-03-15: the data begins on 2012-03-14 at 09:00 local "
            "time, after the init phase (--train-start 2012-03-14") in said
