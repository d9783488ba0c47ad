"""Corr-GP twins: a multi-output GP over time of day whose outputs are the references and the
target (DESIGN.md §3).

- :class:`CorrGpLcm` (thesis 6.11/6.16): zero mean, all references, K = Σ_k B_k ⊗ k_k.
  All outputs share one affine normalization (y − c)/s so their level differences survive.
- :class:`CorrGpTriv` (thesis 6.15/6.17/6.18): one reference, ICM, prior means from TRIV.
  The target's prior mean is TRIV: O(τ) + ref(t). The reference's prior mean is its own
  average training-day profile P_ref(τ), shifted to today's level by the mean deviation of the
  reference from P_ref during the init phase (``ref_mean="shifted"``; ``"profile"`` keeps the
  unshifted P_ref). The GP therefore only sees deviations from the typical daily shape and
  never the season's level. (Thesis eq. 6.4 prints ½(offset + ref), which is not a sensible
  temperature level; this reading matches its text: "TRIV included as prior mean", "trained
  on deviations". The choice lives here, in :meth:`CorrGpTriv._ref_mean`, and nowhere else.)
"""

from __future__ import annotations

import datetime as dt
import math
from typing import Any, ClassVar, TypeVar

import numpy as np

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import DataError
from pseudotwin.gp.fitdata import FitData, FitReport
from pseudotwin.gp.kernels import DEFAULT_KERNEL, KERNEL_REGISTRY, LcmParams
from pseudotwin.gp.posterior import IncrementalPosterior
from pseudotwin.models.base import DayEstimator, Estimate, Numerics, TrainingSet, TwinModel
from pseudotwin.models.triv import HeldValues, TrivModel, slot_matrix

MIN_POINTS_PER_OUTPUT = 8


# A reference value or an array of them: the prior mean works on either.
F = TypeVar("F", float, np.ndarray)

def _kernel_for(kernel: str | None, quantity: str) -> str:
    k = kernel or DEFAULT_KERNEL.get(quantity, "rq")
    if k not in KERNEL_REGISTRY:
        raise DataError(f"unknown kernel {k!r}; choose one of {', '.join(KERNEL_REGISTRY)}")
    return k


def _fit_data(per_output: list[np.ndarray], hours: OperatingHours) -> FitData:
    """Grid values per output [days, S] → day-blocked training points (NaNs dropped)."""
    slot_h = hours.window_slots() * hours.slot_hours
    ts, os_, ys, blocks = [], [], [], []
    start = 0
    n_days = per_output[0].shape[0]
    for d in range(n_days):
        n0 = start
        for p, grid in enumerate(per_output):
            ok = np.isfinite(grid[d])
            ts.append(slot_h[ok])
            os_.append(np.full(ok.sum(), p))
            ys.append(grid[d][ok])
            start += int(ok.sum())
        if start > n0:
            blocks.append(slice(n0, start))
    o = np.concatenate(os_).astype(int)
    for p in range(len(per_output)):
        if (o == p).sum() < MIN_POINTS_PER_OUTPUT:
            raise DataError(
                f"too little training data: output {p} has {(o == p).sum()} grid points "
                f"(at least {MIN_POINTS_PER_OUTPUT} needed)"
            )
    return FitData(np.concatenate(ts), o, np.concatenate(ys), tuple(blocks), len(per_output))


def _numerics(post: IncrementalPosterior) -> Numerics:
    return Numerics(post.jitter, post.refactorizations, post.n)


class _GpModel(TwinModel):
    """Shared settings and serialization of both Corr-GP models."""

    options: ClassVar[tuple[str, ...]] = (
        "kernel", "restarts", "artificial_noise", "max_iter", "seed",
    )
    validation_options: ClassVar[dict[str, Any]] = {"restarts": 1}

    def __init__(
        self,
        kernel: str | None = None,
        restarts: int = 3,
        artificial_noise: float = 0.0,
        max_iter: int = 1000,
        seed: int = 0,
    ) -> None:
        self.kernel = kernel
        self.restarts = restarts
        self.artificial_noise = artificial_noise
        self.max_iter = max_iter
        self.seed = seed

    def _train(self, fd: FitData, kernel: str, n_terms: int) -> None:
        ys = fd.y
        self.c_ = float(np.mean(ys))
        self.s_ = float(np.std(ys)) or 1.0
        norm = FitData(fd.t, fd.o, (ys - self.c_) / self.s_, fd.blocks, fd.n_outputs)
        from pseudotwin.gp.train import fit_lcm  # GPy: only where a model is trained

        self.params_, self.report_, _ = fit_lcm(
            norm, kernel, n_terms=n_terms, restarts=self.restarts,
            artificial_noise=self.artificial_noise, max_iter=self.max_iter, seed=self.seed,
        )
        self.fit_data_ = norm

    def _common_dict(self) -> dict[str, Any]:
        return {
            "kernel": self.params_.kernel,
            "scaling": {"offset": self.c_, "scale": self.s_},
            "hyperparameters": self.params_.to_dict(),
            "diagnostics": self.report_.to_dict(),
            "settings": {
                "restarts": self.restarts, "artificial_noise": self.artificial_noise,
                "max_iter": self.max_iter, "seed": self.seed,
            },
        }

    def _load_common(self, d: dict[str, Any], hours: OperatingHours) -> None:
        self.hours_ = hours
        self.c_ = float(d["scaling"]["offset"])
        self.s_ = float(d["scaling"]["scale"])
        self.params_ = LcmParams.from_dict(d["hyperparameters"])
        rep = FitReport()
        for k, v in d.get("diagnostics", {}).items():
            if hasattr(rep, k):
                setattr(rep, k, v)
        self.report_ = rep

    def fit_summary(self) -> str:
        r = self.report_
        return (f"NLML {r.nlml:.2f}, {r.seconds:.1f} s, max jitter {r.jitter_max:.1e}, "
                f"max condition {r.condition_max:.2e}")


