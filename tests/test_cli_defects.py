"""Defects a new user met (issue 12 item 7), one test each: real CLI runs in-process."""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from daemon_support import sml_csv
from pseudotwin.analysis.training import check_plausible, plausible_readings
from pseudotwin.cli import build_parser, main
from pseudotwin.cli.bridge import build_parser as bridge_parser
from pseudotwin.cli.util import EX_CONFIG, EX_TEMPFAIL
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.edge.mqttconn import EX_NOPERM
from pseudotwin.errors import DataError
from pseudotwin.history.convert import SHARED_DATA_ENV
from pseudotwin.history.store import SCHEMA_VERSION

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def sml(tmp_path_factory) -> Path:
    """SML2010, 2012-03-14 … 2012-03-20 (five training days and two test days)."""
    return sml_csv(tmp_path_factory.mktemp("sml"), dt.date(2012, 3, 20))


def run(*args: str) -> int:
    return main(["--log-level", "WARNING", *args])


def desk_twin(command: str, history: Path, *extra: str) -> tuple[str, ...]:
    """``command``'s (train, evaluate) arguments for SML2010's desk temperature twin."""
    return (command, "--history", str(history), "--references", "dining/temp", "--target",
            "room/temp", "--quantity", "temperature", "--train-start", "2012-03-14",
            "--timezone", "Europe/Madrid", *extra)


def refused(args: tuple[str, ...], option: str, values: tuple[str, ...], out: Path,
            capsys: pytest.CaptureFixture[str]) -> None:
    """Each of ``values`` for ``option`` is a usage error (2) naming it, nothing written."""
    capsys.readouterr()
    for bad in values:
        with pytest.raises(SystemExit) as exc:
            run(*args, option, bad, "--out", str(out))
        assert exc.value.code == 2 and option in capsys.readouterr().err
    assert not out.exists()


def _evaluate(sml: Path, out: Path, *extra: str) -> int:
    return run(*desk_twin("evaluate", sml, "--models", "triv", "--out", str(out), *extra))


def test_plot_day_without_data_is_an_error(sml: Path, tmp_path: Path, capsys) -> None:
    rc = _evaluate(sml, tmp_path / "o", "--plot-day", "2012-05-02")
    err = capsys.readouterr().err
    assert rc == 2
    assert "--plot-day 2012-05-02: no readings of room/temp in that day's operating hours" in err
    assert "Traceback" not in err
    assert not list(tmp_path.glob("o/*.png"))


def test_plot_day_with_desk_readings_only_at_night_fails_before_training(
        sml: Path, tmp_path: Path, capsys) -> None:
    """The day had desk readings, none scored: it failed only after every output was
    written."""
    from pseudotwin.core.series import read_history, write_history

    df = read_history(sml)
    local = df["ts"].dt.tz_convert("Europe/Madrid")
    night = ~((df["sensor"] == "room/temp") & (local.dt.day == 20) & (local.dt.hour.between(7, 20)))
    write_history(df[night], tmp_path / "night.csv")
    rc = _evaluate(tmp_path / "night.csv", tmp_path / "o", "--plot-day", "2012-03-20")
    assert rc == 2
    assert "no readings of room/temp in that day's operating hours" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_plot_day_in_the_training_period_is_an_error(sml: Path, tmp_path: Path, capsys) -> None:
    rc = _evaluate(sml, tmp_path / "o", "--plot-day", "2012-03-15")
    err = capsys.readouterr().err
    assert rc == 2
    assert "--plot-day 2012-03-15 is not scored" in err and "2012-03-19" in err
    assert not list(tmp_path.glob("o/*.png"))


def test_plot_day_with_data_still_plots(sml: Path, tmp_path: Path) -> None:
    assert _evaluate(sml, tmp_path / "o", "--plot-day", "2012-03-20") == 0
    assert (tmp_path / "o" / "day_2012-03-20.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    "refs,target,quantity",
    [("dining/co2", "room/co2", "temperature"),  # ≈ 200 ppm are no °C
     ("dining/temp", "room/temp", "co2")],  # ≈ 20 °C are no ppm
)
def test_train_rejects_data_of_another_quantity(
    sml: Path, tmp_path: Path, capsys, refs: str, target: str, quantity: str
) -> None:
    out = tmp_path / "a.json"
    rc = run("train", "--history", str(sml), "--references", refs, "--target", target,
             "--quantity", quantity, "--train-start", "2012-03-14", "--models", "triv",
             "--out", str(out))
    err = capsys.readouterr().err
    assert rc == 2
    assert f"sensor {refs}: readings implausible for the quantity {quantity}" in err
    assert "Traceback" not in err
    assert not out.exists()


