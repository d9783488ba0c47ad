"""TRIV (thesis 6.7/6.8): the target is a reference plus its typical offset at this time of day.

On the slot grid (COV values sample-and-hold), O_m(τ) = mean over training days of
(target − ref_m) at slot τ, and TRIV(t) = mean over m of (O_m(τ(t)) + ref_m(t)).
"""

from __future__ import annotations

import datetime as dt
from typing import Any, ClassVar, Self

import numpy as np

from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import DataError
from pseudotwin.models.base import DayEstimator, Estimate, TrainingSet, Tuned, TwinModel

#: triv-smooth's spans [min], from the smoothest (validation prefers the earlier of two alike)
SMOOTH_SPANS: tuple[int, ...] = (240, 120, 60)


def fill_slots(profile: np.ndarray) -> np.ndarray:
    """Fill slots no training day covered by linear interpolation over the covered ones:
    [S] → [S]; raises DataError when no slot is covered."""
    ok = np.isfinite(profile)
    if not ok.any():
        raise DataError("no training day covers any slot of the operating hours")
    x = np.arange(len(profile))
    return np.interp(x, x[ok], profile[ok])


def slot_matrix(training: TrainingSet, sensor: str) -> np.ndarray:
    """One sensor's level per training day and window slot: [days, S], the mean of its
    readings in the slot (DayReadings.slot_means). TRIV's offset holds for a whole slot, so
    it is learnt from the whole slot: with 1-minute readings a value held at the slot's
    start is one minute of fifteen, and its noise would become the offset's."""
    return np.array([d.slot_means(sensor, training.hours) for d in training.days])


