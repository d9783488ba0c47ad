"""The thesis's evaluation protocol (DESIGN.md §7), causal, on any canonical history.

Train on the first ``train_days`` usable days from ``train_start``, then replay every later
reading through one :class:`~pseudotwin.live.twin.Twin` in time order — exactly as the daemon would
receive them — and at each true target reading in operating hours ask every model for its
estimate. The target is never fed to the twin, and an estimate at t uses only readings ≤ t.
"""

from __future__ import annotations

import datetime as dt
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pseudotwin.analysis.training import ALL_MODELS, train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import require_sensors
from pseudotwin.errors import DataError
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin

log = logging.getLogger(__name__)

REF_PREFIX = "ref:"


@dataclass(frozen=True)
class Evaluation:
    """Outputs of one evaluation run (all frames also written as CSV)."""

    artifact: Artifact
    estimates: pd.DataFrame  # ts, model, value, std, truth
    daily: pd.DataFrame  # day, model, nrmse_pct, dmax_pct, pearson_r, n
    monthly: pd.DataFrame  # month, model, nrmse_pct
    seconds: float


def replay_estimates(
    artifact: Artifact,
    history: pd.DataFrame,
    start: dt.date,
    models: Sequence[str] | None = None,
) -> pd.DataFrame:
    """Estimates at every true target reading in operating hours of days ≥ ``start``.

    Also emits, as pseudo-models ``ref:<sensor>``, the raw reference value held at that time
    (its daily Pearson r with the target is the evidence of how much a reference can tell).
    """
    hours = artifact.hours
    twin = Twin(artifact, models=models)
    refs = list(artifact.references)
    sub = history[history["sensor"].isin([*refs, artifact.target])]
    days, hrs = hours.day_and_hours(sub["ts"])
    is_target = (sub["sensor"] == artifact.target).values
    score = is_target & (days >= np.datetime64(start)) & hours.in_operating_hours(hrs)
    # Readings at the same instant: references first, so an estimate at t sees them.
    order = np.lexsort((is_target, pd.DatetimeIndex(sub["ts"]).asi8))
    sensors = sub["sensor"].values[order]
    stamps = pd.DatetimeIndex(sub["ts"]).tz_convert("UTC")[order]
    values = sub["value"].values[order]
    scored = score[order]
    held: dict[str, float] = {}
    rows: list[tuple] = []
    for s, ts, v, sc in zip(sensors, stamps, values, scored, strict=True):
        t = ts.to_pydatetime()
        if s != artifact.target:
            twin.observe(s, t, float(v))
            held[s] = float(v)
            continue
        if not sc:
            continue
        for kind, e in twin.estimate(t).items():
            if e.finite:
                rows.append((t, kind, e.value, e.std, float(v), e.quality))
        for r in refs:
            if r in held:
                rows.append((t, REF_PREFIX + r, held[r], np.nan, float(v), "ok"))
    return pd.DataFrame(rows, columns=["ts", "model", "value", "std", "truth", "quality"])


def daily_scores(est: pd.DataFrame, hours: OperatingHours) -> pd.DataFrame:
    """Per day and model: NRMSE (6.10) and ΔT_max (6.14) in % of the day's mean truth."""
    if est.empty:
        return pd.DataFrame(columns=["day", "model", "nrmse_pct", "dmax_pct", "pearson_r", "n"])
    days, _ = hours.day_and_hours(est["ts"])
    e = est.assign(day=pd.to_datetime(days).date)
    out = []
    for (day, model), g in e.groupby(["day", "model"], sort=True):
        err = g["value"].values - g["truth"].values
        mean_truth = float(np.mean(g["truth"].values))
        denom = abs(mean_truth) if mean_truth else float("nan")
        r = np.nan
        if len(g) > 2 and np.std(g["value"].values) > 0 and np.std(g["truth"].values) > 0:
            r = float(np.corrcoef(g["value"].values, g["truth"].values)[0, 1])
        out.append((
            str(day), model,
            100.0 * float(np.sqrt(np.mean(err**2))) / denom,
            100.0 * float(np.max(np.abs(err))) / denom,
            r, len(g),
        ))
    return pd.DataFrame(out, columns=["day", "model", "nrmse_pct", "dmax_pct", "pearson_r", "n"])


