#!/usr/bin/env python3
"""Benchmark: the least CPU a paho-mqtt client spends per reading, without any twin.

What the daemon does per reading, reduced to its MQTT part: a QoS 1 reading comes in
(manual ack), the reading is acknowledged and one QoS 1 estimate published (its PUBACK comes
back). Two shapes:

- ``worker``: as the daemon does it, paho's network thread queues the message and a worker
  thread acks and publishes (the guide: no model work on the network thread);
- ``network``: the ack and the publish inside ``on_message``, no second thread.

A real Mosquitto on a free port; the readings come from a separate process at --rate per
second over 1,000 topics (the rate of scripts/bench_daemon.py --twins 1000: ~200/s). The
CPU of each thread of this process is read from /proc before and after. Compare with
bench_daemon.py's ``daemon_cpu_ms_per_reading``, whose target at 1,000 twins is 0.5 ms.
Prints a table and, last, one JSON line.
Usage: .venv/bin/python scripts/bench_mqtt_floor.py [--rate 200] [--seconds 30] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import paho.mqtt
import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from brokerutil import (
    die_with_parent,
    exit_on_signals,
    free_port,
    start_broker,
    stop_process,
    thread_cpu,
)
from tables import print_table

PUBLISHER = """
import sys, time
import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
port, rate, n = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="floor-publisher")
pub.connect("127.0.0.1", port)
pub.loop_start()
t0 = time.monotonic()
for i in range(n):
    info = pub.publish(f"floor/in/{i % 1000}", b'{"value": 21.5}', qos=1)
    lag = t0 + (i + 1) / rate - time.monotonic()
    if lag > 0:
        time.sleep(lag)
info.wait_for_publish(10)
pub.loop_stop()
"""


def run(port: int, shape: str, rate: float, seconds: float) -> dict[str, Any]:
    n = int(rate * seconds)
    handled = threading.Semaphore(0)
    work: queue.Queue[tuple[int, int, bytes] | None] = queue.Queue()
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"floor-{shape}",
                         manual_ack=True)
    client.max_inflight_messages_set(0)

    def answer(mid: int, qos: int, payload: bytes) -> None:
        client.ack(mid, qos)
        client.publish("floor/out", payload, qos=1)
        handled.release()

    def on_message(c: mqtt.Client, userdata: Any, msg: mqtt.MQTTMessage) -> None:
        if shape == "network":
            answer(msg.mid, msg.qos, msg.payload)
        else:
            work.put((msg.mid, msg.qos, msg.payload))

    subscribed = threading.Event()
    network_id: list[int] = []

    def on_subscribe(c: mqtt.Client, userdata: Any, mid: int, codes: Any, props: Any) -> None:
        network_id.append(threading.get_native_id())  # paho's network thread calls it
        subscribed.set()

    client.on_message = on_message
    client.on_connect = lambda c, u, f, rc, p: c.subscribe("floor/in/#", qos=1)
    client.on_subscribe = on_subscribe
    worker_id: list[int] = []

    def worker() -> None:
        worker_id.append(threading.get_native_id())
        while (item := work.get()) is not None:
            answer(*item)

    w = threading.Thread(target=worker, daemon=True)
    w.start()
    client.connect("127.0.0.1", port)
    client.loop_start()
    try:
        if not subscribed.wait(10):
            raise SystemExit("no SUBACK from the broker")
        before = thread_cpu(os.getpid())
        subprocess.run([sys.executable, "-c", PUBLISHER, str(port), str(rate), str(n)],
                       check=True, preexec_fn=die_with_parent)
        for _ in range(n):
            if not handled.acquire(timeout=30):
                raise SystemExit(f"{shape}: a reading was not answered")
        time.sleep(0.5)  # the last PUBACKs of the estimates come back
        after = thread_cpu(os.getpid())
    finally:
        work.put(None)
        client.disconnect()
        client.loop_stop()

    def ms(tid: int) -> float:
        return (after.get(tid, 0.0) - before.get(tid, 0.0)) / n * 1e3

    net = ms(network_id[0])
    wrk = ms(worker_id[0]) if shape == "worker" else 0.0
    return {"shape": shape, "readings": n, "network_ms": net, "worker_ms": wrk,
            "total_ms": net + wrk}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rate", type=float, default=200.0, help="readings per second")
    ap.add_argument("--seconds", type=float, default=30.0, help="length of one run [s]")
    ap.add_argument("--repeat", type=int, default=3,
                    help="runs per shape; the run with the median total is reported")
    a = ap.parse_args()
    if a.rate * a.seconds < 1 or a.repeat < 1:
        ap.error("--rate × --seconds and --repeat must give at least one reading and run")
    exit_on_signals()
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        broker = start_broker(Path(tmp), port)
        try:
            runs = [run(port, shape, a.rate, a.seconds)
                    for _ in range(a.repeat) for shape in ("worker", "network")]
        finally:
            stop_process(broker)
    rows = []
    for shape in ("worker", "network"):
        # The run with the median total, whole (its columns add up), and the totals' range.
        mine = sorted((r for r in runs if r["shape"] == shape), key=lambda r: r["total_ms"])
        median = mine[(len(mine) - 1) // 2]
        rows.append({"shape": shape, "rate": a.rate, "runs": len(mine),
                     **{k: round(median[k], 3) for k in ("network_ms", "worker_ms", "total_ms")},
                     "total_ms_min": round(mine[0]["total_ms"], 3),
                     "total_ms_max": round(mine[-1]["total_ms"], 3)})
    print(f"paho-mqtt {paho.mqtt.__version__}: CPU per reading, {a.rate:g} readings/s, "
          f"{a.repeat} run(s) of {a.seconds:g} s each (the run with the median total)")
    print_table("mqtt_floor", rows, [
        ("shape", "shape", None), ("network thread [ms]", "network_ms", 3),
        ("worker [ms]", "worker_ms", 3), ("total [ms]", "total_ms", 3),
        ("total, min [ms]", "total_ms_min", 3), ("total, max [ms]", "total_ms_max", 3)])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
