"""The README's promise, checked where a user test broke it: errors in input, configuration
or artifacts end in one clear message and a non-zero status, never a traceback (issue of the
user test after ab178f3). Real files, real subprocesses or the CLI's main function."""

from __future__ import annotations

import datetime as dt
import json
import os
import socket
import stat
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from conftest import closed_port
from daemon_support import HOURS, REF, TARGET, TZ, write_config
from pseudotwin.cli import main
from pseudotwin.cli.check_config import main as check_config_main
from pseudotwin.core.series import read_history, require_sensors, write_history
from pseudotwin.errors import DataError
from pseudotwin.history.convert import load

EXE = [sys.executable, "-m", "pseudotwin.cli"]


def _with_state_dir(cfg: Path, state_dir: str) -> Path:
    cfg.write_text(cfg.read_text().replace('state_dir = "state"', f'state_dir = "{state_dir}"'))
    return cfg


def _one_line(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


# ------------------------------------------------------------------ 1. state_dir


@pytest.mark.parametrize("command", ["run", "record"])
def test_a_state_dir_that_cannot_be_created_exits_78(
    desk_artifact: Path, tmp_path: Path, command: str
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder\n")
    cfg = _with_state_dir(write_config(tmp_path, 1, desk_artifact, store="h.db"),
                          f"{blocker}/state")
    p = subprocess.run([*EXE, command, "--config", str(cfg)], capture_output=True, text=True,
                       timeout=60, check=False)
    assert p.returncode == 78, p.stderr
    line = _one_line(p.stderr)
    assert f"pseudotwin {command}: configuration error in {cfg}" in line
    assert f"service.state_dir: {blocker}/state cannot be created" in line


def test_a_state_dir_the_os_refuses_exits_78(desk_artifact: Path, tmp_path: Path) -> None:
    """/proc/nope: nothing on the path is a file, only mkdir can tell (check-config cannot
    without creating it); run names state_dir and the OS's reason."""
    cfg = _with_state_dir(write_config(tmp_path, 1, desk_artifact), "/proc/nope")
    p = subprocess.run([*EXE, "run", "--config", str(cfg)], capture_output=True, text=True,
                       timeout=60, check=False)
    assert p.returncode == 78, p.stderr
    line = _one_line(p.stderr)
    assert "service.state_dir: /proc/nope cannot be created: " in line
    assert not Path("/proc/nope").exists()


def test_check_config_reports_a_state_dir_under_a_file(
    desk_artifact: Path, tmp_path: Path, capsys
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder\n")
    cfg = _with_state_dir(write_config(tmp_path, 1, desk_artifact), f"{blocker}/x/state")
    assert check_config_main([str(cfg)]) == 1
    err = capsys.readouterr().err
    assert f"service.state_dir: {blocker}/x/state cannot be created: {blocker} is not a " \
           "directory" in err
    assert not (tmp_path / "state").exists()  # check-config creates nothing


# ------------------------------------------------------------------ 2. bad history files


def run(*args: str) -> int:
    return main(["--log-level", "WARNING", *args])


def _csv(folder: Path, name: str, rows: str) -> Path:
    path = folder / name
    path.write_text("sensor,ts,value\n" + rows, encoding="utf-8")
    return path


TRAIN = ("--references", "a", "--target", "b", "--quantity", "temperature")


def _every_command(path: Path, tmp_path: Path) -> list[tuple[str, ...]]:
    return [("import", str(path), "--store", str(tmp_path / "h.db")),
            ("train", "--history", str(path), *TRAIN, "--out", str(tmp_path / "z.json")),
            ("evaluate", "--history", str(path), *TRAIN, "--train-start", "2012-03-14",
             "--out", str(tmp_path / "ev"))]


@pytest.mark.parametrize(
    "rows,message",
    [("a,2012-03-14T10:00:00+00:00,nan\n",
      "no valid readings: dropped 1 of 1 rows (1 with a blank, NaN or infinite value)"),
     ("a,2012-03-14T10:00:00+00:00,inf\nb,2012-03-14T10:00:00+00:00,\n",
      "no valid readings: dropped 2 of 2 rows (2 with a blank, NaN or infinite value)"),
     ("a,0,20.5\n", "no valid readings: dropped 1 of 1 rows (1 stamped before 2000-01-01, a "
                    "device clock never set, as the recorder rejects them)"),
     # stamps beyond a nanosecond timestamp's years (1677–2262) too, which crashed the reader
     *((f"a,{ts},20.5\n", f"no valid readings: dropped 1 of 1 rows (1 stamped {why})")
       for ts, why in (
           ("2099-01-01T00:00:00Z", "more than 1 day after now, a device clock far ahead, as "
                                    "the recorder rejects them"),
           ("2999-01-01T00:00:00Z", "more than 1 day after now, a device clock far ahead, as "
                                    "the recorder rejects them"),
           ("99999999999", "more than 1 day after now, a device clock far ahead, as the "
                           "recorder rejects them"),
           ("1500-01-01T00:00:00Z", "before 2000-01-01, a device clock never set, as the "
                                    "recorder rejects them"))),
     # pandas read the extra field as an index and shifted the rest: a at 1970-01-01T00:00:01
     ("b,2012-03-14T10:00:00Z,2\na,2012-03-14T10:00:00Z,1,5\n",
      "data row 2 has 4 fields, the header 3 (sensor,ts,value): an extra column, or a value "
      "with a comma?"),
     ("a,1331719200000000000,1\n", "epoch value 1331719200000000000 in data row 1 is too "
      "large for seconds or milliseconds (microseconds or nanoseconds? divide by 1e3 or 1e6 "
      "first)"),
     ("a,2012-03-14T10:00:00Z,1\na,2012-02-30T10:00:00Z,1\n",
      "'2012-02-30T10:00:00Z' in data row 2 is not a valid ISO 8601 instant"),
     (",2012-03-14T10:00:00+00:00,1\n", "data row 1 has no sensor name"),
     ("a,2012-03-14T10:00:00+00:00,1\n  ,2012-03-14T10:01:00+00:00,1\n",
      "data row 2 has no sensor name"),
     ("a,,1\n", "data row 1 has no timestamp")],
)
def test_a_history_file_without_valid_readings_is_one_line(
    tmp_path: Path, capsys, rows: str, message: str
) -> None:
    path = _csv(tmp_path, "bad.csv", rows)
    for args in _every_command(path, tmp_path):
        assert run(*args) == 2, args
        line = _one_line(capsys.readouterr().err)
        assert line == f"pseudotwin {args[0]}: error: {path}: {message}"
    assert not (tmp_path / "h.db").exists() and not (tmp_path / "z.json").exists()


def _import_warnings(path: Path, capsys, caplog) -> tuple[str, list[str]]:
    """Import ``path`` into a new store beside it: (stdout, the warnings logged)."""
    assert run("import", str(path), "--store", str(path.with_suffix(".db"))) == 0
    return (capsys.readouterr().out,
            [r.getMessage() for r in caplog.records if r.levelname == "WARNING"])


def test_dropped_rows_are_counted_and_explained(tmp_path: Path, capsys, caplog) -> None:
    path = _csv(tmp_path, "some.csv", "a,2012-03-14T10:00:00+00:00,nan\n"
                                      "a,2012-03-14T10:01:00+00:00,1\n"
                                      "a,2012-03-14T10:01:00+00:00,1\n"
                                      "a,2012-03-14T10:02:00+00:00,-inf\n")
    out, warnings = _import_warnings(path, capsys, caplog)
    assert "1 readings of 1 sensor(s)" in out
    assert warnings == [f"{path}: dropped 3 of 4 rows (2 with a blank, NaN or infinite value, "
                        "1 exact duplicate(s))"]


def test_readings_within_one_millisecond_are_counted_as_repeats_not_as_stored(
    tmp_path: Path, capsys, caplog
) -> None:
    """Two readings 0.3 ms apart in an empty store: the store keeps one per sensor and
    millisecond, and the summary says the second repeats the first, not that it was stored."""
    path = _csv(tmp_path, "submilli.csv", "a,2012-03-14T10:00:00.0001+00:00,20.5\n"
                                          "a,2012-03-14T10:00:00.0004+00:00,25.0\n"
                                          "a,2012-03-14T10:00:00.0012+00:00,25.5\n")
    out, _ = _import_warnings(path, capsys, caplog)
    assert "3 readings" in out
    assert "2 new, 0 already stored, 1 repeating an earlier row's sensor and millisecond" in out


def test_a_sensor_and_time_repeated_with_another_value_is_reported(
    tmp_path: Path, capsys, caplog
) -> None:
    path = _csv(tmp_path, "conflict.csv", "a,2012-03-14T10:00:00+00:00,20.5\n"
                                          "a,2012-03-14T10:00:00+00:00,21.5\n")
    out, warnings = _import_warnings(path, capsys, caplog)
    assert "1 new, 0 already stored" in out
    assert warnings == [f"{path}: dropped 1 of 2 rows (1 repeating a sensor and time with "
                        "another value: the first is used, as the store and the daemon's "
                        "window keep it)"]
    # every reader of the file gets the first (evaluate averaged the two as the truth)
    assert read_history(path)["value"].tolist() == [20.5]


def test_missing_sensors_of_a_file_without_readings_say_so() -> None:
    empty = pd.DataFrame({"sensor": pd.Series([], dtype=str), "ts": [], "value": []})
    with pytest.raises(DataError, match=r"sensor\(s\) a, b not found; it has no valid readings"):
        require_sensors(empty, ["a", "b"], "x.csv")


# ------------------------------------------------------------------ 3., 5.: argparse-level


def _usage_error(capsys, *args: str) -> str:
    """The last stderr line of a command argparse refuses (status 2)."""
    with pytest.raises(SystemExit) as exc:
        run(*args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err.strip().splitlines()[-1]


REPLAY = ("replay", "--config", "c.toml", "--history", "h.csv",
          "--start", "2012-03-20T06:30:00+01:00")


@pytest.mark.parametrize("speed", ["0", "-1", "inf", "nan"])
def test_speed_must_be_positive(capsys, speed: str) -> None:
    line = _usage_error(capsys, "run", "--config", "c.toml",
                        "--replay-from", "2012-03-20T06:30:00+01:00", "--speed", speed)
    assert line == f"pseudotwin run: error: argument --speed: {speed}: the speed must be positive"
    line = _usage_error(capsys, *REPLAY, "--end", "2012-03-20T19:30:00+01:00", "--speed", speed)
    assert "argument --speed" in line and "the speed must be positive" in line


def test_a_speed_or_an_instant_the_clock_cannot_count_is_a_usage_error(capsys) -> None:
    """(helper's fuzzing: OverflowError tracebacks)"""
    line = _usage_error(capsys, "run", "--config", "c.toml",
                        "--replay-from", "2012-03-20T06:30:00+01:00", "--speed", "1e308")
    assert line == "pseudotwin run: error: argument --speed: 1e308: at most 1e+06 times real time"
    for instant in ("0001-01-01T00:30:00+01:00", "9999-12-31T23:00:00+00:00"):
        line = _usage_error(capsys, "run", "--config", "c.toml", "--replay-from", instant)
        assert line.endswith(f"{instant!r}: expected a year in 2000..2200"), line
        line = _usage_error(capsys, *REPLAY[:-1], instant)
        assert "argument --start" in line and "expected a year" in line


def test_speed_without_replay_from_is_an_error(capsys) -> None:
    line = _usage_error(capsys, "run", "--config", "c.toml", "--speed", "600")
    assert line.startswith("pseudotwin run: error: --speed needs --replay-from")


def _train(tmp_path: Path, *extra: str) -> tuple[str, ...]:
    return ("train", "--history", str(tmp_path / "h.csv"), *TRAIN, *extra)


def test_train_out_is_checked_before_training(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "somedir"
    folder.mkdir()
    line = _usage_error(capsys, *_train(tmp_path, "--out", str(folder)))
    assert line.startswith(f"pseudotwin train: error: argument --out: {folder} is a directory")
    line = _usage_error(capsys, *_train(tmp_path, "--out", ""))
    assert line == "pseudotwin train: error: argument --out: an empty path"
    blocker = tmp_path / "ok.csv"
    blocker.write_text("x\n")
    line = _usage_error(capsys, *_train(tmp_path, "--out", str(tmp_path / "a.json"),
                                        "--report", str(blocker)))
    assert line == f"pseudotwin train: error: argument --report: {blocker} exists and is not " \
                   "a directory"
    line = _usage_error(capsys, *_train(tmp_path, "--out", f"{blocker}/a.json"))
    assert line.endswith(f"{blocker} is not a directory")
    pipe = tmp_path / "pipe"  # as a device (--out /dev/null): never replaced by a file
    os.mkfifo(pipe)
    line = _usage_error(capsys, *_train(tmp_path, "--out", str(pipe)))
    assert line.endswith(f"{pipe} exists and is not a regular file")
    assert stat.S_ISFIFO(pipe.stat().st_mode)
    pipe.unlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.csv", "somedir"]
    assert not list(folder.iterdir())


def test_a_file_written_whole_never_replaces_a_device_or_a_pipe(tmp_path: Path, capsys
                                                               ) -> None:
    """convert --out /dev/null, run as root, made /dev/null a plain file of 3 MB."""
    from pseudotwin.core.files import write_replacing

    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    link = tmp_path / "link"
    link.symlink_to(pipe)
    for path in (pipe, link):
        with pytest.raises(OSError, match="not a regular file"):
            write_replacing(path, lambda tmp: tmp.write_text("x"))
        assert stat.S_ISFIFO(path.stat().st_mode)
    assert main(["convert", "appliances", "--out", str(link)]) == 2
    assert f"{pipe}: exists and is not a regular file (nothing written)" in capsys.readouterr().err


def test_evaluate_out_must_be_a_folder(tmp_path: Path, capsys) -> None:
    blocker = tmp_path / "my.toml"
    blocker.write_text("x\n")
    line = _usage_error(capsys, "evaluate", "--history", str(tmp_path / "h.csv"), *TRAIN,
                        "--train-start", "2012-03-14", "--out", str(blocker))
    assert line == f"pseudotwin evaluate: error: argument --out: {blocker} exists and is not " \
                   "a directory"


def test_replay_end_before_start(capsys) -> None:
    line = _usage_error(capsys, *REPLAY, "--end", "2012-03-20T06:00:00+01:00")
    assert line == ("pseudotwin replay: error: --end 2012-03-20T06:00:00+01:00 is not after "
                    "--start 2012-03-20T06:30:00+01:00")


def test_init_minutes_must_not_be_negative(tmp_path: Path, capsys) -> None:
    line = _usage_error(capsys, *_train(tmp_path, "--out", str(tmp_path / "a.json"),
                                        "--init-minutes", "-5"))
    assert line == "pseudotwin train: error: argument --init-minutes: -5 min: must be ≥ 0"


# ------------------------------------------------------------------ 4. broker


def test_replay_with_an_unreachable_broker_is_one_line(tmp_path: Path, capsys) -> None:
    port = closed_port()
    cfg = write_config(tmp_path, port, tmp_path / "none.json")
    history = _csv(tmp_path, "h.csv", f"{REF},2012-03-20T06:40:00+00:00,20.5\n")
    rc = run("replay", "--config", str(cfg), "--history", str(history),
             "--start", "2012-03-20T06:30:00Z", "--end", "2012-03-20T07:00:00Z")
    assert rc == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith(f"pseudotwin replay: error: MQTT broker 127.0.0.1:{port} "
                           "unreachable: ")


# ------------------------------------------------------------------ 6. Parquet


def test_import_and_train_from_parquet(tmp_path: Path, capsys) -> None:
    """The help says CSV or Parquet: a slice of SML2010 through the project's converter,
    written as Parquet, imports and trains like the CSV."""
    df = load("sml2010")
    df = df[(df["ts"] >= HOURS.at(dt.date(2012, 3, 14), 0.0))
            & (df["ts"] < HOURS.at(dt.date(2012, 3, 19), 0.0))]
    path = tmp_path / "sml.parquet"
    df.to_parquet(path, index=False)
    assert run("import", str(path), "--store", str(tmp_path / "h.db")) == 0
    assert f"{len(df)} readings of 17 sensor(s)" in capsys.readouterr().out
    out = tmp_path / "a.json"
    assert run("train", "--history", str(path), "--references", REF, "--target", TARGET,
               "--quantity", "temperature", "--timezone", TZ, "--models", "triv",
               "--out", str(out)) == 0
    art = json.loads(out.read_text())
    assert art["training"]["days"] == [f"2012-03-{d}" for d in range(14, 19)]


# ------------------------------------------------------------------ 7. train --config


def test_train_with_config_takes_its_time_zone_and_hours(tmp_path: Path, capsys) -> None:
    df = load("sml2010")
    df = df[(df["ts"] >= HOURS.at(dt.date(2012, 3, 14), 0.0))
            & (df["ts"] < HOURS.at(dt.date(2012, 3, 19), 0.0))]
    write_history(df, tmp_path / "h.csv")
    cfg = write_config(tmp_path, 1883, tmp_path / "desk.json", store="h.db", day_start="07:30")
    assert run("import", str(tmp_path / "h.csv"), "--store", str(tmp_path / "h.db")) == 0
    args = ("train", "--config", str(cfg), "--references", REF, "--target", TARGET,
            "--quantity", "temperature", "--models", "triv")
    assert run(*args, "--out", str(tmp_path / "desk.json")) == 0
    hours = json.loads((tmp_path / "desk.json").read_text())["hours"]
    assert (hours["timezone"], hours["day_start"]) == ("Europe/Madrid", 7.5)
    capsys.readouterr()
    assert run("check-config", str(cfg)) == 0  # the artifact fits the configuration
    # an option may repeat the configuration, not contradict it
    assert run(*args, "--timezone", TZ, "--day-start", "07:30",
               "--out", str(tmp_path / "same.json")) == 0
    assert run(*args, "--timezone", "UTC", "--out", str(tmp_path / "utc.json")) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"pseudotwin train: error: --timezone UTC contradicts {cfg}, whose timezone is "
        f"{TZ}: the artifact would not fit it (leave the option out)")
    assert run(*args, "--day-start", "08:00", "--out", str(tmp_path / "utc.json")) == 2
    assert "whose day_start is 07:30" in capsys.readouterr().err
    assert not (tmp_path / "utc.json").exists()


# ------------------------------------------------------------------ 8. wording


def test_check_config_says_an_artifact_folder_is_a_folder(
    desk_artifact: Path, tmp_path: Path, capsys
) -> None:
    folder = tmp_path / "artifacts"
    folder.mkdir()
    cfg = write_config(tmp_path, 1, folder)
    assert check_config_main([str(cfg)]) == 1
    err = capsys.readouterr().err
    assert f"twins[0].artifact: {folder} is a directory, not an artifact file" in err
    assert "does not exist" not in err


def test_a_word_for_a_timestamp_is_not_a_timestamp(tmp_path: Path, capsys) -> None:
    path = _csv(tmp_path, "t.csv", "a,2012-03-14T10:00:00+00:00,1\na,notatime,1\n")
    assert run("import", str(path), "--store", str(tmp_path / "h.db")) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"pseudotwin import: error: {path}: 'notatime' in data row 2 is not a timestamp (use "
        "ISO 8601 with a UTC offset, or epoch seconds / ms)")
    path = _csv(tmp_path, "n.csv", "a,2012-03-14T10:00:00,1\n")
    assert run("import", str(path), "--store", str(tmp_path / "h.db")) == 2
    assert "timestamp '2012-03-14T10:00:00' has no UTC offset" in capsys.readouterr().err


@pytest.mark.parametrize(
    "options,message",
    [(("--day-start", "19:00", "--day-end", "08:00"),
      "operating hours: day_start 19:00 must be before day_end 08:00"),
     (("--slot-minutes", "7"), "slot_minutes 7: must divide a day and lie in 1..120"),
     (("--day-start", "00:10"),
      "operating hours: init phase of 30 min does not fit before day_start on the same day")],
)
def test_hours_problems_read_as_written(
    tmp_path: Path, capsys, options: tuple[str, ...], message: str
) -> None:
    path = _csv(tmp_path, "h.csv", "a,2012-03-14T10:00:00+00:00,1\n")
    assert run(*_train(tmp_path, "--out", str(tmp_path / "a.json"), *options)) == 2
    assert _one_line(capsys.readouterr().err) == f"pseudotwin train: error: {message}"
    assert path.exists()


def test_evaluate_on_a_file_without_valid_readings(tmp_path: Path, capsys) -> None:
    path = _csv(tmp_path, "h.csv", "a,2012-03-14T10:00:00+00:00,nan\nb,2012-03-14T10:00:00Z,\n")
    assert run(*_every_command(path, tmp_path)[2]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.endswith("no valid readings: dropped 2 of 2 rows (2 with a blank, NaN or "
                         "infinite value)")
    assert "file has:" not in line


# ------------------------------------------------------------------ a reader that goes away


def test_a_reader_that_closes_the_pipe_ends_the_command_quietly(tmp_path: Path) -> None:
    """`pseudotwin … | head`: the pipe closes before the command has written; no traceback,
    the shell's status for SIGPIPE."""
    csv = tmp_path / "h.csv"
    csv.write_text("sensor,ts,value\na,2012-03-14T10:00:00+00:00,20.5\n")
    p = subprocess.Popen([*EXE, "import", str(csv), "--store", str(tmp_path / "h.db")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()  # long before the interpreter has started and printed anything
    stderr = p.stderr.read().decode()
    assert p.wait(timeout=60) == 141, stderr
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr, stderr


# ------------------------------------------------------------------ a store to read from


def test_a_mistyped_store_to_read_from_is_an_error_not_a_new_database(
    desk_artifact: Path, tmp_path: Path
) -> None:
    db = tmp_path / "histroy.db"  # the store is history.db
    train = [*EXE, "train", "--store", str(db), "--references", REF, "--target", TARGET,
             "--quantity", "temperature", "--train-start", "2012-03-14", "--timezone", TZ,
             "--out", str(tmp_path / "a.json")]
    cfg = write_config(tmp_path, 1883, desk_artifact, store=db.name)
    backfill = [*EXE, "backfill", "--config", str(cfg), "--twin", "desk", "--from",
                "2012-03-20", "--to", "2012-03-20"]
    for command in (train, backfill):
        p = subprocess.run(command, capture_output=True, text=True, timeout=120)
        assert p.returncode != 0, command
        assert "no such database file" in _one_line(p.stderr), command
        assert not db.exists()


def test_check_config_reports_a_store_in_a_folder_that_does_not_exist(
    desk_artifact: Path, tmp_path: Path
) -> None:
    cfg = write_config(tmp_path, 1883, desk_artifact, store="nodir/history.db")
    p = subprocess.run([*EXE, "check-config", str(cfg)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode != 0
    assert "service.store" in p.stderr + p.stdout and "does not exist" in p.stderr + p.stdout
    assert not (tmp_path / "nodir").exists()


def test_an_unreachable_crate_store_is_one_line(tmp_path: Path) -> None:
    """The CrateDB client's HTTP pool warned once per retry before the store's own error."""
    path = _csv(tmp_path, "one.csv", "a,2012-03-14T10:00:00+00:00,1\n")
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = subprocess.run([*EXE, "import", str(path), "--store", f"crate://127.0.0.1:{port}"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert "Retrying" not in p.stderr and "urllib3" not in p.stderr
    assert "cannot connect to CrateDB" in _one_line(
        "\n".join(x for x in p.stderr.splitlines() if " INFO " not in x))


def test_an_offset_of_hours_alone_is_iso_8601_too(tmp_path: Path) -> None:
    """``+01`` is ISO 8601's offset of one hour (it was refused as 'no UTC offset')."""
    path = _csv(tmp_path, "short.csv", "a,2012-03-14T10:00:00+01,1\na,2012-03-14T10:00:00-0230,2\n")
    assert [t.isoformat() for t in read_history(path)["ts"]] == [
        "2012-03-14T09:00:00+00:00", "2012-03-14T12:30:00+00:00"]
    # a date alone ends in what looks like an offset: it is no instant
    with pytest.raises(DataError, match="'2012-03-14' has no UTC offset"):
        read_history(_csv(tmp_path, "date.csv", "a,2012-03-14,1\n"))