class CorrGpLcm(_GpModel):
    """Zero-mean multi-input LCM. Outputs: references 0..q−1, target q.

    n_terms: LCM terms (default: one per reference).
    """

    kind = "corrgp-lcm"
    options = (*_GpModel.options, "n_terms")

    def __init__(self, kernel: str | None = None, n_terms: int | None = None, **kw: Any) -> None:
        super().__init__(kernel, **kw)
        self.n_terms = n_terms

    def fit(self, training: TrainingSet) -> CorrGpLcm:
        self.hours_ = training.hours
        self.references_ = tuple(training.references)
        self.target_ = training.target
        grids = [slot_matrix(training, s) for s in training.sensors]
        fd = _fit_data(grids, training.hours)
        n_terms = self.n_terms or len(self.references_)
        self._train(fd, _kernel_for(self.kernel, training.quantity), n_terms)
        return self

    def start_day(self, day: dt.date) -> LcmDay:
        return LcmDay(self)

    def to_dict(self) -> dict[str, Any]:
        return {"references": list(self.references_), **self._common_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> CorrGpLcm:
        m = cls(kernel=d["kernel"])
        m._load_common(d, spec.hours)
        m.references_ = tuple(d["references"])
        m.target_ = spec.target
        if m.params_.n_outputs != len(m.references_) + 1:
            raise ValueError("LCM outputs do not match its references")
        return m


class LcmDay(DayEstimator):
    def __init__(self, model: CorrGpLcm) -> None:
        self.model = model
        self.index = {r: i for i, r in enumerate(model.references_)}
        self.post = IncrementalPosterior(model.params_, capacity=512)

    def observe(self, sensor: str, hours: float, value: float) -> None:
        o = self.index.get(sensor)
        if o is not None:
            self.post.add(hours, o, (value - self.model.c_) / self.model.s_)

    def revise(self, sensor: str, hours: float, value: float) -> None:
        o = self.index.get(sensor)
        if o is not None:
            self.post.revise(self.post.index_of(hours, o), (value - self.model.c_) / self.model.s_)

    def numerics(self) -> Numerics:
        return _numerics(self.post)

    def predict(self, hours: float) -> Estimate:
        m = self.model
        if self.post.n == 0:
            return Estimate(float("nan"), float("nan"))
        mu, var = self.post.predict(hours, len(m.references_))
        return Estimate(m.c_ + m.s_ * mu, m.s_ * math.sqrt(var))


class CorrGpTriv(_GpModel):
    """Single-input ICM with TRIV as the target's prior mean. Outputs: reference 0, target 1.

    reference: which of the twin's references to use (default: the first).
    ref_mean: "shifted" (P_ref moved to today's level in the init phase) or "profile".
    """

    kind = "corrgp-triv"
    options = (*_GpModel.options, "reference", "ref_mean")

    def __init__(
        self, kernel: str | None = None, reference: str | None = None,
        ref_mean: str = "shifted", **kw: Any,
    ) -> None:
        super().__init__(kernel, **kw)
        self.reference = reference
        self.ref_mean = ref_mean

    def fit(self, training: TrainingSet) -> CorrGpTriv:
        if self.ref_mean not in ("shifted", "profile"):
            raise DataError(f"ref_mean must be 'shifted' or 'profile', not {self.ref_mean!r}")
        ref = self.reference or training.references[0]
        if ref not in training.references:
            raise DataError(f"corrgp-triv reference {ref!r} is not one of the twin's references")
        self.hours_ = training.hours
        self.references_ = (ref,)
        self.target_ = training.target
        self.triv_ = TrivModel((ref,)).fit(training)
        refg = slot_matrix(training, ref)
        tgtg = slot_matrix(training, training.target)
        slot_h = training.hours.window_slots() * training.hours.slot_hours
        prof = self.triv_.profiles_[ref]
        init = slot_h < training.hours.day_start
        ref_res = np.full_like(refg, np.nan)
        for d in range(refg.shape[0]):
            dev = refg[d] - prof
            init_dev = dev[init & np.isfinite(dev)]
            if not len(init_dev):
                first = dev[np.isfinite(dev)]
                init_dev = first[:1]
            delta = self._shift(init_dev)
            ref_res[d] = dev - delta
        tgt_res = tgtg - (self.triv_.offsets_[0][None, :] + refg)
        fd = _fit_data([ref_res, tgt_res], training.hours)
        self._train(fd, _kernel_for(self.kernel, training.quantity), 1)
        return self

    def _shift(self, init_deviations: np.ndarray) -> float:
        """Today's level shift of the reference's prior mean (the one place of the choice)."""
        if self.ref_mean == "profile" or not len(init_deviations):
            return 0.0
        return float(np.mean(init_deviations))

    def _ref_mean(self, profile: F, shift: float) -> F:
        """The reference's prior mean from its profile value(s) at the readings' times."""
        return profile + shift

    def start_day(self, day: dt.date) -> TrivGpDay:
        return TrivGpDay(self)

    def fallback(self) -> TwinModel:
        return self.triv_

    def to_dict(self) -> dict[str, Any]:
        return {
            "reference": self.references_[0],
            "ref_mean": self.ref_mean,
            "triv": self.triv_.to_dict(),
            **self._common_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> CorrGpTriv:
        m = cls(kernel=d["kernel"], reference=d["reference"], ref_mean=d["ref_mean"])
        m._load_common(d, spec.hours)
        m.references_ = (d["reference"],)
        m.target_ = spec.target
        m.triv_ = TrivModel.from_dict(d["triv"], spec)
        if m.params_.n_outputs != 2:
            raise ValueError("corrgp-triv must have exactly two outputs")
        return m


class TrivGpDay(DayEstimator):
    """Live state: ICM posterior on the reference's deviations from its prior mean.

    The level shift is a function of the *set* of readings (all init-phase deviations, or
    the earliest reading's when there is none), so arrival order never changes it.
    """

    def __init__(self, model: CorrGpTriv) -> None:
        self.model = model
        self.ref = model.references_[0]
        self.post = IncrementalPosterior(model.params_, capacity=512)
        self.held = HeldValues()
        self.values: list[float] = []  # raw reference values, in the posterior's order
        self.profile: list[float] = []  # the reference's profile at each value's time
        self.init_dev: dict[int, float] = {}  # posterior index → init-phase deviation
        self.earliest: tuple[float, int, float] | None = None  # (hours, index, deviation)
        self.shift = 0.0

    def _residual(self, profile: float, value: float) -> float:
        """The GP residual of a reference value whose profile value is ``profile``; the prior
        mean is the profile moved by today's shift."""
        m = self.model
        return (value - m._ref_mean(profile, self.shift) - m.c_) / m.s_

    def _note_deviation(self, i: int, hours: float, value: float, profile: float) -> bool:
        """Record point i's deviation from the profile; True when today's shift moved (every
        residual then moves with the prior mean)."""
        m = self.model
        dev = value - profile
        moved = False
        if hours < m.hours_.day_start:
            self.init_dev[i] = dev
            moved = True
        if self.earliest is None or hours < self.earliest[0] or i == self.earliest[1]:
            self.earliest = (hours, i, dev)
            moved = moved or not self.init_dev  # the earliest counts only without init ones
        if not moved:
            return False
        devs = list(self.init_dev.values()) or [self.earliest[2]]
        new_shift = m._shift(np.array(devs))
        if new_shift == self.shift:
            return False
        self.shift = new_shift
        return True

    def _reset_residuals(self) -> None:
        m = self.model
        values, profile = np.array(self.values), np.array(self.profile)
        self.post.set_residuals((values - m._ref_mean(profile, self.shift) - m.c_) / m.s_)

    def observe(self, sensor: str, hours: float, value: float) -> None:
        if sensor != self.ref:
            return
        self.held.update(sensor, hours, value)
        # A failed add raises here and the twin rebuilds this estimator from the window, so
        # the deviation noted for the lost point never outlives it.
        profile = self.model.triv_.profile(self.ref, hours)
        if self._note_deviation(self.post.n, hours, value, profile):
            self._reset_residuals()
        self.post.add(hours, 0, self._residual(profile, value))
        self.values.append(value)
        self.profile.append(profile)

    def revise(self, sensor: str, hours: float, value: float) -> None:
        if sensor != self.ref:
            return
        self.held.update(sensor, hours, value)
        i = self.post.index_of(hours, 0)
        self.values[i] = value
        if self._note_deviation(i, hours, value, self.profile[i]):
            self._reset_residuals()
        else:
            self.post.revise(i, self._residual(self.profile[i], value))

    def numerics(self) -> Numerics:
        return _numerics(self.post)

    def predict(self, hours: float) -> Estimate:
        m = self.model
        ref = self.held.get(self.ref)
        if ref is None:
            return Estimate(float("nan"), float("nan"))
        mu, var = self.post.predict(hours, 1)
        value = m.triv_.offset(0, hours) + ref + m.c_ + m.s_ * mu
        return Estimate(float(value), m.s_ * math.sqrt(var))