class TrivModel(TwinModel):
    """TRIV with any number of references.

    Fitted: offsets_ [M, S] target − ref_m per window slot; std_ [S] spread of the TRIV error
    on the training days; profiles_ sensor → [S] average daily profile (used as prior means).
    """

    kind = "triv"
    options: ClassVar[tuple[str, ...]] = ("references",)

    def __init__(self, references: tuple[str, ...] | None = None) -> None:
        self.references = references

    def fit(self, training: TrainingSet) -> Self:
        refs = tuple(self.references or training.references)
        self.hours_ = training.hours
        self.references_ = refs
        self.target_ = training.target
        tgt = slot_matrix(training, training.target)
        offsets, estimates = [], []
        self.profiles_: dict[str, np.ndarray] = {}
        with np.errstate(invalid="ignore"), _quiet():
            for r in refs:
                ref = slot_matrix(training, r)
                offsets.append(self._offset_profile(tgt - ref))
                self.profiles_[r] = fill_slots(np.nanmean(ref, axis=0))
            self.profiles_[training.target] = fill_slots(np.nanmean(tgt, axis=0))
            self.offsets_ = np.array(offsets)
            day_offsets = self._day_offsets(training)  # [D, M, S]
            for m, r in enumerate(refs):
                estimates.append(day_offsets[:, m, :] + slot_matrix(training, r))
            err = tgt - np.nanmean(np.array(estimates), axis=0)
            spread = np.sqrt(np.nanmean(err**2, axis=0))
            overall = float(np.sqrt(np.nanmean(err**2))) if np.isfinite(err).any() else 0.0
        self.std_ = np.where(np.isfinite(spread), spread, overall)
        self.std_ = np.maximum(self.std_, 1e-6)
        return self

    def _offset_profile(self, diffs: np.ndarray) -> np.ndarray:
        """Target − reference per day and slot [D, S] → the offset profile [S]."""
        return fill_slots(np.nanmean(diffs, axis=0))

    def _day_offsets(self, training: TrainingSet) -> np.ndarray:
        """The offsets each training day is estimated with: [D, M, S] (TRIV: every day the
        same ``offsets_``)."""
        return np.broadcast_to(self.offsets_, (len(training.days), *self.offsets_.shape))

    def day_offsets(self, day: dt.date) -> np.ndarray:
        """The offsets [M, S] of local ``day`` (TRIV: the same every day)."""
        return self.offsets_

    def slot_index(self, hours: float) -> int:
        """Index into the window slots [S] of wall-clock hours (clamped to the window)."""
        return self.hours_.window_slot_index(hours)

    def offset(self, m: int, hours: float) -> float:
        return float(self.offsets_[m, self.slot_index(hours)])

    def profile(self, sensor: str, hours: float) -> float:
        return float(self.profiles_[sensor][self.slot_index(hours)])

    def start_day(self, day: dt.date) -> TrivDay:
        return TrivDay(self, self.day_offsets(day))

    def to_dict(self) -> dict[str, Any]:
        return {
            "references": list(self.references_),
            "offsets": self.offsets_.tolist(),
            "std": self.std_.tolist(),
            "profiles": {k: v.tolist() for k, v in self.profiles_.items()},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> Self:
        hours = spec.hours
        m = cls(tuple(d["references"]))
        m.hours_ = hours
        m.references_ = tuple(d["references"])
        m.target_ = spec.target
        m.offsets_ = np.asarray(d["offsets"], float)
        m.std_ = np.asarray(d["std"], float)
        m.profiles_ = {k: np.asarray(v, float) for k, v in d["profiles"].items()}
        S = len(hours.window_slots())
        if m.offsets_.shape != (len(m.references_), S):
            raise ValueError("TRIV offsets do not match the references and the slot grid")
        # (a short array passed every check, then failed every estimate with an IndexError)
        if m.std_.shape != (S,) or any(v.shape != (S,) for v in m.profiles_.values()):
            raise ValueError("TRIV std or profiles do not match the slot grid")
        return m


class TrivShrunkModel(TrivModel):
    """TRIV whose offset profile is shrunk towards its daily mean as far as the training
    days disagree about its shape (James–Stein, one factor per reference).

    With D training days, the profile's shape (O(τ) − Ō) is estimated with a sampling
    variance of about mean_τ(s²(τ)/D), s²(τ) the spread at slot τ of the days' offsets each
    taken from its day's mean offset (a day's level cancels out of the shape, so days that
    agree on the shape at different levels agree), while its spread across slots is
    mean_τ (O(τ) − Ō)². The factor λ = max(0, 1 − sampling / spread) keeps the shape only as
    far as it stands out of the days' disagreement: five alike days keep it (λ ≈ 1), five
    days that each had their own offset course leave the constant mean offset (λ = 0).
    Fitted: shrink_ [M] the factors λ per reference.
    """

    kind = "triv-shrunk"
    live_baseline = False

    def fit(self, training: TrainingSet) -> Self:
        self.shrink_: list[float] = []
        super().fit(training)
        return self

    def _offset_profile(self, diffs: np.ndarray) -> np.ndarray:
        profile = super()._offset_profile(diffs)
        n = np.isfinite(diffs).sum(axis=0)
        keep = n >= 2
        if not keep.any():
            self.shrink_.append(1.0)
            return profile
        mean = float(np.mean(profile))
        spread = float(np.mean((profile - mean) ** 2))
        shapes = diffs - np.nanmean(diffs, axis=1, keepdims=True)  # each day's level out
        sampling = float(np.mean(np.nanvar(shapes[:, keep], axis=0, ddof=1) / n[keep]))
        lam = max(0.0, 1.0 - sampling / spread) if spread > 0 else 0.0
        self.shrink_.append(lam)
        return mean + lam * (profile - mean)

    def fit_summary(self) -> str:
        factors = ", ".join(f"{r} {lam:.2f}" for r, lam in zip(self.references_, self.shrink_,
                                                                strict=True))
        return f"offset profile kept by a factor λ (1 = TRIV's, 0 = constant): {factors}"

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "shrink": list(self.shrink_)}

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> Self:
        m = super().from_dict(d, spec)
        m.shrink_ = [float(x) for x in d.get("shrink", [])]
        return m


def smooth_profile(profile: np.ndarray, half: int) -> np.ndarray:
    """A day's profile [S] smoothed across its slots: at each slot a straight line fitted to
    the slots up to ``half`` slots either side, tricube-weighted (LOWESS without its
    robustness iterations: a linear smoother, so a straight profile comes back unchanged, and
    at the day's start and end the line follows the profile's slope rather than flattening
    it; there the nearest slots are all on one side). ``half`` < 1: the profile as it is."""
    # statsmodels (~50 MB) is for fitting: the daemon loads this module, never calls this
    from statsmodels.nonparametric.smoothers_lowess import lowess

    n = len(profile)
    if half < 1 or n < 3:
        return profile.copy()
    # LOWESS takes the frac·n nearest points and gives the farthest of them weight zero: one
    # more each side than ``half`` weights every slot within it (never above 1, which
    # statsmodels refuses: then a single line through all slots)
    frac = min(1.0, (2 * half + 3 + 1e-6) / n)  # frac·n is floored: a hair above
    x = np.arange(n, dtype=float)
    return np.asarray(lowess(profile, x, frac=frac, it=0, delta=0.0, return_sorted=False),
                      dtype=float)


