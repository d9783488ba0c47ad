"""statsmodels' VARMAX, for fitting VARMA and reading its matrices off fitted parameters.

Imported only where a VARMA is fitted or an artifact without stored matrices is loaded:
statsmodels adds ~50 MB to a process, and the daemon's live path needs only the matrices
(models/varma.py ``_StateSpace``), which artifacts store.
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np
from statsmodels.tsa.statespace.tools import prepare_trend_spec, solve_discrete_lyapunov
from statsmodels.tsa.statespace.varmax import VARMAX

__all__ = ["VARMAX", "BoundedVARMAX", "FitTimeout", "prepare_trend_spec", "quiet_varmax",
           "solve_discrete_lyapunov"]


class FitTimeout(Exception):
    """The VARMAX optimizer ran past ``max_seconds``."""


class BoundedVARMAX(VARMAX):
    """VARMAX with a wall-clock deadline and a well-scaled trend for the optimizer.

    The trend regressor τ runs up to a few hundred slots, so the likelihood's gradient with
    respect to the drift is hundreds of times that of the intercept and L-BFGS stalls in its
    first line search. The optimizer therefore sees each degree-d trend parameter multiplied
    by ``nobs**d`` (a change of the whole trend over the training span); the constrained
    parameters, which the results report and the artifact stores, are the ordinary ones.
    """

    deadline: float | None = None

    def _trend_scale(self) -> np.ndarray:
        """Optimizer scale of each parameter: [k_params] (1 except for trend terms)."""
        scale = np.ones(self.k_params)
        degrees = np.flatnonzero(self.polynomial_trend)
        per_series = np.asarray(float(self.nobs)) ** degrees
        scale[self._params_trend] = np.tile(per_series, self.k_endog)
        return scale

    def transform_params(self, unconstrained: np.ndarray) -> np.ndarray:
        constrained = super().transform_params(unconstrained)
        sl = self._params_trend
        constrained[sl] = np.asarray(unconstrained)[sl] / self._trend_scale()[sl]
        return constrained

    def untransform_params(self, constrained: np.ndarray) -> np.ndarray:
        unconstrained = super().untransform_params(constrained)
        sl = self._params_trend
        unconstrained[sl] = np.asarray(constrained)[sl] * self._trend_scale()[sl]
        return unconstrained

    def loglike(self, params: np.ndarray, *args: Any, **kwargs: Any) -> float:
        # Every objective and finite-difference gradient evaluation passes here, so this is
        # where a fit that runs out of time can be stopped.
        if self.deadline is not None and time.monotonic() > self.deadline:
            raise FitTimeout
        return super().loglike(params, *args, **kwargs)


def quiet_varmax(endog: np.ndarray, order: tuple[int, int], trend: str, **kw: Any) -> VARMAX:
    """A plain VARMAX without the identification warning every VARMA(p, q>0) issues."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return VARMAX(endog, order=order, trend=trend, **kw)
