"""Scores of the self-aware indication (quality ``uncertain``, live/envelope.py): does the twin
know when today is unlike training? Its ``uncertain`` estimates should err more than its
``ok`` ones, it should hardly fire on the training days themselves, and ±2σ should cover
the truth for both (the widened σ of ``uncertain`` included). Which criteria may fire at all is
decided on the held-out training days (analysis/criteria.py); these are the scores on the days
that decision never saw."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
import pandas as pd

from pseudotwin.analysis.criteria import Judged, abs_errors, fired_sets, judge_rows
from pseudotwin.analysis.replay import ESTIMATE, replay_estimates
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Quality


@dataclass(frozen=True)
class SelfAware:
    """Over a run's published (``estimate``) rows: n of ``ok`` and ``uncertain``, the share
    of ``uncertain`` among both, MAE [unit] and ±2σ coverage [%] of each; train_share: share of
    ``uncertain`` when the training days are replayed (NaN: not measured)."""

    n_ok: int
    n_uncertain: int
    mae_ok: float
    mae_uncertain: float
    cover2_ok: float
    cover2_uncertain: float
    train_share: float = float("nan")

    @property
    def share(self) -> float:
        n = self.n_ok + self.n_uncertain
        return self.n_uncertain / n if n else float("nan")

    @property
    def mae_ratio(self) -> float:
        """MAE of uncertain / MAE of ok (the issue's figure: ≥ 2 where it fires)."""
        return self.mae_uncertain / self.mae_ok if self.mae_ok > 0 else float("nan")


def _mae_cover(rows: pd.DataFrame) -> tuple[float, float]:
    if rows.empty:
        return float("nan"), float("nan")
    err = (rows["value"] - rows["truth"]).abs().to_numpy()
    return float(np.mean(err)), float(100 * np.mean(err <= 2 * rows["std"].to_numpy()))


def selfaware(estimates: pd.DataFrame, train_share: float = float("nan")) -> SelfAware:
    """From replay rows (replay.COLUMNS), their ``estimate`` model only."""
    e = estimates[estimates["model"] == ESTIMATE]
    ok = e[e["quality"] == Quality.OK.value]
    unc = e[e["quality"] == Quality.UNCERTAIN.value]
    (mae_ok, cover_ok), (mae_unc, cover_unc) = _mae_cover(ok), _mae_cover(unc)
    return SelfAware(len(ok), len(unc), mae_ok, mae_unc, cover_ok, cover_unc, train_share)


def training_share(artifact: Artifact, history: pd.DataFrame) -> float:
    """Share of ``uncertain`` among the published estimates when the artifact's own training
    days are replayed through a Twin (the primary only, to keep it cheap)."""
    days = [dt.date.fromisoformat(d) for d in artifact.training.get("days", [])]
    if not days:
        return float("nan")
    est = replay_estimates(artifact, history, days[0], models=[artifact.primary], end=days[-1])
    if est.empty:
        return float("nan")
    local_day, _ = artifact.hours.day_and_hours(est["ts"])
    trained = np.isin(local_day.astype("datetime64[D]"), np.array(days, dtype="datetime64[D]"))
    e = est[(est["model"] == ESTIMATE).to_numpy() & trained]
    if e.empty:
        return float("nan")
    return float(np.mean(e["quality"] == Quality.UNCERTAIN.value))


@dataclass(frozen=True)
class OnTest:
    """One criterion on the test days, kept or not (a dropped one is recorded, never acting):
    judged there by the rule validation applies to the held-out days (analysis/criteria.py),
    the share of the published estimates it fired on [%] and their ±2σ coverage with σ as
    published [%]."""

    judged: Judged
    share_pct: float
    cover2_pct: float


def criteria_on_test(artifact: Artifact, history: pd.DataFrame,
                     test_start: dt.date) -> dict[str, OnTest]:
    """Every criterion of the artifact's training ranges on the days from ``test_start`` on:
    would it have flagged larger errors where validation could not tell? The evidence behind
    validation's choice, not an input to it (a replay of the primary only)."""
    if artifact.envelope is None:
        return {}
    est = replay_estimates(artifact, history, test_start, models=[artifact.primary],
                           criteria=True)
    rows = est[(est["model"] == ESTIMATE)
               & est["quality"].isin([Quality.OK.value, Quality.UNCERTAIN.value])]
    days, _ = artifact.hours.day_and_hours(rows["ts"])
    rows = rows.assign(day=days)
    fired_on = fired_sets(rows)
    judged = judge_rows(artifact.envelope.criteria, rows, fired_on, abs_errors(rows))
    out: dict[str, OnTest] = {}
    for key, j in judged.items():
        fired = np.array([key in f for f in fired_on], dtype=bool)
        share = 100.0 * j.n / len(rows) if len(rows) else float("nan")
        out[key] = OnTest(j, share, _mae_cover(rows[fired])[1])
    return out
