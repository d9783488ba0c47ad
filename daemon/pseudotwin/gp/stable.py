"""The numerically stable factorization of DESIGN.md §4 (thesis 3.2).

Two-sided scaling K → S = D⁻¹ K D⁻¹ with D = diag(k_ii^½) comes first; Tikhonov jitter is
added to S only if its Cholesky fails, escalating from ``1e-8 · mean diag(S)`` by ×10 per retry
up to a bound. Then log|K| = log|S| + 2 Σ ln D_ii and K⁻¹y = D⁻¹ L⁻ᵀ L⁻¹ D⁻¹ y.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError, cho_solve, cholesky, solve_triangular

from pseudotwin.errors import NumericalError

log = logging.getLogger(__name__)

JITTER_START = 1e-8
JITTER_TRIES = 7  # 1e-8 … 1e-2 of the (unit) scaled diagonal
COND_WARN = 1e5  # "approaching 1e6": warn a decade early


@dataclass(frozen=True)
class ScaledCholesky:
    """K = D (L Lᵀ - jitter·I) D, i.e. L is the Cholesky factor of D⁻¹ K D⁻¹ + jitter·I.

    L: [N, N] lower triangular; d: [N] the scaling D_ii = k_ii^½; jitter: absolute jitter
    added to the scaled matrix (0.0 when none was needed).
    """

    L: np.ndarray
    d: np.ndarray
    jitter: float

    def logdet(self) -> float:
        """log|K + D jitter D| = 2 Σ ln L_ii + 2 Σ ln D_ii."""
        return float(2.0 * np.sum(np.log(np.diag(self.L))) + 2.0 * np.sum(np.log(self.d)))

    def solve(self, y: np.ndarray) -> np.ndarray:
        """K⁻¹ y = D⁻¹ L⁻ᵀ L⁻¹ D⁻¹ y; y: [N] or [N, M]."""
        dd = self.d if y.ndim == 1 else self.d[:, None]
        return cho_solve((self.L, True), y / dd, check_finite=False) / dd

    def inverse(self) -> np.ndarray:
        """K⁻¹: [N, N]."""
        Li = solve_triangular(self.L, np.eye(len(self.d)), lower=True, check_finite=False)
        Si = Li.T @ Li
        return Si / np.outer(self.d, self.d)

    def condition_number(self) -> float:
        """2-norm condition number of the scaled, regularized matrix D⁻¹KD⁻¹ (+ jitter)."""
        s = np.linalg.svd(self.L, compute_uv=False)
        return float((s[0] / s[-1]) ** 2) if s[-1] > 0 else float("inf")


def scaled_cholesky(
    K: np.ndarray, *, max_tries: int = JITTER_TRIES, min_jitter: float = 0.0
) -> ScaledCholesky:
    """Factorize a symmetric positive (semi-)definite K after two-sided scaling.

    min_jitter: jitter to start from (a regularized refactorization starts above zero).
    Raises NumericalError when even the largest jitter does not give a factor.
    """
    diag = np.diag(K).copy()
    if not np.all(np.isfinite(K)) or np.any(diag <= 0):
        raise NumericalError("kernel matrix has a non-positive or non-finite diagonal")
    d = np.sqrt(diag)
    S = K / np.outer(d, d)
    base = JITTER_START * float(np.mean(np.diag(S)))
    jitter = float(min_jitter)
    for attempt in range(max_tries + 1):
        try:
            A = S if jitter == 0.0 else S + jitter * np.eye(len(d))
            L = cholesky(A, lower=True, check_finite=False)
            if not np.all(np.isfinite(L)):
                raise LinAlgError("non-finite factor")
            if jitter:
                log.debug("Cholesky needed jitter %.1e (attempt %d)", jitter, attempt)
            return ScaledCholesky(L, d, jitter)
        except LinAlgError:
            jitter = base if jitter == 0.0 else jitter * 10.0
    raise NumericalError(
        f"matrix of size {len(d)} not positive definite even with jitter {jitter / 10:.1e}"
    )
