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
- :class:`CorrGpMulti` (issue 10): the same TRIV-mean model over all references, an LCM on
  their deviations (the thesis uses one reference only because its data has one).
"""

from __future__ import annotations

import datetime as dt
import math
import warnings
from array import array
from typing import Any, ClassVar, TypeVar

import numpy as np

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import DataError
from pseudotwin.gp import points as gp_points
from pseudotwin.gp.fitdata import FitData, FitReport
from pseudotwin.gp.kernels import DEFAULT_KERNEL, KERNEL_REGISTRY, LcmParams
from pseudotwin.gp.posterior import IncrementalPosterior
from pseudotwin.models.base import DayEstimator, Estimate, Numerics, TrainingSet, TwinModel
from pseudotwin.models.triv import HeldValues, TrivModel, list_mean, slot_matrix

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

    def _terms(self, references: int) -> int:
        """The LCM terms to fit: ``n_terms`` when set (the models that have it), else one
        per reference."""
        n_terms: int | None = getattr(self, "n_terms", None)
        if n_terms is not None and n_terms < 1:
            raise DataError(f"{self.kind} n_terms must be at least 1, not {n_terms}")
        return n_terms or references

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
        n_terms = self._terms(len(self.references_))
        fd = _fit_data(grids, training.hours)
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
        m.n_terms = len(m.params_.terms)
        if m.params_.n_outputs != len(m.references_) + 1:
            raise ValueError("LCM outputs do not match its references")
        return m


class LcmDay(DayEstimator):
    def __init__(self, model: CorrGpLcm) -> None:
        self.model = model
        self.index = {r: i for i, r in enumerate(model.references_)}
        self.post = IncrementalPosterior(model.params_)
        self.points = gp_points.merging()  # None: one GP point per window point

    def _res(self, value: float) -> float:
        return (value - self.model.c_) / self.model.s_

    def observe(self, sensor: str, hours: float, value: float) -> None:
        o = self.index.get(sensor)
        if o is None:
            return
        if self.points is None:
            self.post.add(hours, o, self._res(value))
            return
        i, h, v = self.points.offer(o, hours, value, self.post.n)
        if i is None:
            self.post.add(h, o, self._res(v))
        else:
            self.post.move(i, h, self._res(v))

    def revise(self, sensor: str, hours: float, value: float) -> None:
        o = self.index.get(sensor)
        if o is None:
            return
        if self.points is None:
            self.post.revise(self.post.index_of(hours, o), self._res(value))
        else:
            i, h, v = self.points.revise(o, hours, value)
            self.post.move(i, h, self._res(v))

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
        self._fit_deviations(training, (ref,), 1)
        return self

    def _fit_deviations(self, training: TrainingSet, refs: tuple[str, ...],
                        n_terms: int) -> None:
        """Fit the GP on the deviations of ``refs`` (outputs 0..q−1) and of the target
        (output q) from their prior means; TRIV over ``refs`` is the target's."""
        self.hours_ = training.hours
        self.references_ = refs
        self.target_ = training.target
        self.triv_ = TrivModel(refs).fit(training)
        slot_h = training.hours.window_slots() * training.hours.slot_hours
        init = slot_h < training.hours.day_start
        grids = [slot_matrix(training, r) for r in refs]
        residuals = []
        for r, refg in zip(refs, grids, strict=True):
            ref_res = np.full_like(refg, np.nan)
            for d in range(refg.shape[0]):
                dev = refg[d] - self.triv_.profiles_[r]
                init_dev = dev[init & np.isfinite(dev)]
                if not len(init_dev):
                    first = dev[np.isfinite(dev)]
                    init_dev = first[:1]
                ref_res[d] = dev - self._shift(init_dev)
            residuals.append(ref_res)
        triv = np.array([o[None, :] + g for o, g in zip(self.triv_.offsets_, grids, strict=True)])
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            # A slot no reference covers yet (before its first reading) stays NaN: dropped.
            warnings.simplefilter("ignore", RuntimeWarning)
            tgt_res = slot_matrix(training, training.target) - np.nanmean(triv, axis=0)
        fd = _fit_data([*residuals, tgt_res], training.hours)
        self._train(fd, _kernel_for(self.kernel, training.quantity), n_terms)

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


