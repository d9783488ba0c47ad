"""The commissioning path through the recorder: the desk sensor's days are recorded before
any twin is trained (train --config reads them from the store). The recorder needs the
sensors, broker and store of the configuration, never a twin's artifact (real Mosquitto,
real SQLite, the real `pseudotwin record` process)."""

from __future__ import annotations

import datetime as dt
import signal
import subprocess
import sys
from pathlib import Path

from daemon_support import REF, wait_for, write_config
from pseudotwin.history.store import open_store
from test_daemon import publisher, reading

EXE = [sys.executable, "-m", "pseudotwin.cli"]


def test_record_starts_before_the_twins_are_trained(mosquitto, tmp_path: Path) -> None:
    """record refused a configuration whose artifacts did not exist yet ("train the twin
    first"), and train --config said "import or record readings into it first": the
    readings of the commissioning days could not be recorded at all."""
    cfg = write_config(tmp_path, mosquitto.port, tmp_path / "artifacts" / "desk.json",
                       store="history.db")
    proc = subprocess.Popen([*EXE, "record", "--config", str(cfg)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    pub = publisher(mosquitto.port, "commissioning-bridge")
    try:
        t = dt.datetime(2012, 3, 14, 9, 0, tzinfo=dt.UTC)
        db = tmp_path / "history.db"

        def stored() -> bool:
            if proc.poll() is not None:
                raise AssertionError(f"record exited {proc.returncode}: {proc.stdout.read()}")  # type: ignore[union-attr]
            pub.publish("house/dining/temp", reading(t, 21.5), qos=1).wait_for_publish(10)
            if not db.exists():
                return False
            with open_store(str(db), existing=True) as store:
                return store.reading_range([REF]) is not None

        wait_for(stored, timeout=30, what="the reading in the store")
    finally:
        pub.loop_stop()
        pub.disconnect()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out


def test_train_from_the_store_names_a_covariate_missing_on_the_training_days(
        tmp_path: Path, capsys) -> None:
    """The store held the covariate, on other days only (a bare-number sensor replayed
    through the recorder is stamped on arrival): train said "sensor(s) … not found; file
    has: …", of a store, and of a sensor it holds."""
    from daemon_support import TARGET, sml
    from pseudotwin.cli import main

    df = sml()
    df = df[df["ts"] < "2012-03-30T00:00Z"]
    late = (df["sensor"] != "dining/co2") | (df["ts"] >= "2012-03-25T00:00Z")
    db = tmp_path / "history.db"
    with open_store(str(db)) as store:
        store.write_readings(df[late])
    rc = main(["--log-level", "WARNING", "train", "--store", str(db), "--references", REF,
               "--target", TARGET, "--covariates", "dining/co2", "--quantity", "temperature",
               "--timezone", "Europe/Madrid", "--models", "ref,triv,triv-cov",
               "--out", str(tmp_path / "a.json")])
    err = capsys.readouterr().err
    assert rc != 0
    assert "file has" not in err
    assert "dining/co2" in err and "training days" in err
    assert "stored from 2012-03-25" in err


def test_check_config_says_what_to_do_about_a_renamed_reference_or_time_zone(
        mosquitto, tmp_path: Path, capsys) -> None:
    """The second week: a reference renamed in the configuration, a time zone corrected.
    check-config said only that they "differ from the artifact's"."""
    from daemon_support import HOURS, TARGET, sml
    from pseudotwin.analysis.training import train_twin
    from pseudotwin.cli import _artifact_check
    from pseudotwin.cli.check_config import main as check_config_main
    from pseudotwin.core.spec import Quantity, TwinSpec

    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    art = train_twin(sml(), spec, dt.date(2012, 3, 14), 5, models=["ref", "triv"])
    path = art.save(tmp_path / "desk.json")
    cfg = write_config(tmp_path, mosquitto.port, path)
    text = cfg.read_text()
    cfg.write_text(text.replace(f'"{REF}"', '"wall/temp"'))
    assert check_config_main([str(cfg)], artifact_check=_artifact_check) == 1
    out = capsys.readouterr()
    said = out.out + out.err
    assert "differ from the artifact's" in said
    assert "keep the id the twin was trained with" in said and "train --config" in said
    cfg.write_text(text.replace('timezone = "Europe/Madrid"', 'timezone = "UTC"'))
    assert check_config_main([str(cfg)], artifact_check=_artifact_check) == 1
    out = capsys.readouterr()
    assert "time zone" in out.out + out.err and "train --config" in out.out + out.err


def test_a_retrained_artifact_is_told_to_wait_for_a_restart(
        mosquitto, tmp_path: Path, caplog) -> None:
    """Retrained with more days while the daemon ran, the artifact file changed and the
    daemon went on with the one it had loaded: no line said so, and the monitor's
    `artifact` was the one thing that told (the old hash)."""
    import logging
    import shutil

    from daemon_support import DAY, HOURS, TARGET, config, off_grid, sml
    from pseudotwin.analysis.training import train_twin
    from pseudotwin.core.spec import Quantity, TwinSpec
    from pseudotwin.edge.clock import ReplayClock
    from pseudotwin.edge.service import Service
    from test_daemon import Viewer

    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    first = train_twin(sml(), spec, dt.date(2012, 3, 14), 5, models=["ref", "triv"])
    more = train_twin(sml(), spec, dt.date(2012, 3, 14), 6, models=["ref", "triv"])
    path = first.save(tmp_path / "desk.json")
    retrained = more.save(tmp_path / "retrained.json")
    svc = Service(config(tmp_path, mosquitto.port, path),
                  clock=ReplayClock(off_grid(12.0), 1.0))
    viewer = Viewer(mosquitto.port, "pt/desk/monitor")
    caplog.set_level(logging.WARNING)
    svc.start(wait_connected=15)
    try:
        svc.queue.put(("tick", HOURS.at(DAY, 10.0)))
        wait_for(lambda: len(viewer.on("/monitor")) >= 1, what="the 10:00 monitor")
        assert "changed on disk" not in caplog.text
        shutil.copyfile(retrained, tmp_path / "new.json")
        (tmp_path / "new.json").replace(path)  # as train writes it: a new file over the old
        svc.queue.put(("tick", HOURS.at(DAY, 11.0)))
        wait_for(lambda: len(viewer.on("/monitor")) >= 2, what="the 11:00 monitor")
        wait_for(lambda: "changed on disk" in caplog.text, timeout=5,
                 what="the line on the retrained artifact")
        assert "next restart" in caplog.text
        svc.queue.put(("tick", HOURS.at(DAY, 12.0)))
        wait_for(lambda: len(viewer.on("/monitor")) >= 3, what="the 12:00 monitor")
        assert caplog.text.count("changed on disk") == 1  # once per new file
    finally:
        viewer.close()
        svc.stop()


def test_replay_says_a_recorder_stamps_bare_numbers_on_its_own_clock(
        mosquitto, tmp_path: Path, caplog) -> None:
    """Replayed through the broker to `record`, a bare-number sensor's commissioning days
    were stored at today's time (stamped on arrival), and nothing said so until train
    --config could not find the sensor on the training days."""
    import logging

    from pseudotwin.config import load_config
    from pseudotwin.edge.replay import replay

    cfg = write_config(tmp_path, mosquitto.port, tmp_path / "desk.json")
    cfg.write_text(cfg.read_text().replace('topic = "house/dining/temp"',
                                           'topic = "house/dining/temp"\nformat = "number"'))
    t0 = dt.datetime(2012, 3, 14, 9, 0, tzinfo=dt.UTC)
    import pandas as pd
    history = pd.DataFrame({"sensor": [REF, REF], "ts": [t0, t0 + dt.timedelta(minutes=1)],
                            "value": [21.0, 21.1]})
    caplog.set_level(logging.WARNING)
    n = replay(load_config(cfg), history, t0, t0 + dt.timedelta(minutes=2), 600.0)
    assert n == 2
    assert f"sensor(s) {REF} have no timestamp of their own" in caplog.text
    assert "`record` stamps them on arrival" in caplog.text


def test_backfill_notes_days_the_artifact_trained_on(mosquitto, tmp_path: Path,
                                                     capsys) -> None:
    """Retrained with more days, a backfill wrote the new artifact's in-sample estimates of
    its training days over the causal ones of the earlier artifact, and said nothing."""
    from daemon_support import HOURS, TARGET, sml
    from pseudotwin.analysis.training import train_twin
    from pseudotwin.cli import main
    from pseudotwin.core.spec import Quantity, TwinSpec

    df = sml()
    df = df[df["ts"] < "2012-03-22T00:00Z"]
    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    art = train_twin(df, spec, dt.date(2012, 3, 14), 5, models=["ref", "triv"])
    assert art.training["days"][-1] == "2012-03-18"
    path = art.save(tmp_path / "desk.json")
    with open_store(str(tmp_path / "history.db")) as store:
        store.write_readings(df)
    cfg = write_config(tmp_path, mosquitto.port, path, store="history.db")
    assert main(["backfill", "--config", str(cfg), "--twin", "desk", "--from", "2012-03-18",
                 "--to", "2012-03-19", "--jobs", "1", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "desk: 2012-03-18 is a day its artifact was trained on" in err
    assert "2012-03-19" not in err
    assert main(["backfill", "--config", str(cfg), "--twin", "desk", "--from", "2012-03-20",
                 "--to", "2012-03-20", "--jobs", "1", "--quiet"]) == 0
    assert "trained on" not in capsys.readouterr().err
    # the training day done already with this artifact is skipped, and so not named
    assert main(["backfill", "--config", str(cfg), "--twin", "desk", "--from", "2012-03-18",
                 "--to", "2012-03-19", "--jobs", "1", "--quiet"]) == 0
    assert "trained on" not in capsys.readouterr().err


def test_train_config_refuses_to_overwrite_a_twin_artifact_its_configuration_refuses(
        mosquitto, tmp_path: Path, capsys) -> None:
    """train --config F --out <a twin's artifact> with other references wrote over the
    artifact the daemon runs one that check-config then refused (the next start exits 78)."""
    from daemon_support import HOURS, TARGET, sml
    from pseudotwin.analysis.training import train_twin
    from pseudotwin.cli import main
    from pseudotwin.core.spec import Quantity, TwinSpec

    df = sml()
    df = df[df["ts"] < "2012-03-22T00:00Z"]
    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    path = train_twin(df, spec, dt.date(2012, 3, 14), 5, models=["ref", "triv"]).save(
        tmp_path / "desk.json")
    before = path.read_bytes()
    with open_store(str(tmp_path / "history.db")) as store:
        store.write_readings(df)
    cfg = write_config(tmp_path, mosquitto.port, path, store="history.db")
    cfg.write_text(cfg.read_text() + '\n[[sensors]]\nid = "dining/co2"\n'
                   'topic = "house/dining/co2"\nunit = "ppm"\nmin = 0\nmax = 5000\n')
    train = ["--log-level", "WARNING", "train", "--config", str(cfg), "--target", TARGET,
             "--quantity", "temperature", "--models", "ref,triv"]
    rc = main([*train, "--references", REF, "--covariates", "dining/co2", "--models",
               "ref,triv,triv-cov", "--out", str(path)])
    assert rc != 0
    err = capsys.readouterr().err
    assert "is the artifact of twin desk" in err and "covariates" in err
    assert path.read_bytes() == before
    assert main([*train, "--references", REF, "--out", str(path)]) == 0  # as configured
