#!/usr/bin/env python3
"""Benchmark: the PLC bridge's publisher, readings in → acknowledged by a real Mosquitto,
without a spool, with a spool (``spool_fsync = false``) and with a synced spool (the default).

The readings are put on the bridge's queue directly, as its ADS notification thread does
(no PLC runs here: the bridge's supervisor keeps failing to reach one at 127.0.0.1, which
costs nothing measurable), as fast as the queue takes them; the figure is N / time until
the broker acknowledged them, and this process's CPU time over that span (publisher, paho's
network thread, the feeding loop). Fed faster than the broker acknowledges, a bridge
without a spool drops what finds ``queue_size`` readings in flight (each sensor's newest
kept); the table says how many it published. Then the broker is stopped, N more readings are
fed (each run: all kept, in paho's queue up to ``queue_size`` and on disk beyond, or only
each sensor's newest without a spool), the bridge is stopped and started again against a
broker that is back: what reached the broker in the end is counted.

Prints a table and, last, one JSON line.
Usage: .venv/bin/python scripts/bench_bridge.py [--readings 20000] [--queue-size 10000]
"""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from brokerutil import free_port, start_broker, stop_process
from pseudotwin.edge.bridge import Bridge, load_bridge_config
from pseudotwin.edge.bridge.plc import _Item
from tables import print_table

SENSORS = 10
MODES = ("no spool", "spool, no fsync", "spool, fsync")


def config_text(port: int, folder: Path, mode: str, queue_size: int) -> str:
    spool = {"no spool": "", "spool, no fsync": 'spool_dir = "spool"\nspool_fsync = false\n',
             "spool, fsync": 'spool_dir = "spool"\n'}[mode]
    text = (f'[broker]\nhost = "127.0.0.1"\nport = {port}\nclient_id = "bench-bridge"\n\n'
            f'[bridge]\nqueue_size = {queue_size}\n{spool}\n'
            '[plc]\nams_net_id = "127.0.0.1.1.1"\nhost = "127.0.0.1"\n'
            "reconnect_max_seconds = 30\n")
    for i in range(SENSORS):
        text += (f'\n[[sensors]]\nid = "s{i}"\ntopic = "bench/s{i}"\nunit = "°C"\n'
                 "min = -50\nmax = 150\n")
    for i in range(SENSORS):
        text += (f'\n[[plc.symbols]]\nsymbol = "MAIN.f{i}"\nsensor = "s{i}"\n'
                 'plc_type = "LREAL"\n')
    path = folder / f"{mode.replace(' ', '').replace(',', '-')}.toml"
    path.write_text(text, encoding="utf-8")
    return str(path)


class Counter:
    """A subscriber counting the readings the broker delivers (QoS 1)."""

    def __init__(self, port: int) -> None:
        self.n = 0
        self.lock = threading.Lock()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-bridge-sub",
                                  clean_session=False)
        self.client.on_message = self._on_message
        self.client.on_connect = lambda c, *a: c.subscribe("bench/#", qos=1)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def _on_message(self, client: Any, userdata: Any, msg: mqtt.MQTTMessage) -> None:
        with self.lock:
            self.n += 1

    def stop(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def feed(bridge: Bridge, n: int, start: dt.datetime) -> None:
    symbols = bridge.cfg.plc.symbols
    for k in range(n):
        sym = symbols[k % SENSORS]
        ts = start + dt.timedelta(milliseconds=k)
        bridge.queue.put(_Item(sym, bridge.cfg.sensor_of(sym), ts, 20.0 + (k % 97) / 10, ts,
                               "notification"))


def wait(condition: Any, timeout: float = 600.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise RuntimeError("not within the deadline")
        time.sleep(0.005)  # poll interval of a benchmark, not a timing assumption


def run(mode: str, folder: Path, n: int, queue_size: int) -> dict[str, Any]:
    port = free_port()
    broker = start_broker(folder, port, "persistence false\nmax_queued_messages 0\n")
    counter = Counter(port)
    cfg = load_bridge_config(config_text(port, folder, mode, queue_size))
    bridge = Bridge(cfg)
    try:
        bridge.start()
        wait(bridge.mqtt_connected.is_set)
        cpu0, t0 = time.process_time(), time.perf_counter()
        feed(bridge, n, dt.datetime(2026, 11, 28, tzinfo=dt.UTC))
        wait(lambda: bridge.published + bridge.dropped >= n)
        took, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        published = bridge.published
        wait(lambda: counter.n >= published)
        # The outage: the broker away while n more readings come, then the bridge restarted.
        stop_process(broker)
        wait(lambda: not bridge.mqtt_connected.is_set())
        feed(bridge, n, dt.datetime(2026, 11, 29, tzinfo=dt.UTC))
        wait(bridge.queue.empty)
        bridge.stop()
        spool_bytes = cfg.spool_path.stat().st_size \
            if cfg.spool_path is not None and cfg.spool_path.exists() else 0
        broker = start_broker(folder, port, "persistence false\nmax_queued_messages 0\n")
        counter.stop()
        counter = Counter(port)  # a fresh session: counts what the restarted bridge sends
        bridge = Bridge(cfg)
        bridge.start()
        wait(bridge.mqtt_connected.is_set)
        settle = time.monotonic() + 3.0  # what the bridge has left goes out at its start
        wait(lambda: counter.n >= n or (time.monotonic() > settle and bridge.queue.empty()))
        if cfg.spool_path is not None:
            wait(lambda: counter.n >= n)
        delivered = counter.n
    finally:
        bridge.stop()
        counter.stop()
        stop_process(broker)
    return {"mode": mode, "readings": n, "published": published, "s": took,
            "readings_per_s": published / took,
            "cpu_ms_per_reading": 1000 * cpu / n, "outage_readings": n,
            "outage_delivered": delivered, "spool_bytes_at_stop": spool_bytes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--readings", type=int, default=20_000)
    ap.add_argument("--queue-size", type=int, default=10_000)
    a = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("pseudotwin").setLevel(logging.CRITICAL)  # the PLC nobody runs
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-bridge-") as tmp:
        for mode in MODES:
            folder = Path(tmp) / mode.replace(" ", "").replace(",", "-")
            folder.mkdir()
            rows.append(run(mode, folder, a.readings, a.queue_size))
    print(f"{a.readings} readings of {SENSORS} sensors into the bridge's queue, queue_size "
          f"{a.queue_size}; then the broker stopped, {a.readings} more, the bridge restarted")
    for r in rows:
        r["spool_mb_at_stop"] = r.pop("spool_bytes_at_stop") / 1e6
    print_table("bench_bridge", rows, [
        ("mode", "mode", None), ("published", "published", None),
        ("readings/s", "readings_per_s", 0),
        ("CPU ms/reading", "cpu_ms_per_reading", 3), ("outage readings", "outage_readings", None),
        ("delivered after the restart", "outage_delivered", None),
        ("spool at stop [MB]", "spool_mb_at_stop", 2),
    ])

if __name__ == "__main__":
    main()