class _LevelShift:
    """Today's level shift of one reference's prior mean.

    A function of the *set* of that reference's readings (all init-phase deviations, or the
    earliest reading's when there is none), so arrival order never changes it.
    """

    def __init__(self, model: CorrGpTriv) -> None:
        self.model = model
        self.init_dev: dict[int, float] = {}  # posterior index → init-phase deviation
        self.earliest: tuple[float, int, float] | None = None  # (hours, index, deviation)
        self.value = 0.0

    def note(self, i: int, hours: float, deviation: float) -> bool:
        """Record point i's deviation from the profile; True when the shift moved (every
        residual of this reference then moves with its prior mean)."""
        moved = False
        if hours < self.model.hours_.day_start:
            self.init_dev[i] = deviation
            moved = True
        elif self.init_dev.pop(i, None) is not None:  # a merged point moved past day start
            moved = True
        if self.earliest is None or hours < self.earliest[0] or i == self.earliest[1]:
            self.earliest = (hours, i, deviation)
            moved = moved or not self.init_dev  # the earliest counts only without init ones
        if not moved:
            return False
        devs = list(self.init_dev.values()) or [self.earliest[2]]
        new = self.model._shift(np.array(devs))
        if new == self.value:
            return False
        self.value = new
        return True


# Noise variance floor of corrgp-multi's outputs [normalized units: (σ/s)², i.e. σ ≥ 1 % of
# the deviations' spread]. The optimizer may drive a reference's noise to zero (Room Climate
# A's A1: 3e-111, as its second, near-constant term explains the 15-min training grid
# exactly); live, the window's 1-minute points are then conditioned on as exact values and
# the posterior mean explodes (RMSE 2300 K on 2016-03-22, 0.14 K with the floor).
MULTI_NOISE_FLOOR = 1e-4


