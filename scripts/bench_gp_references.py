#!/usr/bin/env python3
"""Benchmark: what one fit of the Corr-GPs over all references costs as references are added.

corrgp-lcm and corrgp-multi model every reference and the target as outputs of one LCM with,
by default, one term per reference: outputs, parameters and optimizer work all grow with the
references. Data: the Appliances house (UCI, 10-min readings, converted from the shared
data), target `parents/temp`, references taken in the order `ironing/temp`, `living/temp`,
`kitchen/temp`, `office/temp`, `teen/temp`; the first five days from 2016-01-12, the report's
training days. One fit per model and count with the training defaults (3 restarts), no
validation (which refits each model once per training day with 1 restart); the history is cut
to the training days' fortnight first, so the time is the fit's (and the few days' thinning).

Prints a table and, last, one JSON line.

    .venv/bin/python scripts/bench_gp_references.py [--references 2,3,4,5]
                                                    [--models corrgp-lcm,corrgp-multi]
                                                    [--lcm-terms N]
"""

from __future__ import annotations

import argparse
import datetime as dt
import time
from typing import Any

import pandas as pd

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy does any work)
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load
from tables import print_table

REFS = ("ironing/temp", "living/temp", "kitchen/temp", "office/temp", "teen/temp")
TARGET = "parents/temp"
START = dt.date(2016, 1, 12)
GP_MODELS = ("corrgp-lcm", "corrgp-multi", "corrgp-triv")  # corrgp-triv: first reference only


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--references", default="2,3,4,5",
                    help=f"reference counts, comma-separated, each ≤ {len(REFS)} "
                         "(default 2,3,4,5)")
    ap.add_argument("--models", default="corrgp-lcm,corrgp-multi",
                    help="models to fit (default corrgp-lcm,corrgp-multi)")
    ap.add_argument("--lcm-terms", type=int, default=None,
                    help="LCM terms (default: the models' own, one per reference)")
    args = ap.parse_args()
    counts = [int(x) for x in args.references.split(",")]
    if any(not 1 <= n <= len(REFS) for n in counts):
        ap.error(f"--references: counts between 1 and {len(REFS)}")
    models = args.models.split(",")
    if unknown := [m for m in models if m not in GP_MODELS]:
        ap.error(f"--models: not a Corr-GP: {', '.join(unknown)}; choose from "
                 f"{', '.join(GP_MODELS)}")
    if args.lcm_terms is not None and args.lcm_terms < 1:
        ap.error("--lcm-terms must be at least 1")
    history = load("appliances")
    first = pd.Timestamp(START, tz="UTC") - pd.Timedelta(days=1)
    history = history[(history["ts"] >= first) & (history["ts"] < first + pd.Timedelta(days=16))]
    rows: list[dict[str, Any]] = []
    for model in models:
        for n in counts:
            spec = TwinSpec(REFS[:n], TARGET, Quantity.TEMPERATURE,
                            OperatingHours(timezone="Europe/Brussels"))
            options = None if args.lcm_terms is None else {model: {"n_terms": args.lcm_terms}}
            t0 = time.perf_counter()
            art = train_twin(history, spec, START, models=[model], options=options,
                             validate=False)
            seconds = time.perf_counter() - t0
            fitted: Any = art.models[model]  # a Corr-GP: params_ and report_ of its LCM fit
            report = fitted.report_
            rows.append({"model": model, "references": n, "terms": len(fitted.params_.terms),
                         "points": report.n_points, "parameters": report.n_params,
                         "seconds": seconds})
            print(f"{model}, {n} references: {seconds:.1f} s", flush=True)
    print_table("fits", rows, [
        ("model", "model", None), ("references", "references", None),
        ("LCM terms", "terms", None), ("training points", "points", None),
        ("parameters", "parameters", None), ("fit [s]", "seconds", 1),
    ])


if __name__ == "__main__":
    main()
