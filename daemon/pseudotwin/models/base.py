"""The contract shared by all twin models."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any, Protocol

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import DayReadings


@dataclass(frozen=True)
class TrainingSet:
    """What a model is trained on: a few days on which the target stood next to the references.

    days: the training days' windows (init start … day end, with carry-over).
    """

    references: tuple[str, ...]
    target: str
    hours: OperatingHours
    days: tuple[DayReadings, ...]
    quantity: str = "temperature"

    @property
    def sensors(self) -> tuple[str, ...]:
        return (*self.references, self.target)


@dataclass(frozen=True)
class Estimate:
    """One model's estimate of the target: value [unit of the quantity], std [same unit]."""

    value: float
    std: float


class DayEstimator(Protocol):
    """One model's live state for one operating day (the rolling-horizon window)."""

    def observe(self, sensor: str, hours: float, value: float) -> None:
        """Condition on a reference reading at wall-clock ``hours`` [h]; in time order."""

    def predict(self, hours: float) -> Estimate:
        """Estimate the target at wall-clock ``hours`` [h] from what was observed so far."""


class TwinModel(Protocol):
    kind: str

    def fit(self, training: TrainingSet) -> TwinModel: ...

    def start_day(self, day: dt.date) -> DayEstimator: ...

    def to_dict(self) -> dict[str, Any]: ...
