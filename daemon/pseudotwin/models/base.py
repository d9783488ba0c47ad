"""The contract every twin model follows, and the value types it trades in.

A model is one class behind :class:`TwinModel` plus one entry in ``models/registry.py``;
the twin, the artifact, training and the command line need nothing else of it.
"""

from __future__ import annotations

import datetime as dt
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

from pseudotwin.core.series import DayReadings
from pseudotwin.core.spec import OfTwin, TwinSpec


@dataclass(frozen=True)
class TrainingSet(OfTwin):
    """What a model is trained on: a few days on which the target stood next to the references.

    days: the training days' windows (init start … day end, with carry-over).
    """

    spec: TwinSpec
    days: tuple[DayReadings, ...]


@dataclass(frozen=True)
class Estimate:
    """One model's estimate of the target: value [unit of the quantity], std [same unit]."""

    value: float
    std: float


@dataclass(frozen=True)
class Numerics:
    """Numerical health of a live GP posterior: jitter added to the diagonal, full
    refactorizations after a failed extension, points in today's factor."""

    jitter: float = 0.0
    refactorizations: int = 0
    points: int = 0


class DayEstimator(ABC):
    """One model's live state for one operating day (the rolling-horizon window)."""

    @abstractmethod
    def observe(self, sensor: str, hours: float, value: float) -> None:
        """Condition on a reference reading (a new point) at wall-clock ``hours`` [h]."""

    def revise(self, sensor: str, hours: float, value: float) -> None:
        """Give ``sensor``'s newest point, observed at ``hours`` [h], the new ``value``.

        The window's thinning (core/thinning.py) revises a point as more readings of its
        bucket arrive. This default suits estimators that hold each sensor's latest value
        only: the revision is an observation again. Estimators with a conditioning set
        replace the point's value instead of adding one.
        """
        self.observe(sensor, hours, value)

    @abstractmethod
    def predict(self, hours: float) -> Estimate:
        """Estimate the target at wall-clock ``hours`` [h] from what was observed so far."""

    def numerics(self) -> Numerics | None:
        """The posterior's numerical health; None for models without one."""
        return None


@dataclass(frozen=True)
class Tuned:
    """A model setting chosen on the training days (analysis/validation.choose_setting): each
    of ``values`` (from the simplest) is scored leave-one-day-out and the first (simplest) one
    within noise of the lowest held-out error wins. ``fit_with``: settings that go with a
    tuned value, so that the model fit is the form validation scored; ``pinned_by``: settings
    by which a user asks for a form of their own (with the setting itself, they skip the
    search)."""

    name: str
    values: tuple[int, ...]
    fit_with: Mapping[str, Any] = field(default_factory=dict)
    pinned_by: tuple[str, ...] = ()

    def pinned(self, options: Mapping[str, Any]) -> bool:
        """Whether the user's ``options`` set the setting, or a form of their own."""
        return any(k in options for k in (self.name, *self.pinned_by, *self.fit_with))


class TwinModel(ABC):
    """A trainable, serializable estimator of the target from the references.

    scikit-learn contract: ``__init__`` stores settings (the names in ``options`` may be set
    from the command line or the configuration), ``fit`` returns self, fitted attributes end
    in ``_``. ``candidate``: whether validation may choose it as the primary (a baseline
    published for monitoring is not). ``references_`` are the references the fitted model
    reads: a reference outside them never makes its estimate stale.
    """

    kind: ClassVar[str]
    options: ClassVar[tuple[str, ...]] = ()
    candidate: ClassVar[bool] = True  # may become the twin's primary by validation
    # Published live as a baseline when not the primary (DESIGN's baselines and the thesis's
    # models); a variant of one of them (another offset profile, covariates, more
    # references) runs live only when validation makes it the primary.
    live_baseline: ClassVar[bool] = True
    # Settings of the refits on held-out training days (validation): cheaper where a full
    # fit per fold would cost minutes.
    validation_options: ClassVar[dict[str, Any]] = {}
    # A setting validation chooses when the user leaves it unset (Tuned; None: none).
    tuned: ClassVar[Tuned | None] = None
    # Made from other fitted models and validation's held-out scores (models/blend.py) rather
    # than fit on days: training builds it after validation, validation's folds skip it.
    stacked: ClassVar[bool] = False
    # Reads the twin's covariates (TwinSpec.covariates); the others ignore them.
    reads_covariates: ClassVar[bool] = False
    # Training days the model needs at least (training skips it, and says why, with fewer).
    min_days: ClassVar[int] = 1
    references_: tuple[str, ...]

    @classmethod
    def not_applicable(cls, spec: TwinSpec) -> str:
        """Why this model cannot serve the twin ``spec`` (training then skips it); empty when
        it can. E.g. a model of covariates for a twin without any."""
        return ""

    @abstractmethod
    def fit(self, training: TrainingSet) -> Self:
        """Train on ``training``; returns self."""

    @abstractmethod
    def start_day(self, day: dt.date) -> DayEstimator:
        """Fresh live state for one operating day."""

    @abstractmethod
    def to_dict(self) -> dict[str, Any]:
        """The fitted state as JSON-ready data (the artifact's ``models.<kind>``)."""

    @classmethod
    @abstractmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> Self:
        """Rebuild a fitted model of the twin ``spec`` from :meth:`to_dict` output; raises
        ValueError, KeyError or ArtifactError when ``d`` does not fit."""

    @property
    def model_name(self) -> str:
        """What the ``model`` field of an estimate says (e.g. ``var-fallback``)."""
        return self.kind

    def fallback(self) -> TwinModel | None:
        """A simpler fitted model to publish when this one fails numerically."""
        return None

    def publish_problem(self) -> str:
        """Why this fitted model must not be published live whatever validation says (e.g.
        a trend extrapolated beyond the training days); empty when there is none."""
        return ""

    def fit_summary(self) -> str:
        """One line on how the fit went (printed by ``train``); empty when nothing to say."""
        return ""

    def parts(self) -> Mapping[str, TwinModel]:
        """A stacked model's fitted members (kind → model), whose estimates :meth:`combine`
        turns into its own; empty for a model that runs on its own."""
        return {}

    def share(self, models: Mapping[str, TwinModel]) -> None:
        """Let a stacked model use ``models``' fitted models of its members' kinds (an
        artifact's), so that one copy is held and, live, one state runs; a no-op for others."""
        return None

    def combine(self, parts: Mapping[str, Estimate]) -> Estimate:
        """A stacked model's estimate from its members' estimates at one instant (kind →
        estimate, every kind of :meth:`parts`)."""
        raise TypeError(f"{self.kind} is not a stacked model: it has no parts to combine")
