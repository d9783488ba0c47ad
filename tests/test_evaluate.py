"""End-to-end ``pseudotwin evaluate`` on small real slices, causality, and bad input."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from daemon_support import sml_csv, write_config
from pseudotwin.analysis.evaluate import median_day, replay_estimates
from pseudotwin.analysis.training import train_twin
from pseudotwin.cli import main
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import write_history
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load
from pseudotwin.live.artifact import Artifact


@pytest.fixture(scope="module")
def sml(tmp_path_factory) -> Path:
    """SML2010, 2012-03-14 … 2012-03-22 (five training days, then test days)."""
    return sml_csv(tmp_path_factory.mktemp("sml"), dt.date(2012, 3, 22))


@pytest.fixture(scope="module")
def room_a(tmp_path_factory) -> Path:
    df = load("room-climate-a")
    df = df[df["ts"] < "2016-03-25T00:00Z"]
    p = tmp_path_factory.mktemp("rca") / "a.csv"
    write_history(df, p)
    return p


def run(*args: str) -> int:
    return main(["--log-level", "WARNING", *args])


def test_evaluate_sml2010_writes_tables_and_plots(sml: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "ev"
    rc = run("evaluate", "--history", str(sml), "--references", "dining/temp",
             "--target", "room/temp", "--quantity", "temperature", "--train-start", "2012-03-14",
             "--timezone", "Europe/Madrid", "--models", "corrgp-triv,corrgp-lcm,triv,varma",
             "--out", str(out))
    assert rc == 0
    printed = capsys.readouterr().out
    assert "| corrgp-triv |" in printed and "| varma |" in printed
    daily = pd.read_csv(out / "daily.csv")
    assert list(daily.columns) == ["day", "model", "nrmse_pct", "dmax_pct", "pearson_r", "n",
                                   "cover1_pct", "cover2_pct", "crps", "mean_std", "rmse"]
    assert set(daily["day"]) == {"2012-03-19", "2012-03-20", "2012-03-21", "2012-03-22"}
    assert {"corrgp-triv", "corrgp-lcm", "triv", "varma", "ref:dining/temp"} <= set(daily["model"])
    assert (daily["nrmse_pct"] > 0).all()
    gp_and_triv = daily[daily["model"].isin(["corrgp-triv", "corrgp-lcm", "triv"])]
    assert (gp_and_triv["nrmse_pct"] < 10).all()  # temperatures within a few tenths of °C
    assert (daily["dmax_pct"] >= daily["nrmse_pct"]).all()
    monthly = pd.read_csv(out / "monthly.csv")
    assert list(monthly.columns) == ["month", "model", "nrmse_pct"]
    assert set(monthly["month"]) == {"2012-03"}
    # what the daemon publishes is scored by the month too: the mean of its daily NRMSE
    est_month = monthly.loc[monthly["model"] == "estimate", "nrmse_pct"]
    assert len(est_month) == 1
    assert est_month.iloc[0] == pytest.approx(
        daily.loc[daily["model"] == "estimate", "nrmse_pct"].mean())
    est = pd.read_csv(out / "estimates.csv")
    assert list(est.columns) == ["ts", "model", "value", "std", "truth", "quality", "slope",
                                 "source", "lost"]
    # source: the payload's "model", what produced the value; VARMA's stream says which
    # VARMA it ran (as <twin>/varma does), the raw reference is itself
    art = Artifact.load(out / "artifact.json")
    varma = est[est["model"] == "varma"]
    assert set(varma["source"]) == {art.models["varma"].model_name} != {"varma"}
    primary = est[est["model"] == "estimate"]
    assert set(primary["source"]) == {art.models[art.primary].model_name}
    assert set(est.loc[est["model"] == "ref:dining/temp", "source"]) == {"ref:dining/temp"}
    assert set(est["lost"]) == {"[]"}  # one reference: nothing to fail over
    gp = est[est["model"] == "corrgp-triv"]
    assert np.isfinite(gp["value"]).all() and (gp["std"] > 0).all()
    # a true reading every 15 min from 08:00 to 19:00 local on each test day
    assert len(gp) == 4 * 45
    assert (out / "daily_nrmse.png").stat().st_size > 10_000
    assert list(out.glob("day_*.png"))
    assert (out / "artifact.json").exists()


def test_estimates_are_causal(room_a: Path) -> None:
    """Cutting the history at t changes no estimate made before t."""
    df = pd.read_csv(room_a)
    from pseudotwin.core.series import normalize

    df = normalize(df)
    hours = OperatingHours(timezone="Europe/Berlin")
    art = train_twin(df, TwinSpec(("A1/temp", "A3/temp"), "A4/temp", Quantity.TEMPERATURE, hours),
                     dt.date(2016, 3, 15), 3, ["corrgp-triv", "corrgp-lcm", "triv"])
    start = dt.date.fromisoformat(art.training["end"]) + dt.timedelta(days=1)
    full = replay_estimates(art, df, start)
    cut = full["ts"].iloc[len(full) // 2]
    part = replay_estimates(art, df[df["ts"] <= cut], start)
    before = full[full["ts"] <= cut].reset_index(drop=True)
    assert len(before) == len(part) > 100
    pd.testing.assert_frame_equal(before, part.reset_index(drop=True), check_exact=True)


def test_evaluate_room_climate_with_two_references(room_a: Path, tmp_path: Path) -> None:
    rc = run("evaluate", "--history", str(room_a), "--references", "A1/temp,A3/temp",
             "--target", "A4/temp", "--quantity", "temperature", "--train-start", "2016-03-15",
             "--train-days", "3", "--timezone", "Europe/Berlin",
             "--models", "corrgp-triv,corrgp-lcm,triv", "--out", str(tmp_path / "a"))
    assert rc == 0
    daily = pd.read_csv(tmp_path / "a" / "daily.csv")
    assert {"ref:A1/temp", "ref:A3/temp", "corrgp-lcm"} <= set(daily["model"])
    assert daily["day"].nunique() >= 3


@pytest.mark.parametrize(
    "args,message",
    [
        (["--references", "nope/temp"], "sensor(s) nope/temp not found"),
        # (how to train on fewer days: said with it)
        (["--train-start", "2012-03-21"], "too little training data: 2 day(s) from "
                                          "2012-03-21 on"),
        (["--train-start", "2012-03-21"], "5 needed (--train-days sets how many; the "
                                          "primary is chosen and σ calibrated by validation "
                                          "from 3 days on, the more days the surer)"),
        # three readings a day in half an hour: the rule they miss is named
        (["--day-end", "08:30"], "have at least 4 readings of each of dining/temp, room/temp "
                                 "in operating hours (08:00–08:30"),
        (["--references", "room/temp"], "also listed as a reference"),
    ],
)
def test_bad_requests_fail_with_a_clear_message(
    sml: Path, tmp_path: Path, capsys, args: list[str], message: str
) -> None:
    base = {"--references": "dining/temp", "--train-start": "2012-03-14"}
    for k, v in zip(args[::2], args[1::2], strict=True):
        base[k] = v
    rc = run("evaluate", "--history", str(sml), "--target", "room/temp",
             "--quantity", "temperature", "--models", "triv", "--out", str(tmp_path / "o"),
             *[x for kv in base.items() for x in kv])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err
    assert "Traceback" not in err


def test_malformed_file_fails_cleanly(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_bytes(b"\x00\xff garbage\n1,2\n")
    rc = run("evaluate", "--history", str(bad), "--references", "a", "--target", "b",
             "--quantity", "co2", "--train-start", "2020-01-01", "--out", str(tmp_path / "o"))
    err = capsys.readouterr().err
    assert rc == 2 and "error" in err and "Traceback" not in err


def test_bad_arguments_are_usage_errors(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        run("evaluate", "--history", "x.csv", "--references", "a", "--target", "b",
            "--quantity", "humidity", "--train-start", "2020-01-01", "--out", "o")
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_days_the_reference_is_silent_are_left_out_of_every_row_and_named(
        sml: Path, tmp_path: Path, caplog, capsys) -> None:
    """The reference dead after 2012-03-20: the models' rows stopped there, while its raw
    `ref:` row held its last value for every later day and was scored on other days than
    the twin it is compared with."""
    df = pd.read_csv(sml)
    ts = pd.to_datetime(df["ts"], utc=True)
    dead = ts >= pd.Timestamp("2012-03-20T23:00Z")  # 2012-03-21 00:00 Madrid
    cut = df[~(dead & (df["sensor"] == "dining/temp"))]
    path = tmp_path / "dies.csv"
    cut.to_csv(path, index=False)
    with caplog.at_level("WARNING", logger="pseudotwin.analysis.evaluate"):
        rc = run("evaluate", "--history", str(path), "--references", "dining/temp",
                 "--target", "room/temp", "--quantity", "temperature", "--train-start",
                 "2012-03-14", "--timezone", "Europe/Madrid", "--models", "ref,triv",
                 "--out", str(tmp_path / "ev"))
    assert rc == 0
    daily = pd.read_csv(tmp_path / "ev" / "daily.csv")
    by_model = {m: set(g["day"]) for m, g in daily.groupby("model")}
    assert by_model["ref:dining/temp"] == by_model["estimate"] == by_model["triv"]
    assert "2012-03-22" not in by_model["estimate"] and "2012-03-19" in by_model["estimate"]
    said = [r.getMessage() for r in caplog.records]
    assert any("but no estimate" in m and "2012-03-22" in m for m in said)
    # 2012-03-21 is scored from the value the reference read on the evening before: said
    assert ["twin room/temp: 1 scored day(s) on which dining/temp did not report in "
            "operating hours, estimated from the last value it reported before, held "
            "(--stale-after scores what the daemon would publish instead): 2012-03-21"] == [
        m for m in said if "did not report in operating hours" in m]
    caplog.clear()  # scored as the daemon publishes: said so
    with caplog.at_level("WARNING", logger="pseudotwin.analysis.evaluate"):
        assert run("evaluate", "--history", str(path), "--references", "dining/temp",
                   "--target", "room/temp", "--quantity", "temperature", "--train-start",
                   "2012-03-14", "--timezone", "Europe/Madrid", "--models", "ref,triv",
                   "--stale-after", "30", "--out", str(tmp_path / "stale")) == 0
    assert ["twin room/temp: 1 scored day(s) on which dining/temp did not report in "
            "operating hours, their estimates stale or from a failover (--stale-after): "
            "2012-03-21"] == [m for r in caplog.records
                              if "did not report in" in (m := r.getMessage())]
    # such a day asked for as the plotted one fails before any output is written
    rc = run("evaluate", "--history", str(path), "--references", "dining/temp",
             "--target", "room/temp", "--quantity", "temperature", "--train-start",
             "2012-03-14", "--timezone", "Europe/Madrid", "--models", "ref,triv",
             "--plot-day", "2012-03-22", "--out", str(tmp_path / "plot"))
    assert rc == 2 and not (tmp_path / "plot").exists()
    assert "--plot-day 2012-03-22: no estimate of room/temp that day" in capsys.readouterr().err


def test_a_scored_day_with_few_desk_readings_is_named(
        sml: Path, tmp_path: Path, caplog) -> None:
    """A desk sensor that read once on 2012-03-21 (its other readings lost): the day counts in
    the mean daily NRMSE as a full day does, on one reading, and is named with its n."""
    df = pd.read_csv(sml)
    local = pd.to_datetime(df["ts"], utc=True).dt.tz_convert("Europe/Madrid")
    day = local.dt.date.astype(str)
    desk = df.index[(df["sensor"] == "room/temp") & (day == "2012-03-21")
                    & (local.dt.hour >= 8) & (local.dt.hour <= 19)]
    path = tmp_path / "thin.csv"
    df.drop(desk[1:]).to_csv(path, index=False)
    said = {}
    for name, history in (("full", sml), ("thin", path)):
        caplog.clear()
        with caplog.at_level("WARNING", logger="pseudotwin.analysis.evaluate"):
            assert run("evaluate", "--history", str(history), "--references", "dining/temp",
                       "--target", "room/temp", "--quantity", "temperature", "--train-start",
                       "2012-03-14", "--timezone", "Europe/Madrid", "--models", "triv",
                       "--out", str(tmp_path / name)) == 0
        said[name] = [m for r in caplog.records if "fewer than half" in (m := r.getMessage())]
    assert said["full"] == []
    assert len(said["thin"]) == 1
    assert "1 scored day(s) with fewer than half the usual" in said["thin"][0]
    assert said["thin"][0].endswith(": 2012-03-21 (n = 1)")


def test_a_second_reference_silent_for_days_is_not_scored_on_them(room_a: Path) -> None:
    """With two references the twin answers from the one alive, and the dead one's `ref:`
    row held its days-old value on every later day."""
    from pseudotwin.core.series import normalize

    df = normalize(pd.read_csv(room_a))
    hours = OperatingHours(timezone="Europe/Berlin")
    art = train_twin(df, TwinSpec(("A1/temp", "A3/temp"), "A4/temp", Quantity.TEMPERATURE,
                                  hours), dt.date(2016, 3, 15), 3, ["ref", "triv"])
    start = dt.date.fromisoformat(art.training["end"]) + dt.timedelta(days=1)
    dead = hours.at(start + dt.timedelta(days=1), 0.0)
    cut = df[~((df["sensor"] == "A3/temp") & (df["ts"] >= dead))]
    est = replay_estimates(art, cut, start)
    days = {m: set(g["ts"].map(lambda t: hours.day_of(t)))
            for m, g in est.groupby("model")}
    assert start in days["ref:A3/temp"] and days["ref:A3/temp"] == {start}
    assert days["ref:A1/temp"] == days["estimate"] and len(days["estimate"]) > 1


def test_the_typical_day_plotted_is_not_a_day_cut_short() -> None:
    """The median day by NRMSE was a day with three readings before a gap in the data: its
    plot spanned half an hour."""
    daily = pd.DataFrame({"day": ["2012-04-09", "2012-04-10", "2012-04-11"],
                          "model": "triv", "nrmse_pct": [1.0, 3.0, 2.0], "n": [45, 44, 3]})
    assert median_day(daily, "triv") == dt.date(2012, 4, 10)
    whole = daily.assign(n=45)  # every day whole: the median by NRMSE
    assert median_day(whole, "triv") == dt.date(2012, 4, 11)
    assert median_day(daily, "ref") is None


def test_outputs_never_overwrite_the_inputs_and_primary_is_checked_first(
        sml: Path, tmp_path: Path, capsys) -> None:
    """`train --out` equal to `--history` replaced the readings by the artifact; a --primary
    not among --models was refused only after every model had been fitted."""
    history = tmp_path / "h.csv"
    history.write_bytes(sml.read_bytes())
    common = ["--references", "dining/temp", "--target", "room/temp", "--quantity",
              "temperature", "--train-start", "2012-03-14", "--timezone", "Europe/Madrid"]
    with pytest.raises(SystemExit) as exc:
        run("train", "--history", str(history), *common, "--models", "ref,triv",
            "--out", str(history))
    assert exc.value.code == 2
    assert "would overwrite the --history file" in capsys.readouterr().err
    assert history.read_bytes() == sml.read_bytes()
    store = tmp_path / "h.db"
    assert main(["import", str(history), "--store", str(store)]) == 0
    kept = store.read_bytes()
    for url in (str(store), f"sqlite:///{store}"):
        with pytest.raises(SystemExit) as exc:
            run("train", "--store", url, *common, "--models", "ref,triv", "--out", str(store))
        assert exc.value.code == 2
        assert "would overwrite the --store file" in capsys.readouterr().err
    cfg = write_config(tmp_path, 1883, tmp_path / "x.json", store="h.db")  # that store
    assert run("train", "--config", str(cfg), "--references", "dining/temp", "--target",
               "room/temp", "--quantity", "temperature", "--models", "ref,triv",
               "--out", str(store)) == 2
    assert "--out would overwrite the store of" in capsys.readouterr().err
    assert store.read_bytes() == kept
    renamed = tmp_path / "o" / "estimates.csv"
    renamed.parent.mkdir()
    renamed.write_bytes(sml.read_bytes())
    with pytest.raises(SystemExit) as exc:
        run("evaluate", "--history", str(renamed), *common, "--models", "ref,triv",
            "--out", str(renamed.parent))
    assert exc.value.code == 2 and "would overwrite the --history file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        run("train", "--history", str(history), *common, "--models", "ref,triv",
            "--primary", "corrgp-lcm", "--out", str(tmp_path / "p.json"))
    assert exc.value.code == 2 and "--primary corrgp-lcm is not among --models" in \
        capsys.readouterr().err
    assert not (tmp_path / "p.json").exists()


def test_a_second_evaluation_into_a_folder_leaves_only_its_own_day_plot(
        sml: Path, tmp_path: Path) -> None:
    out = tmp_path / "ev"
    args = ["evaluate", "--history", str(sml), "--references", "dining/temp", "--target",
            "room/temp", "--quantity", "temperature", "--train-start", "2012-03-14",
            "--timezone", "Europe/Madrid", "--models", "ref,triv", "--out", str(out)]
    assert run(*args, "--plot-day", "2012-03-19") == 0
    (out / "day_summary.png").write_bytes(b"the user's own")
    assert run(*args, "--plot-day", "2012-03-20") == 0
    assert sorted(p.name for p in out.glob("day_*.png")) == ["day_2012-03-20.png",
                                                             "day_summary.png"]


def test_train_from_a_configuration_leaves_out_readings_outside_its_ranges(
        sml: Path, tmp_path: Path, caplog) -> None:
    """A stored 85 °C (a DS18B20's power-on value) of a -10..50 °C sensor: train --config
    learnt from it, its held-out error tenfold, without a word."""
    df = pd.read_csv(sml)
    glitch = pd.DataFrame({"sensor": "dining/temp", "value": 85.0,
                           "ts": [f"2012-03-{d}T10:07:00Z" for d in (14, 15, 16)]})
    clean, dirty = tmp_path / "clean.db", tmp_path / "dirty.db"
    for path, frame in ((clean, df), (dirty, pd.concat([df, glitch]))):
        frame.to_csv(tmp_path / "h.csv", index=False)
        assert main(["import", str(tmp_path / "h.csv"), "--store", str(path)]) == 0
    scores = {}
    for path in (clean, dirty):
        cfg = write_config(tmp_path, 1883, tmp_path / "x.json", store=path.name)
        out = tmp_path / f"{path.stem}.json"
        with caplog.at_level("WARNING"):
            assert run("train", "--config", str(cfg), "--references", "dining/temp",
                       "--target", "room/temp", "--quantity", "temperature", "--models",
                       "ref,triv", "--train-start", "2012-03-14", "--out", str(out)) == 0
        scores[path.stem] = json.loads(out.read_text())["validation"]["scores"]["triv"]
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "training leaves out 3 reading(s) outside their sensor's min..max" in said
    assert "dining/temp: 3" in said
    assert scores["dirty"] == scores["clean"]