def check_span(span: object) -> int:
    """triv-smooth's span [min], a positive whole number (``True`` is none); ValueError
    otherwise, from a setting or from a damaged artifact alike."""
    if isinstance(span, bool) or not isinstance(span, int) or span <= 0:
        raise ValueError(f"triv-smooth's span must be a positive whole number of minutes, "
                         f"got {span!r}")
    return span


class TrivSmoothModel(TrivModel):
    """TRIV whose offset profile is smoothed across the slots of the day (LOWESS, a local
    straight line through the slots within ±``span``/2 minutes; :func:`smooth_profile`).

    A slot's offset is the mean of as many values as there are training days, so a few days
    leave its 15-minute wiggles partly noise: one day's door opened at 10:15 becomes a dent
    the profile repeats every day. Smoothing trades that noise for bias where the offset
    really turns within ``span``. The span is chosen on the training days like VARMA's
    order (``tuned``: the widest, the smoothest, within noise of the lowest held-out error
    wins); 60 minutes, the narrowest, where too few days are held out to choose.
    Fitted: offsets_ the smoothed profiles.
    """

    kind = "triv-smooth"
    options: ClassVar[tuple[str, ...]] = ("references", "span")
    tuned = Tuned("span", SMOOTH_SPANS)
    live_baseline = False

    def __init__(self, references: tuple[str, ...] | None = None,
                 span: int = SMOOTH_SPANS[-1]) -> None:
        super().__init__(references)
        self.span = span

    def _half(self) -> int:
        """Slots either side that the span reaches: [slots]."""
        return int(round(check_span(self.span) / (2 * self.hours_.slot_hours * 60)))

    def _offset_profile(self, diffs: np.ndarray) -> np.ndarray:
        return smooth_profile(super()._offset_profile(diffs), self._half())

    def fit_summary(self) -> str:
        if self._half() < 1:  # e.g. 60 min on 60-min slots: TRIV's profile
            return (f"span {self.span} min reaches no neighbouring slot of "
                    f"{self.hours_.slot_hours * 60:g} min: offset profile not smoothed")
        return f"offset profile smoothed over {self.span} min (LOWESS)"

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "span": self.span}

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> Self:
        m = super().from_dict(d, spec)
        m.span = check_span(d["span"])
        return m


WEEKEND_TYPE, WEEKDAY_TYPE = "weekend", "weekday"
MIN_WEEKEND_DAYS = 2  # weekend training days a live weekend profile is learnt from


def day_type(day: dt.date) -> str:
    """Saturday and Sunday are ``weekend``, Monday to Friday ``weekday``."""
    return WEEKEND_TYPE if day.weekday() >= 5 else WEEKDAY_TYPE


