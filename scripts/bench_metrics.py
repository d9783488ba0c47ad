"""Scrape time of the daemon's Prometheus endpoint with many twins (issue 12's figure).

Builds the daemon's metric set (edge/prometheus.py) for N twins with two reference sensors
each, fills every series as a day of operation would, serves it with the same HTTP server
the daemon uses and times real scrapes over HTTP (urllib) and the parse of the body. No
models run: the endpoint's cost depends only on the number of series. Not part of the test
suite. Prints the figures and, last, one JSON line.

    .venv/bin/python scripts/bench_metrics.py [--twins 1000] [--scrapes 20]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import socket
import statistics
import time
import urllib.request
from pathlib import Path
from tempfile import TemporaryDirectory

from prometheus_client.parser import text_string_to_metric_families

from pseudotwin.edge.prometheus import DaemonMetrics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twins", type=int, default=1000)
    ap.add_argument("--scrapes", type=int, default=20)
    a = ap.parse_args()
    twins = [f"room{i}-desk" for i in range(a.twins)]
    sensors = [f"room{i}/{s}" for i in range(a.twins) for s in ("hmi/temp", "ceiling/temp")]
    t0 = time.perf_counter()
    m = DaemonMetrics(sensors, twins)
    with TemporaryDirectory() as tmp:
        m.watch(queue_size=lambda: 0, queue_bound=10000, connected=lambda: True,
                journal_dir=Path(tmp), journal_healthy=lambda: True,
                fallbacks=lambda: dict.fromkeys(twins, 0))
        build = time.perf_counter() - t0
        now = dt.datetime.now(dt.UTC)
        for s in sensors:
            m.accepted.labels(s).inc(600)
            m.rejected_one(s, "out-of-range")
        for t in twins:
            for _ in range(3):
                m.published(t, "ok", now)
        for _ in range(1000):
            m.latency.observe(0.004)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        server = m.serve("127.0.0.1", port, "bench")
        times, body = [], b""
        try:
            for _ in range(a.scrapes):
                t1 = time.perf_counter()
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics") as resp:
                    body = resp.read()
                times.append(time.perf_counter() - t1)
        finally:
            server.close()
    t2 = time.perf_counter()
    series = sum(len(f.samples) for f in text_string_to_metric_families(body.decode()))
    parse = time.perf_counter() - t2
    print(f"twins {a.twins}, sensors {len(sensors)}: {series} samples, "
          f"{len(body) / 1e6:.2f} MB per scrape (uncompressed)")
    print(f"build the metric set: {build * 1e3:.0f} ms")
    print(f"scrape over HTTP ({a.scrapes}×): median {statistics.median(times) * 1e3:.0f} ms, "
          f"max {max(times) * 1e3:.0f} ms")
    print(f"parse with prometheus_client.parser: {parse * 1e3:.0f} ms")
    print(json.dumps({"twins": a.twins, "sensors": len(sensors), "samples": series,
                      "scrape_bytes": len(body), "build_ms": round(build * 1e3, 1),
                      "scrape_median_ms": round(statistics.median(times) * 1e3, 1),
                      "scrape_max_ms": round(max(times) * 1e3, 1),
                      "parse_ms": round(parse * 1e3, 1)}))


if __name__ == "__main__":
    main()
