"""VARMA baseline (thesis 6.9): statsmodels VARMAX on the deseasonalized slot grid.

Training builds one continuous grid of *all* slots of every calendar day from the first to
the last training day (``n_slots`` per day; outside the window slots, and on calendar days
missing from the training set, every value is NaN), with the series ``references + target``
as columns. Each series' average daily profile (mean over the training days per window
slot) is subtracted, then ``VARMAX(order=(p, q), trend)`` is fitted by maximum likelihood;
the Kalman filter carries the state through the NaN nights. The trend's time index τ is the
slot count since 00:00 of the first training day.

If VARMAX fails, does not converge within ``maxiter`` iterations / ``max_seconds``, or ends
non-stationary, the model falls back to VAR(p) estimated by ordinary least squares on the
same grid and says so in ``model_name_`` ("var-fallback"; "var" when VAR(p) was asked for,
``force_fallback``, as training does with the order validation chose), ``converged_`` (False
for "var-fallback" only; artifacts saved before this rule say False for "var" too) and
``fit_message_``. The fallback is stored as VARMAX(p, 0) parameters, so the live path is
the same state-space filter either way.

Live, the target is unobserved: each slot's observation vector holds the references'
deseasonalized sample-and-hold values and NaN for the target, and the estimate is the
Kalman-*filtered* target at the current slot plus the target's profile. The filter is our
own small incremental implementation of statsmodels' conventions (a test checks it against
``VARMAX.filter`` to 1e-8), advanced one slot at a time and cached, so a ``predict`` after
every reading costs a list lookup unless a slot was completed or changed.

Level (``target_mode``, default "shifted"): a stationary VARMA pulls the deseasonalized
target back to its training mean, so on days warmer or colder than the training days its
estimate sits between the training level and today's (SML2010: 2.5-3.2 % NRMSE with trend
"c"/"n" vs TRIV's 2.06 %). "shifted" moves all series of a day by that day's level shift δ,
the references' mean deviation from their (unshifted) training profile in the init-phase
slots (corrgp-triv's rule, DESIGN §3), both in training (per training day) and live (δ is
final once the init phase is over, i.e. before anything is published; it may still move
estimates *of init-phase slots*); the estimate adds δ back. The VARMA then models only
deviations from the typical day at today's level, so no constant or drift is needed: the
default trend is "n". ("offset", target − mean of the references, is an invertible linear
map of the series and therefore no re-levelling at all for an unrestricted VARMA: kept for
comparison only.) ``live_refs`` adds the references' mean change since the slot start to
the slot's estimate (TRIV's assumption that the target moves with them), removing the up to
one-slot lag of the sample-and-hold grid on fast-moving data.

Caveat of trend "ct" (the thesis's setting): the drift fitted on the training days is
extrapolated to every later day, amplified by (I − ΣA)⁻¹ of a near-unit-root VAR. On
SML2010 (train 2012-03-14…18, which warmed up day by day) the implied mean of the
deseasonalized series rises by ~1 K per day after training and daily RMSE reaches 2–3.5 K;
trend "c" keeps it at 0.3–1 K on the same days.
"""

from __future__ import annotations

import bisect
import contextlib
import ctypes
import datetime as dt
import logging
import math
import time
import warnings
from array import array
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import ArtifactError, DataError, NumericalError
from pseudotwin.models.base import DayEstimator, Estimate, TrainingSet, Tuned, TwinModel
from pseudotwin.models.triv import fill_slots, list_mean

log = logging.getLogger(__name__)

# statsmodels refuses a stationary initialization at or above this spectral radius.
STATIONARY_LIMIT = 1.0 - 1e-10
# An explosive OLS fallback is shrunk to this spectral radius: the live filter starts every
# day from the stationary distribution, which only exists below 1.
FALLBACK_RADIUS = 0.999
# L-BFGS-B stopping rules. statsmodels' defaults (factr 1e2, pgtol 1e-8) ask for machine
# precision on a likelihood surface that VARMA's identification issues make nearly flat, so
# the optimizer would run into maxiter every time. factr 1e10 stops once an iteration lowers
# -loglike/nobs by less than ~2e-6 relative; pgtol bounds the projected gradient of the
# same per-observation objective.
LBFGS_FACTR = 1e10
LBFGS_PGTOL = 1e-4
FORMAT_VERSION = 1
# "level": the target series is the target itself; "offset": target − mean of the
# references (TRIV's offset), so the estimate's level comes from today's live references.
# "shifted": every series of a day is moved by that day's level shift δ, the references'
# mean deviation from their average profile in the init-phase slots (corrgp-triv's rule,
# DESIGN §3), so the VARMA only sees deviations from the typical day at today's level.
TARGET_MODES = ("level", "offset", "shifted")


def day_shift(raw_refs: np.ndarray, ref_profile: np.ndarray, init: np.ndarray) -> float:
    """Today's level shift δ: mean of (reference − its profile) over the init-phase slots.

    raw_refs [S, M] held reference values (NaN unknown), ref_profile [S, M], init [S] bool.
    Without any init-phase value the earliest slot with one is used; without any, 0.
    """
    dev = raw_refs - ref_profile
    ok = np.isfinite(dev)
    if (ok & init[:, None]).any():
        return float(np.mean(dev[ok & init[:, None]]))
    rows = np.flatnonzero(ok.any(axis=1))
    if not len(rows):
        return 0.0
    return float(np.mean(dev[rows[0]][ok[rows[0]]]))
#: A Kalman filter state: mean a [m], covariance P [m, m].
_State = tuple[np.ndarray, np.ndarray]
_SLOT_EPS = 1e-9  # [h] a reading exactly at a slot start belongs to that slot (as history.py)


