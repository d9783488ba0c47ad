"""What "like training" means for a twin's references: the self-aware failing indication
(thesis ch. 4, DESIGN.md §6 quality ``uncertain``).

From the training days only, per reference, three ranges of what it did in operating hours:

- its level (the reading's value) [unit];
- its deviation from its own mean daily profile (the TRIV profile: mean over the training days
  of its sample-and-hold value per slot) [unit];
- how fast it moved: |slope| over the last ``SLOPE_WINDOW_H`` [unit/h], the term that drives
  the calibrated σ (live/calibration.py): a reference moving faster than in any training hour
  puts σ above the level the validation measured.

Each range is fixed a priori, never tuned on test days: the robust quantiles
[q(``Q_LO``), q(``Q_HI``)] of the training readings widened on both sides by ``MARGIN`` × their
span (slope: the upper bound only). Live, a reference whose latest value, deviation or slope
falls outside makes the twin's ``ok`` estimates ``uncertain`` with σ × ``WIDEN``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.live.calibration import SLOPE_WINDOW_H
from pseudotwin.models.base import TrainingSet

Q_LO, Q_HI = 0.005, 0.995  # robust: a glitch or two of the training days does not set a bound
MARGIN = 0.25  # share of the inter-quantile span added on each side
WIDEN = 2.0  # σ factor of an uncertain estimate: the calibration no longer describes today


@dataclass(frozen=True)
class RefEnvelope:
    """One reference's training ranges: level and deviation (lo, hi) [unit], slope_hi [unit/h],
    profile [S] its mean sample-and-hold value per window slot [unit]."""

    level: tuple[float, float]
    deviation: tuple[float, float]
    slope_hi: float
    profile: tuple[float, ...]

    def why(self, sensor: str, hours: OperatingHours, h: float, value: float,
            slope: float) -> list[str]:
        """Why ``sensor`` reading ``value`` at wall-clock ``h`` and moving at ``slope`` is
        unlike training (empty: it is like training)."""
        out = []
        lo, hi = self.level
        if not lo <= value <= hi:
            out.append(f"{sensor}: level {value:.4g} outside training {lo:.4g}…{hi:.4g}")
        dev = value - self.profile[hours.window_slot_index(h)]
        lo, hi = self.deviation
        if not lo <= dev <= hi:
            out.append(f"{sensor}: deviation from its daily profile {dev:+.3g} outside "
                       f"training {lo:+.3g}…{hi:+.3g}")
        if slope > self.slope_hi:
            out.append(f"{sensor}: moving at {slope:.3g}/h, faster than in training "
                       f"(≤ {self.slope_hi:.3g}/h): σ above its validated level")
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"level": list(self.level), "deviation": list(self.deviation),
                "slope_hi": self.slope_hi, "profile": list(self.profile)}

    @classmethod
    def from_dict(cls, d: dict[str, Any], n_slots: int) -> RefEnvelope:
        lv, dv = d["level"], d["deviation"]
        profile = tuple(float(x) for x in d["profile"])
        if len(profile) != n_slots:
            raise ValueError("envelope profile does not match the slot grid")
        return cls((_bound(lv[0], -1), _bound(lv[1], 1)), (_bound(dv[0], -1), _bound(dv[1], 1)),
                   _bound(d["slope_hi"], 1), profile)


def _bound(x: float | None, sign: int) -> float:
    """A stored bound; null is an open one (saved artifacts write ±inf as null)."""
    return sign * math.inf if x is None else float(x)


@dataclass(frozen=True)
class Envelope:
    """The training ranges of every reference: sensor → :class:`RefEnvelope`."""

    refs: dict[str, RefEnvelope]

    @classmethod
    def fit(cls, training: TrainingSet) -> Envelope:
        hours = training.hours
        out = {}
        for s in training.references:
            slots = np.array([d.slot_values(s, hours) for d in training.days])
            with np.errstate(invalid="ignore"):
                ok = np.isfinite(slots).any(axis=0)
                profile = np.full(slots.shape[1], np.nan)
                profile[ok] = np.nanmean(slots[:, ok], axis=0)
            x = np.arange(len(profile))
            profile = np.interp(x, x[ok], profile[ok])
            levels, devs, slopes = [], [], []
            for d in training.days:
                if not d.has(s):
                    continue
                h, v = d.series[s]
                sel = hours.in_operating_hours(h)
                idx = hours.slot_of(h[sel]) - hours.window_slots()[0]
                levels.append(v[sel])
                devs.append(v[sel] - profile[np.clip(idx, 0, len(profile) - 1)])
                slopes.append(_slopes(h, v)[sel])
            out[s] = RefEnvelope(_range(np.concatenate(levels)), _range(np.concatenate(devs)),
                                 _range(np.concatenate(slopes))[1],
                                 tuple(float(p) for p in profile))
        return cls(out)

    def to_dict(self) -> dict[str, Any]:
        return {"rule": {"quantiles": [Q_LO, Q_HI], "margin": MARGIN, "widen": WIDEN},
                "references": {s: r.to_dict() for s, r in self.refs.items()}}

    @classmethod
    def from_dict(cls, d: dict[str, Any], hours: OperatingHours) -> Envelope:
        n = len(hours.window_slots())
        return cls({str(s): RefEnvelope.from_dict(r, n) for s, r in d["references"].items()})


def _range(x: np.ndarray) -> tuple[float, float]:
    """[q_lo − m, q_hi + m] with m = MARGIN × (q_hi − q_lo) over the finite values of ``x``."""
    x = x[np.isfinite(x)]
    if not len(x):  # nothing seen: nothing can be called unlike it
        return -math.inf, math.inf
    lo, hi = np.quantile(x, [Q_LO, Q_HI])
    m = MARGIN * (hi - lo)
    return float(lo - m), float(hi + m)


def _slopes(h: np.ndarray, v: np.ndarray) -> np.ndarray:
    """|slope| [unit/h] at every reading as Twin.slope takes it: from the reading held
    ``SLOPE_WINDOW_H`` earlier (or the first) to this one, over at least that span."""
    i0 = np.maximum(np.searchsorted(h, h - SLOPE_WINDOW_H, side="right") - 1, 0)
    span = np.maximum(h - h[i0], SLOPE_WINDOW_H)
    return np.abs(v - v[i0]) / span
