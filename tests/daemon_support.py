"""Shared pieces of the daemon tests: a trained artifact, configs, waiting on conditions, a
subscriber that keeps what the daemon publishes."""

from __future__ import annotations

import datetime as dt
import json
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import paho.mqtt.client as mqtt
import pandas as pd
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from pseudotwin.config import ServiceConfig, load_config
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.edge import readinglines
from pseudotwin.edge.service import Service
from pseudotwin.history.convert import load

TZ = "Europe/Madrid"
HOURS = OperatingHours(timezone=TZ)
REF, TARGET = "dining/temp", "room/temp"
DAY = dt.date(2012, 3, 20)


def off_grid(hours: float) -> dt.datetime:
    """``hours`` on DAY and a minute on: a daemon clock started there has no grid instant due
    within a test (one within the tick grace of its start is ticked, which publishes it and
    opens today's window) unless the test ticks it."""
    return HOURS.at(DAY, hours) + dt.timedelta(minutes=1)


def sml() -> pd.DataFrame:
    return load("sml2010")


def sml_csv(folder: Path, last_day: dt.date) -> Path:
    """SML2010 from its first training day (2012-03-14, Madrid) through ``last_day``, as a
    canonical CSV in ``folder``: what the CLI tests feed `train` and `evaluate`."""
    from pseudotwin.core.series import write_history

    df = sml()
    end = HOURS.at(last_day + dt.timedelta(days=1), 0.0)
    df = df[(df["ts"] >= HOURS.at(dt.date(2012, 3, 14), 0.0)) & (df["ts"] < end)]
    path = folder / "sml.csv"
    write_history(df, path)
    return path


def day_readings(df: pd.DataFrame, day: dt.date = DAY, sensors=(REF,)) -> pd.DataFrame:
    """One local day's readings of ``sensors`` from 00:00 to 19:30, in time order."""
    start = HOURS.at(day, 0.0)
    end = HOURS.at(day, 19.5)
    sub = df[df["sensor"].isin(sensors) & (df["ts"] >= start) & (df["ts"] < end)]
    return sub.sort_values(["ts", "sensor"], kind="stable").reset_index(drop=True)


def write_config(folder: Path, port: int, artifact: Path, *, target: bool = True,
                 keepalive: int = 30, **service: object) -> Path:
    extra = "".join(f"{k} = {str(v).lower()}\n" if isinstance(v, bool)
                    else f"{k} = {v!r}\n".replace("'", '"') for k, v in service.items())
    text = f"""
[broker]
host = "127.0.0.1"
port = {port}
client_id = "pt-{folder.name}"
keepalive = {keepalive}

[service]
base_topic = "pt"
timezone = "{TZ}"
state_dir = "state"
{extra}
[[sensors]]
id = "{REF}"
topic = "house/dining/temp"
unit = "°C"
min = -10
max = 50

[[sensors]]
id = "{TARGET}"
topic = "house/room/temp"
unit = "°C"
min = -10
max = 50

[[twins]]
id = "desk"
references = ["{REF}"]
{f'target = "{TARGET}"' if target else ""}
quantity = "temperature"
artifact = "{artifact}"
"""
    p = folder / "config.toml"
    p.write_text(text, encoding="utf-8")
    return p


def config(folder: Path, port: int, artifact: Path, **kw: object) -> ServiceConfig:
    return load_config(write_config(folder, port, artifact, **kw))


