"""REF (DESIGN.md §3): the raw reference, held — the simplest answer, and the floor every
other model has to beat to be worth running."""

from __future__ import annotations

import datetime as dt
from typing import Any

import numpy as np

from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import DataError
from pseudotwin.models.base import DayEstimator, Estimate, TrainingSet, TwinModel
from pseudotwin.models.triv import HeldValues, slot_matrix


class RefModel(TwinModel):
    """The value of one reference as the target's estimate.

    reference: which reference (default: the one closest to the target on the training days,
    by RMSE on the slot grid). Fitted: references_ (that one), rmse_ sensor → training RMSE
    [unit] of every reference against the target; std_ [unit] the chosen one's.
    """

    kind = "ref"
    options = ("reference",)

    def __init__(self, reference: str | None = None) -> None:
        self.reference = reference

    def fit(self, training: TrainingSet) -> RefModel:
        if self.reference is not None and self.reference not in training.references:
            raise DataError(f"ref: {self.reference!r} is not one of the twin's references")
        tgt = slot_matrix(training, training.target)
        self.rmse_: dict[str, float] = {}
        for r in training.references:
            err = slot_matrix(training, r) - tgt
            ok = np.isfinite(err)
            self.rmse_[r] = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("inf")
        best = self.reference or min(training.references, key=lambda r: self.rmse_[r])
        if not np.isfinite(self.rmse_[best]):
            raise DataError(f"ref: {best} and the target never report at the same time")
        self.references_ = (best,)
        self.target_ = training.target
        self.std_ = max(self.rmse_[best], 1e-6)
        return self

    def start_day(self, day: dt.date) -> RefDay:
        return RefDay(self.references_[0], self.std_)

    def to_dict(self) -> dict[str, Any]:
        rmse = {r: v for r, v in self.rmse_.items() if np.isfinite(v)}
        return {"reference": self.references_[0], "std": self.std_, "rmse": rmse}

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> RefModel:
        ref = str(d["reference"])
        if ref not in spec.references:
            raise ValueError(f"ref: {ref!r} is not one of the twin's references")
        m = cls(ref)
        m.references_ = (ref,)
        m.target_ = spec.target
        m.std_ = float(d["std"])
        m.rmse_ = {str(k): float(v) for k, v in d.get("rmse", {}).items()}
        return m


class RefDay(DayEstimator):
    def __init__(self, reference: str, std: float) -> None:
        self.reference = reference
        self.std = std
        self.held = HeldValues()

    def observe(self, sensor: str, hours: float, value: float) -> None:
        if sensor == self.reference:
            self.held.update(sensor, hours, value)

    def predict(self, hours: float) -> Estimate:
        v = self.held.get(self.reference)
        if v is None:
            return Estimate(float("nan"), float("nan"))
        return Estimate(v, self.std)
