"""BLEND: a weighted mean of the candidates that did best on the held-out training days.

Five training days rarely single out one model: the runner-up often errs where the winner does
not (one follows the references' course, the other the day's offset), and a combination of
forecasts with weights from their past errors is the classic hedge against choosing wrongly
(Bates & Granger 1969; stacking, Wolpert 1992). The rule is fixed a priori, never tuned on
test days:

- members: the ``MAX_MEMBERS`` candidates with the lowest mean held-out daily NRMSE in
  validation (at least two; the blend itself and monitoring baselines never);
- weights w_m ∝ 1 / NRMSE_m², summing to 1 (inverse mean squared error, Bates–Granger).

The blend is a candidate: validation scores it on each held-out day with members and
weights chosen from the *other* days' held-out errors (so its score is as honest as a single
model's), and it wins only when it beats, by more than the tie margin, the held-out error of
choosing one candidate measured the same way (analysis/validation.py). Its σ is calibrated on
those held-out errors like every model's.

Its members are fitted models of the twin, so it is not fit on days itself: :func:`weights`
turns validation's scores into members and weights, and ``fit`` only checks them.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from typing import Any

from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import DataError
from pseudotwin.models.base import DayEstimator, Estimate, Numerics, TrainingSet, TwinModel

MAX_MEMBERS = 3


def weights(scores: Mapping[str, float]) -> dict[str, float]:
    """Members and weights from candidates' mean held-out daily NRMSE [%] (kind → score):
    the ``MAX_MEMBERS`` lowest, w ∝ 1/NRMSE². Empty when fewer than two are usable."""
    usable = sorted((s, k) for k, s in scores.items() if math.isfinite(s) and s > 0)
    top = usable[:MAX_MEMBERS]
    if len(top) < 2:
        return {}
    inv = {k: 1.0 / s**2 for s, k in top}
    total = sum(inv.values())
    return {k: v / total for k, v in inv.items()}


def combine(weights: Mapping[str, float], parts: Mapping[str, Estimate]) -> Estimate:
    """Σ_k w_k · estimate_k, σ² = Σ_k (w_k σ_k)² (the members' own spreads, as if
    independent): live (BlendModel.combine) and on validation's held-out rows alike."""
    value = var = 0.0
    for k, w in weights.items():
        e = parts[k]
        value += w * e.value
        var += (w * e.std) ** 2
    return Estimate(value, math.sqrt(var))


class BlendModel(TwinModel):
    """Σ_m w_m · estimate_m over fitted member models.

    members: kind → fitted model of this twin; weights: kind → w (positive, summing to 1),
    from :func:`weights`. Fitted: members_, weights_ (the same, checked); references_ every
    reference a member reads (in the twin's order): a silent one makes the blend stale.
    """

    kind = "blend"
    live_baseline = False  # published only as the primary
    stacked = True  # made from validation's held-out scores, not trained on days

    def __init__(self, members: Mapping[str, TwinModel] | None = None,
                 weights: Mapping[str, float] | None = None) -> None:
        self.members = members
        self.weights = weights

    def fit(self, training: TrainingSet) -> BlendModel:
        members, w = dict(self.members or {}), dict(self.weights or {})
        if len(w) < 2 or set(w) != set(members):
            raise DataError("blend: needs two or more validated candidates, each with a weight")
        if not all(math.isfinite(x) and x > 0 for x in w.values()) or \
                not math.isclose(sum(w.values()), 1.0, rel_tol=1e-9):
            raise DataError(f"blend: weights {w} must be positive and sum to 1")
        if any(isinstance(m, BlendModel) for m in members.values()):
            raise DataError("blend: a blend cannot be its own member")
        self.members_ = members
        self.weights_ = w
        used = {r for m in members.values() for r in m.references_}
        self.references_ = tuple(r for r in training.references if r in used)
        return self

    def start_day(self, day: dt.date) -> BlendDay:
        """The blend on its own: its members' day states side by side. A twin running the
        members anyway combines their estimates instead (live/twin.py), one state each."""
        return BlendDay({k: m.start_day(day) for k, m in self.members_.items()}, self)

    def parts(self) -> Mapping[str, TwinModel]:
        return self.members_

    def share(self, models: Mapping[str, TwinModel]) -> None:
        # The artifact stores each member twice (its own entry and here) so that either
        # loads alone; once loaded, one object serves both.
        self.members_ = {k: models.get(k, m) for k, m in self.members_.items()}

    def combine(self, parts: Mapping[str, Estimate]) -> Estimate:
        return combine(self.weights_, parts)

    def to_dict(self) -> dict[str, Any]:
        return {"weights": self.weights_,
                "members": {k: m.to_dict() for k, m in self.members_.items()}}

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> BlendModel:
        from pseudotwin.models.registry import MODELS  # the registry lists this class too

        members: dict[str, TwinModel] = {}
        for kind, md in d["members"].items():
            if kind not in MODELS or kind == cls.kind:
                raise ValueError(f"blend: unknown member model {kind!r}")
            members[kind] = MODELS[kind].from_dict(md, spec)
        w = {str(k): float(v) for k, v in d["weights"].items()}
        try:
            return cls(members, w).fit(TrainingSet(spec, ()))
        except DataError as exc:
            raise ValueError(str(exc)) from None

    def fit_summary(self) -> str:
        return "blend of " + ", ".join(f"{k} {w:.2f}" for k, w in self.weights_.items())


class BlendDay(DayEstimator):
    """The members' day states side by side; a numerical failure of any member is the
    blend's (the twin then falls back as for any model)."""

    def __init__(self, members: dict[str, DayEstimator], model: BlendModel) -> None:
        self.members = members
        self.model = model

    def observe(self, sensor: str, hours: float, value: float) -> None:
        for est in self.members.values():
            est.observe(sensor, hours, value)

    def revise(self, sensor: str, hours: float, value: float) -> None:
        for est in self.members.values():
            est.revise(sensor, hours, value)

    def predict(self, hours: float) -> Estimate:
        return self.model.combine({k: e.predict(hours) for k, e in self.members.items()})

    def numerics(self) -> Numerics | None:
        found = [n for e in self.members.values() if (n := e.numerics()) is not None]
        if not found:
            return None
        return Numerics(max(n.jitter for n in found), sum(n.refactorizations for n in found),
                        max(n.points for n in found))