class CorrGpMulti(CorrGpTriv):
    """TRIV-mean Corr-GP over all references: an LCM on deviations (Trust II, issue 10).

    Outputs: references 0..q−1, target q. Each reference's prior mean is its training-day
    profile shifted to today's level (as :class:`CorrGpTriv`, ``ref_mean``); the target's is
    TRIV over all references. The GP sees deviations only, and its coregionalization learns
    how the target's deviation follows *every* reference's, not just the first one's.
    With a single reference it is exactly corrgp-triv (same fit, same estimates, unless the
    noise floor below applies); validation then prefers corrgp-triv, the earlier entry of the
    registry.

    references: which of the twin's references to use (default: all).
    n_terms: LCM terms (default: one per reference, each a rank-1 B_k = w_k w_kᵀ + diag(κ_k),
    so q references can each drive the target with their own weight and lengthscale).
    """

    kind = "corrgp-multi"
    live_baseline = False
    options = (*_GpModel.options, "references", "ref_mean", "n_terms")

    def __init__(
        self, kernel: str | None = None, references: tuple[str, ...] | None = None,
        ref_mean: str = "shifted", n_terms: int | None = None, **kw: Any,
    ) -> None:
        super().__init__(kernel, ref_mean=ref_mean, **kw)
        self.references = references
        self.n_terms = n_terms

    @classmethod
    def not_applicable(cls, spec: TwinSpec) -> str:
        # The same fit as corrgp-triv, five validation refits included: minutes for nothing.
        return "" if len(spec.references) > 1 else "one reference: it would be corrgp-triv"

    def fit(self, training: TrainingSet) -> CorrGpMulti:
        if self.ref_mean not in ("shifted", "profile"):
            raise DataError(f"ref_mean must be 'shifted' or 'profile', not {self.ref_mean!r}")
        refs = tuple(self.references or training.references)
        if unknown := [r for r in refs if r not in training.references]:
            raise DataError(f"corrgp-multi references {', '.join(unknown)} are not among the "
                            f"twin's references ({', '.join(training.references)})")
        self._fit_deviations(training, refs, self._terms(len(refs)))
        p = self.params_
        if (p.noise < MULTI_NOISE_FLOOR).any():
            self.params_ = LcmParams(p.kernel, p.terms, np.maximum(p.noise, MULTI_NOISE_FLOOR))
        return self

    def coupling(self) -> np.ndarray:
        """The target's deviation regressed on the references' at one instant: [q] weights
        β = Σ_rr⁻¹ Σ_rt of the latent prior covariance (B_k scaled by its kernel's
        variance, summed over the terms), a summary of what the fit learnt."""
        p = self.params_
        cov = np.sum([t.variance * t.B for t in p.terms], axis=0)
        q = p.n_outputs - 1
        return np.asarray(np.linalg.solve(cov[:q, :q], cov[:q, q]), float)

    def start_day(self, day: dt.date) -> TrivGpDay:
        return TrivGpDay(self)

    def to_dict(self) -> dict[str, Any]:
        return {
            "references": list(self.references_),
            "ref_mean": self.ref_mean,
            "triv": self.triv_.to_dict(),
            **self._common_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> CorrGpMulti:
        refs = tuple(d["references"])
        m = cls(kernel=d["kernel"], references=refs, ref_mean=d["ref_mean"])
        m._load_common(d, spec.hours)
        m.references_ = refs
        m.target_ = spec.target
        m.triv_ = TrivModel.from_dict(d["triv"], spec)
        m.n_terms = len(m.params_.terms)
        if m.params_.n_outputs != len(refs) + 1:
            raise ValueError("corrgp-multi outputs do not match its references")
        if m.triv_.references_ != refs:
            raise ValueError("corrgp-multi TRIV mean does not use its references")
        return m


class TrivGpDay(DayEstimator):
    """Live state of :class:`CorrGpTriv` and :class:`CorrGpMulti`: one posterior on the
    deviations of the model's references (one for corrgp-triv) from their prior means, one
    level shift per reference; the target's prior mean is TRIV over those references."""

    def __init__(self, model: CorrGpTriv) -> None:
        self.model = model
        self.index = {r: i for i, r in enumerate(model.references_)}
        self.post = IncrementalPosterior(model.params_)
        self.held = HeldValues()
        self.shifts = [_LevelShift(model) for _ in model.references_]
        # Raw reference values in the posterior's order, and each one's reference profile at
        # its time. Arrays of doubles, not lists: the garbage collector never traverses them.
        self.values = array("d")
        self.profile = array("d")
        self.points = gp_points.merging()  # None: one GP point per window point

    def _residual(self, o: int, profile: float, value: float) -> float:
        m = self.model
        return (value - m._ref_mean(profile, self.shifts[o].value) - m.c_) / m.s_

    def _reset_residuals(self) -> None:
        m = self.model
        values, profile, outs = np.array(self.values), np.array(self.profile), self.post.o
        r = np.empty(len(values))
        for o, shift in enumerate(self.shifts):
            mine = outs == o
            r[mine] = (values[mine] - m._ref_mean(profile[mine], shift.value) - m.c_) / m.s_
        self.post.set_residuals(r)

    def observe(self, sensor: str, hours: float, value: float) -> None:
        o = self.index.get(sensor)
        if o is None:
            return
        self.held.update(sensor, hours, value)
        if self.points is not None:
            i, h, v = self.points.offer(o, hours, value, self.post.n)
            if i is not None:
                self._move(o, i, h, v)
                return
        # A failed add raises here and the twin rebuilds this estimator from the window, so
        # the deviation noted for the lost point never outlives it.
        profile = self.model.triv_.profile(sensor, hours)
        if self.shifts[o].note(self.post.n, hours, value - profile):
            self._reset_residuals()
        self.post.add(hours, o, self._residual(o, profile, value))
        self.values.append(value)
        self.profile.append(profile)

    def revise(self, sensor: str, hours: float, value: float) -> None:
        o = self.index.get(sensor)
        if o is None:
            return
        self.held.update(sensor, hours, value)
        if self.points is not None:
            self._move(o, *self.points.revise(o, hours, value))
            return
        i = self.post.index_of(hours, o)
        self.values[i] = value
        if self.shifts[o].note(i, hours, value - self.profile[i]):
            self._reset_residuals()
        else:
            self.post.revise(i, self._residual(o, self.profile[i], value))

    def _move(self, o: int, i: int, hours: float, value: float) -> None:
        """GP point i of output o (merged window points, gp/points.py) is now at (hours,
        value)."""
        # A revised reading leaves its point's time as it was (a chatty sensor's usual
        # case): the profile there is known.
        profile = (self.profile[i] if hours == self.post.t[i]
                   else self.model.triv_.profile(self.model.references_[o], hours))
        self.values[i], self.profile[i] = value, profile
        moved = self.shifts[o].note(i, hours, value - profile)
        self.post.move(i, hours, self._residual(o, profile, value))
        if moved:
            self._reset_residuals()

    def numerics(self) -> Numerics:
        return _numerics(self.post)

    def predict(self, hours: float) -> Estimate:
        m = self.model
        trivs = [
            m.triv_.offset(i, hours) + v
            for i, r in enumerate(m.references_)
            if (v := self.held.get(r)) is not None
        ]
        if not trivs:
            return Estimate(float("nan"), float("nan"))
        mu, var = self.post.predict(hours, len(m.references_))
        return Estimate(list_mean(trivs) + m.c_ + m.s_ * mu, m.s_ * math.sqrt(var))