def test_train_learns_for_the_window_it_is_given(sml: Path, tmp_path: Path, capsys) -> None:
    """--min-interval sets the window policy training thins with; the artifact records it;
    a width the daemon would refuse is refused here too."""
    out = tmp_path / "a.json"
    args = ("train", "--history", str(sml), "--references", "dining/temp", "--target",
            "room/temp", "--quantity", "temperature", "--train-start", "2012-03-14",
            "--models", "triv", "--out", str(out))
    assert run(*args, "--min-interval", "30") == 0
    assert json.loads(out.read_text())["training"]["thinning"] == "one point per 30 s"
    assert run(*args) == 0
    assert json.loads(out.read_text())["training"]["thinning"] == "one point per 60 s"
    with pytest.raises(SystemExit) as exc:
        run(*args, "--min-interval", "0")
    assert exc.value.code == 2
    assert "--min-interval" in capsys.readouterr().err


def _frame(values: dict[str, np.ndarray]) -> pd.DataFrame:
    ts = pd.date_range("2024-03-04", periods=len(next(iter(values.values()))), freq="15min",
                       tz="UTC")
    return pd.concat([pd.DataFrame({"sensor": s, "ts": ts, "value": v})
                      for s, v in values.items()], ignore_index=True)


def test_plausibility_tolerates_a_few_glitches_but_names_the_bad_sensor() -> None:
    spec = TwinSpec(("a/temp",), "desk/temp", Quantity.TEMPERATURE, OperatingHours())
    ok = 21.0 + np.sin(np.arange(1000) / 50)
    glitchy = ok.copy()
    glitchy[:5] = 85.0  # a DS18B20's power-on value, 0.5 % of the readings
    check_plausible(_frame({"a/temp": glitchy, "desk/temp": ok}), spec)
    fahrenheit = np.full(1000, 120.0)
    with pytest.raises(DataError, match="sensor desk/temp: .* temperature .*median 120 °C"):
        check_plausible(_frame({"a/temp": ok, "desk/temp": fahrenheit}), spec)


def test_readings_outside_the_quantitys_plausible_range_are_left_out_as_the_daemon_does(
        sml: Path, tmp_path: Path, caplog, capsys) -> None:
    """A disconnected probe's −127 °C and an 850 °C glitch, of a reference and of the desk,
    on training days and on scored days, and the desk probe disconnected for the last two
    days (−127 °C every minute: most of its readings): train and evaluate leave them out with
    a warning that counts them per sensor (the daemon rejects them with the configuration
    train --report proposes), so every score is the clean history's. A desk sensor reading
    °F on the training days is refused by name."""
    df = pd.read_csv(sml)
    minutes = pd.date_range("2012-03-18T23:00Z", "2012-03-20T22:59Z", freq="min")
    dropout = minutes[minutes.minute % 15 != 0]  # not on the 15-min readings' instants
    glitches = pd.concat([pd.DataFrame({
        "sensor": ["dining/temp", "dining/temp", "room/temp", "room/temp"],
        "ts": ["2012-03-15T10:07:00+00:00", "2012-03-17T12:07:00+00:00",
               "2012-03-16T09:07:00+00:00", "2012-03-20T11:07:30+00:00"],
        "value": [850.0, -127.0, -127.0, 850.0]}), pd.DataFrame({
            "sensor": "room/temp", "ts": dropout.strftime("%Y-%m-%dT%H:%M:%S+00:00"),
            "value": -127.0})], ignore_index=True)
    assert len(dropout) > len(df[df["sensor"] == "room/temp"])  # its median is -127
    dirty = tmp_path / "dirty.csv"
    pd.concat([df, glitches], ignore_index=True).to_csv(dirty, index=False)
    daily = {}
    for name, history in (("clean", sml), ("dirty", dirty)):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="pseudotwin.analysis.training"):
            assert run(*desk_twin("evaluate", history, "--models", "ref,triv,blend",
                                  "--out", str(tmp_path / name))) == 0
        warned = [m for r in caplog.records if "left out" in (m := r.getMessage())]
        daily[name] = pd.read_csv(tmp_path / name / "daily.csv")
        if name == "clean":
            assert warned == []
        else:
            assert len(warned) == 1
            assert f"left out {len(glitches)} reading(s) outside their sensor's range" in \
                warned[0]
            assert "dining/temp: 2 outside -40 … 80 °C (e.g. 850 at 2012-03-15 10:07" in \
                warned[0]
            assert f"room/temp: {len(dropout) + 2} outside -40 … 80 °C" in warned[0]
    pd.testing.assert_frame_equal(daily["clean"], daily["dirty"])

    f = df.copy()  # °F of a warmer room: median 75, 14 % of the training days' above 80
    desk = f["sensor"] == "room/temp"
    f.loc[desk, "value"] = (f.loc[desk, "value"] + 4.4) * 9 / 5 + 32
    fahrenheit = tmp_path / "fahrenheit.csv"
    f.to_csv(fahrenheit, index=False)
    capsys.readouterr()
    assert run(*desk_twin("train", fahrenheit, "--models", "triv",
                          "--out", str(tmp_path / "f.json"))) == 2
    err = capsys.readouterr().err
    assert "sensor room/temp: readings implausible for the quantity temperature" in err
    assert "outside -40 … 80 °C on the training days); is it another quantity's" in err


