"""Measure the self-aware indication (quality ``uncertain``) on the report's shared runs
without regenerating docs/results.md: per run, how often it fires on the test days and on the
training days, MAE and ±2σ coverage of ``ok`` vs ``uncertain`` published estimates.

``--far SPANS`` also measures, without acting, a level criterion fixed wider than the
envelope's: a reference beyond its training quantiles by SPANS × their span (the envelope's
margin is ``MARGIN``): extrapolation far past anything the held-out days could show, the case
for an ``uncertain`` that acts whatever validation kept.

Prints a Markdown table and, last, one JSON line.

    .venv/bin/python scripts/selfaware.py [--runs NAME,...] [--models ref,triv,corrgp-triv]
                                          [--far SPANS]
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
import pandas as pd

from pseudotwin.analysis.criteria import criteria_table
from pseudotwin.analysis.evaluate import ESTIMATE, evaluate
from pseudotwin.analysis.report.runs import RUN_NAMES, RUNS
from pseudotwin.analysis.selfaware import selfaware, training_share
from pseudotwin.history.convert import load
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.envelope import MARGIN
from tables import print_table


def far_level(art: Artifact, history: pd.DataFrame, estimates: pd.DataFrame,
              spans: float) -> dict[str, Any]:
    """The published estimates at which a reference lies beyond its training quantiles by
    ``spans`` × their span: share [%], days, MAE there / elsewhere, ±2σ coverage there [%]."""
    e = estimates[estimates["model"] == ESTIMATE].sort_values("ts", kind="stable")
    far = np.zeros(len(e), dtype=bool)
    for sensor, ref in (art.envelope.refs.items() if art.envelope else ()):
        lo, hi = ref.level  # the quantiles widened by MARGIN × their span on each side
        span = (hi - lo) / (1 + 2 * MARGIN)
        extra = (spans - MARGIN) * span
        held = history.loc[history["sensor"] == sensor, ["ts", "value"]].sort_values("ts")
        at = e[["ts"]].astype({"ts": held["ts"].dtype})
        level = pd.merge_asof(at, held, on="ts")["value"].to_numpy(dtype=float)
        far |= (level < lo - extra) | (level > hi + extra)
    err = (e["value"] - e["truth"]).abs().to_numpy(dtype=float)
    std = e["std"].to_numpy(dtype=float)
    day, _ = art.hours.day_and_hours(e["ts"])
    quiet = err[~far].mean() if (~far).any() else float("nan")
    return {"far_pct": 100 * float(far.mean()) if len(far) else float("nan"),
            "far_days": len(set(day[far].tolist())),
            "far_ratio": float(err[far].mean() / quiet) if far.any() else float("nan"),
            "far_cover2": 100 * float(np.mean(err[far] <= 2 * std[far])) if far.any()
            else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", default=",".join(RUN_NAMES),
                    help="comma-separated runs of the report (default: all, "
                         f"{', '.join(RUN_NAMES)})")
    ap.add_argument("--models", default="ref,triv,corrgp-triv",
                    help="models trained (validation picks the primary among them; default "
                         "%(default)s, the cheap ones)")
    ap.add_argument("--far", type=float, metavar="SPANS",
                    help="also measure a level criterion beyond the training quantiles by "
                         "SPANS × their span (not acting; see the module docstring)")
    a = ap.parse_args()
    wanted = [r.strip() for r in a.runs.split(",") if r.strip()]
    unknown = sorted(set(wanted) - set(RUN_NAMES))
    if unknown:
        ap.error(f"unknown run(s) {', '.join(unknown)}; known: {', '.join(RUN_NAMES)}")
    models = tuple(m.strip() for m in a.models.split(",") if m.strip())
    rows = []
    for spec in (r for r in RUNS if r.name in wanted):
        t0 = time.perf_counter()
        history = load(spec.dataset)
        ev = evaluate(history, spec.twin, spec.train_start, spec.train_days, models)
        sa = selfaware(ev.estimates, training_share(ev.artifact, history))
        rows.append({"run": spec.name, "primary": ev.artifact.primary,
                     "test_pct": 100 * sa.share, "train_pct": 100 * sa.train_share,
                     "mae_ok": sa.mae_ok, "mae_uncertain": sa.mae_uncertain,
                     "mae_ratio": sa.mae_ratio, "cover2_ok": sa.cover2_ok,
                     "cover2_uncertain": sa.cover2_uncertain, "n_ok": sa.n_ok,
                     "n_uncertain": sa.n_uncertain,
                     "kept": " ".join(sorted(env.kept or ())) if (env := ev.artifact.envelope)
                     else "", "widen": env.widen if env else float("nan"),
                     "seconds": round(time.perf_counter() - t0, 1),
                     **(far_level(ev.artifact, history, ev.estimates, a.far)
                        if a.far is not None else {})})
        print(f"# {spec.name} done in {rows[-1]['seconds']} s", flush=True)
        print(criteria_table(ev.artifact.to_dict().get("envelope"), ev.artifact.unit),
              flush=True)
    far = [(f"beyond {a.far:g} spans % test", "far_pct", 1), ("days", "far_days", 0),
           ("MAE there / elsewhere", "far_ratio", 2), ("±2σ cov there %", "far_cover2", 1)]
    print_table("selfaware", rows, [
        ("run", "run", None), ("primary", "primary", None),
        ("uncertain % test", "test_pct", 1), ("uncertain % training", "train_pct", 1),
        ("MAE ok", "mae_ok", 3), ("MAE uncertain", "mae_uncertain", 3), ("ratio", "mae_ratio", 2),
        ("±2σ cov ok %", "cover2_ok", 1), ("±2σ cov uncertain %", "cover2_uncertain", 1),
        ("n ok", "n_ok", 0), ("n uncertain", "n_uncertain", 0),
        ("kept criteria", "kept", None), ("σ widen", "widen", 2),
        *(far if a.far is not None else []),
    ])


if __name__ == "__main__":
    main()
