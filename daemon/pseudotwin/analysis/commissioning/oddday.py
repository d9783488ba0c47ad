"""One training day unlike the others: the commissioning check of σ's day-level part.

No model's day-level σ is below the spread (std) of the training days' mean target −
reference offset (analysis/validation.py), and with five days one day can set that spread
alone: a day of commissioning work, the desk sensor settling in, the heating off. Whether
such a day will come back is what no statistic of the training days can say and the engineer
may know, so the check only advises; training keeps the day, and σ stays as wide as it says.

The test is Grubbs' (two-sided, α = 5 %) on the daily offsets: is the day farthest from the
mean an outlier of a normal sample of that size? Training days that are all ordinary (a normal
sample) are flagged one time in twenty. For five days it flags a day exactly when the spread
without it is below 0.328 of the spread with it.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

ALPHA = 0.05
MIN_DAYS = 3  # Grubbs' statistic needs n − 2 ≥ 1 degrees of freedom


def grubbs_critical(n: int, alpha: float = ALPHA) -> float:
    """Grubbs' two-sided critical value of max|x − mean| / s for a normal sample of n."""
    t = float(stats.t.ppf(1.0 - alpha / (2 * n), n - 2))
    return (n - 1) / np.sqrt(n) * np.sqrt(t * t / (n - 2 + t * t))


@dataclass(frozen=True)
class OddDay:
    """A training day unlike the others.

    offset: its mean target − reference offset [unit]; others: the other days' [unit];
    spread, spread_without: std (ddof 1) of all the days' offsets and of the others' [unit].
    """

    day: dt.date
    offset: float
    others: tuple[float, ...]
    spread: float
    spread_without: float

    def advice(self, unit: str, references: int = 1) -> str:
        """What the engineer can do about it, in two sentences and a choice; ``references``:
        how many references the twin has (the offset is from their mean)."""
        base = "the reference" if references == 1 else f"the mean of the {references} references"
        return (
            f"One training day is unlike the others: on {self.day} the desk sensor read "
            f"{self.offset:+.2f} {unit} from {base} on average, on the other days "
            f"{min(self.others):+.2f} to {max(self.others):+.2f} {unit} (Grubbs' test, "
            f"{100 * ALPHA:.0f} %). The spread of the daily offset, the floor of every model's "
            f"day-level σ, is {self.spread:.2f} {unit} with it and {self.spread_without:.2f} "
            f"{unit} without. If that day was unusual for a reason that will not come back "
            f"(commissioning work, the sensor settling in, the heating off, a window left "
            f"open), train without it (--skip-days {self.day}); if days like it will come "
            "back, keep it: σ is then as wide as it should be.")


def odd_day(offsets: Mapping[dt.date, float], alpha: float = ALPHA) -> OddDay | None:
    """The training day whose offset is an outlier among ``offsets`` (day → mean target −
    reference offset [unit]), or None: too few days, all alike, or none an outlier."""
    days = sorted(d for d, x in offsets.items() if np.isfinite(x))
    x = np.array([offsets[d] for d in days])
    if len(x) < MIN_DAYS:
        return None
    spread = float(np.std(x, ddof=1))
    if not spread > 0:
        return None
    i = int(np.argmax(np.abs(x - x.mean())))
    if abs(x[i] - x.mean()) / spread <= grubbs_critical(len(x), alpha):
        return None
    rest = np.delete(x, i)
    return OddDay(days[i], float(x[i]), tuple(float(v) for v in rest), spread,
                  float(np.std(rest, ddof=1)))


def odd_training_day(validation: Mapping[str, Any]) -> OddDay | None:
    """:func:`odd_day` of an artifact's ``validation`` (None for artifacts saved before it
    recorded the daily offsets, or not validated)."""
    saved = validation.get("offset_by_day") or {}
    return odd_day({dt.date.fromisoformat(d): float(x) for d, x in saved.items()
                    if x is not None})
