#!/usr/bin/env python3
"""Benchmark: backfill throughput and the recorder's sustained write rate, into SQLite.

Backfill: one twin (trained on SML2010, dining room → bedroom) over 7 months of 1-minute
reference readings. The readings are the Appliances house's ironing-room temperature (real,
10-minute, Jan–May 2016) interpolated to one minute and continued cyclically to fill seven
months (2016-01-12 … 2016-08-11). ``pseudotwin backfill`` runs as its own process, so its
peak RSS (getrusage of the child) is the backfill's alone.

Recorder: ``pseudotwin record`` as its own process against a real Mosquitto; a publisher
sends N readings (QoS 1) as fast as the broker takes them; the figure is N / time until all
N are in the store (count in = count stored is checked).

Prints a table and, last, one JSON line.
Usage: .venv/bin/python scripts/bench_history.py [--months 7] [--recorder-readings 50000]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import paho.mqtt.client as mqtt
import pandas as pd
from paho.mqtt.enums import CallbackAPIVersion

import pseudotwin  # noqa: F401
from brokerutil import free_port, start_broker
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--months", type=int, default=7)
    ap.add_argument("--recorder-readings", type=int, default=50_000)
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="pseudotwin-bench-history-"))
    try:
        hours = OperatingHours(timezone=TZ)
        art = train_twin(load("sml2010"),
                         TwinSpec(("dining/temp",), "room/temp", Quantity.TEMPERATURE, hours),
                         dt.date(2012, 3, 14), 5)
        art.save(tmp / "desk.json")
        db = tmp / "history.db"
        readings = minute_series(a.months)
        t0 = time.perf_counter()
        with open_store(str(db)) as store:
            store.write_readings(readings)
        load_s = time.perf_counter() - t0
        port = free_port()
        cfg = tmp / "config.toml"
        cfg.write_text(
            f'[broker]\nhost = "127.0.0.1"\nport = {port}\nclient_id = "bench-hist"\n\n'
            f'[service]\ntimezone = "{TZ}"\nstate_dir = "state"\nstore = "history.db"\n\n'
            '[[sensors]]\nid = "dining/temp"\ntopic = "h/dining"\nunit = "°C"\nmin = -20\n'
            'max = 60\n\n[[twins]]\nid = "desk"\nreferences = ["dining/temp"]\n'
            'quantity = "temperature"\nartifact = "desk.json"\n')
        first = readings["ts"].iloc[0].tz_convert(TZ).date()
        last = readings["ts"].iloc[-1].tz_convert(TZ).date()
        t0 = time.perf_counter()
        p = subprocess.run([EXE, "--log-level", "WARNING", "backfill", "--config", str(cfg),
                            "--twin", "desk", "--from", str(first), "--to", str(last),
                            "--quiet"], capture_output=True, text=True)
        bf_s = time.perf_counter() - t0
        if p.returncode:
            print(p.stdout, p.stderr)
            return 1
        rss_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        with open_store(str(db)) as store:
            n_est = len(store.read_estimates("desk"))
        days = (last - first).days + 1

        # -- recorder ----------------------------------------------------------------------
        broker = start_broker(tmp, port, "max_queued_messages 0\nmax_inflight_messages 0\n")
        rec_db = tmp / "rec.db"
        cfg.write_text(cfg.read_text().replace('store = "history.db"', 'store = "rec.db"'))
        rec = subprocess.Popen([EXE, "--log-level", "WARNING", "record", "--config", str(cfg)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(1.0)  # let the recorder subscribe (a benchmark, not a test)
        pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-rec-pub")
        pub.max_inflight_messages_set(1000)
        pub.connect("127.0.0.1", port)
        pub.loop_start()
        base = dt.datetime(2016, 3, 1, tzinfo=dt.UTC)
        n = a.recorder_readings
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
        rec_s = time.perf_counter() - t0
        rec.terminate()
        rec.wait(30)
        pub.loop_stop()
        broker.terminate()
        broker.wait(10)
        fig = {
            "backfill_days": days, "backfill_readings": len(readings),
            "backfill_estimates": n_est, "backfill_s": round(bf_s, 1),
            "backfill_days_per_s": round(days / bf_s, 2),
            "backfill_peak_rss_mb": round(rss_mb, 1), "store_load_s": round(load_s, 1),
            "recorder_readings": n, "recorder_stored": stored,
            "recorder_s": round(rec_s, 1), "recorder_readings_per_s": round(n / rec_s, 0),
        }
        print(f"backfill: {days} days ({len(readings)} 1-min readings) in {bf_s:.1f} s = "
              f"{fig['backfill_days_per_s']} days/s, {n_est} estimates, peak RSS "
              f"{fig['backfill_peak_rss_mb']} MB (the backfill process)")
        print(f"recorder: {n} readings in {rec_s:.1f} s = {fig['recorder_readings_per_s']:.0f} "
              f"readings/s, {stored} stored (count in = count stored: {stored == n})")
        print(json.dumps(fig))
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