# (setter, getter) symbol names of OpenBLAS builds: scipy's wheel, numpy's wheel, plain.
_OPENBLAS_THREADS = (
    ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
    ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
    ("openblas_set_num_threads", "openblas_get_num_threads"),
)


@contextlib.contextmanager
def _single_threaded_blas() -> Iterator[None]:
    """Run the block with every loaded OpenBLAS limited to one thread (Linux; else no-op).

    statsmodels' Kalman filter makes thousands of tiny LAPACK calls per likelihood. With
    OpenBLAS's default one thread per core, each call waits for its helper threads, and on
    a 2-core box with anything else running (the daemon, a GP fit) a VARMAX fit measured
    5-75x slower (0.4 s → 30 s for the same work); single-threaded it is unaffected.
    """
    restore: list[tuple[Any, int]] = []
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            paths = sorted({
                line.split()[-1] for line in maps
                if "openblas" in line.lower() and line.rstrip().split()[-1].startswith("/")
            })
    except OSError:
        paths = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for set_name, get_name in _OPENBLAS_THREADS:
            setter, getter = getattr(lib, set_name, None), getattr(lib, get_name, None)
            if setter is not None and getter is not None:
                restore.append((setter, int(getter())))
                setter(1)
                break
    try:
        yield
    finally:
        for setter, n in restore:
            setter(n)


def _spectral_radius(transition: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(transition)))) if transition.size else 0.0


_STATE_SPACE_FIELDS = ("design", "obs_intercept", "obs_cov", "transition", "selection",
                       "state_cov", "trend_degrees", "trend_params", "init_cov")


