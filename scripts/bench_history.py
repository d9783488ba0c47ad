#!/usr/bin/env python3
"""Benchmark: backfill throughput and the recorder's sustained write rate, into SQLite.

Backfill: one twin (trained on SML2010, dining room → bedroom) over 7 months of 1-minute
reference readings. The readings are the Appliances house's ironing-room temperature (real,
10-minute, Jan–May 2016) interpolated to one minute and continued cyclically to fill seven
months (2016-01-12 … 2016-08-11). ``pseudotwin backfill`` runs as its own process, started
by a small launcher process that reports its child's peak RSS: the backfill's alone (read
in this process, a forked child's peak starts at the memory it copies from this one, which
holds the training data and the readings: 254 MB at c34db46 where the backfill's own peak
was about 158 MB). Three runs, each into a fresh
copy of the readings-only store: one twin with ``--jobs 1`` (in one process), the same twin
with ``--jobs J`` (default: the CPUs), and N twins (default 8, copies of the artifact under
other twin ids, all on the same reference sensor) with ``--jobs J``. The rows of the
parallel one-twin run are checked to equal the serial ones. CPU seconds (user + system of
the backfill and its workers) are reported too: on a machine shared with other work, wall
time alone says little.

Recorder: ``pseudotwin record`` as its own process against a real Mosquitto; a publisher
sends N readings (QoS 1) as fast as the broker takes them; the figure is N / time until all
N are in the store (count in = count stored is checked). Twice: with ``journal_fsync = true``
(the default: every commit synced) and with false.

Prints a table and, last, one JSON line.
Every process it starts (broker, recorder, backfills) is stopped on the way out, also on
Ctrl-C, SIGTERM or an error; check with ``pgrep -a mosquitto`` before and after.
Usage: .venv/bin/python scripts/bench_history.py [--months 7] [--twins 8] [--jobs N]
       [--recorder-readings 50000] [--artifact desk.json (skip training)]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import resource
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import paho.mqtt.client as mqtt
import pandas as pd
from paho.mqtt.enums import CallbackAPIVersion

import pseudotwin  # noqa: F401
from brokerutil import die_with_parent, exit_on_signals, free_port, start_broker, stop_process
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load
from pseudotwin.history.store import open_store

ROOT = Path(__file__).resolve().parent.parent
EXE = str(ROOT / ".venv" / "bin" / "pseudotwin")
TZ = "Europe/Madrid"


def minute_series(months: int) -> pd.DataFrame:
    src = load("appliances")
    src = src[src["sensor"] == "ironing/temp"].sort_values("ts")
    t = src["ts"].astype("int64").to_numpy() / 1e9
    v = src["value"].to_numpy()
    start = pd.Timestamp("2016-01-12T00:00Z")
    end = start + pd.DateOffset(months=months)
    grid = pd.date_range(start, end, freq="1min", inclusive="left")
    g = grid.astype("int64").to_numpy() / 1e9
    span = t[-1] - t[0]
    vals = np.interp(t[0] + (g - t[0]) % span, t, v)  # cyclic beyond the data's end
    return pd.DataFrame({"sensor": "dining/temp", "ts": grid, "value": np.round(vals, 3)})


#: Runs argv[1:] and prints its peak RSS [KiB] last on stderr: forked from this small process,
#: the child's ru_maxrss is its own. The child gets SIGTERM when the launcher dies (prctl
#: PR_SET_PDEATHSIG, as die_with_parent), so stopping this script stops the backfill too.
PEAK_RSS_LAUNCHER = ("import ctypes, resource, signal, subprocess, sys; "
                     "libc = ctypes.CDLL(None, use_errno=True); "
                     "rc = subprocess.call(sys.argv[1:], "
                     "preexec_fn=lambda: libc.prctl(1, signal.SIGTERM)); "
                     "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, "
                     "file=sys.stderr); sys.exit(rc)")


def children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def config_text(port: int, store: str, twins: list[str], journal_fsync: bool = True) -> str:
    text = (f'[broker]\nhost = "127.0.0.1"\nport = {port}\nclient_id = "bench-hist"\n\n'
            f'[service]\ntimezone = "{TZ}"\nstate_dir = "state"\nstore = "{store}"\n'
            f'journal_fsync = {str(journal_fsync).lower()}\n\n'
            '[[sensors]]\nid = "dining/temp"\ntopic = "h/dining"\nunit = "°C"\nmin = -20\n'
            'max = 60\n')
    for t in twins:
        text += (f'\n[[twins]]\nid = "{t}"\nreferences = ["dining/temp"]\n'
                 f'quantity = "temperature"\nartifact = "{t}.json"\n')
    return text


def run_backfill(tmp: Path, name: str, base: Path, twins: list[str], first: dt.date,
                 last: dt.date, jobs: int, port: int) -> dict[str, float]:
    """One ``pseudotwin backfill`` into a fresh copy of the readings-only store ``base``."""
    db = tmp / f"{name}.db"
    shutil.copy(base, db)
    cfg = tmp / f"{name}.toml"
    cfg.write_text(config_text(port, db.name, twins))
    cpu0 = children_cpu_s()
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", PEAK_RSS_LAUNCHER,
                        EXE, "--log-level", "WARNING", "backfill", "--config", str(cfg),
                        "--twin", ",".join(twins), "--from", str(first), "--to", str(last),
                        "--jobs", str(jobs), "--quiet"], capture_output=True, text=True,
                       preexec_fn=die_with_parent)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise RuntimeError(f"backfill {name} failed ({p.returncode}):\n{p.stdout}{p.stderr}")
    peak_kib = int(p.stderr.strip().splitlines()[-1])
    with sqlite3.connect(db) as con:
        n = con.execute("SELECT count(*) FROM estimates").fetchone()[0]
    days = ((last - first).days + 1) * len(twins)
    return {"s": wall, "cpu_s": children_cpu_s() - cpu0, "estimates": n, "days": days,
            "db": str(db), "peak_rss_mb": peak_kib / 1024}


def same_rows(a: str, b: str) -> bool:
    """Every estimate column but written_at equal, row for row."""
    cols = "twin, model, ts, value, std, quality, artifact_hash, source, lost"
    with sqlite3.connect(a) as con:
        con.execute("ATTACH DATABASE ? AS other", (b,))
        diff = con.execute(f"SELECT count(*) FROM (SELECT {cols} FROM estimates EXCEPT "
                           f"SELECT {cols} FROM other.estimates)").fetchone()[0]
        n_a = con.execute("SELECT count(*) FROM estimates").fetchone()[0]
        n_b = con.execute("SELECT count(*) FROM other.estimates").fetchone()[0]
    return diff == 0 and n_a == n_b


def bench_recorder(tmp: Path, port: int, n: int, journal_fsync: bool) -> tuple[int, float]:
    """Readings per second ``pseudotwin record`` stores into a new SQLite file, with its
    commits synced (``journal_fsync``, the default) or not; (stored, seconds)."""
    broker = rec = None
    pub = None
    name = "rec" if journal_fsync else "rec-nosync"
    try:
        broker = start_broker(tmp, port, "max_queued_messages 0\nmax_inflight_messages 0\n")
        cfg = tmp / f"{name}.toml"
        cfg.write_text(config_text(port, f"{name}.db", ["desk"], journal_fsync))
        rec_db = tmp / f"{name}.db"
        rec = subprocess.Popen([EXE, "--log-level", "WARNING", "record", "--config", str(cfg)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               preexec_fn=die_with_parent)
        pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-rec-pub")
        pub.max_inflight_messages_set(1000)
        online = threading.Event()
        pub.on_message = lambda c, u, m: m.payload == b"online" and online.set()
        pub.connect("127.0.0.1", port)
        pub.loop_start()
        # The recorder announces "online" (retained) after subscribing; readings published
        # before that would be lost, and its start-up takes seconds on a busy machine.
        pub.subscribe("pseudotwin/recorder/status", qos=1)
        if not online.wait(120):
            raise RuntimeError("the recorder did not come online within 120 s")
        base = dt.datetime(2016, 3, 1, tzinfo=dt.UTC)
        t0 = time.perf_counter()
        infos = [pub.publish("h/dining", json.dumps(
            {"ts": (base + dt.timedelta(seconds=i)).isoformat(), "value": 20 + (i % 100) / 100}),
            qos=1) for i in range(n)]
        for info in infos:
            info.wait_for_publish(60)
        stored = 0
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            if rec_db.exists():
                with open_store(str(rec_db)) as store:
                    stored = store.count_readings()
                if stored >= n:
                    break
            time.sleep(0.2)
        return stored, time.perf_counter() - t0
    finally:
        if pub is not None:
            pub.loop_stop()
        stop_process(rec, timeout=30)
        stop_process(broker)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--months", type=int, default=7)
    ap.add_argument("--twins", type=int, default=8, help="twins of the fleet run (default 8)")
    ap.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)),
                    help="worker processes of the parallel runs (default: the CPUs)")
    ap.add_argument("--recorder-readings", type=int, default=50_000)
    ap.add_argument("--artifact", type=Path,
                    help="a trained dining/temp artifact to use instead of training one")
    a = ap.parse_args()
    exit_on_signals()  # SIGTERM/SIGHUP: the finally blocks stop what was started
    load_start = os.getloadavg()[0]  # the machine may be shared: say how busy it was
    tmp = Path(tempfile.mkdtemp(prefix="pseudotwin-bench-history-"))
    try:
        if a.artifact:
            shutil.copy(a.artifact, tmp / "desk.json")
        else:
            hours = OperatingHours(timezone=TZ)
            art = train_twin(load("sml2010"), TwinSpec(("dining/temp",), "room/temp",
                                                       Quantity.TEMPERATURE, hours),
                             dt.date(2012, 3, 14), 5)
            art.save(tmp / "desk.json")
        fleet = [f"desk{i}" for i in range(1, a.twins + 1)]
        for t in fleet:
            shutil.copy(tmp / "desk.json", tmp / f"{t}.json")
        base = tmp / "readings.db"
        readings = minute_series(a.months)
        t0 = time.perf_counter()
        with open_store(str(base)) as store:
            store.write_readings(readings)
        load_s = time.perf_counter() - t0
        port = free_port()
        first = readings["ts"].iloc[0].tz_convert(TZ).date()
        last = readings["ts"].iloc[-1].tz_convert(TZ).date()
        days = (last - first).days + 1
        one = run_backfill(tmp, "serial", base, ["desk"], first, last, 1, port)
        rss_mb = one["peak_rss_mb"]
        par = run_backfill(tmp, "parallel", base, ["desk"], first, last, a.jobs, port)
        equal = same_rows(one["db"], par["db"])
        many = run_backfill(tmp, "fleet", base, fleet, first, last, a.jobs, port)
        stored, rec_s = bench_recorder(tmp, port, a.recorder_readings, journal_fsync=True)
        nosync_stored, nosync_s = bench_recorder(tmp, port, a.recorder_readings,
                                                 journal_fsync=False)
        n = a.recorder_readings
        fig = {
            "backfill_days": days, "backfill_readings": len(readings),
            "backfill_estimates": one["estimates"], "backfill_s": round(one["s"], 1),
            "backfill_days_per_s": round(days / one["s"], 2),
            "backfill_peak_rss_mb": round(rss_mb, 1), "store_load_s": round(load_s, 1),
            "recorder_readings": n, "recorder_stored": stored,
            "recorder_s": round(rec_s, 1), "recorder_readings_per_s": round(n / rec_s, 0),
            "recorder_nosync_stored": nosync_stored, "recorder_nosync_s": round(nosync_s, 1),
            "recorder_nosync_readings_per_s": round(n / nosync_s, 0),
            "backfill_cpu_s": round(one["cpu_s"], 1), "jobs": a.jobs,
            "backfill_parallel_s": round(par["s"], 1),
            "backfill_parallel_cpu_s": round(par["cpu_s"], 1),
            "backfill_parallel_rows_equal": equal,
            "fleet_twins": a.twins, "fleet_days": many["days"],
            "fleet_estimates": many["estimates"], "fleet_s": round(many["s"], 1),
            "fleet_cpu_s": round(many["cpu_s"], 1),
            "fleet_days_per_s": round(many["days"] / many["s"], 2),
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "load_avg_1min_start": round(load_start, 2),
            "backfill_cpu_s_per_day": round(one["cpu_s"] / one["days"], 3),
            "fleet_cpu_s_per_day": round(many["cpu_s"] / many["days"], 3),
        }
        rows = [("1 twin, --jobs 1", one), (f"1 twin, --jobs {a.jobs}", par),
                (f"{a.twins} twins, --jobs {a.jobs}", many)]
        print(f"backfill, {a.months} months of 1-min readings ({len(readings)} readings, "
              f"{days} days per twin); load average {load_start:.2f} at the start, "
              f"{fig['load_avg_1min']} now")
        print(f"{'run':<22} {'days':>6} {'estimates':>10} {'wall s':>8} {'CPU s':>8} "
              f"{'days/s':>7} {'CPU s/day':>9}")
        for label, r in rows:
            print(f"{label:<22} {r['days']:>6} {r['estimates']:>10} {r['s']:>8.1f} "
                  f"{r['cpu_s']:>8.1f} {r['days'] / r['s']:>7.2f} "
                  f"{r['cpu_s'] / r['days']:>9.3f}")
        print(f"parallel rows equal the serial ones: {equal}; peak RSS of the serial backfill "
              f"{fig['backfill_peak_rss_mb']} MB")
        print(f"recorder: {n} readings in {rec_s:.1f} s = {fig['recorder_readings_per_s']:.0f} "
              f"readings/s, {stored} stored (count in = count stored: {stored == n}); "
              "journal_fsync = true (the default: spool and SQLite commits synced)")
        print(f"recorder: {n} readings in {nosync_s:.1f} s = "
              f"{fig['recorder_nosync_readings_per_s']:.0f} readings/s, {nosync_stored} stored "
              f"(count in = count stored: {nosync_stored == n}); journal_fsync = false")
        print(json.dumps(fig))
        return 0 if equal and stored == nosync_stored == n else 1
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