def monthly_scores(daily: pd.DataFrame) -> pd.DataFrame:
    """Monthly mean of daily NRMSE per model (thesis Tables 6.2–6.4)."""
    if daily.empty:
        return pd.DataFrame(columns=["month", "model", "nrmse_pct"])
    d = daily.assign(month=daily["day"].str[:7])
    m = d.groupby(["month", "model"], sort=True)["nrmse_pct"].mean().reset_index()
    return m


def evaluate(
    history: pd.DataFrame,
    references: Sequence[str],
    target: str,
    quantity: str,
    hours: OperatingHours,
    train_start: dt.date,
    train_days: int = 5,
    models: Sequence[str] = ALL_MODELS,
    out: Path | None = None,
    options: dict | None = None,
    plot_day: dt.date | None = None,
) -> Evaluation:
    t0 = time.perf_counter()
    require_sensors(history, [*references, target])
    artifact = train_twin(
        history, references, target, quantity, hours, train_start, train_days, models, options
    )
    test_start = dt.date.fromisoformat(artifact.training["end"]) + dt.timedelta(days=1)
    est = replay_estimates(artifact, history, test_start, models)
    if est.empty:
        raise DataError(
            f"no target readings of {target} in operating hours after the training period "
            f"(from {test_start} on): nothing to evaluate"
        )
    daily = daily_scores(est, hours)
    monthly = monthly_scores(daily)
    ev = Evaluation(artifact, est, daily, monthly, time.perf_counter() - t0)
    if out is not None:
        write_outputs(ev, history, out, plot_day)
    return ev


def write_outputs(
    ev: Evaluation, history: pd.DataFrame, out: Path, plot_day: dt.date | None = None
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    ev.artifact.save(out / "artifact.json")
    est = ev.estimates.copy()
    est["ts"] = pd.DatetimeIndex(est["ts"]).tz_convert("UTC").strftime("%Y-%m-%dT%H:%M:%S+00:00")
    est.to_csv(out / "estimates.csv", index=False, float_format="%.6g")
    ev.daily.to_csv(out / "daily.csv", index=False, float_format="%.4f")
    ev.monthly.to_csv(out / "monthly.csv", index=False, float_format="%.4f")
    from pseudotwin.analysis.plots import plot_daily_nrmse, plot_day_estimate

    plot_daily_nrmse(ev.daily, out / "daily_nrmse.png", ev.artifact)
    day = plot_day or _median_day(ev)
    if day is not None:
        plot_day_estimate(ev, history, day, out / f"day_{day}.png")


def _median_day(ev: Evaluation) -> dt.date | None:
    """The day whose primary-model NRMSE is the median: a typical day, not the best."""
    d = ev.daily[ev.daily["model"] == ev.artifact.primary].sort_values("nrmse_pct")
    if d.empty:
        return None
    return dt.date.fromisoformat(d["day"].iloc[len(d) // 2])


def summary_table(ev: Evaluation) -> str:
    """Mean daily NRMSE / ΔT_max / r per model, as a Markdown table."""
    g = ev.daily.groupby("model").agg(
        nrmse_pct=("nrmse_pct", "mean"), dmax_pct=("dmax_pct", "mean"),
        pearson_r=("pearson_r", "median"), days=("day", "nunique"),
    )
    order = [m for m in (*ALL_MODELS,) if m in g.index] + sorted(
        m for m in g.index if m not in ALL_MODELS
    )
    lines = ["| model | mean daily NRMSE % | mean ΔT_max % | median daily r | days |",
             "|---|---:|---:|---:|---:|"]
    for m in order:
        row = g.loc[m]
        lines.append(
            f"| {m} | {row.nrmse_pct:.2f} | {row.dmax_pct:.2f} | {row.pearson_r:.3f} "
            f"| {int(row.days)} |"
        )
    return "\n".join(lines)
