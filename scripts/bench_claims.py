"""What the twins' claims (edge/ownership.py) cost a fleet: message size, the claim's encoding
on the worker, and its handling on the MQTT network thread, where no reading can be read
meanwhile, for daemons of N twins.

Per N: the size of one claim and the parts it goes in (at most CLAIM_BYTES each); the time
to encode it (at connect and hourly, on the worker); the time ``Ownership.heard`` takes for
all parts of the four claims a daemon hears (its own echo, a fleet peer's claim of other
twins, a second daemon claiming all of its twins, answered with a claim of as many, and that
daemon's answer, which reports it and counts every twin in the other-publishers gauge), and
the longest one part holds the network thread; and, through a real Mosquitto on a free port,
the time from publishing a claim's parts to the last one's arrival at a subscriber of
``<base>/claims`` (median of the round trips, the broker and both clients on this host). Not
part of the test suite. Prints a table and, last, one JSON line.

    .venv/bin/python scripts/bench_claims.py [--twins 1000,10000,100000] [--repeat 20]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import statistics
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

sys.path.insert(0, str(Path(__file__).resolve().parent))
from brokerutil import exit_on_signals, free_port, start_broker, stop_process  # noqa: E402
from pseudotwin.edge.ownership import Claim, Ownership  # noqa: E402

TOPIC = "pseudotwin/claims"


def median_ms(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1000


def daemon(client_id: str, twins: list[str]) -> Ownership:
    o = Ownership(client_id, "bench-host", 4242, twins)
    o.start(dt.datetime.now(dt.UTC))
    return o


def heard_ms(n: int, repeat: int) -> dict[str, float]:
    """Median ms of what the network thread does with all parts of a claim on the daemon with
    twins 0..n-1 (``Ownership.heard``, and the other-publishers gauge's counts of the twins a
    part names once their sender is reported, as edge/service.py does), per kind of claim,
    and the longest part of them (``longest_part``)."""
    twins = [f"site/room{i:06d}-desk" for i in range(n)]
    peer_twins = [f"site/room{i:06d}-desk" for i in range(n, 2 * n)]
    ours = daemon("pseudotwin-1", twins)
    echo = ours.claim()
    peer = daemon("pseudotwin-2", peer_twins).claim()
    second = daemon("pseudotwin-dup", twins)
    longest = 0.0

    def hear(o: Ownership, parts: list[bytes]) -> None:
        nonlocal longest
        for p in parts:
            t0 = time.perf_counter()
            h = o.heard(p)
            if h.counted:
                o.publishers(h.counted)
            longest = max(longest, time.perf_counter() - t0)

    def answered(o: Ownership) -> list[bytes]:  # the second owner's answer to ``o``'s claim
        assert o.run is not None and second.run is not None
        return Claim(second.run, "bench-host", 4243, frozenset(twins), o.run).payloads()

    # a new first daemon each time: its first hearing answers, or reports
    fresh = [daemon("pseudotwin-1", twins) for _ in range(2 * repeat)]
    pairs = [(o, answered(o)) for o in fresh[repeat:]]
    claimed = second.claim()
    out = {"echo": median_ms(lambda: hear(ours, echo), repeat),
           "peer": median_ms(lambda: hear(ours, peer), repeat),
           "duplicate": median_ms(lambda: hear(fresh.pop(), claimed), repeat),
           "reported": median_ms(lambda: hear(*pairs.pop()), repeat)}
    out["longest_part"] = longest * 1000
    return out


def round_trip_ms(port: int, parts: list[bytes], repeat: int) -> float:
    """Median ms from publishing ``parts`` (QoS 1) to the last one's arrival at another
    client, through the broker."""
    arrived = threading.Event()
    ready = threading.Event()
    got = [0]

    def on_message(c: mqtt.Client, userdata: object, msg: mqtt.MQTTMessage) -> None:
        got[0] += 1
        if got[0] == len(parts):
            arrived.set()


    def on_connect(c: mqtt.Client, userdata: object, flags: object, rc: object,
                   props: object) -> None:
        c.subscribe(TOPIC, qos=1)

    def on_subscribe(*args: object) -> None:
        ready.set()

    sub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-sub")
    sub.on_connect = on_connect
    sub.on_subscribe = on_subscribe
    sub.on_message = on_message
    pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-pub")
    sub.connect("127.0.0.1", port)
    pub.connect("127.0.0.1", port)
    sub.loop_start()
    pub.loop_start()
    try:
        if not ready.wait(10):
            raise SystemExit("the subscriber was not subscribed within 10 s")
        times = []
        for _ in range(repeat):
            arrived.clear()
            got[0] = 0
            t0 = time.perf_counter()
            for p in parts:
                pub.publish(TOPIC, p, qos=1)
            if not arrived.wait(30):
                raise SystemExit("a claim did not arrive within 30 s")
            times.append(time.perf_counter() - t0)
        return statistics.median(times) * 1000
    finally:
        for c in (sub, pub):
            c.disconnect()
            c.loop_stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twins", default="1000,10000,100000",
                    help="comma-separated twin counts (default 1000,10000,100000)")
    ap.add_argument("--repeat", type=int, default=20, help="timed repetitions (median taken)")
    a = ap.parse_args()
    counts = [int(x) for x in a.twins.split(",")]
    exit_on_signals()
    rows: list[dict[str, Any]] = []
    with TemporaryDirectory() as tmp:
        port = free_port()
        broker = start_broker(Path(tmp), port)
        try:
            for n in counts:
                o = daemon("pseudotwin-1", [f"site/room{i:06d}-desk" for i in range(n)])
                parts = o.claim()
                rows.append({"twins": n, "claim_bytes": sum(len(p) for p in parts),
                             "parts": len(parts),
                             "largest_part_bytes": max(len(p) for p in parts),
                             "encode_ms": median_ms(o.claim, a.repeat),
                             "heard_ms": heard_ms(n, a.repeat),
                             "round_trip_ms": round_trip_ms(port, parts, a.repeat)})
        finally:
            stop_process(broker)
    print(f"claims (edge/ownership.py), median of {a.repeat}, all parts of a claim; heard() "
          "runs on the network thread; twin ids like 'site/room000123-desk'")
    print("| twins | claim [kB] | parts | largest part [kB] | encode [ms] | heard: echo [ms] | "
          "heard: fleet peer [ms] | heard: second owner, answered [ms] | heard: its answer, "
          "reported and counted [ms] | longest part [ms] | broker round trip [ms] |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        h = r["heard_ms"]
        print(f"| {r['twins']} | {r['claim_bytes'] / 1000:.1f} | {r['parts']} | "
              f"{r['largest_part_bytes'] / 1000:.1f} | {r['encode_ms']:.2f} | "
              f"{h['echo']:.2f} | {h['peer']:.2f} | {h['duplicate']:.2f} | "
              f"{h['reported']:.2f} | {h['longest_part']:.2f} | {r['round_trip_ms']:.2f} |")
    print(json.dumps({"bench_claims": rows}))


if __name__ == "__main__":
    main()
