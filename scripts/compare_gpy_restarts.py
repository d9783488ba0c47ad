#!/usr/bin/env python3
"""One-off: our staged, data-initialized LCM fit vs GPy's plain ``optimize_restarts(5)``.

Same data (Room Climate A: references A1, A3, target A4; the five training days of
scripts/bench_update.py on the default 15-min grid), same normalization, same model (a 3-term
LCM with rank-1 B matrices, RQ kernels; 3×(variance, lengthscale, power, W[3], κ[3]) + 3
noise variances = 30 free parameters) and the same objective (the day-block likelihood).
GPy starts from its default initialization and randomizes each restart, as a user would get.

Takes ~10 minutes. Prints a table and, last, one JSON line.
Usage: .venv/bin/python scripts/compare_gpy_restarts.py [--restarts 5] [--terms 3]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import pseudotwin  # noqa: F401
from pseudotwin.analysis.training import choose_training_days
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import read_history
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.gp.kernels import LcmParams, Term
from pseudotwin.gp.train import FitData, gpy_model, params_from_gpy
from pseudotwin.history.convert import convert
from pseudotwin.models.base import TrainingSet
from pseudotwin.models.corrgp import CorrGpLcm

REFS = ("A1/temp", "A3/temp")
TARGET = "A4/temp"


def exact_nlml(params: LcmParams, fd: FitData) -> float:
    """The NLML by dense LU per day block, no scaling and no jitter: an independent check that
    neither optimum owes its value to regularization."""
    total = 0.0
    for b in fd.blocks:
        K = params.K(fd.t[b], fd.o[b], fd.t[b], fd.o[b])
        K[np.diag_indices_from(K)] += params.noise[fd.o[b]]
        sign, logdet = np.linalg.slogdet(K)
        if sign <= 0:
            return float("nan")
        y = fd.y[b]
        total += 0.5 * (logdet + y @ np.linalg.solve(K, y) + len(y) * np.log(2 * np.pi))
    return float(total)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--restarts", type=int, default=5)
    ap.add_argument("--terms", type=int, default=3)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        convert("room-climate-a", None, Path(tmp) / "a.csv")
        df = read_history(Path(tmp) / "a.csv")
    hours = OperatingHours(timezone="Europe/Berlin")
    days, _ = choose_training_days(df, [*REFS, TARGET], hours, dt.date(2016, 3, 15), 5)
    ts = TrainingSet(TwinSpec(tuple(REFS), TARGET, Quantity.TEMPERATURE, hours), tuple(days))

    t0 = time.perf_counter()
    ours = CorrGpLcm(kernel="rq", n_terms=a.terms).fit(ts)
    ours_s = time.perf_counter() - t0
    fd = ours.fit_data_

    rng = np.random.default_rng(0)
    np.random.seed(0)  # GPy's randomize() draws from numpy's global generator
    P = fd.n_outputs
    init = LcmParams("rq", tuple(
        Term(1.0, 0.5 * rng.standard_normal((P, 1)), 0.5 * np.ones(P), variance=1.0, power=2.0)
        for _ in range(a.terms)
    ), np.ones(P))
    model = gpy_model(init, fd.t, fd.o, fd.y, blocks=fd.blocks, fix_variance=False)
    n_params = model.optimizer_array.size
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.optimize_restarts(num_restarts=a.restarts, robust=True, verbose=False,
                                messages=False)
    gpy_s = time.perf_counter() - t0
    per_restart = [float(o.f_opt) for o in model.optimization_runs]
    statuses = [str(o.status) for o in model.optimization_runs]
    gpy_best = float(model.objective_function())

    ours_exact = exact_nlml(ours.params_, fd)
    gpy_exact = exact_nlml(params_from_gpy(model, "rq"), fd)
    gpy_jitter = float(model.inference_method.last_jitter)
    print(f"{a.terms}-term LCM, {n_params} free parameters, {len(fd.y)} training points in "
          f"{len(fd.blocks)} day blocks")
    print(f"{'':34}{'NLML':>12}{'seconds':>10}")
    print(f"{'pseudotwin staged fit':34}{ours.report_.nlml:>12.3f}{ours_s:>10.1f}")
    print(f"{'GPy optimize_restarts, best':34}{gpy_best:>12.3f}{gpy_s:>10.1f}")
    for i, (f, st) in enumerate(zip(per_restart, statuses, strict=True)):
        print(f"{'  restart ' + str(i):34}{f:>12.3f}    {st}")
    print(f"jitter-free NLML at the optima: pseudotwin {ours_exact:.3f}, GPy {gpy_exact:.3f} "
          f"(GPy's optimum needed jitter {gpy_jitter:.1e}; ours "
          f"{ours.report_.jitter_max:.1e})")
    out = {
        "terms": a.terms, "gpy_params": int(n_params), "ours_params": ours.report_.n_params,
        "ours_nlml": round(ours.report_.nlml, 3), "ours_s": round(ours_s, 1),
        "gpy_best_nlml": round(gpy_best, 3), "gpy_s": round(gpy_s, 1),
        "gpy_restarts_nlml": [round(f, 3) for f in per_restart], "gpy_status": statuses,
        "ours_exact_nlml": round(ours_exact, 3), "gpy_exact_nlml": round(gpy_exact, 3),
        "gpy_jitter": gpy_jitter, "ours_jitter": ours.report_.jitter_max,
        "ours_at_least_as_good": bool(ours.report_.nlml <= gpy_best + 1e-3),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