@dataclass(frozen=True)
class _StateSpace:
    """Time-invariant matrices of a fitted VARMAX plus its trend (m states, k series).

    design Z [k, m], obs_intercept d [k], obs_cov H [k, k], transition T [m, m],
    selection R [m, k], state_cov Q [k, k]; trend_degrees [k_trend] and trend_params
    [k_trend, k] give the state intercept c(τ) = [Σ_j τ^deg_j · trend_params[j], 0, …] [m]
    that statsmodels places in the transition α_{τ+1} = T α_τ + c(τ+1) + R η.
    init_cov P₀ [m, m] is the stationary state covariance (discrete Lyapunov equation).
    """

    design: np.ndarray
    obs_intercept: np.ndarray
    obs_cov: np.ndarray
    transition: np.ndarray
    selection: np.ndarray
    state_cov: np.ndarray
    trend_degrees: np.ndarray
    trend_params: np.ndarray
    init_cov: np.ndarray
    # The filter's per-slot matrices, by which series are seen (see observed); not data.
    _observed: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=dict, init=False, repr=False, compare=False)
    _zero_intercept: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # One memory layout whether read off statsmodels or an artifact: BLAS rounds a
        # product by layout, and a fitted and a loaded model must predict the same bits.
        for name in _STATE_SPACE_FIELDS:
            object.__setattr__(self, name, np.ascontiguousarray(getattr(self, name), float))
        zeros = np.zeros(self.k_states)
        zeros.setflags(write=False)  # shared by every filter step (state_intercept)
        object.__setattr__(self, "_zero_intercept", zeros)

    def observed(self, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Z [n, m], H [n, n] and d [n] of the ``seen`` series (bool [k], n of them true).

        Cached per pattern: every slot of a day asks for the same one or two (the target is
        never seen live), and indexing them out anew was a third of a filter step.
        """
        key = seen.tobytes()
        got = self._observed.get(key)
        if got is None:
            got = (self.design[seen], self.obs_cov[np.ix_(seen, seen)],
                   self.obs_intercept[seen])
            self._observed[key] = got
        return got

    @property
    def k_endog(self) -> int:
        return self.design.shape[0]

    @property
    def k_states(self) -> int:
        return self.transition.shape[0]

    def state_intercept(self, tau: float) -> np.ndarray:
        """c(τ) [m] for the state at trend time τ [slots since 00:00 of the first day]."""
        if not self.trend_params.size:
            return self._zero_intercept  # read-only, shared: no allocation per filter step
        c = np.zeros(self.k_states)
        c[: self.k_endog] = (float(tau) ** self.trend_degrees) @ self.trend_params
        return c

    def initial_state(self, tau0: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted state for the first slot (trend time τ₀): mean [m], cov [m, m].

        As statsmodels' stationary initialization: mean = (I − T)⁻¹ c, with the intercept
        of the *second* period (its state_intercept column 0 belongs to τ₀ + 1).
        """
        eye = np.eye(self.k_states)
        mean = np.linalg.solve(eye - self.transition, self.state_intercept(tau0 + 1))
        return mean, self.init_cov.copy()

    def to_dict(self) -> dict[str, list[Any]]:
        return {name: getattr(self, name).tolist() for name in _STATE_SPACE_FIELDS}

    @classmethod
    def from_dict(cls, d: dict[str, Any], k: int) -> _StateSpace:
        """The matrices an artifact stores (k series), checked for shape and finiteness."""
        try:
            arrays = {name: np.asarray(d[name], float).reshape(np.shape(d[name]))
                      for name in _STATE_SPACE_FIELDS}
        except (KeyError, TypeError, ValueError) as exc:
            raise ArtifactError(f"VARMA state_space unreadable: {exc!r}") from None
        ssm = cls(**arrays)
        m = ssm.k_states
        shapes = {"design": (k, m), "obs_intercept": (k,), "obs_cov": (k, k),
                  "transition": (m, m), "selection": (m, k), "state_cov": (k, k),
                  "init_cov": (m, m)}
        for name, shape in shapes.items():
            if arrays[name].shape != shape:
                raise ArtifactError(f"VARMA state_space {name} has shape "
                                    f"{arrays[name].shape}, expected {shape}")
        if ssm.trend_params.size and ssm.trend_params.shape != (len(ssm.trend_degrees), k):
            raise ArtifactError(f"VARMA state_space trend_params has shape "
                                f"{ssm.trend_params.shape}")
        if not all(np.isfinite(a).all() for a in arrays.values()):
            raise ArtifactError("VARMA state_space holds non-finite values")
        radius = _spectral_radius(ssm.transition)
        if not radius < STATIONARY_LIMIT:  # as from_params: no stationary start for a day
            raise ArtifactError(f"VARMA state_space transition has spectral radius "
                                f"{radius:.6f}: not stationary")
        return ssm

    @classmethod
    def from_params(
        cls, order: tuple[int, int], trend: str, params: np.ndarray, k: int
    ) -> _StateSpace:
        """Read the matrices off a statsmodels VARMAX updated with ``params`` (constrained)."""
        from pseudotwin.models.varmax import (
            prepare_trend_spec,
            quiet_varmax,
            solve_discrete_lyapunov,
        )

        mod = quiet_varmax(np.zeros((2, k)), order, trend, trend_offset=0)
        if len(params) != mod.k_params:
            raise ArtifactError(
                f"VARMA: {len(params)} parameters given, VARMAX{order} with trend {trend!r} "
                f"on {k} series has {mod.k_params}"
            )
        mod.update(np.asarray(params, float))
        ssm = mod.ssm
        poly, k_trend = prepare_trend_spec(trend)
        transition = np.array(ssm["transition"], float).reshape(ssm.k_states, ssm.k_states)
        selection = np.array(ssm["selection"], float).reshape(ssm.k_states, ssm.k_posdef)
        state_cov = np.array(ssm["state_cov"], float).reshape(ssm.k_posdef, ssm.k_posdef)
        radius = _spectral_radius(transition)
        if not radius < STATIONARY_LIMIT:
            raise NumericalError(
                f"VARMA transition has spectral radius {radius:.6f}: not stationary, "
                "no stationary start for the day"
            )
        rqr = selection @ state_cov @ selection.T
        return cls(
            design=np.array(ssm["design"], float).reshape(k, ssm.k_states),
            obs_intercept=np.array(ssm["obs_intercept"], float).reshape(k),
            obs_cov=np.array(ssm["obs_cov"], float).reshape(k, k),
            transition=transition,
            selection=selection,
            state_cov=state_cov,
            trend_degrees=np.flatnonzero(poly).astype(float),
            trend_params=np.asarray(params[: k * k_trend], float).reshape(k, k_trend).T,
            init_cov=np.asarray(solve_discrete_lyapunov(transition, rqr), float),
        )


def _ols_var(
    grid: np.ndarray, p: int, trend: str
) -> tuple[np.ndarray, float]:
    """VAR(p) with the VARMAX trend by least squares on the grid [n, k].

    Rows whose lag window holds any NaN are dropped. Returns the VARMAX(p, 0) parameter
    vector (trend, AR, lower Cholesky factor of the innovation covariance, in statsmodels'
    order) and the spectral radius of the OLS companion matrix before any shrinking.
    """
    from pseudotwin.models.varmax import prepare_trend_spec

    n, k = grid.shape
    poly, k_trend = prepare_trend_spec(trend)
    degrees = np.flatnonzero(poly).astype(float)
    rows = [
        t for t in range(p, n) if np.isfinite(grid[t - p: t + 1]).all()
    ]
    n_reg = k_trend + k * p
    if len(rows) <= n_reg + k:
        raise DataError(
            f"VARMA: only {len(rows)} complete {p + 1}-slot stretches in the training days, "
            f"VAR({p}) needs more than {n_reg + k}"
        )
    t_idx = np.asarray(rows)
    trend_x = t_idx[:, None].astype(float) ** degrees[None, :]  # τ of y_t is its row index
    lags = [grid[t_idx - i] for i in range(1, p + 1)]  # each [N, k]
    x = np.hstack([trend_x, *lags])  # [N, k_trend + k p]
    y = grid[t_idx]  # [N, k]
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)  # [n_reg, k]
    resid = y - x @ coef
    sigma = resid.T @ resid / max(len(rows) - n_reg, 1)
    b = coef.T  # [k, n_reg]: equation i in row i, as VARMAX lays its parameters out
    ar = b[:, k_trend:].reshape(k, p, k)  # [eq, lag, series]
    companion = np.zeros((k * p, k * p))
    companion[:k] = ar.reshape(k, k * p)
    companion[k:, :-k] = np.eye(k * (p - 1))
    radius = _spectral_radius(companion)
    if radius >= FALLBACK_RADIUS:
        # A_i ρ^i scales every companion eigenvalue by ρ exactly.
        rho = FALLBACK_RADIUS / radius
        ar = ar * rho ** np.arange(1, p + 1)[None, :, None]
    chol = np.linalg.cholesky(sigma + 1e-12 * np.trace(sigma) / k * np.eye(k))
    params = np.concatenate([
        b[:, :k_trend].ravel(),
        ar.reshape(k, k * p).ravel(),
        chol[np.tril_indices(k)],
    ])
    return params, radius


