#!/usr/bin/env python3
"""Benchmark: the daemon with 100 twins fed 5-minute COV readings at 60× replay speed.

Each twin has its own reference sensor and artifact (copies of one twin trained on SML2010,
dining room → bedroom, with the sensor names changed). Readings come from the real day
2012-03-20 of SML2010, interpolated to 5 minutes and offset per room (a few seconds apart,
as independent sensors report), published through a real Mosquitto broker while the daemon
runs as its own process in replay mode at the same speed.

Measured: end-to-end latency from a reading's publish to the arrival of the estimate it
caused (median, p99); the part of it spent in the daemon, from its metrics endpoint (the
``pseudotwin_reading_to_estimate_seconds`` histogram: mean, share within 100 ms, the
bucket bounding the p99), which tells the daemon's delays from those of the broker and of
this measuring process on the same two cores; the daemon's CPU time (per reading and as a
share of one core; per reading = the daemon's CPU from "online" to the last estimate / the
readings published) and its peak RSS (VmHWM). The CPU is also split by thread, largest
first: the worker (models, payloads, publish calls), then paho's network thread (reading the
broker's messages and PUBACKs, writing ours). Next to it, the CPU of Mosquitto and of this
measuring process over the same time (the cores they share). From the daemon's log while the
readings went in: its full garbage collections longer than 100 ms (pseudotwin/core/heap.py),
its worker batches that held the readings behind them longer than 0.5 s (edge/service.py:
their wall time, the worker's CPU in it and their journal writes, so a stall tells a
blocked worker from a busy one) and its other warnings, counted by kind. Prints a table
and, last, one JSON line.

``--profile FILE`` also samples the running daemon with py-spy (``pip install -e
'.[profile]'``; non-blocking, 100 Hz, idle samples left out) while the readings go in, keeps
py-spy's raw stacks in FILE and prints, for each busy thread, the functions its CPU went to
(inclusive, in ms per reading: the thread's share of samples in the function × the thread's
measured CPU). Sampling costs the daemon a little CPU: compare figures of runs without it.
``--no-journal-fsync`` runs the daemon with ``journal_fsync = false`` (readings acknowledged
once their journal lines are in the kernel, not on disk): the cost of the default's fsync.
Usage: .venv/bin/python scripts/bench_daemon.py [--twins 100] [--hours 2] [--speed 60]
       [--baselines grid|reading|none] [--artifact FILE] [--profile FILE]
       [--no-journal-fsync]
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import gc
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from prometheus_client.parser import text_string_to_metric_families

import pseudotwin  # noqa: F401
from brokerutil import (
    die_with_parent,
    exit_on_signals,
    free_port,
    proc_stats,
    start_broker,
    stop_process,
    thread_cpu,
)
from pseudotwin.analysis.training import train_twin
from pseudotwin.config.model import BASELINE_CADENCES
from pseudotwin.core.heap import LONG_PAUSE_PATTERN, LONG_PAUSE_S
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.prometheus import LATENCY_BUCKETS
from pseudotwin.edge.service import LONG_BATCH_PATTERN, LONG_BATCH_S
from pseudotwin.history.convert import load

ROOT = Path(__file__).resolve().parent.parent
TZ = "Europe/Madrid"
DAY = dt.date(2012, 3, 20)
REF, TARGET = "dining/temp", "room/temp"


def relabel(obj, mapping: dict[str, str]):
    """The artifact with its sensor names replaced (keys and values)."""
    if isinstance(obj, dict):
        return {mapping.get(k, k): relabel(v, mapping) for k, v in obj.items()}
    if isinstance(obj, list):
        return [relabel(v, mapping) for v in obj]
    return mapping.get(obj, obj) if isinstance(obj, str) else obj


def daemon_latency(port: int) -> dict[str, float | None]:
    """The daemon's own view of its latency, scraped from its metrics endpoint: the
    ``pseudotwin_reading_to_estimate_seconds`` histogram (arrival on its network thread →
    estimates handed to paho). Its buckets bound the p99 from above; the share within
    100 ms is exact. Set against the end-to-end figures it tells the daemon's delays from
    those of the broker and of this measuring process, which share the two cores.
    ``p99_at_most_ms`` is None when the p99 lies beyond the last finite bucket (JSON has no
    infinity)."""
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read()
    buckets: dict[float, float] = {}
    total = count = 0.0
    for family in text_string_to_metric_families(text.decode()):
        if family.name != "pseudotwin_reading_to_estimate_seconds":
            continue
        for s in family.samples:
            if s.name.endswith("_bucket"):
                buckets[float(s.labels["le"])] = s.value
            elif s.name.endswith("_sum"):
                total = s.value
            elif s.name.endswith("_count"):
                count = s.value
    if not count:
        return {"count": 0}
    p99 = min(le for le, c in buckets.items() if c >= 0.99 * count)
    return {"count": int(count), "mean_ms": round(1e3 * total / count, 2),
            "within_100ms_pct": round(100 * buckets[0.1] / count, 2),  # a bucket's bound
            "p99_at_most_ms": round(1e3 * p99, 1) if p99 != float("inf") else None}


def start_profiler(pid: int, out: Path) -> subprocess.Popen[bytes]:
    """py-spy recording ``pid``'s threads into ``out`` (raw stacks) until SIGINT."""
    exe = shutil.which("py-spy") or str(ROOT / ".venv" / "bin" / "py-spy")
    if not Path(exe).exists():
        raise SystemExit("--profile needs py-spy: .venv/bin/pip install -e '.[profile]'")
    return subprocess.Popen(
        [exe, "record", "--pid", str(pid), "--threads", "--nonblocking", "--rate", "100",
         "--format", "raw", "--output", str(out)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)


def profile_table(raw: Path, cpu_by_tid: dict[int, float], readings: int, top: int = 15
                  ) -> dict[str, list[tuple[str, float]]]:
    """Per thread (by name, busiest first): its ``top`` functions by inclusive CPU [ms per
    reading], from py-spy's raw stacks (``thread (tid): name;frame;…;frame count``) and the
    thread's measured CPU. Frames in ≥ 90 % of a thread's samples (its run loop) say nothing
    about where the time goes and are left out. py-spy counts a thread inside a system call
    (socket I/O, select) as idle: for paho's network thread the functions seen are only the
    Python part of its CPU."""
    samples: dict[int, int] = {}
    names: dict[int, str] = {}
    incl: dict[int, dict[str, int]] = {}
    for line in raw.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        head, *frames = stack.split(";")
        tid_text, _, name = head.removeprefix("thread (").partition("): ")
        tid, n = int(tid_text.rstrip(")"), 0), int(count)
        names[tid] = name or str(tid)
        samples[tid] = samples.get(tid, 0) + n
        seen = incl.setdefault(tid, {})
        # "Twin.estimate (pseudotwin/live/twin.py:373)" → per function, not per line
        for f in {f.rsplit(":", 1)[0] + ")" if f.endswith(")") else f for f in frames}:
            seen[f] = seen.get(f, 0) + n
    out = {}
    for tid in sorted(samples, key=lambda t: -cpu_by_tid.get(t, 0.0)):
        ms = 1e3 * cpu_by_tid.get(tid, 0.0) / readings
        if ms < 0.01:
            continue
        rows = [(f, round(ms * c / samples[tid], 3)) for f, c in incl[tid].items()
                if c < 0.9 * samples[tid]]
        key = f"{names[tid]} ({ms:.3f} ms, {samples[tid]} samples)"
        out[key] = sorted(rows, key=lambda r: -r[1])[:top]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--twins", type=int, default=100)
    ap.add_argument("--hours", type=float, default=2.0, help="day time to replay from 08:00")
    ap.add_argument("--speed", type=float, default=60.0)
    ap.add_argument("--baselines", choices=BASELINE_CADENCES, default="grid",
                    help="the daemon's [service] baselines (none: the twins run their primary "
                         "model only)")
    ap.add_argument("--artifact", type=Path, default=None,
                    help="the trained twin to copy: read from this file if it exists, else "
                         "trained (≈ 1 min) and written there, so that reruns skip training")
    ap.add_argument("--profile", type=Path, default=None, metavar="FILE",
                    help="sample the daemon with py-spy while the readings go in, keep the "
                         "raw stacks in FILE and print where each thread's CPU went")
    ap.add_argument("--no-journal-fsync", dest="journal_fsync", action="store_false",
                    help="the daemon's [service] journal_fsync = false")
    a = ap.parse_args()
    exit_on_signals()
    hours = OperatingHours(timezone=TZ)
    tmp = Path(tempfile.mkdtemp(prefix="pseudotwin-bench-"))
    # Unwound last to first on every way out (error, Ctrl-C, SIGTERM): clients, daemon,
    # broker, then the folder. Nothing started here outlives the run.
    cleanup = contextlib.ExitStack()
    cleanup.callback(shutil.rmtree, tmp, ignore_errors=True)
    try:
        df = load("sml2010")
        spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, hours)
        if a.artifact is not None and a.artifact.exists():
            base = json.loads(a.artifact.read_text())
        else:
            art = train_twin(df, spec, dt.date(2012, 3, 14), 5)
            base = json.loads(json.dumps(art.to_dict(), allow_nan=True))
            if a.artifact is not None:
                a.artifact.write_text(json.dumps(base))
        (tmp / "artifacts").mkdir()
        sensors, twins = [], []
        for i in range(a.twins):
            ref, tgt = f"room{i:03d}/wall/temp", f"room{i:03d}/desk/temp"
            d = relabel(base, {REF: ref, TARGET: tgt})
            (tmp / "artifacts" / f"t{i:03d}.json").write_text(json.dumps(d))
            sensors.append(f'[[sensors]]\nid = "{ref}"\ntopic = "b/{ref}"\nunit = "°C"\n'
                           f"min = -10\nmax = 50\n")
            twins.append(f'[[twins]]\nid = "t{i:03d}"\nreferences = ["{ref}"]\n'
                         f'quantity = "temperature"\nartifact = "artifacts/t{i:03d}.json"\n')
        port = metrics_port = free_port()
        while metrics_port == port:  # the OS may hand out the port it just gave back
            metrics_port = free_port()
        (tmp / "config.toml").write_text(
            f'[broker]\nhost = "127.0.0.1"\nport = {port}\nclient_id = "bench"\n\n'
            f'[service]\nbase_topic = "pt"\ntimezone = "{TZ}"\nstate_dir = "state"\n'
            f"stale_after_minutes = 30\nlog_level = \"WARNING\"\n"
            f"baselines = \"{a.baselines}\"\n"
            f"journal_fsync = {str(a.journal_fsync).lower()}\n\n"
            f"[metrics]\nport = {metrics_port}\n\n"
            + "\n".join(sensors) + "\n" + "\n".join(twins))
        broker = start_broker(tmp, port, "max_queued_messages 100000\n")
        cleanup.callback(stop_process, broker)

        # 5-minute readings of the real day, interpolated, per room offset by a few seconds
        day = df[(df["sensor"] == REF) & (df["ts"] >= hours.at(DAY, 0.0))
                 & (df["ts"] < hours.at(DAY, 23.9))]
        t0 = hours.at(DAY, 7.5)
        n_steps = int((a.hours + 0.5) * 12)
        grid = [t0 + dt.timedelta(minutes=5 * k) for k in range(n_steps)]
        src_t = day["ts"].astype("int64").to_numpy() / 1e9
        vals = np.interp([g.timestamp() for g in grid], src_t, day["value"].to_numpy())
        events = sorted(
            (g + dt.timedelta(seconds=(7 * i) % 290), i, float(v) + 0.01 * (i % 7))
            for k, (g, v) in enumerate(zip(grid, vals, strict=True)) for i in range(a.twins)
        )

        # The measuring process's own full collections (training's GPy and pandas objects,
        # 100,000s of events) would delay the arrival times it records: out of their way.
        gc.collect()
        gc.freeze()
        start = t0 - dt.timedelta(minutes=1)
        launched = time.monotonic()
        daemon = subprocess.Popen(
            [str(ROOT / ".venv" / "bin" / "pseudotwin"), "run", "--config",
             str(tmp / "config.toml"), "--replay-from", start.isoformat(),
             "--speed", str(a.speed)],
            stdout=open(tmp / "daemon.log", "w"), stderr=subprocess.STDOUT,  # noqa: SIM115
            preexec_fn=die_with_parent)
        cleanup.callback(stop_process, daemon, signal.SIGTERM, 60)
        sent: dict[tuple[int, str], tuple[float, float]] = {}  # → (monotonic, day hour)
        lat: list[float] = []
        lat_hour: list[float] = []  # the day hour [h] of each latency's reading
        lock = threading.Lock()
        online = threading.Event()

        counts = dict.fromkeys(("estimate", "baseline", "monitor"), 0)

        def on_message(c, u, m) -> None:
            now = time.monotonic()
            if m.topic == "pt/status":
                if m.payload == b"online":
                    online.set()
                return
            kind = m.topic.split("/")[2]
            counts[kind] += 1
            if kind != "estimate":
                return
            body = json.loads(m.payload)
            i = int(m.topic.split("/")[1][1:])
            with lock:
                t = sent.pop((i, body["ts"]), None)
                if t is not None:
                    lat.append(now - t[0])
                    lat_hour.append(t[1])

        sub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-sub")
        sub.on_connect = lambda c, *_: c.subscribe([("pt/+/estimate", 1), ("pt/status", 1),
                                                    ("pt/+/baseline/+", 0), ("pt/+/monitor", 0)])
        sub.on_message = on_message
        sub.connect("127.0.0.1", port)
        sub.loop_start()
        cleanup.callback(sub.loop_stop)
        # Loading a twin's artifact takes a few ms: 10,000 of them, more than two minutes.
        patience = 120 + 0.05 * a.twins
        if not online.wait(patience):
            print(f"the daemon did not come online within {patience:.0f} s (still loading its "
                  f"{a.twins} twins?); its log:\n{(tmp / 'daemon.log').read_text()}",
                  file=sys.stderr)
            return 1
        startup = time.monotonic() - launched
        profiler = None
        if a.profile is not None:
            profiler = start_profiler(daemon.pid, a.profile)
            cleanup.callback(stop_process, profiler, signal.SIGINT, 60)
        pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-pub")
        pub.max_queued_messages_set(0)
        pub.connect("127.0.0.1", port)
        pub.loop_start()
        cleanup.callback(pub.loop_stop)
        clock = ReplayClock(start, a.speed)
        stop = threading.Event()
        cpu0, _ = proc_stats(daemon.pid)
        # The other processes on the same cores: are the daemon's delays its own?
        broker_cpu0, own_cpu0 = proc_stats(broker.pid)[0], time.process_time()
        counted0 = dict(counts)
        threads0 = thread_cpu(daemon.pid)
        log_from = (tmp / "daemon.log").stat().st_size  # what it logs from now on
        wall0 = time.monotonic()
        published = in_hours = 0
        for ts, i, v in events:
            clock.wait_until(ts, stop)
            key = (i, ts.astimezone(dt.UTC).isoformat().replace("+00:00", "Z"))
            if (day_hour := hours.hours_of(ts)) >= hours.day_start:
                with lock:
                    sent[key] = (time.monotonic(), day_hour)
                in_hours += 1
            pub.publish(f"b/room{i:03d}/wall/temp",
                        json.dumps({"ts": ts.isoformat(), "value": round(v, 3)}), qos=1)
            published += 1
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and len(lat) < in_hours:
            time.sleep(0.1)
        wall = time.monotonic() - wall0
        cpu1, hwm = proc_stats(daemon.pid)
        broker_cpu, own_cpu = proc_stats(broker.pid)[0] - broker_cpu0, \
            time.process_time() - own_cpu0
        # The daemon's MQTT packets per reading: in, each reading and the PUBACK of each
        # QoS 1 message it sent (estimates); out, the reading's PUBACK and its messages.
        out = {k: round((counts[k] - counted0[k]) / published, 3) for k in counts}
        threads1 = thread_cpu(daemon.pid)
        with open(tmp / "daemon.log", "rb") as f:  # its log while the readings went in
            f.seek(log_from)
            log_text = f.read(max((tmp / "daemon.log").stat().st_size - log_from, 0)).decode(
                errors="replace")
        in_daemon = daemon_latency(metrics_port)
        cpu_by_tid = {t: c - threads0.get(t, 0.0) for t, c in threads1.items()}
        by_thread = sorted((round(c, 2) for c in cpu_by_tid.values()), reverse=True)
        # SIGINT: py-spy writes its file and exits (before the daemon goes: its pid)
        stop_process(profiler, signal.SIGINT, 60)
        stop_process(daemon, signal.SIGTERM, 60)  # before the figures: its exit status
        ms = np.array(lat) * 1e3
        # The daemon logs each full garbage collection that held it > LONG_PAUSE_S (heap.py).
        gc_logged = re.findall(LONG_PAUSE_PATTERN, log_text)
        # Everything else the daemon warned about while the readings went in (reconnects,
        # a full queue, ...): the message of each kind, digits blanked, with its count.
        warned: dict[str, int] = {}
        for m in re.finditer(r" (WARNING|ERROR) (.*)", log_text):
            if not re.search(f"{LONG_PAUSE_PATTERN}|{LONG_BATCH_PATTERN}", m.group(2)):
                kind = re.sub(r"\d+(\.\d+)?", "#", m.group(2).strip())[:120]
                warned[kind] = warned.get(kind, 0) + 1
        gc_pauses = [float(pause) for pause, _ in gc_logged]
        # ... and each worker batch that held the readings behind it > LONG_BATCH_S, with
        # its own CPU and its journal write (edge/service.py): blocked or computing?
        long_batches = np.array(re.findall(LONG_BATCH_PATTERN, log_text), dtype=float
                                ).reshape(-1, 3)
        fig = {
            "twins": a.twins, "speed": a.speed, "day_hours": a.hours,
            "baselines": a.baselines, "journal_fsync": a.journal_fsync,
            "readings_published": published, "estimates_matched": len(lat),
            "estimates_expected": in_hours,
            "latency_median_ms": round(float(np.median(ms)), 2),
            "latency_p99_ms": round(float(np.percentile(ms, 99)), 2),
            "latency_max_ms": round(float(ms.max()), 2),
            "readings_per_s": round(published / wall, 1),
            "daemon_cpu_s": round(cpu1 - cpu0, 2),
            "daemon_cpu_share_of_core": round((cpu1 - cpu0) / wall, 3),
            "daemon_cpu_ms_per_reading": round(1e3 * (cpu1 - cpu0) / published, 3),
            "daemon_peak_rss_mb": round(hwm / 1024, 1),
            "daemon_cpu_threads_s": [c for c in by_thread if c > 0],
            "broker_cpu_share_of_core": round(broker_cpu / wall, 3),
            "bench_cpu_share_of_core": round(own_cpu / wall, 3),
            "daemon_exit": daemon.returncode,
            "daemon_startup_s": round(startup, 1),
            "daemon_reading_to_estimate": in_daemon,
            "daemon_gc_long_pauses": len(gc_pauses),
            "daemon_gc_longest_pause_ms": max(gc_pauses, default=None),
            "daemon_warnings": warned,
            "daemon_gc_most_tracked_objects": max((int(n) for _, n in gc_logged), default=None),
            "daemon_long_batches": len(long_batches),
            "daemon_long_batches_ms": {k: round(float(v), 1) for k, v in zip(
                ("wall", "worker_cpu", "journal"), long_batches.sum(axis=0), strict=True)},
            "daemon_longest_batch_ms": (round(float(long_batches[:, 0].max()), 1)
                                        if len(long_batches) else None),
            "messages_out_per_reading": out,
            "packets_per_reading": {"in": round(1 + out["estimate"], 3),
                                    "out": round(1 + sum(out.values()), 3)},
        }
        print(f"{a.twins} twins, 5-min COV readings at {a.speed:g}×, {a.hours:g} h of day time "
              f"({published} readings in {wall:.0f} s, {fig['readings_per_s']}/s), "
              f"baselines {a.baselines!r}, journal_fsync {str(a.journal_fsync).lower()}")
        print(f"  reading → estimate latency: median {fig['latency_median_ms']} ms, "
              f"p99 {fig['latency_p99_ms']} ms, max {fig['latency_max_ms']} ms "
              f"({len(lat)} of {in_hours} estimates matched)")
        if in_daemon.get("count"):
            p99 = in_daemon["p99_at_most_ms"]
            p99_text = (f"p99 ≤ {p99:g} ms" if p99 is not None
                        else f"p99 above {1e3 * max(LATENCY_BUCKETS):g} ms")
            print(f"  in the daemon (arrival → handed to paho; its histogram, "
                  f"{in_daemon['count']} readings): mean {in_daemon['mean_ms']} ms, "
                  f"{in_daemon['within_100ms_pct']} % within 100 ms, {p99_text}")
        if a.hours >= 2:  # where in the day the slow estimates were
            by_hour = np.floor(np.array(lat_hour))
            fig["latency_by_hour_ms"] = {
                f"{h:02.0f}": [round(float(np.percentile(ms[by_hour == h], q)), 1)
                               for q in (50, 99, 100)]
                for h in np.unique(by_hour)}
            print("  latency by hour of the day [ms] (median, p99, max): " + ", ".join(
                f"{h}h {v[0]:g}/{v[1]:g}/{v[2]:g}" for h, v in fig["latency_by_hour_ms"].items()))
        print(f"  daemon CPU: {fig['daemon_cpu_s']} s = {fig['daemon_cpu_share_of_core']:.1%} "
              f"of one core, {fig['daemon_cpu_ms_per_reading']} ms per reading; "
              f"peak RSS {fig['daemon_peak_rss_mb']} MB; online {fig['daemon_startup_s']} s "
              "after its start")
        print(f"  the other processes on the {len(os.sched_getaffinity(0))} cores: Mosquitto "
              f"{fig['broker_cpu_share_of_core']:.1%} of one core, this measuring process "
              f"{fig['bench_cpu_share_of_core']:.1%}")
        print(f"  MQTT packets per reading: in {fig['packets_per_reading']['in']} (the reading, "
              f"PUBACKs of estimates), out {fig['packets_per_reading']['out']} (its PUBACK, "
              + ", ".join(f"{k} {v}" for k, v in out.items()) + ")")
        print(f"  full garbage collections holding the daemon > {LONG_PAUSE_S * 1e3:g} ms: "
              f"{len(gc_pauses)}"
              + (f", the longest {max(gc_pauses):g} ms, up to "
                 f"{fig['daemon_gc_most_tracked_objects']} tracked objects left"
                 if gc_pauses else ""))
        print(f"  worker batches holding the readings > {LONG_BATCH_S * 1e3:g} ms: "
              f"{len(long_batches)}"
              + (f", the longest {fig['daemon_longest_batch_ms']:g} ms; together "
                 f"{fig['daemon_long_batches_ms']['wall']:g} ms, of it the worker's CPU "
                 f"{fig['daemon_long_batches_ms']['worker_cpu']:g} ms and its journal writes "
                 f"{fig['daemon_long_batches_ms']['journal']:g} ms" if len(long_batches) else ""))
        for kind, n in sorted(warned.items(), key=lambda kv: -kv[1])[:5]:
            print(f"  the daemon warned {n}×: {kind}")
        print(f"  daemon CPU by thread [s], largest first (worker, network): "
              f"{', '.join(map(str, fig['daemon_cpu_threads_s']))}")
        if a.profile is not None:
            fig["profile_ms_per_reading"] = profile_table(a.profile, cpu_by_tid, published)
            print("  where each thread's CPU went (py-spy, inclusive) [ms per reading]:")
            for thread, rows in fig["profile_ms_per_reading"].items():
                print(f"    {thread}")
                for func, ms in rows:
                    print(f"      {ms:>7.3f}  {func}")
        print(json.dumps(fig))
        return 0
    finally:
        cleanup.close()


if __name__ == "__main__":
    sys.exit(main())
