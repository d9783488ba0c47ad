"""An honest σ: what a model's estimate does not know today, measured on the training days.

A model's own spread (TRIV's slot RMSE, the GP's posterior std) describes the days it was fit
on. What the twin does not know on a *new* day is dominated by the day-to-day variation of the
reference–target offset, which no reading of today reveals. The calibration therefore comes
from leave-one-day-out replays of the training days (``analysis/validation.py``): each day is
estimated by the model trained on the other days, exactly as the daemon would, and the errors
e [unit] are split into

- a day level b_d = mean of e over day d: s_b² = mean_d b_d² (uncentred, so a systematic bias
  of, say, the raw reference stays in σ), never below the spread of the daily mean
  reference–target offset across the training days (``offset_var``): a model cannot know
  today's offset better than the offset varies, however well it did on five alike days;
- a within-day part w = e − b_d whose variance grows with how fast the references move:
  w² ≈ a(τ) + k·|ṙ| (non-negative least squares), a(τ) in 1-hour bins of wall-clock time,
  each shrunk towards the pooled a (the pooled value counts as ``SHRINK_DAYS`` extra days);
  a bin stands out only as far as two training days show it: the day with the bin's largest
  mean of w² − k·|ṙ| counts at the next day's level (a bin seen on one day only is at the
  level of the others), and what that takes off (or adds) is spread over every reading. One wild
  hour of one day (say a CO2 spike at noon) says that such an hour can come, not that it
  comes at noon: σ keeps the risk, but not its time of day;

σ²(t) = C · (s_b² + a(τ) + k·|ṙ(t)|), with ṙ the references' net change per hour over the last
``SLOPE_WINDOW_H`` of today's window [unit/h] and C = (t_ν(Φ(2)) / 2)² the small-sample
widening of a ±2σ band whose variance was estimated from a few days (ν by
Welch–Satterthwaite from the day-level and within-day degrees of freedom).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import nnls

BIN_HOURS = 1.0  # width of the time-of-day bins of the within-day spread [h]
SHRINK_DAYS = 2.0  # weight of the pooled within-day variance in each bin [days]
BIN_FLOOR = 0.25  # a bin's variance never drops below this share of the pooled one
WITHIN_DAY_DOF = 11.0  # ~independent within-day residuals per day (errors decorrelate in ~1 h)
SLOPE_WINDOW_H = 0.5  # [h] the references' slope is taken over this much of the window
Z2 = 2.0


@dataclass(frozen=True)
class SigmaCalibration:
    """σ of one model, from its leave-one-day-out errors on the training days.

    day_var: s_b² [unit²]; within_var: pooled a [unit²]; bins: hour bin → a(τ) [unit²];
    slope_coef: k [unit²/(unit/h)]; factor: C; days: training days it was estimated on.
    """

    day_var: float
    within_var: float
    slope_coef: float
    factor: float
    days: int
    bins: dict[int, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        values = (self.day_var, self.within_var, self.slope_coef, self.factor,
                  *self.bins.values())
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError("σ calibration needs finite, non-negative numbers")

    def sigma(self, hours: float, slope: float) -> float:
        """σ [unit] at wall-clock ``hours`` [h] with the references moving at ``slope`` [unit/h]."""
        a = self.bins.get(int(math.floor(hours / BIN_HOURS)), self.within_var)
        return math.sqrt(self.factor * (self.day_var + a + self.slope_coef * abs(slope)))

    @classmethod
    def fit(cls, day: np.ndarray, hours: np.ndarray, error: np.ndarray, slope: np.ndarray,
            offset_var: float = 0.0) -> SigmaCalibration:
        """From held-out errors: day [n] (labels), hours [n] [h], error [n] = estimate − truth,
        slope [n] |ṙ| at each estimate [unit/h]; offset_var: floor of the day-level variance."""
        labels, inverse = np.unique(day, return_inverse=True)
        n_days = len(labels)
        if n_days == 0:
            raise ValueError("no held-out errors to calibrate on")
        b = np.bincount(inverse, weights=error) / np.bincount(inverse)
        day_var = max(float(np.mean(b**2)), float(offset_var))
        w2 = (error - b[inverse]) ** 2
        s = np.abs(slope)
        (a, k), _ = nnls(np.column_stack([np.ones(len(w2)), s]), w2)
        a = max(float(a), 1e-12)
        rest = w2 - k * s
        bins: dict[int, float] = {}
        idx = np.floor(hours / BIN_HOURS).astype(int)
        keys = np.unique(idx)
        sel = {bi: idx == bi for bi in keys}
        count = {bi: float(np.sum(m)) for bi, m in sel.items()}
        two_day = {bi: _two_day_mean(inverse[m], rest[m]) for bi, m in sel.items()}
        shown = {bi: v for bi, v in two_day.items() if v is not None}
        # A bin seen on one day only is at the level of the bins two days show.
        typical = (sum(count[bi] * v for bi, v in shown.items()) / sum(count[bi] for bi in shown)
                   if shown else float(np.mean(rest)))
        own = {bi: shown.get(bi, typical) for bi in keys}
        # What the two-day rule took from single days is spread over every reading: the risk
        # stays in σ (the bins' total is kept), only its time of day is not believed.
        spread = (float(np.sum(rest)) - sum(count[bi] * own[bi] for bi in keys)) / len(rest)
        for bi in keys:
            n = count[bi]
            n0 = SHRINK_DAYS * n / n_days
            bins[int(bi)] = max((n * (own[bi] + spread) + n0 * a) / (n + n0), BIN_FLOOR * a)
        within = float(np.mean(w2))
        total = day_var + within
        # The held-out day levels are centred on the other days' mean: n − 1 dof.
        day_dof = max(n_days - 1, 1)
        nu = total**2 / (day_var**2 / day_dof + within**2 / (WITHIN_DAY_DOF * n_days) + 1e-300)
        # No held-out error at all (the target is a copy of a reference): nothing to widen.
        from scipy import stats  # training only: the daemon need not load scipy.stats

        factor = float((stats.t.ppf(stats.norm.cdf(Z2), max(nu, 1.0)) / Z2) ** 2
                       if total > 0 else 1.0)
        return cls(day_var, a, float(k), factor, n_days, bins)

    def to_dict(self) -> dict[str, Any]:
        return {
            "day_var": self.day_var, "within_var": self.within_var,
            "slope_coef": self.slope_coef, "factor": self.factor, "days": self.days,
            "bins": {str(k): v for k, v in sorted(self.bins.items())},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SigmaCalibration:
        return cls(
            float(d["day_var"]), float(d["within_var"]), float(d["slope_coef"]),
            float(d["factor"]), int(d["days"]),
            {int(k): float(v) for k, v in d.get("bins", {}).items()},
        )


def _two_day_mean(day: np.ndarray, value: np.ndarray) -> float | None:
    """Mean of ``value`` [n] over its days ``day`` [n] (labels), the day with the largest mean
    taken at the second largest day's mean (winsorized), so no single day sets it alone;
    None when only one day has values."""
    labels, inverse, counts = np.unique(day, return_inverse=True, return_counts=True)
    if len(labels) < 2:
        return None
    means = np.bincount(inverse, weights=value) / counts
    top = int(np.argmax(means))
    means[top] = float(np.max(np.delete(means, top)))
    return float(np.sum(means * counts) / np.sum(counts))
