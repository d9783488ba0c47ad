#!/usr/bin/env python3
"""Benchmark: a flood on one sensor — N readings published as fast as possible (issue 13).

A real Mosquitto with deploy/mosquitto.conf's back-pressure settings (max_inflight_messages
20, max_queued_messages 100000), the daemon as its own process in replay mode (clock at
2012-03-20 12:00 Europe/Madrid), one twin trained on SML2010. The flood's readings are 0.2 s
apart from 08:00 on, so every one enters the day's window.

Measured every second: readings journaled (= acknowledged: the daemon acks only journaled
readings), the daemon's throughput, its lag (publish time of the newest journaled reading to
now), peak RSS (VmHWM); at the end the time SIGTERM takes, the daemon's own "flood" reports,
and how many readings the broker acknowledged to the publisher. Stops after --max-seconds
if the daemon has not caught up (throughput falls as the window grows: the per-sensor rate
bound of the scale issue is what keeps a window small). Prints a table and, last, one JSON
line. Usage: .venv/bin/python scripts/bench_flood.py [--readings 50000] [--max-seconds 300]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from brokerutil import free_port, start_broker
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load

ROOT = Path(__file__).resolve().parent.parent
TZ = "Europe/Madrid"
DAY = dt.date(2012, 3, 20)
REF, TARGET = "dining/temp", "room/temp"
BROKER_SETTINGS = "max_inflight_messages 20\nmax_queued_messages 100000\nmax_queued_bytes 0\n"


def config_text(port: int, artifact: Path) -> str:
    return f"""
[broker]
host = "127.0.0.1"
port = {port}
client_id = "pt-flood"

[service]
base_topic = "pt"
timezone = "{TZ}"
state_dir = "state"

[[sensors]]
id = "{REF}"
topic = "house/dining/temp"
unit = "°C"
min = -10
max = 50

[[twins]]
id = "desk"
references = ["{REF}"]
quantity = "temperature"
artifact = "{artifact}"
"""


def peak_rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def journaled(state: Path) -> int:
    return sum(p.read_bytes().count(b"\n") for p in (state / "journal").glob("*.jsonl"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--readings", type=int, default=50_000)
    ap.add_argument("--max-seconds", type=float, default=300.0)
    ap.add_argument("--artifact", type=Path, help="a trained desk artifact (else trained)")
    a = ap.parse_args()
    hours = OperatingHours(timezone=TZ)
    work = Path(tempfile.mkdtemp(prefix="pt-flood-"))
    artifact = a.artifact
    if artifact is None:
        spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, hours)
        art = train_twin(load("sml2010"), spec, dt.date(2012, 3, 14), 5, primary="corrgp-triv")
        artifact = art.save(work / "desk.json")
    port = free_port()
    broker = start_broker(work, port, BROKER_SETTINGS)
    cfg = work / "config.toml"
    cfg.write_text(config_text(port, artifact))
    log = work / "daemon.log"
    env = {**os.environ, "PYTHONPATH": str(ROOT / "daemon")}
    d = subprocess.Popen([sys.executable, "-m", "pseudotwin.cli", "run", "--config", str(cfg),
                          "--replay-from", hours.at(DAY, 12.0).isoformat()],
                         stdout=open(log, "w"), stderr=subprocess.STDOUT, env=env)  # noqa: SIM115
    try:
        deadline = time.monotonic() + 60
        while "connected to" not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="flood-pub")
        pub.max_inflight_messages_set(1000)
        pub.max_queued_messages_set(0)
        pub.connect("127.0.0.1", port)
        pub.loop_start()
        start = hours.at(DAY, 8.0)
        t0 = time.monotonic()
        sent_at: list[float] = []
        infos = []
        for i in range(a.readings):
            ts = start + dt.timedelta(seconds=0.2 * i)
            body = json.dumps({"ts": ts.isoformat(), "value": 20.0 + (i % 50) / 100})
            infos.append(pub.publish("house/dining/temp", body, qos=1))
            sent_at.append(time.monotonic() - t0)
        for info in infos:
            info.wait_for_publish(60)
        publish_s = time.monotonic() - t0
        broker_acked = sum(1 for info in infos if info.is_published())
        rows = []
        last = 0
        while True:
            time.sleep(1.0)
            now = time.monotonic() - t0
            n = journaled(work / "state")
            lag = now - sent_at[n - 1] if n else float("nan")
            rows.append((now, n, n - last, lag, peak_rss_mb(d.pid)))
            last = n
            if n >= a.readings or now > a.max_seconds:
                break
            if len(rows) > 10 and all(r[2] == 0 for r in rows[-10:]):
                break  # nothing for 10 s: the rest never reached the daemon
        rss = peak_rss_mb(d.pid)
        ts0 = time.monotonic()
        d.send_signal(signal.SIGTERM)
        rc = d.wait(120)
        stop_s = time.monotonic() - ts0
        pub.disconnect()
        pub.loop_stop()
    finally:
        if d.poll() is None:
            d.kill()
        broker.terminate()
        broker.wait(10)
    text = log.read_text()
    floods = text.count("flood: behind")
    n = rows[-1][1]
    print(f"{'t [s]':>7} {'journaled':>10} {'per s':>7} {'lag [s]':>8} {'RSS [MB]':>9}")
    for i, (t, k, dk, lag, r) in enumerate(rows):
        if i % max(1, len(rows) // 25) == 0 or i == len(rows) - 1:
            print(f"{t:7.1f} {k:10d} {dk:7d} {lag:8.1f} {r:9.0f}")
    first = [r[2] for r in rows[:10]]
    tail = [r[2] for r in rows[-10:]]
    out = {
        "readings_sent": a.readings,
        "broker_acknowledged_to_publisher": broker_acked,
        "publish_seconds": round(publish_s, 1),
        "journaled_and_acknowledged": n,
        "not_yet_processed_at_stop": a.readings - n,
        "seconds": round(rows[-1][0], 1),
        "throughput_first_10s_per_s": round(sum(first) / max(1, len(first)), 1),
        "throughput_last_10s_per_s": round(sum(tail) / max(1, len(tail)), 1),
        "lag_at_end_s": round(rows[-1][3], 1),
        "peak_rss_mb": round(rss, 0),
        "sigterm_seconds": round(stop_s, 2),
        "exit_status": rc,
        "flood_reports_in_log": floods,
    }
    for k, v in out.items():
        print(f"{k:36} {v}")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
