#!/usr/bin/env python3
"""The end-to-end demo: the daemon on a real day of SML2010, through a real MQTT broker.

1. converts SML2010 and trains two twins on 2012-03-14…18 (dining room → bedroom, temperature
   and CO2), writing their artifacts;
2. starts a Mosquitto broker on a free port and the daemon (``pseudotwin run``) in replay
   mode, its clock at 2012-03-20 07:00 Europe/Madrid running at --speed × real time;
3. replays that day's readings through the broker (``pseudotwin.edge.replay``), as a PLC bridge
   would publish them, including the temporary desk sensor as a live target;
4. prints each pseudo-measurement as it arrives next to the truth, then stops the daemon
   with SIGTERM and prints the day's scores.

Usage: .venv/bin/python scripts/demo.py [--speed 900] [--day 2012-03-20] [--out out/demo]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np
import paho.mqtt.client as mqtt
import pandas as pd
from paho.mqtt.enums import CallbackAPIVersion

import pseudotwin  # noqa: F401
from brokerutil import free_port, start_broker
from pseudotwin.analysis.commissioning.oddday import odd_training_day
from pseudotwin.analysis.training import train_twin
from pseudotwin.config import load_config
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.core.twinlog import twin_context
from pseudotwin.edge.replay import replay
from pseudotwin.errors import PseudotwinError
from pseudotwin.history.convert import SHARED_DATA_ENV, load
from pseudotwin.live import dayscore

ROOT = Path(__file__).resolve().parent.parent
TZ = "Europe/Madrid"
TWINS = {
    "bedroom-temp": ("dining/temp", "room/temp", "temperature", "°C"),
    "bedroom-co2": ("dining/co2", "room/co2", "co2", "ppm"),
}

CONFIG = """\
# written by scripts/demo.py
[broker]
host = "127.0.0.1"
port = {port}
client_id = "pseudotwin-demo"

