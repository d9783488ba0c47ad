#!/usr/bin/env python3
"""Benchmark: live conditioning per reading vs rebuilding a GPy model per reading, and
training time of corrgp-triv / corrgp-lcm on five days.

Data: Room Climate location A (real, converted to 1-min means; default 15-min training grid):
references A1 (ceiling) and A3 (wall), target A4 (desk). Training: the first five days from
2016-03-15; the live day is 2016-04-01 (138 readings per reference between 08:00 and 19:00
Europe/Berlin).

Prints a table, and as its last line one JSON object with the figures.
Usage: .venv/bin/python scripts/bench_update.py [--day 2016-04-01] [--repeat 3]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy is used)
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import read_history
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.gp.train import gpy_model
from pseudotwin.history.convert import convert
from pseudotwin.live.twin import Twin

REFS = ("A1/temp", "A3/temp")
TARGET = "A4/temp"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--day", type=dt.date.fromisoformat, default=dt.date(2016, 4, 1))
    ap.add_argument("--repeat", type=int, default=3, help="live-day repetitions (default 3)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "rc-a.csv"
        convert("room-climate-a", None, csv)
        df = read_history(csv)
    hours = OperatingHours(timezone="Europe/Berlin")  # default 15-min grid
    start = dt.date(2016, 3, 15)

    t0 = time.perf_counter()
    spec = TwinSpec(tuple(REFS), TARGET, Quantity.TEMPERATURE, hours)
    # The model fits alone (validation, which refits on held-out days, is timed by `train`).
    art_triv = train_twin(df, spec, start, 5, ["corrgp-triv"], validate=False)
    train_triv = time.perf_counter() - t0
    t0 = time.perf_counter()
    art = train_twin(df, spec, start, 5, ["corrgp-lcm"], validate=False)
    train_lcm = time.perf_counter() - t0
    lcm = art.models["corrgp-lcm"]

    # The live day's reference readings, in arrival (time) order.
    loc = df["ts"].dt.tz_convert(hours.timezone)
    sel = df["sensor"].isin(REFS) & (loc.dt.date == a.day)
    day = df[sel].sort_values("ts")
    readings = [(s, t.to_pydatetime(), float(v))
                for s, t, v in zip(day["sensor"], day["ts"], day["value"], strict=True)]
    per_ref = day[hours.in_operating_hours(hours.day_and_hours(day["ts"])[1])]
    counts = per_ref.groupby("sensor").size().to_dict()

    lat: list[float] = []
    n_window = 0
    for _ in range(a.repeat):
        twin = Twin(art, models=["corrgp-lcm"])
        for s, ts, v in readings:
            t1 = time.perf_counter()
            if twin.observe(s, ts, v):
                twin.estimate(ts)
                lat.append(time.perf_counter() - t1)
        n_window = len(twin.window)

    # The same day, rebuilding a GPy model per reading (what live conditioning replaces).
    tt = np.array([hours.hours_of(ts) for _, ts, _ in readings])
    oo = np.array([REFS.index(s) for s, _, _ in readings])
    yy = (np.array([v for _, _, v in readings]) - lcm.c_) / lcm.s_
    keep = hours.in_window(tt)
    tt, oo, yy = tt[keep], oo[keep], yy[keep]
    P = len(REFS)
    rebuild: list[float] = []
    for i in range(1, len(tt) + 1):
        t1 = time.perf_counter()
        m = gpy_model(lcm.params_, tt[:i], oo[:i], yy[:i], fix_variance=False)
        m.predict(np.array([[tt[i - 1], P]]), Y_metadata={"output_index": np.array([[P]])})
        rebuild.append(time.perf_counter() - t1)

    lat_ms = np.array(lat) * 1e3
    reb_ms = np.array(rebuild) * 1e3
    tail = lat_ms[-max(1, len(lat_ms) // (5 * a.repeat)):]  # the day's last fifth, last run
    fig = {
        "day": str(a.day),
        "readings_per_reference": counts,
        "window_size_end_of_day": n_window,
        "update_median_ms": round(float(np.median(lat_ms)), 4),
        "update_p99_ms": round(float(np.percentile(lat_ms, 99)), 4),
        "update_end_of_day_p99_ms": round(float(np.percentile(tail, 99)), 4),
        "gpy_rebuild_median_ms": round(float(np.median(reb_ms)), 3),
        "gpy_rebuild_p99_ms": round(float(np.percentile(reb_ms, 99)), 3),
        "speedup": round(float(np.median(reb_ms) / np.median(lat_ms)), 1),
        "train_triv_s": round(train_triv, 2),
        "train_lcm_s": round(train_lcm, 2),
        "lcm_nlml": round(float(lcm.report_.nlml), 3),
        "lcm_terms": len(lcm.params_.terms),
        "lcm_params": lcm.report_.n_params,
        "triv_nlml": round(float(art_triv.models["corrgp-triv"].report_.nlml), 3),
    }
    print(f"live day {a.day}: {counts} readings per reference in operating hours, "
          f"window of {n_window} readings at day end")
    print(f"{'':32}{'median ms':>12}{'p99 ms':>12}")
    print(f"{'live conditioning (per reading)':32}{fig['update_median_ms']:>12.3f}"
          f"{fig['update_p99_ms']:>12.3f}")
    print(f"{'  … last fifth of the day':32}{np.median(tail):>12.3f}"
          f"{fig['update_end_of_day_p99_ms']:>12.3f}")
    print(f"{'GPy model rebuilt per reading':32}{fig['gpy_rebuild_median_ms']:>12.3f}"
          f"{fig['gpy_rebuild_p99_ms']:>12.3f}")
    print(f"speedup (median): {fig['speedup']}x")
    print(f"training on 5 days: corrgp-triv {train_triv:.1f} s, corrgp-lcm {train_lcm:.1f} s "
          f"({fig['lcm_terms']} terms, {fig['lcm_params']} free parameters, "
          f"NLML {fig['lcm_nlml']})")
    print(json.dumps(fig))
    return 0


if __name__ == "__main__":
    sys.exit(main())