class VarmaModel(TwinModel):
    """VARMA(p, q) baseline on the slot grid (thesis 6.9); series = references + target.

    Settings: p, q the VARMAX order (q None: q = p; p unset in training: chosen by
    validation among ``tuned``); trend a statsmodels trend ("ct": intercept + drift in
    τ [slots]); maxiter bounds the maximum-likelihood fit (max_seconds [s], off by default,
    adds a wall-clock bound; it makes the outcome depend on machine load);
    force_fallback skips VARMAX and fits the OLS VAR(p) directly; target_mode "shifted"
    (default: each day re-levelled by its init-phase shift δ), "level" or "offset" (see the
    module docstring); live_refs adds the references' change since the slot start.

    Fitted: references_, target_, sensors_ (k = len), hours_; profile_ [S, k] average daily
    profile per window slot [unit of the quantity]; train_day0_ first training day (τ = 0 at
    its 00:00); order_ (p, q) actually used; params_ [n_params] constrained VARMAX
    parameters named by param_names_; model_name_ "varma" | "var" | "var-fallback";
    converged_ (False only for "var-fallback": the VARMAX asked for failed); fit_message_;
    fit_warnings_ (what statsmodels warned, silenced on the console);
    fit_seconds_ {"varmax": s, "fallback": s}; ssm_ the state-space matrices;
    shift_profile_ [S, M] the references' unshifted profiles δ is measured against and
    train_shifts_ [D] the training days' δ (both None unless target_mode is "shifted").
    """

    kind = "varma"
    options = ("p", "q", "trend", "maxiter", "max_seconds", "force_fallback", "target_mode",
               "live_refs")
    candidate = False  # a monitoring baseline (DESIGN.md §3), never the primary
    # With one day, the day is its own typical profile: no deviation is left to fit.
    min_days = 2
    # Held-out folds use the OLS VAR(p) form: a VARMAX fit per fold costs minutes.
    validation_options = {"force_fallback": True}
    # The order, unless the user sets p: five days hold ~220 slots, and a VAR(4) of three
    # series has 36 lag coefficients, which the training days may not support (Room
    # Climate B: VAR(4) 1.59× TRIV on the test days, VAR(1) 1.06×, tied on the training days).
    # Validation scores the OLS VAR(p) form (above), so that is what is fit: VARMAX by
    # maximum likelihood is another model, which validation never saw (Room Climate B, order
    # 1, measured once with evaluate(..., options={"varma": {"p": 1, "q": 1}}) and q 0: VARMAX
    # 1.99× and 1.83× TRIV on the test days, the OLS VAR(1) 1.06×).
    # A user who sets p, or a VARMAX setting, gets VARMAX(p, q) with its fallback, as before.
    tuned = Tuned("p", (1, 2, 4), fit_with={"force_fallback": True},
                  pinned_by=("q", "maxiter", "max_seconds"))

    def __init__(
        self,
        p: int = 4,
        q: int | None = None,
        trend: str = "n",
        maxiter: int = 200,
        max_seconds: float | None = None,
        force_fallback: bool = False,
        target_mode: str = "shifted",
        live_refs: bool = True,
    ) -> None:
        self.p = p
        self.q = q
        self.trend = trend
        self.target_mode = target_mode
        self.live_refs = live_refs
        self.maxiter = maxiter
        self.max_seconds = max_seconds
        self.force_fallback = force_fallback

    @property
    def ma_order(self) -> int:
        """q as fitted: the setting, or p when it is unset (VARMA(p, p), DESIGN §3)."""
        return self.p if self.q is None else self.q

    # -- training ---------------------------------------------------------------------
    def fit(self, training: TrainingSet) -> VarmaModel:
        if self.p < 1 or self.q is not None and self.q < 0:
            raise DataError(f"VARMA order ({self.p}, {self.q}): need p ≥ 1 and q ≥ 0")
        from pseudotwin.models.varmax import prepare_trend_spec, quiet_varmax

        prepare_trend_spec(self.trend)  # rejects an unknown trend before any work
        if self.target_mode not in TARGET_MODES:
            raise DataError(
                f"VARMA target_mode {self.target_mode!r}: choose from {', '.join(TARGET_MODES)}"
            )
        hours = training.hours
        sensors = training.sensors
        if not training.days:
            raise DataError("VARMA: no training days")
        slots = hours.window_slots()
        n = hours.n_slots
        vals = np.array(
            [[d.slot_values(s, hours) for s in sensors] for d in training.days]
        ).transpose(0, 2, 1)  # [D, S, k]
        if self.target_mode == "offset":
            # The target column becomes TRIV's offset: target − mean of the references.
            vals[:, :, -1] -= vals[:, :, :-1].mean(axis=2)
        self.shift_profile_ = None
        self.train_shifts_ = None
        if self.target_mode == "shifted":
            m_refs = len(training.references)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                ref_prof = np.column_stack([
                    fill_slots(np.nanmean(vals[:, :, j], axis=0)) for j in range(m_refs)
                ])  # [S, M] unshifted reference profiles: what δ is measured against
            init = slots * hours.slot_hours < hours.day_start
            shifts = np.array([day_shift(v[:, :m_refs], ref_prof, init) for v in vals])
            vals = vals - shifts[:, None, None]
            self.shift_profile_ = ref_prof
            self.train_shifts_ = shifts
        profile = np.empty(vals.shape[1:])
        for j, s in enumerate(sensors):
            if not np.isfinite(vals[:, :, j]).any():
                raise DataError(f"VARMA: sensor {s} has no readings on the training days")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slots: filled next
                profile[:, j] = fill_slots(np.nanmean(vals[:, :, j], axis=0))
        day0 = min(d.day for d in training.days)
        n_days = (max(d.day for d in training.days) - day0).days + 1
        grid = np.full((n_days * n, len(sensors)), np.nan)  # [n_days · n_slots, k]
        for d, v in zip(training.days, vals, strict=True):
            grid[(d.day - day0).days * n + slots] = v - profile

        self.references_ = tuple(training.references)
        self.target_ = training.target
        self.sensors_ = tuple(sensors)
        self.hours_ = hours
        self.profile_: np.ndarray = profile  # [S, k]
        self.train_day0_ = day0
        self.fit_seconds_: dict[str, float] = {}
        self.fit_warnings_: list[str] = []

        t0 = time.perf_counter()
        ols_params, ols_radius = _ols_var(grid, self.p, self.trend)
        self.fit_seconds_["fallback"] = time.perf_counter() - t0

        params, message = None, ""
        if not self.force_fallback:
            t0 = time.perf_counter()
            params, message = self._fit_varmax(grid)
            self.fit_seconds_["varmax"] = time.perf_counter() - t0
        if params is not None:
            self.order_ = (self.p, self.ma_order)
            self.params_ = params
            self.model_name_ = "varma"
            self.converged_ = True
            self.fit_message_ = message
        else:
            self.order_ = (self.p, 0)
            self.params_ = ols_params
            # Asked for (validation's form, or the user's): "var"; VARMAX failed: the fallback.
            self.model_name_ = "var" if self.force_fallback else "var-fallback"
            # A VAR(p) asked for is a closed-form fit: nothing failed to converge.
            self.converged_ = self.force_fallback
            shrink = (
                f"; OLS spectral radius {ols_radius:.4f} shrunk to {FALLBACK_RADIUS}"
                if ols_radius >= FALLBACK_RADIUS else ""
            )
            self.fit_message_ = (
                f"VAR({self.p}) by least squares, no VARMAX fit (force_fallback){shrink}"
                if self.force_fallback else
                f"{message}; fell back to VAR({self.p}) by least squares{shrink}")
            # Asked-for VARMA that ends as VAR is worth a warning; a forced VAR is not.
            (log.info if self.force_fallback else log.warning)("VARMA: %s", self.fit_message_)
        self.param_names_ = list(
            quiet_varmax(np.zeros((2, len(sensors))), self.order_, self.trend).param_names
        )
        self.ssm_ = _StateSpace.from_params(self.order_, self.trend, self.params_, len(sensors))
        return self

    def _fit_varmax(self, grid: np.ndarray) -> tuple[np.ndarray | None, str]:
        """Maximum likelihood VARMAX(p, q); (params, message), params None on failure."""
        from pseudotwin.models.varmax import BoundedVARMAX, FitTimeout

        k = grid.shape[1]
        with warnings.catch_warnings(record=True) as caught, _single_threaded_blas():
            warnings.simplefilter("always")
            try:
                mod = BoundedVARMAX(
                    grid, order=(self.p, self.ma_order), trend=self.trend, trend_offset=0
                )
                # statsmodels' own start (VAR on the interpolated grid, then a VAR on its
                # residuals for the MA part) converges far sooner than the complete-rows OLS
                # VAR with zero MA terms, which creeps along VARMA's flat likelihood ridge.
                start = mod.start_params
                if self.max_seconds is not None:
                    mod.deadline = time.monotonic() + self.max_seconds
                res = mod.fit(
                    start_params=start, method="lbfgs", maxiter=self.maxiter, disp=False,
                    cov_type="none", factr=LBFGS_FACTR, pgtol=LBFGS_PGTOL,
                )
                mod.deadline = None
            except FitTimeout:
                params, message = None, (
                    f"VARMAX{(self.p, self.ma_order)} did not finish within "
                    f"{self.max_seconds:g} s"
                )
            except Exception as exc:  # whatever breaks inside VARMAX, the design falls back
                params, message = None, (
                    f"VARMAX{(self.p, self.ma_order)} failed: {type(exc).__name__}: {exc}"
                )
            else:
                retvals = getattr(res, "mle_retvals", None) or {}
                iters = retvals.get("iterations", "?")
                params = np.asarray(res.params, float)
                if not retvals.get("converged", False):
                    # L-BFGS-B's warnflag 1 means an iteration *or* function-evaluation
                    # limit was hit, 2 an abnormal stop (e.g. a failed line search).
                    why = {1: "iteration or function-evaluation limit reached",
                           2: "abnormal termination of the line search"}.get(
                        int(retvals.get("warnflag", -1)), f"warnflag {retvals.get('warnflag')}")
                    params, message = None, (
                        f"VARMAX{(self.p, self.ma_order)} did not converge after {iters} "
                        f"iterations ({why}; maxiter {self.maxiter})"
                    )
                elif not (np.isfinite(params).all() and math.isfinite(float(res.llf))):
                    params, message = (
                        None, f"VARMAX{(self.p, self.ma_order)} gave non-finite values")
                else:
                    message = (
                        f"VARMAX{(self.p, self.ma_order)} converged in {iters} iterations, "
                        f"loglike {float(res.llf):.2f}"
                    )
        self.fit_warnings_ = sorted({f"{w.category.__name__}: {w.message}" for w in caught})
        for w in self.fit_warnings_:
            log.debug("VARMA fit: %s", w)
        if params is not None:
            try:
                _StateSpace.from_params((self.p, self.ma_order), self.trend, params, k)
            except (NumericalError, np.linalg.LinAlgError, ValueError) as exc:
                params, message = None, f"VARMAX{(self.p, self.ma_order)} unusable live: {exc}"
        return params, message

    # -- live -------------------------------------------------------------------------
    @property
    def model_name(self) -> str:
        return self.model_name_

    def publish_problem(self) -> str:
        if "t" in self.trend:
            return (f"trend {self.trend!r} extrapolates the training days' drift into every "
                    "later day; that cannot be validated on the training days")
        if self.target_mode == "level":
            return ("target_mode 'level' pulls the target back to the training days' level; "
                    "use 'shifted'")
        return ""

    def fit_summary(self) -> str:
        return self.fit_message_

    def trend_offset(self, day: dt.date) -> int:
        """Trend time τ [slots since 00:00 of ``train_day0_``] of ``day``'s first window slot."""
        first = int(self.hours_.window_slots()[0])
        return (day - self.train_day0_).days * self.hours_.n_slots + first

    def start_day(self, day: dt.date) -> VarmaDay:
        return VarmaDay(self, day)

    # -- artifact ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        slots = self.hours_.window_slots()
        return {
            "version": FORMAT_VERSION,
            "model_name": self.model_name_,
            "converged": bool(self.converged_),
            "fit_message": self.fit_message_,
            "fit_warnings": list(self.fit_warnings_),
            "fit_seconds": {k: float(v) for k, v in self.fit_seconds_.items()},
            "settings": {
                "p": self.p, "q": self.q, "trend": self.trend, "maxiter": self.maxiter,
                "max_seconds": self.max_seconds, "force_fallback": self.force_fallback,
                "target_mode": self.target_mode, "live_refs": self.live_refs,
            },
            "shift_profile": (
                None if self.shift_profile_ is None else self.shift_profile_.tolist()
            ),
            "order": list(self.order_),
            "trend": self.trend,
            "sensors": list(self.sensors_),
            "param_names": list(self.param_names_),
            "params": [float(v) for v in self.params_],
            # The live path reads these (no statsmodels in the daemon); params stay the record.
            "state_space": self.ssm_.to_dict(),
            "profile": self.profile_.tolist(),
            "train_day0": self.train_day0_.isoformat(),
            "slots": {
                "slot_minutes": self.hours_.slot_minutes,
                "n_slots": self.hours_.n_slots,
                "first": int(slots[0]),
                "count": len(slots),
            },
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], spec: TwinSpec) -> VarmaModel:
        """Rebuild a fitted model for live use (no refit) from :meth:`to_dict` output."""
        hours, references, target = spec.hours, spec.references, spec.target
        if int(d.get("version", 1)) > FORMAT_VERSION:
            raise ArtifactError(f"VARMA artifact version {d['version']} is newer than supported")
        # Artifacts written before these settings existed: the target's level, slot-held.
        m = cls(**{"target_mode": "level", "live_refs": False, **d["settings"]})
        sensors = tuple(d["sensors"])
        if sensors != (*references, target):
            raise ArtifactError(
                f"VARMA was trained on {', '.join(sensors)}, the twin has "
                f"{', '.join((*references, target))}"
            )
        slots = hours.window_slots()
        grid = d["slots"]
        if (
            float(grid["slot_minutes"]) != hours.slot_minutes
            or int(grid["n_slots"]) != hours.n_slots
            or int(grid["first"]) != int(slots[0])
            or int(grid["count"]) != len(slots)
        ):
            raise ArtifactError("VARMA slot grid does not match the twin's operating hours")
        m.references_ = tuple(references)
        m.target_ = target
        m.sensors_ = sensors
        m.hours_ = hours
        m.profile_ = np.asarray(d["profile"], float)
        if tuple(m.profile_.shape) != (len(slots), len(sensors)):
            raise ArtifactError(f"VARMA profile has shape {m.profile_.shape}")
        m.train_day0_ = dt.date.fromisoformat(d["train_day0"])
        sp = d.get("shift_profile")
        m.shift_profile_ = None if sp is None else np.asarray(sp, float)
        m.train_shifts_ = None
        if m.target_mode == "shifted" and (
            m.shift_profile_ is None or m.shift_profile_.shape != (len(slots), len(references))
        ):
            raise ArtifactError("VARMA target_mode 'shifted' needs shift_profile [S, M]")
        m.order_ = (int(d["order"][0]), int(d["order"][1]))
        m.trend = str(d["trend"])
        m.model_name_ = str(d["model_name"])
        m.converged_ = bool(d["converged"])
        m.fit_message_ = str(d["fit_message"])
        m.fit_warnings_ = list(d.get("fit_warnings", []))
        m.fit_seconds_ = {k: float(v) for k, v in d.get("fit_seconds", {}).items()}
        if "state_space" in d:  # written by this version: no statsmodels needed
            m.param_names_ = [str(n) for n in d["param_names"]]
            m.params_ = np.array([float(v) for v in d["params"]])
            if len(m.param_names_) != len(m.params_):
                raise ArtifactError("VARMA param_names and params differ in length")
            m.ssm_ = _StateSpace.from_dict(d["state_space"], len(sensors))
            return m
        from pseudotwin.models.varmax import quiet_varmax

        names = list(quiet_varmax(np.zeros((2, len(sensors))), m.order_, m.trend).param_names)
        given = dict(zip(d["param_names"], d["params"], strict=True))
        missing = [n for n in names if n not in given]
        if missing:
            raise ArtifactError(f"VARMA parameters missing: {', '.join(missing[:5])}")
        m.param_names_ = names
        m.params_ = np.array([float(given[n]) for n in names])
        try:
            m.ssm_ = _StateSpace.from_params(m.order_, m.trend, m.params_, len(sensors))
        except NumericalError as exc:
            raise ArtifactError(f"VARMA parameters unusable: {exc}") from None
        return m