[service]
base_topic = "demo"
timezone = "{tz}"
state_dir = "state"
publish_every_minutes = 60
stale_after_minutes = 45
# every model at every reading (the default publishes the baselines on the grid only), so
# the day's table compares them all at the same instants
baselines = "reading"
{sensors}{twins}"""


DRAIN_SECONDS = 60.0


def _last_reading(df: pd.DataFrame, hours: OperatingHours, sensor: str, start: dt.datetime,
                  end: dt.datetime) -> dt.datetime | None:
    """The last reading of ``sensor`` replayed in operating hours: the daemon's last
    reading-triggered estimates are of this instant."""
    sel = df[(df["sensor"] == sensor) & (df["ts"] >= start) & (df["ts"] < end)]
    _, hrs = hours.day_and_hours(sel["ts"])
    ts = sel["ts"][hours.in_operating_hours(hrs)]
    return ts.max().to_pydatetime() if len(ts) else None


def _complete(received: dict[str, list[dayscore.Published]],
              last: dict[str, dt.datetime | None]) -> bool:
    """Every model of every twin has published an estimate that saw the last reading."""
    return all(dayscore.answered(received[tid], t) for tid, t in last.items() if t is not None)


def _day_scores(df: pd.DataFrame, hours: OperatingHours, day: dt.date, ref: str, tgt: str,
                received: list[dayscore.Published]) -> list[dayscore.DayScore]:
    """Every model's and the raw reference's score on ``day``, against the desk sensor."""
    days, hrs = hours.day_and_hours(df["ts"])
    on_day = (days == np.datetime64(day)) & hours.in_operating_hours(hrs)
    target = df[on_day & (df["sensor"] == tgt).to_numpy()]
    truth = {t.to_pydatetime(): float(v) for t, v in zip(target["ts"], target["value"],
                                                          strict=True)}
    r = df[(df["sensor"] == ref).to_numpy() & (days <= np.datetime64(day))]
    refs = {ref: [(t.to_pydatetime(), float(v)) for t, v in zip(r["ts"], r["value"],
                                                                strict=True)]}
    return dayscore.day_scores(received, truth, refs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--speed", type=float, default=900.0, help="replay speed (default 900×)")
    ap.add_argument("--day", type=dt.date.fromisoformat, default=dt.date(2012, 3, 20))
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "demo")
    a = ap.parse_args()
    out = a.out
    try:
        df = load("sml2010")
    except (PseudotwinError, OSError) as exc:
        print(f"demo: the shared SML2010 data is missing or unreadable ({exc}); put it in "
              f"../shared/data/sml2010 or point {SHARED_DATA_ENV} to the data folder",
              file=sys.stderr)
        return 1
    if out.exists():
        shutil.rmtree(out)
    (out / "artifacts").mkdir(parents=True)
    hours = OperatingHours(timezone=TZ)

    print("1/4 training two twins on SML2010, 2012-03-14 … 2012-03-18", flush=True)
    for tid, (ref, tgt, quantity, _) in TWINS.items():
        t0 = time.perf_counter()
        spec = TwinSpec((ref,), tgt, Quantity.parse(quantity), hours)
        with twin_context(tid):
            art = train_twin(df, spec, dt.date(2012, 3, 14), 5)
        art.save(out / "artifacts" / f"{tid}.json")
        print(f"    {tid}: {', '.join(art.models)} in {time.perf_counter() - t0:.0f} s; "
              f"validation chose {art.primary}")
        if odd := odd_training_day(art.validation):  # what train says too: why σ is wide
            print(textwrap.fill(odd.advice(art.unit, len(art.references)), width=96,
                                initial_indent="      ", subsequent_indent="      "))

    port = free_port()
    sensors = "".join(
        f'\n[[sensors]]\nid = "{s}"\ntopic = "house/{s}"\nunit = "{unit}"\n'
        f"min = {lo}\nmax = {hi}\n"
        for tid, (ref, tgt, q, unit) in TWINS.items()
        for s, (lo, hi) in ((ref, (-10, 50) if q == "temperature" else (0, 5000)),
                            (tgt, (-10, 50) if q == "temperature" else (0, 5000)))
    )
    twins = "".join(
        f'\n[[twins]]\nid = "{tid}"\nreferences = ["{ref}"]\ntarget = "{tgt}"\n'
        f'quantity = "{q}"\nartifact = "artifacts/{tid}.json"\n'
        for tid, (ref, tgt, q, _) in TWINS.items()
    )
    cfg_path = out / "config.toml"
    cfg_path.write_text(CONFIG.format(port=port, tz=TZ, sensors=sensors, twins=twins))
    cfg = load_config(cfg_path)

    tmp = Path(tempfile.mkdtemp(prefix="pseudotwin-demo-"))
    broker = start_broker(tmp, port)
    start = hours.at(a.day, hours.init_start) - dt.timedelta(minutes=30)
    end = hours.at(a.day, hours.day_end) + dt.timedelta(minutes=1)
    print(f"2/4 broker on 127.0.0.1:{port}; daemon in replay mode from {start.isoformat()} "
          f"at {a.speed:g}×", flush=True)
    daemon = subprocess.Popen(
        [str(ROOT / ".venv" / "bin" / "pseudotwin"), "run", "--config", str(cfg_path),
         "--replay-from", start.isoformat(), "--speed", str(a.speed)],
        stdout=open(out / "daemon.log", "w"), stderr=subprocess.STDOUT,  # noqa: SIM115
    )
    msgs: queue.Queue[tuple[str, dict | str]] = queue.Queue()
    sub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="demo-viewer")
    sub.on_connect = lambda c, *_: c.subscribe([("demo/#", 1)])
    sub.on_message = lambda c, u, m: msgs.put(
        (m.topic, json.loads(m.payload) if m.payload.startswith(b"{") else m.payload.decode()))
    sub.connect("127.0.0.1", port)
    sub.loop_start()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                topic, body = msgs.get(timeout=1)
                if topic == "demo/status" and body == "online":
                    break
            except queue.Empty:
                if daemon.poll() is not None:
                    print((out / "daemon.log").read_text())
                    return 1
        print("3/4 daemon online; replaying the day's readings through the broker\n",
              flush=True)
        truth = {(s, t): v for s, t, v in zip(df["sensor"], df["ts"], df["value"], strict=True)}
        stop = threading.Event()
        th = threading.Thread(target=replay, args=(cfg, df, start, end, a.speed, stop))
        th.start()
        tz = ZoneInfo(TZ)
        print(f"{'local time':>10}  {'twin':13} {'reference':>10} {'estimate ± 2σ':>20} "
              f"{'truth':>8}  quality")
        # every estimate received, of every model: dayscore picks one per instant by content
        received: dict[str, list[dayscore.Published]] = {t: [] for t in TWINS}
        last_print: dict[str, dt.datetime] = {}
        # Drained until every model's estimate of the day's last reference reading is in (the
        # daemon's worker may lag the replay), not for a fixed time: the scores need them all.
        last = {tid: _last_reading(df, hours, ref, start, end)
                for tid, (ref, *_) in TWINS.items()}
        drain_until: float | None = None
        while True:
            if not th.is_alive():
                drain_until = drain_until or time.monotonic() + DRAIN_SECONDS
                if _complete(received, last) or time.monotonic() > drain_until:
                    break
            try:
                topic, body = msgs.get(timeout=0.5)
            except queue.Empty:
                continue
            parts = topic.split("/")
            if isinstance(body, dict) and body.get("value") is None:
                continue  # stale with no reading to hold: nothing to score or print
            if len(parts) == 4 and parts[2] == "baseline" and isinstance(body, dict) \
                    and parts[1] in received:
                received[parts[1]].append(dayscore.Published.from_payload(parts[3], body))
            if len(parts) != 3 or parts[2] != "estimate" or not isinstance(body, dict):
                continue
            tid = parts[1]
            ref, tgt, _, unit = TWINS[tid]
            received[tid].append(dayscore.Published.from_payload("estimate", body))
            ts = dt.datetime.fromisoformat(body["ts"].replace("Z", "+00:00"))
            key = pd.Timestamp(ts)
            tv = truth.get((tgt, key))
            rv = truth.get((ref, key))
            # a row every hour per twin keeps the screen readable at 900×
            if tid in last_print and ts - last_print[tid] < dt.timedelta(minutes=59):
                continue
            last_print[tid] = ts
            fmt = ".2f" if unit == "°C" else ".1f"
            est = f"{body['value']:{fmt}} ± {2 * body['std']:{fmt}} {unit}"
            print(f"{ts.astimezone(tz):%H:%M:%S}  {tid:13} "
                  f"{(format(rv, fmt) if rv is not None else '-'):>10} {est:>20} "
                  f"{(format(tv, fmt) if tv is not None else '-'):>8}  {body['quality']}",
                  flush=True)
        th.join()
        if not _complete(received, last):
            print(f"(not every estimate of the last reading arrived within {DRAIN_SECONDS} s; "
                  "the scores use those that did)")
        print("\n4/4 stopping the daemon (SIGTERM)", flush=True)
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(timeout=60)
        deadline = time.monotonic() + 5
        status = None
        while time.monotonic() < deadline:
            try:
                topic, body = msgs.get(timeout=0.5)
                if topic == "demo/status":
                    status = body
                    break
            except queue.Empty:
                pass
        print(f"daemon exit status {daemon.returncode}; demo/status = {status!r}")
        print(f"\nthe day's scores at the desk sensor's readings in operating hours ({a.day}; "
              "estimate = what <twin>/estimate published, ref:<sensor> = the raw reference):")
        for tid, (ref, tgt, _, unit) in TWINS.items():
            print(f"{tid}:")
            print(dayscore.table(_day_scores(df, hours, a.day, ref, tgt, received[tid]), unit))
        print(f"\nconfig, artifacts, daemon log and state: {out}")
        return 0 if daemon.returncode == 0 else 1
    finally:
        sub.loop_stop()
        if daemon.poll() is None:
            daemon.kill()
        broker.terminate()
        broker.wait(timeout=10)
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
