"""A sensor silent in operating hours is told by the recorder (commissioning audit: with the
desk sensor dead, nothing said so until `train` found its days missing)."""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path

from daemon_support import DAY, HOURS, REF, TARGET, HandClock, config, wait_for
from pseudotwin.edge.recorder import Recorder
from pseudotwin.edge.silence import LINES_PER_DAY, SilenceWatch
from test_daemon import publisher, reading


def at(hours: float) -> dt.datetime:
    return HOURS.at(DAY, hours)


def test_silence_is_told_in_operating_hours_once_per_silence_and_so_often_a_day(
    caplog,
) -> None:
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.silence")
    watch = SilenceWatch([REF, TARGET], HOURS, dt.timedelta(minutes=30), at(6.0))
    assert watch.check(at(7.9)) == []  # before the day start: a sensor may rest
    assert watch.check(at(8.4)) == []  # silence counts from the day start, not the night
    assert watch.check(at(8.51)) == [REF, TARGET]  # unheard of since
    assert watch.check(at(8.55)) == []  # told once
    watch.heard(REF, at(8.6))
    assert "sensor dining/temp reports again" in caplog.text
    assert watch.check(at(9.0)) == []  # heard 24 min ago
    for k in range(LINES_PER_DAY + 1):  # a flapping sensor: so many silences a day, then
        watch.heard(REF, at(10.0 + k))  # nothing more
        assert watch.check(at(10.6 + k)) == [REF]
    said = [r.message for r in caplog.records if r.levelno == logging.WARNING]
    assert sum(REF in m for m in said) == LINES_PER_DAY  # the first told with the target
    assert f"silent {LINES_PER_DAY} times today" in said[-1]
    watch.heard(REF, at(18.0))
    assert watch.check(at(19.5)) == []  # after the day end


def test_silence_counts_from_the_latest_reconnect() -> None:
    """While the listener was away from the broker nothing could be heard: that is no
    sensor's silence."""
    watch = SilenceWatch([REF], HOURS, dt.timedelta(minutes=30), at(8.0))
    watch.listening(at(9.0))  # back after an hour away
    assert watch.check(at(9.4)) == []
    assert watch.check(at(9.6)) == [REF]


def test_the_recorder_tells_a_desk_sensor_silent_in_operating_hours_and_its_return(
    mosquitto, desk_artifact, tmp_path: Path, caplog
) -> None:
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.silence")
    cfg = config(tmp_path, mosquitto.port, desk_artifact, store=str(tmp_path / "h.db"))
    clock = HandClock(at(12.0))
    rec = Recorder(cfg, clock=clock, flush_seconds=0.05)
    rec.start(wait_connected=15)
    pub = publisher(mosquitto.port, "silence-bridge")
    try:
        clock.set(at(12.4))
        pub.publish("house/dining/temp", reading(at(12.4), 20.0), qos=1)
        wait_for(lambda: rec.written == 1, what="the reference's reading stored")
        clock.set(at(12.55))  # 33 min after the start, 9 after the reference's reading
        wait_for(lambda: "no reading of" in caplog.text, what="the silent desk sensor told")
        told = [r.message for r in caplog.records if "no reading of" in r.message]
        assert len(told) == 1 and f"no reading of {TARGET} for" in told[0]
        pub.publish("house/room/temp", reading(at(12.55), 21.0), qos=1)
        wait_for(lambda: f"sensor {TARGET} reports again" in caplog.text,
                 what="the desk sensor's return told")
    finally:
        pub.loop_stop()
        rec.stop()
