"""TRIV-COV: TRIV plus a linear term in the covariates' deviations from their typical day.

A temperature at the desk moves with more than the wall panel's temperature: people (CO2 is
their trace), lamps, sun, an open window. Covariates are such live sensors of any unit
(``TwinSpec.covariates``). On the slot grid (sample-and-hold), with TRIV's estimate T(t)
(:mod:`pseudotwin.models.triv`) and each covariate c's average training-day profile
P_c(τ)::

    estimate(t) = T(t) + Σ_c β_c · (c(t) − P_c(τ(t)))

The β are least squares of the target's TRIV residual on the deviations over the training
days. Which covariates enter is decided on the training days alone, by forward selection
scored with leave-one-day-out: each held-out day is estimated from TRIV offsets, profiles and
β fitted on the other days, and a covariate is kept only when it lowers the mean held-out
daily NRMSE by at least ``MIN_GAIN`` relative, lowers it on all held-out days but at most
one, and every fold fits its β with the same sign (a gain carried by one or two days, or a
relation that flips sign between folds, is a coincidence of five days). With none kept the
model is TRIV; validation then prefers TRIV (simpler, same score) and the model is not
published live. Live, a covariate silent for more than ``MAX_AGE_H`` contributes nothing
(its deviation counts as zero): a dead CO2 sensor must not freeze a correction into the
estimate.

Each deviation is clipped to the range of deviations seen on the days β was fitted on (live:
all training days; in the leave-one-day-out selection: the fit days): a straight line learned
over a few alike days says nothing beyond them, and covariates drift with the season
(a house's humidity, the weather) where the reference–target offset does not follow
(scripts/origins.py trains the shared runs from many start days and shows where it did).
"""

from __future__ import annotations

import datetime as dt
import math
from typing import Any

import numpy as np

from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import DataError
from pseudotwin.models.base import DayEstimator, Estimate, TrainingSet, TwinModel
from pseudotwin.models.triv import HeldValues, TrivDay, TrivModel, fill_slots, slot_matrix

MIN_GAIN = 0.02  # relative drop of the held-out NRMSE a covariate must bring to be kept
MAX_AGE_H = 1.0  # [h] an older covariate value no longer corrects the estimate
MIN_DAYS = 3  # leave-one-day-out needs at least two days to fit on


def _profile(x: np.ndarray) -> np.ndarray:
    """Mean over days per slot, [days, S] → [S]; slots no day covers interpolated."""
    with np.errstate(invalid="ignore"):
        counts = np.isfinite(x).sum(axis=0)
        sums = np.nansum(x, axis=0)
    mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return fill_slots(mean) if np.isfinite(mean).any() else np.zeros(x.shape[1])


class _Grid:
    """The training days on the slot grid: target [D, S], references [M, D, S], covariates
    name → [D, S] (NaN where a sensor had not reported yet)."""

    def __init__(self, training: TrainingSet, refs: tuple[str, ...],
                 covariates: tuple[str, ...]) -> None:
        self.target = slot_matrix(training, training.target)
        self.refs = np.array([slot_matrix(training, r) for r in refs])
        self.cov = {c: slot_matrix(training, c) for c in covariates}

    def triv(self, days: np.ndarray) -> np.ndarray:
        """TRIV's offsets fitted on ``days`` (a boolean mask [D]): [M, S]."""
        return np.array([_profile(self.target[days] - ref[days]) for ref in self.refs])

    def triv_estimate(self, offsets: np.ndarray) -> np.ndarray:
        """TRIV on every day with ``offsets`` [M, S]: [D, S] (mean over references)."""
        with np.errstate(invalid="ignore"):
            est = offsets[:, None, :] + self.refs
            n = np.isfinite(est).sum(axis=0)
            return np.where(n > 0, np.nansum(est, axis=0) / np.maximum(n, 1), np.nan)

    def deviations(self, chosen: list[str], days: np.ndarray) -> np.ndarray:
        """Deviation of each chosen covariate from its profile fitted on ``days``: [C, D, S];
        0 where a covariate has no value (it then corrects nothing, as live)."""
        out = [self.cov[c] - _profile(self.cov[c][days])[None, :] for c in chosen]
        return np.nan_to_num(np.array(out).reshape(len(chosen), *self.target.shape))


def _dev_range(x: np.ndarray) -> np.ndarray:
    """Range of each covariate's deviations x [C, D', S]: [C, 2] (lowest, highest)."""
    if x.size == 0:
        return np.zeros((x.shape[0], 2))
    flat = x.reshape(x.shape[0], -1)
    return np.column_stack([flat.min(axis=1), flat.max(axis=1)])