def test_a_configured_range_is_the_one_training_applies() -> None:
    """A configuration's min..max, which the daemon applies, replaces the plausible range
    for its sensors: a DS18B20's 85 °C stays for a sensor configured -55..125 °C."""
    spec = TwinSpec(("a/temp",), "desk/temp", Quantity.TEMPERATURE, OperatingHours())
    ok = 21.0 + np.sin(np.arange(100) / 50)
    glitchy = ok.copy()
    glitchy[3] = 85.0
    frame = _frame({"a/temp": glitchy, "desk/temp": ok})
    assert len(plausible_readings(frame, spec)) == len(frame) - 1
    assert len(plausible_readings(frame, spec, {"a/temp": (-55.0, 125.0)})) == len(frame)
    with pytest.raises(DataError, match=r"sensor desk/temp: readings implausible for the "
                                        r"quantity temperature \(median 120 °C, 100 % outside "
                                        r"-40 … 80 °C\)"):
        plausible_readings(_frame({"a/temp": ok, "desk/temp": np.full(100, 120.0)}), spec)


def test_train_refuses_a_stuck_sensor(sml: Path, tmp_path: Path, capsys) -> None:
    """A reference that reads the same on every training day (stuck or disconnected) is
    refused by name; it moving again on a later day does not hide it."""
    df = pd.read_csv(sml)
    stuck = (df["sensor"] == "dining/temp") & (df["ts"] < "2012-03-19")
    df.loc[stuck, "value"] = 20.0
    history = tmp_path / "stuck.csv"
    df.to_csv(history, index=False)
    out = tmp_path / "a.json"
    rc = run("train", "--history", str(history), "--references", "dining/temp", "--target",
             "room/temp", "--quantity", "temperature", "--train-start", "2012-03-14",
             "--timezone", "Europe/Madrid", "--models", "triv", "--out", str(out))
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert "sensor dining/temp: reads 20 °C throughout the training days (100.0 % of" in err
    assert not out.exists()
    # the same days with the sensor moving train as before
    assert run(*desk_twin("train", sml, "--models", "triv", "--out", str(out))) == 0


