"""Figures of an evaluation: daily NRMSE per model (thesis Fig. 6.5) and one day's
references, truth and estimate with the ±2σ band (Fig. 6.9).

Made to be read by someone commissioning a twin: labelled axes with units, a legend that
names the models and the sensors, the raw reference drawn next to the models (the floor
every model has to beat), the published estimate drawn distinctly, a log y-axis when one
model's errors dwarf the others', and no line drawn across days (or hours) without data.
``*_figure`` build the figure (for tests and the report); ``plot_*`` save it as PNG.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")  # headless edge boxes and CI have no display
import matplotlib.dates as mdates  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import ScalarFormatter  # noqa: E402

from pseudotwin.analysis.replay import ESTIMATE, REF_PREFIX  # noqa: E402
from pseudotwin.errors import DataError  # noqa: E402

if TYPE_CHECKING:
    from pseudotwin.analysis.evaluate import Evaluation
    from pseudotwin.live.artifact import Artifact

LOG_RATIO = 5.0  # log y-axis when the worst model's mean NRMSE exceeds 5× the median model's
DAY_GAP = pd.Timedelta(days=1)  # consecutive scored days further apart are not joined
ESTIMATE_GAP = pd.Timedelta(hours=1)  # nor estimates of one day further apart than this
_REF_STYLES = ("--", "-.", ":", (0, (5, 1, 1, 1)))


def with_gaps(x: pd.DatetimeIndex, gap: pd.Timedelta, *ys: np.ndarray
              ) -> tuple[pd.DatetimeIndex, list[np.ndarray]]:
    """``x`` (sorted) and each of ``ys`` with a NaN point inserted halfway into every gap
    longer than ``gap``, so matplotlib breaks the line there instead of bridging it."""
    x = pd.DatetimeIndex(x).as_unit("ns")
    cut = np.flatnonzero(np.diff(x.asi8) > gap.value) + 1
    if not len(cut):
        return x, [np.asarray(y, dtype=float) for y in ys]
    mid = x.asi8[cut - 1] + (x.asi8[cut] - x.asi8[cut - 1]) // 2
    xs = pd.DatetimeIndex(np.insert(x.asi8, cut, mid).astype("datetime64[ns]"))
    if x.tz is not None:
        xs = xs.tz_localize("UTC").tz_convert(x.tz)
    return xs, [np.insert(np.asarray(y, dtype=float), cut, np.nan) for y in ys]


def _model_label(model: str, target: str, primary: str) -> str:
    if model == ESTIMATE:
        return f"estimate of {target} (published: {primary})"
    if model.startswith(REF_PREFIX):
        return f"raw reference {model[len(REF_PREFIX):]}"
    if model == "ref":
        return "ref (closest reference held)"
    return f"{model} (primary)" if model == primary else model


def _dwarfed(daily: pd.DataFrame) -> tuple[bool, str]:
    """Whether one model's mean daily NRMSE dwarfs the others' (→ log axis), and a note."""
    means = daily.groupby("model")["nrmse_pct"].mean()
    means = means[np.isfinite(means) & (means > 0)]
    if len(means) < 2:
        return False, ""
    ratio = float(means.max() / means.median())
    if ratio <= LOG_RATIO:
        return False, ""
    return True, (f"log scale: {means.idxmax()}'s mean NRMSE is {ratio:.0f}× the median "
                  "model's")


def daily_nrmse_figure(daily: pd.DataFrame, target: str, references: Sequence[str],
                       primary: str) -> Figure:
    """Daily NRMSE [%] of every model, the raw references and the published estimate."""
    fig, ax = plt.subplots(figsize=(11, 4.5))
    models = sorted(map(str, daily["model"].unique()),
                    key=lambda m: (m == ESTIMATE, m.startswith(REF_PREFIX), m))
    refs = [m for m in models if m.startswith(REF_PREFIX)]
    for model in models:
        g = daily[daily["model"] == model].sort_values("day")
        x, (y,) = with_gaps(pd.DatetimeIndex(pd.to_datetime(g["day"])), DAY_GAP,
                            g["nrmse_pct"].to_numpy())
        label = _model_label(model, target, primary)
        if model == ESTIMATE:
            # a wide band under the models: distinct, and hides none that coincide with it
            ax.plot(x, y, color="black", lw=6, alpha=0.3, marker="s", ms=8, zorder=1,
                    label=label)
        elif model.startswith(REF_PREFIX):
            ax.plot(x, y, color="0.45", lw=1.5, marker="^", ms=4, zorder=4, label=label,
                    linestyle=_REF_STYLES[refs.index(model) % len(_REF_STYLES)])
        else:
            ax.plot(x, y, lw=1.2, marker="o", ms=3, alpha=0.85, label=label)
    log, note = _dwarfed(daily)
    if log:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(ScalarFormatter())
        ax.text(0.01, 0.98, note, transform=ax.transAxes, va="top", fontsize=8, color="0.3")
    ax.set_xlabel("day")
    ax.set_ylabel("daily NRMSE [%]")
    ax.set_title(f"{target} (desk) from {', '.join(references)}: daily NRMSE per model")
    ax.grid(alpha=0.3, which="both" if log else "major")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
              title="model / sensor", title_fontsize=8)
    fig.autofmt_xdate()
    fig.tight_layout()
    return fig


def plot_daily_nrmse(daily: pd.DataFrame, path: Path, artifact: Artifact) -> None:
    fig = daily_nrmse_figure(daily, artifact.target, artifact.references, artifact.primary)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def day_figure(ev: Evaluation, history: pd.DataFrame, day: dt.date) -> Figure:
    """One evaluated day: the references' readings, the desk truth, the published estimate
    and its ±2σ band, in local time. DataError when the day has no estimates."""
    a = ev.artifact
    hours = a.hours
    tz = hours.timezone
    est = ev.estimates
    loc = pd.DatetimeIndex(est["ts"]).tz_convert(tz)
    model = ESTIMATE if (est["model"] == ESTIMATE).any() else a.primary
    e = est[(loc.date == day) & (est["model"] == model)].sort_values("ts")
    if e.empty:
        scored = sorted(ev.daily["day"].unique())
        span = f"{scored[0]} … {scored[-1]}" if scored else "none"
        raise DataError(f"no estimates of {a.target} on {day} to plot (scored days: {span})")
    fig, ax = plt.subplots(figsize=(11, 4.5))
    h_loc = pd.DatetimeIndex(history["ts"]).tz_convert(tz)
    start = pd.Timestamp(hours.at(day, hours.init_start))
    end = pd.Timestamp(hours.at(day, hours.day_end))
    for s in a.references:
        m = (history["sensor"] == s).to_numpy() & (h_loc >= start) & (h_loc <= end)
        ax.step(h_loc[m], history["value"].to_numpy()[m], where="post", lw=1.2,
                label=f"reference {s} (raw)")
    t = pd.DatetimeIndex(e["ts"]).tz_convert(tz)
    ax.plot(t, e["truth"], "k.", ms=4, label=f"truth {a.target} (desk sensor)")
    tg, (v, sd) = with_gaps(t, ESTIMATE_GAP, e["value"].to_numpy(), e["std"].to_numpy())
    what = f"published {a.primary}" if model == ESTIMATE else a.primary
    ax.plot(tg, v, lw=1.8, color="tab:red", label=f"estimate of {a.target} ({what})")
    ax.fill_between(tg, v - 2 * sd, v + 2 * sd, color="tab:red", alpha=0.2,
                    label="estimate ±2σ")
    ax.set_xlabel(f"local time ({tz})")
    ax.set_ylabel(f"{a.quantity.value} [{a.unit}]")
    ax.xaxis.set_major_formatter(mdates.DateFormatter("%H:%M", tz=t.tz))
    ax.set_title(f"{a.target} on {day}")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    return fig


def plot_day_estimate(ev: Evaluation, history: pd.DataFrame, day: dt.date, path: Path) -> None:
    fig = day_figure(ev, history, day)
    fig.savefig(path, dpi=110)
    plt.close(fig)
