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
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pseudotwin.analysis.replay import ESTIMATE, REF_PREFIX, replay_estimates
from pseudotwin.analysis.training import plausible_readings, train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import iso_utc, require_sensors
from pseudotwin.core.spec import TwinSpec
from pseudotwin.core.thinning import Thinning
from pseudotwin.errors import DataError
from pseudotwin.live import metrics
from pseudotwin.live.artifact import Artifact
from pseudotwin.models.registry import ALL_MODELS

log = logging.getLogger(__name__)

__all__ = ["ESTIMATE", "REF_PREFIX", "Evaluation", "evaluate", "replay_estimates",
           "daily_scores", "monthly_scores", "summary_table", "write_outputs"]



@dataclass(frozen=True)
class Evaluation:
    """Outputs of one evaluation run (all frames also written as CSV)."""

    artifact: Artifact
    estimates: pd.DataFrame  # replay.COLUMNS: ts, model, value, std, truth, quality, slope,
    # source, lost
    daily: pd.DataFrame  # DAILY_COLUMNS
    monthly: pd.DataFrame  # month, model, nrmse_pct
    seconds: float

    @property
    def test_start(self) -> dt.date:
        """The first scored day: the day after the last training day."""
        return first_scored_day(self.artifact)


def first_scored_day(artifact: Artifact) -> dt.date:
    """The first day after ``artifact``'s training days, where scoring begins."""
    if (end := artifact.training_end) is None:
        raise DataError("the artifact does not say when its training days end")
    return end + dt.timedelta(days=1)


DAILY_COLUMNS = ("day", "model", "nrmse_pct", "dmax_pct", "pearson_r", "n",
                 "cover1_pct", "cover2_pct", "crps", "mean_std", "rmse")


def daily_scores(est: pd.DataFrame, hours: OperatingHours) -> pd.DataFrame:
    """Per day and model: NRMSE (6.10) and ΔT_max (6.14) in % of the day's mean truth, r,
    and the calibration of ±σ (coverage of ±1σ/±2σ [%], CRPS and RMSE in the quantity's
    unit, mean σ); see :mod:`pseudotwin.live.metrics`."""
    if est.empty:
        return pd.DataFrame(columns=list(DAILY_COLUMNS))
    days, _ = hours.day_and_hours(est["ts"])
    e = est.assign(day=pd.to_datetime(days).date)
    out = []
    for (day, model), g in e.groupby(["day", "model"], sort=True):
        s = metrics.score(g["truth"].values, g["value"].values, g["std"].values)
        out.append((str(day), model, s.nrmse_pct, s.dmax_pct, s.pearson_r, s.n,
                    s.cover1_pct, s.cover2_pct, s.crps, s.mean_std, s.rmse))
    return pd.DataFrame(out, columns=list(DAILY_COLUMNS))


def monthly_scores(daily: pd.DataFrame) -> pd.DataFrame:
    """Monthly mean of daily NRMSE per model (thesis Tables 6.2–6.4)."""
    if daily.empty:
        return pd.DataFrame(columns=["month", "model", "nrmse_pct"])
    d = daily.assign(month=daily["day"].str[:7])
    m = d.groupby(["month", "model"], sort=True)["nrmse_pct"].mean().reset_index()
    return m