def _beta(x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Least squares r ≈ Σ β_c x_c over the finite residuals: x [C, n], r [n] → β [C]."""
    if x.shape[0] == 0 or r.size == 0:
        return np.zeros(x.shape[0])
    beta, *_ = np.linalg.lstsq(x.T, r, rcond=None)
    return np.asarray(beta, float)


def _heldout(grid: _Grid, chosen: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Held-out daily NRMSE [%] of TRIV + the ``chosen`` covariates' term, [D] (NaN where a
    day has too few slots), and each fold's β [D, C]."""
    n_days = grid.target.shape[0]
    scores = np.full(n_days, np.nan)
    betas = np.zeros((n_days, len(chosen)))
    for d in range(n_days):
        rest = np.arange(n_days) != d
        est = grid.triv_estimate(grid.triv(rest))
        x = grid.deviations(chosen, rest)
        resid = grid.target - est
        fit = rest[:, None] & np.isfinite(resid)
        beta = betas[d] = _beta(x[:, fit], resid[fit])
        lim = _dev_range(x[:, rest])  # the held-out day is clipped as a live day would be
        held = np.clip(x[:, d], lim[:, :1], lim[:, 1:])
        pred = est[d] + np.tensordot(beta, held, axes=1)
        ok = np.isfinite(pred) & np.isfinite(grid.target[d])
        if ok.sum() < 2:
            continue
        rmse = float(np.sqrt(np.mean((pred[ok] - grid.target[d][ok]) ** 2)))
        scores[d] = 100.0 * rmse / abs(float(np.mean(grid.target[d][ok])))
    return scores, betas


def _mean(scores: np.ndarray) -> float:
    return float(np.nanmean(scores)) if np.isfinite(scores).any() else float("inf")


def _consistent(before: np.ndarray, after: np.ndarray, betas: np.ndarray) -> bool:
    """Whether a covariate's gain holds across the training days, not on average only: the
    held-out error drops on all days but at most one, and every fold fits β (of the
    covariate just added, the last column) with the same sign. A relation that flips sign
    between folds is a coincidence of the days, however much it lowers the mean."""
    ok = np.isfinite(before) & np.isfinite(after)
    worse = int(np.sum(after[ok] >= before[ok]))
    signs = np.sign(betas[:, -1])
    return worse <= 1 and bool(np.all(signs == signs[0])) and signs[0] != 0


class TrivCovModel(TwinModel):
    """TRIV corrected by the covariates validation on the training days keeps.

    Fitted: triv_ (the TRIV underneath), covariates_ (kept, in order of selection), beta_
    [C] [unit of the quantity per unit of each covariate], cov_profiles_ covariate → [S],
    dev_range_ [C, 2] the lowest and highest deviation of each covariate on the training days
    [its unit] (live deviations are clipped to it), selection_ (the held-out NRMSE [%] of TRIV
    alone and after each kept covariate), alone_ covariate → held-out NRMSE [%] of TRIV with
    that covariate alone (the evidence).
    """

    kind = "triv-cov"
    live_baseline = False
    reads_covariates = True
    options = ("references",)

    def __init__(self, references: tuple[str, ...] | None = None) -> None:
        self.references = references

    @classmethod
    def not_applicable(cls, spec: TwinSpec) -> str:
        return "" if spec.covariates else "the twin has no covariates"

    def fit(self, training: TrainingSet) -> TrivCovModel:
        if not training.covariates:
            raise DataError("triv-cov needs covariates (--covariates, or covariates = [...] "
                            "in the twin's configuration)")
        self.triv_ = TrivModel(self.references).fit(training)
        self.references_ = self.triv_.references_
        grid = _Grid(training, self.references_, training.covariates)
        chosen: list[str] = []
        selection: list[tuple[str, float]] = []
        self.alone_: dict[str, float] = {}
        if len(training.days) >= MIN_DAYS:
            daily, _ = _heldout(grid, chosen)
            best = _mean(daily)
            selection.append(("triv", best))
            left = [c for c in training.covariates if np.isfinite(grid.cov[c]).any()]
            while left:
                tried = {c: _heldout(grid, [*chosen, c]) for c in left}
                means = {c: _mean(t[0]) for c, t in tried.items()}
                if not chosen:
                    self.alone_ = means
                good = {c: m for c, m in means.items()
                        if m <= best * (1 - MIN_GAIN) and _consistent(daily, *tried[c])}
                if not good:
                    break
                c = min(good, key=lambda k: good[k])
                chosen.append(c)
                left.remove(c)
                daily, best = tried[c][0], good[c]
                selection.append((c, best))
        every = np.ones(grid.target.shape[0], dtype=bool)
        x = grid.deviations(chosen, every)
        resid = grid.target - grid.triv_estimate(self.triv_.offsets_)
        ok = np.isfinite(resid)
        self.covariates_ = tuple(chosen)
        self.beta_ = _beta(x[:, ok], resid[ok])
        self.dev_range_ = _dev_range(x)
        self.cov_profiles_ = {c: _profile(grid.cov[c]) for c in chosen}
        self.selection_ = selection
        return self

    def start_day(self, day: dt.date) -> TrivCovDay:
        return TrivCovDay(self)

    def publish_problem(self) -> str:
        if self.covariates_:
            return ""
        return "no covariate lowered TRIV's held-out error on the training days (it is TRIV)"

    def fit_summary(self) -> str:
        if not self.selection_ or not math.isfinite(self.selection_[0][1]):
            return "too few training days to select covariates: none kept"
        alone = ", ".join(f"+{c} {s:.2f} %" for c, s in self.alone_.items())
        kept = ", ".join(f"{c} (β {b:.4g})" for c, b in zip(self.covariates_, self.beta_,
                                                            strict=True)) or "none"
        return (f"held-out NRMSE: triv {self.selection_[0][1]:.2f} %, {alone}; kept: {kept}"
                + (f" ({self.selection_[-1][1]:.2f} %)" if self.covariates_ else ""))

    def to_dict(self) -> dict[str, Any]:
        return {
            "triv": self.triv_.to_dict(),
            "covariates": list(self.covariates_),
            "beta": self.beta_.tolist(),
            "dev_range": self.dev_range_.tolist(),
            "profiles": {c: p.tolist() for c, p in self.cov_profiles_.items()},
            "selection": [[c, s] for c, s in self.selection_ if math.isfinite(s)],
            "alone": {c: s for c, s in self.alone_.items() if math.isfinite(s)},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> TrivCovModel:
        triv = TrivModel.from_dict(d["triv"], spec)
        m = cls(triv.references_)
        m.triv_ = triv
        m.references_ = triv.references_
        m.covariates_ = tuple(str(c) for c in d["covariates"])
        unknown = [c for c in m.covariates_ if c not in spec.covariates]
        if unknown:
            raise ValueError(f"triv-cov: {', '.join(unknown)} not among the twin's covariates")
        m.beta_ = np.asarray(d["beta"], float)
        m.cov_profiles_ = {str(c): np.asarray(p, float) for c, p in d["profiles"].items()}
        # artifacts before the clipping: deviations unbounded, as they were trained
        m.dev_range_ = np.asarray(d.get("dev_range", [[-np.inf, np.inf]] * len(m.covariates_)),
                                  float).reshape(-1, 2)
        S = len(spec.hours.window_slots())
        if m.beta_.shape != (len(m.covariates_),) or set(m.cov_profiles_) != set(m.covariates_) \
                or any(p.shape != (S,) for p in m.cov_profiles_.values()) \
                or m.dev_range_.shape != (len(m.covariates_), 2):
            raise ValueError("triv-cov: β, profiles and deviation ranges do not match the "
                             "covariates and slots")
        m.selection_ = [(str(c), float(s)) for c, s in d.get("selection", [])]
        m.alone_ = {str(c): float(s) for c, s in d.get("alone", {}).items()}
        return m


class TrivCovDay(DayEstimator):
    def __init__(self, model: TrivCovModel) -> None:
        self.model = model
        self.triv = TrivDay(model.triv_)
        self.held = HeldValues()

    def observe(self, sensor: str, hours: float, value: float) -> None:
        if sensor in self.model.cov_profiles_:
            self.held.update(sensor, hours, value)
        else:
            self.triv.observe(sensor, hours, value)

    def predict(self, hours: float) -> Estimate:
        base = self.triv.predict(hours)
        m = self.model
        if not m.covariates_ or not math.isfinite(base.value):
            return base
        slot = m.triv_.slot_index(hours)
        term = 0.0
        for c, b, (lo, hi) in zip(m.covariates_, m.beta_, m.dev_range_, strict=True):
            seen = self.held.values.get(c)
            if seen is not None and hours - seen[0] <= MAX_AGE_H:
                dev = min(max(seen[1] - float(m.cov_profiles_[c][slot]), lo), hi)
                term += float(b) * dev
        return Estimate(base.value + term, base.std)