def test_train_warns_of_training_days_on_which_a_sensor_was_stuck(
        sml: Path, tmp_path: Path, caplog) -> None:
    """Stuck through the operating hours of two of the five training days only (moving at
    night, one 85 °C glitch among a day's 45 readings): trained, with a warning that names
    the days and how to leave them out."""
    df = pd.read_csv(sml)
    local = pd.to_datetime(df["ts"], utc=True).dt.tz_convert("Europe/Madrid")
    day, hour = local.dt.date.astype(str), local.dt.hour + local.dt.minute / 60
    stuck = ((df["sensor"] == "dining/temp") & day.isin(["2012-03-15", "2012-03-17"])
             & (hour >= 8) & (hour <= 19))
    df.loc[stuck, "value"] = 20.0
    df.loc[stuck[stuck].index[10], "value"] = 85.0
    history = tmp_path / "stuck-two-days.csv"
    df.to_csv(history, index=False)
    out = tmp_path / "a.json"
    with caplog.at_level(logging.WARNING, logger="pseudotwin.analysis.training"):
        assert run("train", "--history", str(history), "--references", "dining/temp",
                   "--target", "room/temp", "--quantity", "temperature", "--train-start",
                   "2012-03-14", "--timezone", "Europe/Madrid", "--models", "triv",
                   "--out", str(out)) == 0
    warned = [m for r in caplog.records if "reads one value" in (m := r.getMessage())]
    assert warned == [
        "twin a: sensor dining/temp reads one value throughout the operating hours of "
        "2012-03-15, 2012-03-17 (2 of 5 training days): stuck or disconnected then? Those "
        "days show nothing of how it moves with the others; --skip-days "
        "2012-03-15,2012-03-17 leaves them out (a sensor that reports only on change may "
        "just have had a quiet day)"]
    assert out.exists()


def test_a_stuck_sensor_is_named_through_minute_means_and_glitches() -> None:
    """Minute means of one repeated value differ in the last bits, and a stuck DS18B20 still
    sends its 85 °C power-on value now and then: neither hides it. A sensor resting on one
    value most of the time but moving on 2 % of its readings is not stuck."""
    spec = TwinSpec(("a/temp",), "desk/temp", Quantity.TEMPERATURE, OperatingHours())
    rng = np.random.default_rng(5)
    ok = 21.0 + np.sin(np.arange(1000) / 50)
    stuck = 18.1 + rng.choice([0.0, 3.6e-15, -3.6e-15], 1000)
    stuck[rng.choice(1000, 5, replace=False)] = 85.0
    with pytest.raises(DataError, match=r"sensor a/temp: reads 18\.1 °C throughout the "
                                        r"training days \(99.5 % of its readings\)"):
        check_plausible(_frame({"a/temp": stuck, "desk/temp": ok}), spec)
    resting = np.full(1000, 20.5)
    resting[::50] = 21.0  # a 0.5-°C step sensor in a quiet room
    check_plausible(_frame({"a/temp": resting, "desk/temp": ok}), spec)


@pytest.mark.parametrize(
    "command,option,needle",
    [("replay", "--start INSTANT", "ISO 8601 with a UTC offset"),
     ("replay", "--end INSTANT", "ISO 8601 with a UTC offset"),
     ("backfill", "--from YYYY-MM-DD", "YYYY-MM-DD"),
     ("backfill", "--to YYYY-MM-DD", "YYYY-MM-DD")],
)
def test_time_options_say_their_format(capsys, command: str, option: str, needle: str) -> None:
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    after = text[text.rindex(option) + len(option):]  # the options list, not the usage
    assert needle in after.split(" --")[0]


@pytest.mark.parametrize("command", ["run", "record"])
def test_long_running_commands_say_their_exit_statuses_and_when_they_acknowledge(
    capsys, command: str
) -> None:
    """systemd's units key on these statuses; an operator reads them in --help."""
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    said = [part.strip() for part in text.split("Exit status:")[1].split(";")]
    for status, why in ((0, "signal"), (EX_TEMPFAIL, "systemd retries"),
                        (EX_NOPERM, "refused the credentials"),
                        (EX_CONFIG, "configuration error")):
        assert any(part.startswith(f"{status} ") and why in part for part in said), status
    assert "acknowledged to the broker" in text and "journal_fsync" in text


def test_demo_without_shared_data_ends_in_one_clear_line(tmp_path: Path) -> None:
    empty = tmp_path / "shared"
    empty.mkdir()
    p = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "demo.py"), "--out", str(tmp_path / "demo")],
        env={**os.environ, SHARED_DATA_ENV: str(empty)}, capture_output=True, text=True,
        timeout=120, check=False,
    )
    assert p.returncode == 1
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in p.stderr
    assert "shared SML2010 data is missing" in lines[0] and SHARED_DATA_ENV in lines[0]
    assert not (tmp_path / "demo").exists()