def evaluate(
    history: pd.DataFrame,
    spec: TwinSpec,
    train_start: dt.date,
    train_days: int = 5,
    models: Sequence[str] = ALL_MODELS,
    out: Path | None = None,
    options: dict[str, dict[str, Any]] | None = None,
    plot_day: dt.date | None = None,
    primary: str | None = None,
    thinning: Thinning | None = None,
    stale_after: dt.timedelta | None = None,
    skip_days: Collection[dt.date] = (),
) -> Evaluation:
    """Train on ``train_days`` days from ``train_start``, then score every later day.

    thinning: the window's policy (default: one point per sensor and minute, the daemon's
    default), for training (core/thinning.thin_history) and the scored days alike;
    stale_after: the daemon's (replay_estimates); skip_days: never trained on (train's
    --skip-days)."""
    t0 = time.perf_counter()
    target, hours = spec.target, spec.hours
    require_sensors(history, list(spec.sensors))
    # fail before training, not with an empty plot
    if plot_day is not None and plot_day not in _desk_days(history, spec):
        raise DataError(f"--plot-day {plot_day}: no readings of {target} in that day's "
                        f"operating hours ({hours.describe()}), nothing to plot")
    artifact = train_twin(history, spec, train_start, train_days, models, options, primary,
                          thinning=thinning, skip_days=skip_days)
    # Scored as the daemon takes readings: an 850 °C glitch is no day's truth or reference
    # (training left them out and said how many).
    history = plausible_readings(history, spec, warn=False)
    test_start = first_scored_day(artifact)
    if plot_day is not None and plot_day < test_start:
        raise DataError(f"--plot-day {plot_day} is not scored: the evaluated days begin on "
                        f"{test_start}, after training")
    # every model trained (training skips those that cannot serve this twin)
    est = replay_estimates(artifact, history, test_start, list(artifact.models),
                           thinning=thinning, stale_after=stale_after)
    if est.empty:
        raise DataError(
            f"no target readings of {target} in operating hours after the training period "
            f"(from {test_start} on): nothing to evaluate"
        )
    _name_unanswered_days(est, history, spec, test_start, stale_after)
    daily = daily_scores(est, hours)
    _name_thin_days(daily, spec)
    # before any output is written: a day the desk read but the twin never answered
    if plot_day is not None and str(plot_day) not in set(daily["day"]):
        raise DataError(f"--plot-day {plot_day}: no estimate of {target} that day (its "
                        f"references did not report), nothing to plot; "
                        f"{daily['day'].nunique()} day(s) scored, from {daily['day'].min()} "
                        f"to {daily['day'].max()}")
    monthly = monthly_scores(daily)
    ev = Evaluation(artifact, est, daily, monthly, time.perf_counter() - t0)
    if out is not None:
        write_outputs(ev, history, out, plot_day)
    return ev


def _desk_days(history: pd.DataFrame, spec: TwinSpec) -> set[dt.date]:
    """The local days with readings of the desk sensor in operating hours."""
    return _reporting_days(history, spec, spec.target)


def _reporting_days(history: pd.DataFrame, spec: TwinSpec, sensor: str) -> set[dt.date]:
    """The local days with readings of ``sensor`` in operating hours."""
    hours = spec.hours
    days, h = hours.day_and_hours(history.loc[history["sensor"] == sensor, "ts"])
    return set(pd.to_datetime(np.unique(days[hours.in_operating_hours(h)])).date)


def _name_unanswered_days(est: pd.DataFrame, history: pd.DataFrame, spec: TwinSpec,
                          start: dt.date, stale_after: dt.timedelta | None = None) -> None:
    """Log the days on which the desk reported but the twin never answered (its references
    silent): they are in no row, so every model's mean leaves them out; and the scored days
    on which a reference did not report in operating hours (answered all the same)."""
    answered = set(pd.to_datetime(np.unique(spec.hours.day_and_hours(est["ts"])[0])).date)
    missing = sorted(d for d in _desk_days(history, spec) - answered if d >= start)
    if missing:
        log.warning("%d day(s) with readings of %s but no estimate, as the references did not "
                    "report (left out of every score): %s", len(missing), spec.target,
                    _some_days(missing))
    # A day the reference never reported on in operating hours is still answered, from the
    # last value it reported before: scored like any other without --stale-after, while the
    # daemon (stale_after_minutes) publishes such estimates stale or from a failover.
    then = ("their estimates stale or from a failover (--stale-after)" if stale_after
            else "estimated from the last value it reported before, held (--stale-after "
                 "scores what the daemon would publish instead)")
    for ref in spec.references:
        held = sorted(d for d in answered - _reporting_days(history, spec, ref) if d >= start)
        if held:
            log.warning("%d scored day(s) on which %s did not report in operating hours, %s: "
                        "%s", len(held), ref, then, _some_days(held))


def _some_days(days: Sequence[object], shown: int = 10) -> str:
    return ", ".join(str(d) for d in days[:shown]) + (
        f" and {len(days) - shown} more" if len(days) > shown else "")


# What evaluate writes into its output folder, besides the plot of one day (DAY_PLOT).
ARTIFACT_FILE, ESTIMATES_FILE, DAILY_FILE, MONTHLY_FILE, NRMSE_PLOT = (
    "artifact.json", "estimates.csv", "daily.csv", "monthly.csv", "daily_nrmse.png")
OUTPUT_FILES = (ARTIFACT_FILE, ESTIMATES_FILE, DAILY_FILE, MONTHLY_FILE, NRMSE_PLOT)
DAY_PLOT = "day_{day}.png"


