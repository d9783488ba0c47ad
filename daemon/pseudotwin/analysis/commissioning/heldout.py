"""What validation saw on the held-out training days, ready to score and plot.

The rows are the ones :func:`pseudotwin.analysis.validation.validate` replayed through the
daemon's twin code, each day estimated by models trained on the other days; nothing is
refit here. Each model's std is replaced by its σ calibrated on the *other* held-out days
(nested, as validation's coverage and CRPS score it): the σ the daemon publishes is
calibrated on every training day, the shown day included, so on that day it would cover by
construction. A day with fewer than two others to calibrate on has no σ.
"""

from __future__ import annotations

import base64
import datetime as dt
import io
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from pseudotwin.analysis.evaluate import Evaluation, daily_scores
from pseudotwin.analysis.replay import REF_PREFIX
from pseudotwin.analysis.validation import NESTED_STD, Validation
from pseudotwin.live.artifact import Artifact

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclass(frozen=True)
class HeldOut:
    """Held-out estimates (replay columns, σ calibrated) and their daily scores
    (evaluate's ``DAILY_COLUMNS``), as an :class:`Evaluation` so the evaluate plots apply."""

    evaluation: Evaluation

    @property
    def daily(self) -> pd.DataFrame:
        return self.evaluation.daily

    def primary_days(self) -> pd.DataFrame:
        """The primary's held-out daily scores, best day first."""
        d = self.daily[self.daily["model"] == self.evaluation.artifact.primary]
        return d.sort_values("nrmse_pct", kind="stable").reset_index(drop=True)

    def typical_and_worst(self) -> list[tuple[str, dt.date]]:
        """[("typical", median day), ("worst", worst day)] of the primary; one entry when
        they coincide, none without scores."""
        d = self.primary_days()
        if d.empty:
            return []
        median = dt.date.fromisoformat(d["day"].iloc[len(d) // 2])
        worst = dt.date.fromisoformat(d["day"].iloc[-1])
        return [("typical (median)", median)] + ([("worst", worst)] if worst != median else [])

    def reference_scores(self) -> pd.DataFrame:
        """Per raw reference: mean held-out daily NRMSE [%] and median daily Pearson r with
        the target, next to the primary's mean NRMSE."""
        rows = []
        for r in self.evaluation.artifact.references:
            g = self.daily[self.daily["model"] == REF_PREFIX + r]
            rows.append((r, float(g["nrmse_pct"].mean()) if len(g) else np.nan,
                         float(g["pearson_r"].median()) if len(g) else np.nan, len(g)))
        return pd.DataFrame(rows, columns=["reference", "nrmse_pct", "pearson_r", "days"])


def held_out(artifact: Artifact, validation: Validation) -> HeldOut:
    """The validation's held-out rows with σ calibrated without each row's day, scored per
    day."""
    rows = validation.held_out
    if rows.empty:
        est = rows
    else:
        # No σ where none could be calibrated without the day (as validation scores it): the
        # published one would cover that day by construction.
        est = rows.drop(columns=["day", NESTED_STD]).assign(std=rows[NESTED_STD])
    daily = daily_scores(est, artifact.hours)
    return HeldOut(Evaluation(artifact, est, daily, pd.DataFrame(), validation.seconds))


def png_data_uri(fig: Figure) -> str:
    """A matplotlib figure as a ``data:image/png;base64,…`` URI (the figure is closed)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def figures(ho: HeldOut, history: pd.DataFrame) -> list[tuple[str, str]]:
    """(caption, PNG data URI): the held-out daily NRMSE of every model and the raw
    references, then the primary's typical and worst held-out days."""
    from pseudotwin.analysis.plots import daily_nrmse_figure, day_figure

    a = ho.evaluation.artifact
    out = []
    if not ho.daily.empty:
        fig = daily_nrmse_figure(ho.daily, a.target, a.references, a.primary)
        fig.axes[0].set_title(f"{a.target}: held-out daily NRMSE on the training days")
        out.append(("Held-out daily NRMSE of every model and of the raw references on each "
                    "training day (each day estimated by models trained on the other days).",
                    png_data_uri(fig)))
    for what, day in ho.typical_and_worst():
        fig = day_figure(ho.evaluation, history, day)
        fig.axes[0].set_title(f"{a.target} on {day}, held out: the primary's {what} day")
        out.append((f"The primary's {what} held-out day, {day}: the references' raw "
                    f"readings, the desk truth, the {a.primary} estimate and its ±2σ band, "
                    "calibrated on the other training days.", png_data_uri(fig)))
    return out