def test_global_log_level_before_a_delegated_subcommand(tmp_path: Path, capsys) -> None:
    # `pseudotwin --log-level WARNING check-config F` took WARNING for the subcommand
    missing = tmp_path / "none.toml"
    assert main(["--log-level", "WARNING", "check-config", str(missing)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "unrecognized arguments" not in err
    # checked as for every subcommand: any case, and a level that is none is a usage error,
    # not taken silently
    assert main(["--log-level", "warning", "check-config", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err
    with pytest.raises(SystemExit) as bad:
        main(["--log-level", "LOUD", "check-config", str(missing)])
    assert bad.value.code == 2 and "invalid choice: 'LOUD'" in capsys.readouterr().err
    # CRITICAL too, as the configuration's log_level, and the bridge's own option alike (their
    # parsers only: running them at CRITICAL would silence the process's log for later tests)
    assert build_parser().parse_args(["--log-level", "critical"]).log_level == "CRITICAL"
    # after the subcommand too (`run ... --log-level DEBUG` was "unrecognized arguments")
    after = build_parser().parse_args(["run", "--config", "c.toml", "--log-level", "debug"])
    assert (after.command, after.log_level) == ("run", "DEBUG")
    assert build_parser().parse_args(["run", "--config", "c.toml"]).log_level is None
    assert bridge_parser().parse_args(
        ["--config", "b.toml", "--log-level", "Critical"]).log_level == "CRITICAL"


def test_train_says_whether_its_training_days_are_enough(sml: Path, tmp_path: Path,
                                                          capsys) -> None:
    """The commissioning report's verdict on the training data, in train's own output."""
    args = ("train", "--references", "dining/temp", "--target", "room/temp", "--quantity",
            "temperature", "--train-start", "2012-03-14", "--timezone", "Europe/Madrid",
            "--models", "ref,triv")
    assert run(*args, "--history", str(sml), "--out", str(tmp_path / "full.json")) == 0
    assert "training data: Enough: 5 training days" in capsys.readouterr().out
    # 2012-03-18 with its morning only: still a training day, but a thin one
    df = pd.read_csv(sml)
    ts = pd.to_datetime(df["ts"], utc=True).dt.tz_convert("Europe/Madrid")
    cut = (ts.dt.date == dt.date(2012, 3, 18)) & (ts.dt.hour >= 10)
    thin = tmp_path / "thin.csv"
    df[~cut.to_numpy()].to_csv(thin, index=False)
    assert run(*args, "--history", str(thin), "--out", str(tmp_path / "thin.json")) == 0
    out = capsys.readouterr().out
    assert "training data: Usable, but thin" in out and "on 2012-03-18" in out


# A setting validation chooses, pinned from the command line: option, value, model kind, the
# pinned model as asked, values refused.
PINNED = [
    ("--varma-p", "1", "varma",
     lambda m: m.p == 1 and not m.force_fallback and m.order_[0] == 1, ("0", "9", "two")),
    ("--smooth-span", "90", "triv-smooth", lambda m: m.span == 90, ("0", "1441", "ninety")),
]


@pytest.mark.parametrize(("option", "value", "kind", "as_asked", "bad"), PINNED,
                         ids=[p[0] for p in PINNED])
def test_a_pinned_setting_is_fitted_as_asked_and_skips_validations_choice(
    option: str, value: str, kind: str, as_asked: Any, bad: tuple[str, ...], sml: Path,
    tmp_path: Path, capsys,
) -> None:
    from pseudotwin.live.artifact import Artifact

    args = desk_twin("train", sml, "--models", f"ref,triv,{kind}")
    assert run(*args, "--out", str(tmp_path / "chosen.json")) == 0
    assert kind in Artifact.load(tmp_path / "chosen.json").validation["tuned"]
    assert run(*args, option, value, "--out", str(tmp_path / "pinned.json")) == 0
    art = Artifact.load(tmp_path / "pinned.json")
    assert as_asked(art.models[kind]) and "tuned" not in art.validation
    refused(args, option, bad, tmp_path / "bad.json", capsys)


def test_lcm_terms_sets_the_corrgp_lcm_terms(sml: Path, tmp_path: Path, capsys) -> None:
    from pseudotwin.live.artifact import Artifact
    from pseudotwin.models.corrgp import CorrGpLcm

    args = desk_twin("train", sml, "--models", "ref,corrgp-lcm")
    # One reference: one term by default, so two can only come from the option.
    assert run(*args, "--lcm-terms", "2", "--out", str(tmp_path / "t2.json")) == 0
    model = Artifact.load(tmp_path / "t2.json").models["corrgp-lcm"]
    assert isinstance(model, CorrGpLcm)
    assert len(model.params_.terms) == 2
    refused(args, "--lcm-terms", ("0", "-1", "two"), tmp_path / "bad.json", capsys)


@pytest.mark.parametrize("command, out", [("train", "/proc/pseudotwin-test/a.json"),
                                          ("evaluate", "/proc/pseudotwin-test")])
def test_an_output_that_cannot_be_written_is_refused_before_training(
        sml: Path, command: str, out: str, capsys) -> None:
    """Root passes permission checks, yet /proc takes no file: the probe says so at once
    (before, training ran to its end and died in a traceback writing the result)."""
    args = desk_twin(command, sml, "--models", "ref,triv", "--out", out)
    with pytest.raises(SystemExit) as exc:
        run(*args)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"{out}: cannot write in /proc" in err


def test_a_write_that_fails_after_the_checks_is_one_line(sml: Path, tmp_path: Path,
                                                         capsys) -> None:
    """The folder takes a file when checked, but the artifact does not fit (a file-size
    limit, as a full disk): one line naming the file, status 2, no half artifact left."""
    import resource

    out = tmp_path / "a.json"
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, limit[1]))  # Python ignores SIGXFSZ
    try:
        code = run(*desk_twin("train", sml, "--models", "ref,triv", "--out", str(out)))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limit)
    err = capsys.readouterr().err
    assert code == 2
    assert err.strip().endswith(f"{out}: File too large")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_fewer_days_than_validation_needs_are_refused_unless_allowed(
        sml: Path, tmp_path: Path, command: str, capsys) -> None:
    out = tmp_path / ("a.json" if command == "train" else "ev")
    args = desk_twin(command, sml, "--models", "ref,triv", "--train-days", "2",
                     "--out", str(out))
    with pytest.raises(SystemExit) as exc:
        run(*args)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--train-days 2" in err and "--allow-unvalidated" in err
    assert not out.exists()
    if command == "train":
        from pseudotwin.live.artifact import Artifact

        assert run(*args, "--allow-unvalidated") == 0
        assert Artifact.load(out).calibration == {}
        # check-config passes it, and says what it is
        from daemon_support import write_config

        capsys.readouterr()
        cfg = write_config(tmp_path, 1883, out)
        assert run("check-config", str(cfg)) == 0
        assert "note: twins.desk: its artifact was trained without validation" in (
            capsys.readouterr().out)


def test_covariates_without_a_model_that_reads_them_are_refused(sml: Path, tmp_path: Path,
                                                                capsys) -> None:
    """They went into the artifact, and the twin's configuration then had to feed sensors
    no model read."""
    args = desk_twin("train", sml, "--covariates", "dining/co2",
                     "--out", str(tmp_path / "a.json"))
    with pytest.raises(SystemExit) as exc:
        run(*args, "--models", "ref,triv")
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "none of the models asked for reads covariates" in err
    assert "only triv-cov does" in err and not (tmp_path / "a.json").exists()
    assert run(*args, "--models", "ref,triv,triv-cov") == 0


@pytest.mark.parametrize("command", [
    ("train", "--references", "dining/temp", "--target", "room/temp", "--quantity",
     "temperature", "--models", "ref,triv"),
    ("backfill", "--twin", "desk", "--from", "2012-03-20", "--to", "2012-03-20"),
])
def test_a_broken_configuration_is_named(tmp_path: Path, command: tuple[str, ...],
                                         capsys) -> None:
    """train --config and backfill --config said "service.timezone: …" without the file."""
    from daemon_support import write_config

    cfg = write_config(tmp_path, 1883, tmp_path / "desk.json", store="history.db")
    cfg.write_text(cfg.read_text().replace('timezone = "Europe/Madrid"',
                                           'timezone = "Europe/Madird"'))
    out = ("--out", str(tmp_path / "a.json")) if command[0] == "train" else ()
    assert run(*command, "--config", str(cfg), *out) == 2
    err = capsys.readouterr().err
    assert f"configuration error in {cfg}: service.timezone" in err


@pytest.mark.parametrize("port", ["0", "65536", "http"])
def test_a_bad_metrics_port_is_a_usage_error(tmp_path: Path, port: str, capsys) -> None:
    """It was read as the configuration's port and reported as a configuration error (78)."""
    with pytest.raises(SystemExit) as exc:
        run("run", "--config", str(tmp_path / "any.toml"), "--metrics-port", port)
    assert exc.value.code == 2 and "--metrics-port" in capsys.readouterr().err


def test_a_window_unlike_trainings_is_refused(sml: Path, tmp_path: Path, capsys) -> None:
    """The artifact records each live sensor's min_interval; a configuration that thins
    otherwise (its σ was measured on another window) fails check-config; train --config
    learns the configuration's window, from a history file too, and refuses a --min-interval
    that contradicts it."""
    from daemon_support import write_config

    out = tmp_path / "desk.json"
    assert run(*desk_twin("train", sml, "--models", "ref,triv", "--out", str(out))) == 0
    cfg = write_config(tmp_path, 1883, out, store=str(tmp_path / "none.db"))
    assert run("check-config", str(cfg)) == 0
    capsys.readouterr()
    topic = 'topic = "house/dining/temp"\n'
    cfg.write_text(cfg.read_text().replace(topic, topic + "min_interval_seconds = 300\n"))
    assert run("check-config", str(cfg)) == 1
    assert ("min_interval_seconds of dining/temp is 300, but the twin learnt from one point "
            "per 60 s (its σ was measured on that window): set min_interval_seconds = 60 on "
            "that sensor") in capsys.readouterr().err
    with_config = desk_twin("train", sml, "--config", str(cfg), "--models", "ref,triv")
    assert run(*with_config, "--out", str(out)) == 0
    assert run("check-config", str(cfg)) == 0
    assert run(*with_config, "--min-interval", "300", "--out", str(tmp_path / "b.json")) == 0
    capsys.readouterr()
    assert run(*with_config, "--min-interval", "900", "--out", str(tmp_path / "c.json")) == 2
    assert ("--min-interval 900 contradicts" in capsys.readouterr().err
            and not (tmp_path / "c.json").exists())


def test_the_daemon_holds_the_artifact_to_its_window_and_says_when_it_is_unvalidated(
        sml: Path, tmp_path: Path, caplog) -> None:
    """run refuses a configuration that thins otherwise than training did; an artifact that
    records no window (older than the check) passes; an unvalidated one is named in a
    warning."""
    import json
    import logging

    from daemon_support import write_config
    from pseudotwin.config import load_config
    from pseudotwin.edge.service import Service
    from pseudotwin.errors import ConfigError

    out = tmp_path / "desk.json"
    assert run(*desk_twin("train", sml, "--models", "ref,triv", "--train-days", "2",
                          "--allow-unvalidated", "--out", str(out))) == 0
    cfg = write_config(tmp_path, 1883, out)
    topic = 'topic = "house/dining/temp"\n'
    cfg.write_text(cfg.read_text().replace(topic, topic + "min_interval_seconds = 300\n"))
    with pytest.raises(ConfigError, match="min_interval_seconds of dining/temp is 300"):
        Service(load_config(cfg))
    doc = json.loads(out.read_text(encoding="utf-8"))
    del doc["training"]["min_interval_seconds"]
    out.write_text(json.dumps(doc), encoding="utf-8")
    with caplog.at_level(logging.WARNING):
        Service(load_config(cfg))
    assert "twin desk: its artifact was trained without validation" in caplog.text


def test_skip_days_that_leave_nothing_out_are_named(sml: Path, tmp_path: Path, capsys) -> None:
    """A day outside the training days (or mistyped) was ignored without a word."""
    out = tmp_path / "a.json"
    assert run(*desk_twin("train", sml, "--models", "ref,triv", "--skip-days",
                          "2012-03-15,2012-04-01", "--out", str(out))) == 0
    printed = capsys.readouterr().out
    assert ("--skip-days: 2012-04-01 would not have been training days anyway (training took "
            "2012-03-14 … 2012-03-19)") in printed
    assert "2012-03-15 would not" not in printed  # that one was left out


def test_one_training_day_trains_what_one_day_can_teach_and_says_what_it_cannot(
        sml: Path, tmp_path: Path, caplog, capsys) -> None:
    """README offers --allow-unvalidated for one or two days: with one, VARMA (the day is its
    own typical profile, nothing is left to fit) is skipped with a reason, not a traceback."""
    from pseudotwin.live.artifact import Artifact

    caplog.set_level(logging.INFO, logger="pseudotwin.analysis.training")
    out = tmp_path / "a.json"
    assert run(*desk_twin("train", sml, "--models", "ref,triv,varma", "--train-days", "1",
                          "--allow-unvalidated", "--out", str(out))) == 0
    assert set(Artifact.load(out).models) == {"ref", "triv"}
    assert "varma is not trained: it needs at least 2 training days, 1 given" in caplog.text
    capsys.readouterr()
    assert run(*desk_twin("train", sml, "--models", "varma", "--train-days", "1",
                          "--allow-unvalidated", "--out", str(tmp_path / "b.json"))) == 2
    assert "none of the models asked for can learn from 1 training day(s)" in (
        capsys.readouterr().err)


def test_estimates_csv_keeps_a_sub_second_reading_stamp(sml: Path, tmp_path: Path) -> None:
    """Stamps were cut to whole seconds: rows no longer joined back to the history, and two
    readings within a second (4-s raw data) collided."""
    from pseudotwin.core.series import read_history, write_history

    df = read_history(sml)
    shifted = tmp_path / "half.csv"
    write_history(df.assign(ts=df["ts"] + pd.Timedelta(milliseconds=500)), shifted)
    out = tmp_path / "ev"
    assert run(*desk_twin("evaluate", shifted, "--models", "ref,triv", "--out", str(out))) == 0
    est = pd.read_csv(out / "estimates.csv", dtype={"ts": str})
    assert len(est) and est["ts"].str.endswith(".5+00:00").all()
    truth = read_history(shifted)
    assert set(pd.to_datetime(est["ts"], format="ISO8601")) <= set(
        truth.loc[truth["sensor"] == "room/temp", "ts"])


def test_evaluate_reads_the_history_store_as_it_reads_the_same_history_from_a_file(
    sml: Path, tmp_path: Path, capsys
) -> None:
    """A site that recorded its commissioning days has them in the store, not in a file:
    evaluate had only --history. From the store it scores exactly what it scores from the
    file the store was imported from; a sensor the store lacks is named."""
    db = tmp_path / "h.db"
    assert run("import", str(sml), "--store", str(db)) == 0
    with sqlite3.connect(db) as con:  # as a build of schema version 1 left it
        con.execute("ALTER TABLE estimates DROP COLUMN source")
        con.execute("ALTER TABLE estimates DROP COLUMN lost")
        con.execute("UPDATE meta SET value = '1' WHERE name = 'schema_version'")
    assert _evaluate(sml, tmp_path / "file") == 0
    stored = [a if a != str(sml) else str(db) for a in desk_twin("evaluate", sml)]
    stored[stored.index("--history")] = "--store"
    assert run(*stored, "--models", "triv", "--out", str(tmp_path / "store")) == 0
    for name in ("daily.csv", "estimates.csv"):
        from_file = pd.read_csv(tmp_path / "file" / name)
        assert len(from_file) > 0
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "store" / name), from_file)
    capsys.readouterr()
    stored[stored.index("room/temp")] = "desk/temp"
    assert run(*stored, "--models", "triv", "--out", str(tmp_path / "none")) == 2
    assert f"the history store {db} has no readings of desk/temp" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # one source, not both
        run(*desk_twin("evaluate", sml), "--store", str(db), "--out", str(tmp_path / "x"))
    assert exc.value.code == 2
    # evaluate only reads readings: the store stays at version 1 for the older recorders
    # that write to it; a writing command of this build migrates it
    version = "SELECT value FROM meta WHERE name = 'schema_version'"
    with sqlite3.connect(db) as con:
        assert con.execute(version).fetchone() == ("1",)
    assert run("import", str(sml), "--store", str(db)) == 0
    with sqlite3.connect(db) as con:
        assert con.execute(version).fetchone() == (str(SCHEMA_VERSION),)