def write_outputs(
    ev: Evaluation, history: pd.DataFrame, out: Path, plot_day: dt.date | None = None
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    ev.artifact.save(out / ARTIFACT_FILE)
    est = ev.estimates.copy()
    est["ts"] = iso_utc(est["ts"])  # a sub-second reading keeps its stamp: it joins back
    est.to_csv(out / ESTIMATES_FILE, index=False, float_format="%.6g")
    ev.daily.to_csv(out / DAILY_FILE, index=False, float_format="%.4f")
    ev.monthly.to_csv(out / MONTHLY_FILE, index=False, float_format="%.4f")
    from pseudotwin.analysis.plots import plot_daily_nrmse, plot_day_estimate

    plot_daily_nrmse(ev.daily, out / NRMSE_PLOT, ev.artifact)
    day = plot_day or median_day(ev.daily, ev.artifact.primary)
    plot = None
    if day is not None:
        plot_day_estimate(ev, history, day, plot := out / DAY_PLOT.format(day=day))
    # An earlier run's day plot would sit beside this run's tables as if it were of them.
    for old in out.glob(DAY_PLOT.format(day="[0-9][0-9][0-9][0-9]-[0-9][0-9]-[0-9][0-9]")):
        if old != plot:
            old.unlink()
            log.info("removed %s, the plot of an earlier evaluation into %s", old.name, out)


THIN_SHARE = 0.5  # a day with fewer than this share of the usual scored readings is thin


def median_day(daily: pd.DataFrame, primary: str) -> dt.date | None:
    """The day whose primary-model NRMSE is the median: a typical day, not the best, among
    the days with at least half the usual number of scored readings (a day cut short by a
    gap in the data is not typical, and its plot spans an hour)."""
    d = daily[daily["model"] == primary]
    if d.empty:
        return None
    d = d[~_thin(d)].sort_values("nrmse_pct")
    return dt.date.fromisoformat(d["day"].iloc[len(d) // 2])


def _thin(rows: pd.DataFrame) -> pd.Series:
    """Of one model's daily rows, the days with fewer than half the usual (median) number
    of scored readings."""
    return rows["n"] < THIN_SHARE * rows["n"].median()


def _name_thin_days(daily: pd.DataFrame, spec: TwinSpec) -> None:
    """Warn of scored days with fewer than half the usual scored readings: each counts in the
    mean daily NRMSE as much as a full day, on less evidence."""
    d = daily[daily["model"] == ESTIMATE]
    thin = d[_thin(d)]
    if len(thin):
        log.warning("%d scored day(s) with fewer than half the usual %d scored readings of %s, "
                    "each counted in the mean daily NRMSE as a full day: %s", len(thin),
                    int(d["n"].median()), spec.target, _some_days(
                        [f"{day} (n = {n})" for day, n in zip(thin["day"], thin["n"],
                                                              strict=True)]))


def summary_table(ev: Evaluation) -> str:
    """Mean daily NRMSE / ΔT_max / r, ±2σ coverage and CRPS per model, as a Markdown table."""
    g = ev.daily.groupby("model").agg(
        nrmse_pct=("nrmse_pct", "mean"), dmax_pct=("dmax_pct", "mean"),
        pearson_r=("pearson_r", "median"), cover2_pct=("cover2_pct", "mean"),
        crps=("crps", "mean"), days=("day", "nunique"),
    )
    order = [m for m in (*ALL_MODELS,) if m in g.index] + sorted(
        m for m in g.index if m not in ALL_MODELS
    )
    unit = ev.artifact.unit
    lines = ["| model | mean daily NRMSE % | mean ΔT_max % | median daily r | ±2σ coverage % "
             f"| mean CRPS [{unit}] | days |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for m in order:
        row = g.loc[m]
        lines.append(
            f"| {m} | {_num(row.nrmse_pct)} | {_num(row.dmax_pct)} | {_num(row.pearson_r, 3)} "
            f"| {_num(row.cover2_pct, 1)} | {_num(row.crps, 3)} | {int(row.days)} |"
        )
    return "\n".join(lines)


def _num(x: float, nd: int = 2) -> str:
    """``x`` to ``nd`` decimals, an em dash when undefined (no σ, no r)."""
    return f"{x:.{nd}f}" if np.isfinite(x) else "—"