class TrivWeekModel(TrivModel):
    """TRIV with an offset profile of its own for weekends (Saturday, Sunday).

    Occupancy, ventilation and heating schedules differ on weekends, and with them the
    course of the target's offset to the references (a house's CO2 above all). Weekend days
    are estimated with the profile of the training's weekend days; weekdays, the majority of
    any few consecutive training days, keep the profile of all training days (TRIV's), the
    best-estimated one: a profile of the three weekdays alone is noisier than what the two
    weekend days would bias it by (SML2010, rolling origins).

    The weekend profile needs ``min_weekend_days`` (2) weekend training days, else the model
    is TRIV: validation must be able to test it. Its refits on held-out days learn the
    weekend from one day (``validation_options``), so with two weekend days each is held out
    against a profile of the other, a pessimistic test of the two-day profile; with one, a
    held-out weekend day has none and the model scores as TRIV, whose simpler form wins.
    Fitted: weekend_ [M, S] the weekend profiles, or None; type_days_ day type → training
    days of that type.
    """

    kind = "triv-week"
    options: ClassVar[tuple[str, ...]] = ("references", "min_weekend_days")
    validation_options: ClassVar[dict[str, Any]] = {"min_weekend_days": 1}
    live_baseline = False

    def __init__(self, references: tuple[str, ...] | None = None,
                 min_weekend_days: int = MIN_WEEKEND_DAYS) -> None:
        super().__init__(references)
        self.min_weekend_days = min_weekend_days

    def fit(self, training: TrainingSet) -> Self:
        weekend = np.array([day_type(d.day) == WEEKEND_TYPE for d in training.days])
        self.type_days_ = {WEEKDAY_TYPE: int((~weekend).sum()), WEEKEND_TYPE: int(weekend.sum())}
        self.weekend_: np.ndarray | None = None
        if weekend.sum() >= max(1, self.min_weekend_days):
            tgt = slot_matrix(training, training.target)[weekend]
            refs = tuple(self.references or training.references)
            with np.errstate(invalid="ignore"), _quiet():
                self.weekend_ = np.array([
                    self._offset_profile(tgt - slot_matrix(training, r)[weekend])
                    for r in refs])
        return super().fit(training)

    def _day_offsets(self, training: TrainingSet) -> np.ndarray:
        return np.array([self.day_offsets(d.day) for d in training.days])

    def day_offsets(self, day: dt.date) -> np.ndarray:
        if self.weekend_ is not None and day_type(day) == WEEKEND_TYPE:
            return self.weekend_
        return self.offsets_

    def fit_summary(self) -> str:
        n = self.type_days_[WEEKEND_TYPE]
        if self.weekend_ is None:
            return (f"{n} weekend day{'' if n == 1 else 's'} among the training days, "
                    f"{max(1, self.min_weekend_days)} needed for a weekend profile: it is TRIV")
        return (f"weekend offset profile from {n} weekend day{'s' if n > 1 else ''}; "
                f"weekdays: all {n + self.type_days_[WEEKDAY_TYPE]} training days' (TRIV's)")

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "type_days": dict(self.type_days_),
                "weekend": None if self.weekend_ is None else self.weekend_.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> Self:
        m = super().from_dict(d, spec)
        m.type_days_ = {str(t): int(n) for t, n in d["type_days"].items()}
        m.weekend_ = None if d["weekend"] is None else np.asarray(d["weekend"], float)
        if m.weekend_ is not None and m.weekend_.shape != m.offsets_.shape:
            raise ValueError("triv-week's weekend offsets do not match its references and "
                             "the slot grid")
        return m


class HeldValues:
    """Latest value of each sensor by reading time (sample-and-hold; late readings of an
    earlier time never overwrite a newer value)."""

    def __init__(self) -> None:
        self.values: dict[str, tuple[float, float]] = {}

    def update(self, sensor: str, hours: float, value: float) -> None:
        old = self.values.get(sensor)
        if old is None or hours >= old[0]:
            self.values[sensor] = (hours, value)

    def get(self, sensor: str) -> float | None:
        v = self.values.get(sensor)
        return None if v is None else v[1]


class TrivDay(DayEstimator):
    """offsets: today's offset profiles [M, S] (``model.offsets_`` unless given)."""

    def __init__(self, model: TrivModel, offsets: np.ndarray | None = None) -> None:
        self.model = model
        self.offsets = model.offsets_ if offsets is None else offsets
        self.held = HeldValues()

    def observe(self, sensor: str, hours: float, value: float) -> None:
        self.held.update(sensor, hours, value)

    def predict(self, hours: float) -> Estimate:
        m = self.model
        slot = m.slot_index(hours)
        vals = [
            float(self.offsets[i, slot]) + v
            for i, r in enumerate(m.references_)
            if (v := self.held.get(r)) is not None
        ]
        if not vals:
            return Estimate(float("nan"), float("nan"))
        return Estimate(list_mean(vals), float(m.std_[m.slot_index(hours)]))


def list_mean(values: list[float]) -> float:
    """np.mean of a short list of floats (0.0 when empty), without numpy's per-call cost
    for the usual single reference: the mean of one value is that value, bit for bit."""
    if len(values) == 1:
        return float(values[0])
    return float(np.mean(values)) if values else 0.0


class _quiet:
    """Silence numpy's 'mean of empty slice' for slots no day covers (handled by fill_slots)."""

    def __enter__(self) -> None:
        import warnings

        self._cm = warnings.catch_warnings()
        self._cm.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc: Any) -> None:
        self._cm.__exit__(*exc)