def wait_for(pred: Callable[[], object], timeout: float = 30.0, what: str = "condition") -> None:
    """Poll ``pred`` until true; fail with ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what() if callable(what) else what}")


class HandClock:
    """A daemon clock (edge/clock.py's protocol) the test moves: the ticker wakes only once
    the test sets a time past the instant it waits for, so what the daemon was given before
    a tick is certain, however much wall time a pause of the test process takes."""

    def __init__(self, start: dt.datetime) -> None:
        self._t = start.astimezone(dt.UTC)  # as edge/clock.py's clocks tell it
        self._moved = threading.Condition()

    def now(self) -> dt.datetime:
        with self._moved:
            return self._t

    def set(self, t: dt.datetime) -> None:
        with self._moved:
            self._t = t.astimezone(dt.UTC)
            self._moved.notify_all()

    def wait_until(self, instant: dt.datetime, stop: threading.Event) -> bool:
        with self._moved:
            while self._t < instant and not stop.is_set():
                self._moved.wait(0.05)  # ``stop`` is an Event of its own: poll it
        return not stop.is_set()


class Lockstep:
    """The clock ``replay`` publishes by: before each reading, wait until the daemon ``svc``
    has taken every reading published so far (accepted or rejected), then step ``clock`` to
    the reading's time. The worker handles items in queue order, so a grid tick, queued
    only once the clock passes its instant, comes after every earlier reading."""

    def __init__(self, clock: HandClock, svc: Service) -> None:
        self.clock, self.sent = clock, 0
        self.taken: Callable[[], int] = lambda: svc.accepted + svc.rejections.run_total

    def now(self) -> dt.datetime:
        return self.clock.now()

    def wait_until(self, instant: dt.datetime, stop: threading.Event) -> bool:
        wait_for(lambda: self.taken() >= self.sent,
                 what=lambda: f"the daemon to take reading {self.sent} "
                              f"(it took {self.taken()})")
        if instant > self.clock.now():
            self.clock.set(instant)
        self.sent += 1  # replay publishes it next
        return not stop.is_set()


def uninterrupted_estimates(artifact: Path, readings: pd.DataFrame, kind: str = "corrgp-triv"
                            ) -> dict[str, Any]:
    """What a daemon that never stopped publishes for ``readings`` of REF (in order): one
    twin fed every reading; ISO-Z timestamp → its ``kind`` estimate (init phase included)."""
    from pseudotwin.live.artifact import Artifact
    from pseudotwin.live.twin import Twin

    twin = Twin(Artifact.load(artifact))
    expected = {}
    for _, r in readings.iterrows():
        t = r["ts"].to_pydatetime()
        if twin.observe(REF, t, float(r["value"])):
            expected[t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")] = \
                twin.estimate(t)[kind]
    return expected


class Viewer:
    """Every estimate the daemon publishes on pt/desk/estimate, in arrival order."""

    def __init__(self, port: int, topic: str = "pt/desk/estimate") -> None:
        self.msgs: list[dict] = []
        self.lock = threading.Lock()
        ready = threading.Event()
        self.c = mqtt.Client(CallbackAPIVersion.VERSION2)
        self.c.on_connect = lambda c, u, f, rc, p: c.subscribe(topic, 1)
        self.c.on_subscribe = lambda c, u, mid, rcs, p: ready.set()  # receiving from now on
        self.c.on_message = self._on
        self.c.connect("127.0.0.1", port)
        self.c.loop_start()
        assert ready.wait(10)

    def _on(self, c: mqtt.Client, u: object, m: mqtt.MQTTMessage) -> None:
        if not m.retain:  # a retained message is an earlier test's
            with self.lock:
                self.msgs.append(json.loads(m.payload))

    def all(self) -> list[dict]:
        with self.lock:
            return list(self.msgs)

    def close(self) -> None:
        self.c.disconnect()
        self.c.loop_stop()


def reference_days(hours: OperatingHours, first: dt.date, sensors: tuple[str, ...], *,
                   offsets: tuple[float, ...], noise: tuple[float, ...],
                   level_sd: float, n_days: int = 6, seed: int = 7) -> pd.DataFrame:
    """References and the desk (``sensors``, the desk last) every 5 min, 06:02:30–19:57:30
    local (off the 15-min publish grid; the readings at an instant: references first): a
    shared daily course and a day level ~ N(0, level_sd), each sensor with its own offset
    and noise (std) [°C]."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n_days):
        day = first + dt.timedelta(days=k)
        level = rng.normal(0.0, level_sd)
        for h in np.arange(6.0 + 2.5 / 60, 20.0, 5 / 60):
            common = 21.0 + level + 1.5 * math.sin(math.pi * (h - 6.0) / 14.0)
            ts = hours.at(day, float(h))
            for sensor, offset, sd in zip(sensors, offsets, noise, strict=True):
                rows.append((sensor, ts, common + offset + rng.normal(0, sd)))
    return pd.DataFrame(rows, columns=["sensor", "ts", "value"])


class Synced:
    """What was fsynced (the real calls proceed): each file's size when it was synced, and
    each folder synced (a file's directory entry)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.size: dict[Path, int] = {}
        self.folders: list[Path] = []
        real_file, real_folder = readinglines.sync_file, readinglines.sync_folder

        def sync_file(path: Path, folder: bool = True) -> None:
            real_file(path, folder)  # its folder through sync_folder below
            self.size[path] = path.stat().st_size

        def sync_folder(folder: Path) -> None:
            real_folder(folder)
            self.folders.append(folder)

        monkeypatch.setattr(readinglines, "sync_file", sync_file)
        monkeypatch.setattr(readinglines, "sync_folder", sync_folder)

    def unsynced(self, path: Path) -> int:
        """Bytes of the file at ``path`` not synced yet (0: none, or no file)."""
        return path.stat().st_size - self.size.get(path, 0) if path.exists() else 0


def watch_acks(client: mqtt.Client, monkeypatch: pytest.MonkeyPatch,
               at_ack: Callable[[], object]) -> list[object]:
    """``at_ack()``'s result at each acknowledgement of a reading ``client`` sends (the
    daemon's or the recorder's worker; not a fleet claim's, acknowledged on paho's network
    thread); the real ack goes out as ever."""
    seen: list[object] = []
    real_ack = client.ack

    def ack(mid: int, qos: int) -> None:
        if not threading.current_thread().name.startswith("paho-mqtt-client-"):
            seen.append(at_ack())
        real_ack(mid, qos)

    monkeypatch.setattr(client, "ack", ack)
    return seen
