"""Figures of an evaluation: daily NRMSE per model (thesis Fig. 6.5) and one day's
references, truth and estimate with the ±2σ band (Fig. 6.9)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")  # headless edge boxes and CI have no display
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

if TYPE_CHECKING:
    from pseudotwin.analysis.evaluate import Evaluation
    from pseudotwin.live.artifact import Artifact


def plot_daily_nrmse(daily: pd.DataFrame, path: Path, artifact: Artifact) -> None:
    fig, ax = plt.subplots(figsize=(10, 4))
    for model, g in daily.groupby("model"):
        if str(model).startswith("ref:"):
            continue
        ax.plot(pd.to_datetime(g["day"]), g["nrmse_pct"], marker="o", ms=3, label=model)
    ax.set_ylabel("daily NRMSE [%]")
    ax.set_title(f"{artifact.target} from {', '.join(artifact.references)}")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.autofmt_xdate()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_day_estimate(ev: Evaluation, history: pd.DataFrame, day: dt.date, path: Path) -> None:
    a = ev.artifact
    hours = a.hours
    tz = hours.timezone
    est = ev.estimates
    loc = pd.DatetimeIndex(est["ts"]).tz_convert(tz)
    e = est[(loc.date == day) & (est["model"] == a.primary)]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    h_loc = pd.DatetimeIndex(history["ts"]).tz_convert(tz)
    start = pd.Timestamp(hours.at(day, hours.init_start))
    end = pd.Timestamp(hours.at(day, hours.day_end))
    for s in a.references:
        m = (history["sensor"] == s).values & (h_loc >= start) & (h_loc <= end)
        ax.step(h_loc[m], history["value"].values[m], where="post", lw=1, label=f"reference {s}")
    if not e.empty:
        t = pd.DatetimeIndex(e["ts"]).tz_convert(tz)
        ax.plot(t, e["truth"], "k.", ms=4, label=f"truth {a.target}")
        ax.plot(t, e["value"], lw=1.5, label=f"{a.primary} estimate")
        ax.fill_between(t, e["value"] - 2 * e["std"], e["value"] + 2 * e["std"], alpha=0.25,
                        label="±2σ")
    ax.set_ylabel(f"{a.quantity} [{a.unit}]")
    ax.set_title(f"{day} ({tz})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.autofmt_xdate()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