class VarmaDay(DayEstimator):
    """One day's incremental Kalman filter over the window slots (target always missing).

    Slot i's observation is each reference's last reading at or before the slot start
    (NaN if none yet) minus its profile. Filtered states are cached per slot; a reading that
    changes an already filtered slot (only an out-of-order one can) invalidates the cache
    from that slot on.

    The cache keeps the newest ``KEEP`` slots' states, and of older slots only the predicted
    state of every ``EVERY``-th (a checkpoint): the others are filtered again from the
    checkpoint before them when asked for, which only an estimate of an earlier time or an
    out-of-order reading does. A day of 5-minute slots then holds ~20 covariance matrices
    instead of ~280, per twin (the same numbers, computed the same way).
    """

    KEEP: ClassVar[int] = 4
    EVERY: ClassVar[int] = 8

    def __init__(self, model: VarmaModel, day: dt.date) -> None:
        self.model = model
        self.day = day
        hours = model.hours_
        self._ss = model.ssm_
        self._first = int(hours.window_slots()[0])
        self._starts = hours.window_slots() * hours.slot_hours + _SLOT_EPS  # [S] h
        self._start_list = self._starts.tolist()  # bisect on a list: no numpy call per reading
        self._tau0 = model.trend_offset(day)
        self._col = {s: j for j, s in enumerate(model.references_)}
        # Each reference's readings (time-sorted): arrays of doubles, which the garbage
        # collector never traverses (a thousand twins' lists made full collections slow).
        self._times = {s: array("d") for s in model.references_}
        self._values = {s: array("d") for s in model.references_}
        S, k = int(model.profile_.shape[0]), int(model.profile_.shape[1])
        self._obs = np.full((S, k), np.nan)  # [S, k] deseasonalized; target column stays NaN
        a0, p0 = self._ss.initial_state(self._tau0)
        # Slot → predicted state for it, slot → its filtered state: the kept ones (KEEP,
        # EVERY) of the first _n slots, which are filtered (a dict holds no entry per slot,
        # which the garbage collector would traverse).
        self._pred: dict[int, _State] = {0: (a0, p0)}
        self._filt: dict[int, _State] = {}
        self._n = 0
        self._rqr = self._ss.selection @ self._ss.state_cov @ self._ss.selection.T
        # The estimate is w · (series at the slot): the target itself, or in "offset" mode
        # the modelled offset plus the mean of the (filtered = observed, when seen) references.
        self._weights = np.zeros(k)
        self._weights[-1] = 1.0
        if model.target_mode == "offset":
            self._weights[:-1] = 1.0 / (k - 1)
        # The estimate's parts that do not change within a day: z = w·Z [m], w·d, w·H·w.
        self._z = self._weights @ self._ss.design
        self._wd = self._weights @ self._ss.obs_intercept
        self._whw = self._weights @ self._ss.obs_cov @ self._weights
        self._raw = np.full((S, k - 1), np.nan)  # [S, M] held reference values
        self._init = hours.window_slots() * hours.slot_hours < hours.day_start  # [S]
        self._last_init = int(np.flatnonzero(self._init).max(initial=-1))
        self.shift = 0.0  # today's level shift δ (target_mode "shifted")
        # Reference column → earliest reading time not yet in the held values (_flush).
        self._pending: dict[int, float] = {}

    # -- readings ---------------------------------------------------------------------
    def observe(self, sensor: str, hours: float, value: float) -> None:
        """Record a reference reading at wall-clock ``hours`` [h].

        Readings of the target or of sensors this model does not use are ignored (the
        target is unobserved live by design); non-finite values are ignored as missing.
        """
        j = self._col.get(sensor)
        if j is None or not math.isfinite(value):
            return
        times, values = self._times[sensor], self._values[sensor]
        if not times or hours >= times[-1]:
            times.append(hours)
            values.append(value)
        else:
            # Out of order: keep both lists sorted by time, later arrivals after equals.
            pos = int(np.searchsorted(times, hours, side="right"))
            times.insert(pos, hours)
            values.insert(pos, value)
        self._mark(j, hours)

    def revise(self, sensor: str, hours: float, value: float) -> None:
        j = self._col.get(sensor)
        if j is None or not math.isfinite(value):
            return
        times, values = self._times[sensor], self._values[sensor]
        # The revised point is the sensor's newest: the last of its time, from the end.
        i = len(times) - 1
        while i >= 0 and times[i] != hours:
            i -= 1
        if i < 0:
            raise KeyError(f"no reading of {sensor} at {hours} h to revise")
        values[i] = value
        self._mark(j, hours)

    def _mark(self, j: int, hours: float) -> None:
        # The held values are brought up to date when next read (_flush), once per estimate
        # rather than once per reading: a 1-minute reference is estimated every 15 minutes.
        # The same refresh from the earliest reading since gives the same arrays.
        self._pending[j] = min(self._pending.get(j, hours), hours)

    def _flush(self) -> None:
        pending, self._pending = self._pending, {}
        for j, hours in pending.items():
            self._refresh(j, hours)

    def _refresh(self, j: int, hours: float) -> None:
        """Update the held values of reference column j from the first slot at or after
        ``hours`` [h] on, and invalidate the filter from the first slot that changed."""
        sensor = self.model.references_[j]
        times, values = self._times[sensor], self._values[sensor]
        first = bisect.bisect_left(self._start_list, hours)
        if first >= len(self._start_list):
            return
        # Every slot from the one after the sensor's newest reading on holds that reading;
        # only slots before it (readings since the last flush spanning a slot start, or an
        # out-of-order one) need a search.
        newest = max(first, bisect.bisect_left(self._start_list, times[-1]))
        if newest > first:
            idx = np.searchsorted(times, self._starts[first:newest], side="right") - 1
            held = np.where(idx >= 0, np.asarray(values)[np.clip(idx, 0, None)], np.nan)
            self._raw[first:newest, j] = held
        self._raw[newest:, j] = values[-1]
        # δ depends on the init slots, or else on the earliest slot with a value: only a
        # change there can move it.
        if self.model.target_mode == "shifted" and (
                first <= self._last_init or not np.isfinite(self._raw[:first]).any()):
            assert self.model.shift_profile_ is not None  # checked on load
            shift = day_shift(self._raw, self.model.shift_profile_, self._init)
            if shift != self.shift:
                self.shift = shift
                first = 0  # a new δ moves every slot
        m = self._raw.shape[1]
        new = self._raw[first:] - self.model.profile_[first:, :m] - self.shift  # [S', M]
        if first >= self._n:  # slots not filtered yet: nothing to invalidate
            self._obs[first:, :m] = new
            return
        old = self._obs[first:, :m]
        changed = (~((new == old) | (np.isnan(new) & np.isnan(old)))).any(axis=1)
        if changed.any():
            self._obs[first:, :m] = new
            self._invalidate(first + int(np.argmax(changed)))

    def _invalidate(self, slot: int) -> None:
        if slot < self._n:
            slot = self._checkpoint(slot)
            self._filt = {i: x for i, x in self._filt.items() if i < slot}
            self._pred = {i: x for i, x in self._pred.items() if i <= slot}
            self._n = slot

    def _checkpoint(self, slot: int) -> int:
        """The latest slot at or before ``slot`` whose predicted state is kept."""
        while slot not in self._pred:
            slot -= 1
        return slot

    # -- estimates --------------------------------------------------------------------
    def predict(self, hours: float) -> Estimate:
        """Filtered target at the last window slot starting at or before ``hours`` [h].

        Before the first window slot no reading may be used yet: the stationary prior of
        the first slot is returned. Without any reference reading yet (today's or a
        carry-over) there is no estimate (NaN): the filter's prior is the typical day, not a
        measurement, and the daemon never invents data.
        """
        if not any(self._times.values()):
            return Estimate(math.nan, math.nan)
        if self._pending:
            self._flush()
        slot = self.model.hours_.slot_index_of(hours) - self._first
        if slot < 0:
            return self._estimate(0, *self._pred[0])  # slot 0 is a checkpoint
        slot = min(slot, len(self._starts) - 1)
        while self._n <= slot:
            self._step()
        a, p = self._filtered(slot)
        e = self._estimate(slot, a, p)
        if self.model.live_refs:
            e = Estimate(e.value + self._within_slot(slot, hours), e.std)
        return e

    def _within_slot(self, slot: int, hours: float) -> float:
        """Mean change of the references since the slot start (the target moves with them,
        TRIV's assumption): latest reading at or before ``hours`` minus the slot's held value."""
        d = []
        for s, j in self._col.items():
            times, held = self._times[s], self._raw[slot, j]
            if not times or not math.isfinite(held):
                continue
            i = bisect.bisect_right(times, hours) - 1  # times: a sorted list, no array
            if i >= 0:
                d.append(self._values[s][i] - held)
        return list_mean(d)

    def _estimate(self, slot: int, a: np.ndarray, p: np.ndarray) -> Estimate:
        z, w = self._z, self._weights
        mean = float(z @ a + self._wd + w @ self.model.profile_[slot]) + self.shift
        var = float(z @ p @ z + self._whw)
        return Estimate(mean, math.sqrt(max(var, 0.0)))

    def _filtered(self, slot: int) -> _State:
        """Slot ``slot``'s filtered state (filtered already), from the cache or filtered
        again from the checkpoint before it."""
        kept = self._filt.get(slot)
        if kept is not None:
            return kept
        i = self._checkpoint(slot)
        state = self._pred[i]
        while True:
            filt, pred = self._filter(i, state)
            if i == slot:
                return filt
            i, state = i + 1, pred

    def _step(self) -> None:
        """Filter the next slot and predict the one after; thin the cache (KEEP, EVERY)."""
        i = self._n
        self._filt[i], self._pred[i + 1] = self._filter(i, self._pred[i])
        self._n = i + 1
        old = i + 1 - self.KEEP
        if old >= 0:  # (a slot filtered again after an invalidation may be gone already)
            self._filt.pop(old, None)
            if old % self.EVERY:
                self._pred.pop(old, None)

    def _filter(self, i: int, state: _State) -> tuple[_State, _State]:
        """Slot i's filtered state from its predicted ``state``, and the predicted state of
        slot i + 1 (statsmodels' conventions)."""
        ss = self._ss
        a, p = state
        y = self._obs[i]
        seen = np.isfinite(y)
        if seen.any():
            z, h, d = ss.observed(seen)
            f = z @ p @ z.T + h
            v = y[seen] - z @ a - d
            pz = p @ z.T
            if f.shape[0] == 1:  # one reference (the usual twin): no LAPACK call
                if f[0, 0] == 0.0:
                    raise NumericalError("VARMA filter: singular innovation covariance")
                # bit for bit what LAPACK's solve gives (OpenBLAS multiplies by 1/f too)
                gain = pz * (1.0 / f[0, 0])
            else:
                try:
                    gain = np.linalg.solve(f, pz.T).T  # P Zᵀ F⁻¹ [m, n_seen]
                except np.linalg.LinAlgError as exc:
                    raise NumericalError(
                        f"VARMA filter: singular innovation covariance ({exc})"
                    ) from None
            a = a + gain @ v
            p = p - gain @ pz.T
            p = 0.5 * (p + p.T)
        if not (np.isfinite(a).all() and np.isfinite(p).all()):
            raise NumericalError(f"VARMA filter: non-finite state at slot {i}")
        a_next = ss.transition @ a + ss.state_intercept(self._tau0 + i + 1)
        p_next = ss.transition @ p @ ss.transition.T + self._rqr
        return (a, p), (a_next, p_next)

    # -- introspection (tests, monitoring) ----------------------------------------------
    @property
    def n_filtered(self) -> int:
        """How many window slots (from the first) have been filtered."""
        self._flush()
        return self._n

    @property
    def n_kept(self) -> int:
        """How many filter states (filtered or predicted) the cache holds."""
        return len(self._filt) + len(self._pred)

    def observations(self) -> np.ndarray:
        """The deseasonalized observation vectors of the window slots: [S, k] (copy)."""
        self._flush()
        return self._obs.copy()
