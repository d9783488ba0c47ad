"""<twin>/monitor goes out every ``monitor_every_minutes`` (default hourly), not at every grid
instant; estimates and baselines keep the grid. Its figures are the day's."""

from __future__ import annotations

import datetime as dt

import pytest

from daemon_support import DAY, HOURS, TZ, config, off_grid, wait_for
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.service import Service
from pseudotwin.errors import ConfigError
from test_daemon import Viewer, publisher, reading


def stamp(t: dt.datetime) -> str:
    return t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


MIDDAY = (10.0, 10.25, 10.5, 10.75, 11.0)  # grid instants [h] the test ticks


@pytest.mark.parametrize(("every", "at", "hours"), [
    (None, MIDDAY, (10.0, 11.0)),  # the default: hourly
    (30, MIDDAY, (10.0, 10.5, 11.0)),
    (20, MIDDAY, (10.0, 10.5, 10.75, 11.0)),  # the first instant at or after 10:20, 10:40, …
    (10, MIDDAY, (10.0, 10.25, 10.5, 10.75, 11.0)),  # shorter than the grid: every instant
    # daily: the day's first and last grid instants only (the last carries the day's figures)
    (1440, (8.0, 8.25, 12.0, 18.75, 19.0), (8.0, 19.0)),
])
def test_the_monitor_follows_its_own_cadence_on_the_grid(
    service_factory, mosquitto, every: int | None, at: tuple[float, ...],
    hours: tuple[float, ...]
) -> None:
    kw = {} if every is None else {"monitor_every_minutes": every}
    svc = service_factory(off_grid(at[0]), 1.0, **kw)  # ticks come from the test
    assert svc.cfg.monitor_every_minutes == (every or 60)
    viewer = Viewer(mosquitto.port, "pt/desk/#")
    pub = publisher(mosquitto.port, f"cadence-bridge-{every}")
    first = HOURS.at(DAY, max(at[0] - 0.1, HOURS.day_start))  # after the unpublished init
    pub.publish("house/dining/temp", reading(first, 17.0), qos=1).wait_for_publish(10)
    wait_for(lambda: any(e["ts"] == stamp(first) for e in viewer.on("/estimate")),
             what="the reading's estimate")  # before the ticks: theirs need its value
    ticks = [HOURS.at(DAY, h) for h in at]
    for t in ticks:
        svc.queue.put(("tick", t))
    # a twin's monitor follows its estimate of the same instant; the last tick has both
    wait_for(lambda: {stamp(t) for t in ticks} <= {e["ts"] for e in viewer.on("/estimate")},
             what=lambda: f"the estimate of every grid instant (got "
                          f"{sorted({e['ts'] for e in viewer.on('/estimate')})})")
    wait_for(lambda: any(m["ts"] == stamp(ticks[-1]) for m in viewer.on("/monitor")),
             what="the monitor of the last grid instant")
    assert [m["ts"] for m in viewer.on("/monitor")] == [stamp(HOURS.at(DAY, h))
                                                          for h in hours]
    pub.loop_stop()
    viewer.close()


@pytest.mark.parametrize("value", [0, -15, "hourly"])
def test_a_bad_monitor_cadence_is_a_clear_config_error(tmp_path, desk_artifact,
                                                         value: object) -> None:
    with pytest.raises(ConfigError, match="service.monitor_every_minutes"):
        config(tmp_path, 1883, desk_artifact, monitor_every_minutes=value)


def test_the_monitor_counts_the_rejections_of_its_own_day(service_factory, mosquitto) -> None:
    """A day's monitor does not carry the day before's rejected readings: the counts start
    afresh with the day, not with the day's first rejection."""
    svc = service_factory(HOURS.at(DAY, 9.95), 1.0)
    viewer = Viewer(mosquitto.port, "pt/desk/#")
    pub = publisher(mosquitto.port, "rejections-bridge")
    bad = HOURS.at(DAY, 9.9)
    pub.publish("house/dining/temp", reading(bad, 99.0), qos=1).wait_for_publish(10)
    wait_for(lambda: svc.rejections.run_total == 1, what="the out-of-range reading rejected")
    today, tomorrow = HOURS.at(DAY, 10.0), HOURS.at(DAY + dt.timedelta(days=1), 10.0)
    for t in (today, tomorrow):
        svc.queue.put(("tick", t))
    wait_for(lambda: {stamp(today), stamp(tomorrow)} <= {m["ts"] for m in viewer.on("/monitor")},
             what="both days' monitors")
    rejected = {m["ts"]: m["rejected"] for m in viewer.on("/monitor")}
    assert rejected[stamp(today)] == {"dining/temp:out-of-range": 1}
    assert rejected[stamp(tomorrow)] == {}
    pub.loop_stop()
    viewer.close()


def test_the_days_first_and_last_grid_instants_carry_a_monitor_whatever_the_hours(
        tmp_path, mosquitto, desk_artifact) -> None:
    """With day_start off the grid (08:10) the first monitor goes out at the first grid
    instant, 08:15; with day_end 24:00 the day's figures go out at its last one, 23:45 (the
    next midnight is the next day's). Hourly in between."""
    svc = Service(config(tmp_path, mosquitto.port, desk_artifact),
                  clock=ReplayClock(off_grid(12.0), 1.0))  # not started: its rule only
    svc.hours = OperatingHours.from_strings(day_start="08:10", day_end="24:00", timezone=TZ)
    grid = svc.hours.grid(DAY, 0.25)
    sent = [svc.hours.hours_of(t) for t in grid if svc._monitor_at(t)]
    assert sent == [8.25, *range(9, 24), 23.75]
    svc.journal.close()
