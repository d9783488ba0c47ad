"""What "like training" means for a twin's references: the self-aware failing indication
(thesis ch. 4, DESIGN.md §6 quality ``uncertain``).

From the training days only, per reference, three ranges of what it did in operating hours:

- its level (the reading's value) [unit];
- its deviation from its own mean daily profile (the TRIV profile: mean over the training days
  of its sample-and-hold value per slot) [unit];
- how fast it moved: |slope| over the last ``SLOPE_WINDOW_H`` [unit/h], the term that drives
  the calibrated σ (live/calibration.py): a reference moving faster than in any training hour
  puts σ above the level the validation measured.

and, per pair of references (a twin with two or more), how far they drifted apart: the gap
between their deviations from their daily profiles, (a − profile_a) − (b − profile_b) [unit],
at every reading of either (the other's value held). References that move together as in
training keep it small whatever the day's level; one that decouples from the other (a heater
or an open window next to one of them, a sensor drifting) pushes it out of range: the
"references decorrelated" of DESIGN.md §6, as it shows at an instant.

Each range is fixed a priori, never tuned on test days: the robust quantiles
[q(``Q_LO``), q(``Q_HI``)] of the training readings widened on both sides by ``MARGIN`` × their
span (slope: the upper bound only). Each (kind, reference) is one *criterion*, keyed
``"<kind>:<sensor>"`` with kind ``level``, ``deviation`` or ``speed``; each pair of references
is one more, ``"disagreement:<a>|<b>"`` (a, b in the twin's order of references).

Out of range is not necessarily a larger error, so a criterion only acts where the training
days show it flags one (analysis/criteria.py judges each on the held-out days of validation):
live, a reference whose latest value, deviation or slope falls outside a *kept* criterion makes
the twin's ``ok`` estimates ``uncertain`` with σ × ``widen``. Criteria not kept change
nothing; a twin asked to record them (``Twin(record_unlike=True)``, validation's replays)
still reports them in ``TwinEstimate.unlike``, which is what validation judges them on.
An envelope saved before criteria were judged (``kept`` None) keeps every criterion and
``WIDEN``, the rule artifacts of format 3–5 were trained under.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.live.calibration import SLOPE_WINDOW_H
from pseudotwin.models.base import TrainingSet

Q_LO, Q_HI = 0.005, 0.995  # robust: a glitch or two of the training days does not set a bound
MARGIN = 0.25  # share of the inter-quantile span added on each side
WIDEN = 2.0  # σ factor of an uncertain estimate under the unjudged rule (kept None)
CRITERIA = ("level", "deviation", "speed")
PAIR = "disagreement"  # the criterion of a pair of references


def criterion(kind: str, sensor: str) -> str:
    """The key of one criterion: ``"<kind>:<sensor>"``."""
    return f"{kind}:{sensor}"


def pair_criterion(a: str, b: str) -> str:
    """The key of the disagreement criterion of references ``a`` and ``b``."""
    return criterion(PAIR, f"{a}|{b}")


@dataclass(frozen=True)
class RefEnvelope:
    """One reference's training ranges: level and deviation (lo, hi) [unit], slope_hi [unit/h],
    profile [S] its mean sample-and-hold value per window slot [unit]."""

    level: tuple[float, float]
    deviation: tuple[float, float]
    slope_hi: float
    profile: tuple[float, ...]

    def unlike(self, sensor: str, hours: OperatingHours, h: float, value: float,
               slope: float) -> list[tuple[str, str]]:
        """The criteria by which ``sensor`` reading ``value`` at wall-clock ``h`` and moving at
        ``slope`` is unlike training, as (key, why) (empty: it is like training)."""
        out = []
        lo, hi = self.level
        if not lo <= value <= hi:
            out.append((criterion("level", sensor),
                        f"{sensor}: level {value:.4g} outside training {lo:.4g}…{hi:.4g}"))
        dev = value - self.profile[hours.window_slot_index(h)]
        lo, hi = self.deviation
        if not lo <= dev <= hi:
            out.append((criterion("deviation", sensor),
                        f"{sensor}: deviation from its daily profile {dev:+.3g} outside "
                        f"training {lo:+.3g}…{hi:+.3g}"))
        if slope > self.slope_hi:
            out.append((criterion("speed", sensor),
                        f"{sensor}: moving at {slope:.3g}/h, faster than in training "
                        f"(≤ {self.slope_hi:.3g}/h): σ above its validated level"))
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


@dataclass(frozen=True)
class PairEnvelope:
    """Two references a, b and the training range (lo, hi) [unit] of the gap between their
    deviations from their daily profiles (a − profile_a) − (b − profile_b)."""

    a: str
    b: str
    gap: tuple[float, float]

    @property
    def key(self) -> str:
        return pair_criterion(self.a, self.b)

    def unlike(self, dev_a: float, dev_b: float) -> list[tuple[str, str]]:
        """(key, why) when deviations ``dev_a`` and ``dev_b`` [unit] are further apart (or
        closer) than in training; empty otherwise."""
        gap = dev_a - dev_b
        lo, hi = self.gap
        if lo <= gap <= hi:
            return []
        return [(self.key, f"{self.a} and {self.b} disagree: {gap:+.3g} apart from their "
                           f"daily profiles, outside training {lo:+.3g}…{hi:+.3g}")]

    def to_dict(self) -> dict[str, Any]:
        return {"references": [self.a, self.b], "gap": list(self.gap)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PairEnvelope:
        a, b = (str(x) for x in d["references"])
        lo, hi = d["gap"]
        return cls(a, b, (_bound(lo, -1), _bound(hi, 1)))


def _bound(x: float | None, sign: int) -> float:
    """A stored bound; null is an open one (saved artifacts write ±inf as null)."""
    return sign * math.inf if x is None else float(x)


@dataclass(frozen=True)
class Envelope:
    """The training ranges of every reference (sensor → :class:`RefEnvelope`) and of every
    pair of references (:class:`PairEnvelope`; none in artifacts saved before pairs were).

    kept: the criteria that make an estimate ``uncertain`` (None: all of them, the rule of
    envelopes saved before criteria were judged); widen: σ factor of an uncertain estimate;
    judged: per criterion, the held-out numbers it was kept or dropped on (for ``train`` and
    the report; analysis/criteria.py).
    """

    refs: dict[str, RefEnvelope]
    pairs: tuple[PairEnvelope, ...] = ()
    kept: frozenset[str] | None = None
    widen: float = WIDEN
    judged: dict[str, dict[str, Any]] = field(default_factory=dict, compare=False)

    @property
    def criteria(self) -> tuple[str, ...]:
        """Every criterion this envelope evaluates."""
        return (tuple(criterion(k, s) for s in self.refs for k in CRITERIA)
                + tuple(p.key for p in self.pairs))

    def acts(self, key: str) -> bool:
        """Whether criterion ``key`` makes an estimate uncertain."""
        return self.kept is None or key in self.kept

    def keeping(self, kept: frozenset[str], widen: float,
                judged: dict[str, dict[str, Any]] | None = None) -> Envelope:
        """This envelope with only ``kept`` acting, uncertain σ × ``widen``."""
        return replace(self, kept=frozenset(kept), widen=float(widen), judged=judged or {})

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
        refs = list(training.references)
        pairs = tuple(PairEnvelope(a, b, _range(_gaps(training, out[a], out[b], a, b)))
                      for i, a in enumerate(refs) for b in refs[i + 1:])
        return cls(out, pairs)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "rule": {"quantiles": [Q_LO, Q_HI], "margin": MARGIN, "widen": self.widen},
            "references": {s: r.to_dict() for s, r in self.refs.items()},
        }
        if self.pairs:
            out["pairs"] = [p.to_dict() for p in self.pairs]
        if self.kept is not None:
            out["kept"] = sorted(self.kept)
            out["judged"] = self.judged
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], hours: OperatingHours) -> Envelope:
        n = len(hours.window_slots())
        refs = {str(s): RefEnvelope.from_dict(r, n) for s, r in d["references"].items()}
        pairs = tuple(PairEnvelope.from_dict(p) for p in d.get("pairs") or ())
        if unknown := {x for p in pairs for x in (p.a, p.b)} - set(refs):
            raise ValueError(f"envelope pair of unknown reference {sorted(unknown)[0]}")
        if d.get("kept") is None:  # saved before criteria were judged: every one acts
            return cls(refs, pairs)
        kept = frozenset(str(k) for k in d["kept"])
        widen = float(d["rule"]["widen"])
        if not widen >= 1.0:
            raise ValueError(f"envelope widen {widen} is below 1")
        return cls(refs, pairs, kept, widen, dict(d.get("judged") or {}))


def _range(x: np.ndarray) -> tuple[float, float]:
    """[q_lo − m, q_hi + m] with m = MARGIN × (q_hi − q_lo) over the finite values of ``x``."""
    x = x[np.isfinite(x)]
    if not len(x):  # nothing seen: nothing can be called unlike it
        return -math.inf, math.inf
    lo, hi = np.quantile(x, [Q_LO, Q_HI])
    m = MARGIN * (hi - lo)
    return float(lo - m), float(hi + m)


def _gaps(training: TrainingSet, env_a: RefEnvelope, env_b: RefEnvelope, a: str,
          b: str) -> np.ndarray:
    """(a − profile_a) − (b − profile_b) [unit] at every operating-hours reading of either
    reference on the training days, the other's value held (NaN before its first reading)."""
    hours = training.hours
    first = hours.window_slots()[0]
    prof_a, prof_b = np.asarray(env_a.profile), np.asarray(env_b.profile)
    out = []
    for d in training.days:
        if not (d.has(a) and d.has(b)):
            continue
        (ha, va), (hb, vb) = d.series[a], d.series[b]
        h = np.union1d(ha, hb)
        h = h[hours.in_operating_hours(h)]
        slot = np.clip(hours.slot_of(h) - first, 0, len(prof_a) - 1)
        out.append((_held(ha, va, h) - prof_a[slot]) - (_held(hb, vb, h) - prof_b[slot]))
    return np.concatenate(out) if out else np.zeros(0)


def _held(h: np.ndarray, v: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The value of series (h, v) held at times ``at`` (NaN before its first reading)."""
    i = np.searchsorted(h, at, side="right") - 1
    return np.where(i >= 0, v[np.clip(i, 0, None)], np.nan)


def _slopes(h: np.ndarray, v: np.ndarray) -> np.ndarray:
    """|slope| [unit/h] at every reading as Twin.slope takes it: from the reading held
    ``SLOPE_WINDOW_H`` earlier (or the first) to this one, over at least that span."""
    i0 = np.maximum(np.searchsorted(h, h - SLOPE_WINDOW_H, side="right") - 1, 0)
    span = np.maximum(h - h[i0], SLOPE_WINDOW_H)
    return np.abs(v - v[i0]) / span
