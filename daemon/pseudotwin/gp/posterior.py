"""Live conditioning: today's GP posterior, grown by one Cholesky row per reading.

The kernel matrix of today's observations is kept two-sided scaled, S = D⁻¹ K D⁻¹, as its
Cholesky factor L, stored as packed rows (row i at offset i(i+1)/2): half the memory of a
square buffer, and a new row goes at the end without moving the others. A new reading
appends one row to L (a triangular solve, O(n²)) instead of re-factorizing (O(n³)) or
rebuilding a GPy model; a revised value (the window's thinning) re-solves only the rows from
its own on. Observation order does not matter to a GP posterior, so out-of-order readings
are simply appended.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_triangular

from pseudotwin.errors import NumericalError
from pseudotwin.gp.kernels import LcmParams
from pseudotwin.gp.stable import JITTER_START, ScaledCholesky, scaled_cholesky
from pseudotwin.gp.trsv import solve_packed_lower

# Below this, the new pivot of the *unit-diagonal* scaled matrix has lost all digits to
# cancellation: the extension is treated as a loss of positive definiteness.
PIVOT_MIN = 1e-10


def _packed(n: int) -> int:
    """Entries of an n-row packed lower triangle; also where row n starts."""
    return n * (n + 1) // 2


class IncrementalPosterior:
    """Posterior of a multi-output GP given point observations of some outputs.

    Observations: times t [h], output indices o, residuals r (observation minus prior mean,
    normalized units). State: t, o, r, d: [n]; L: [n, n] lower; a = L⁻¹ D⁻¹ r: [n].
    """

    # Buffers of ``capacity`` rows; the first n are in use.
    _t: np.ndarray  # [cap] float: times [h]
    _o: np.ndarray  # [cap] int: output indices
    _r: np.ndarray  # [cap] float: residuals
    _d: np.ndarray  # [cap] float: two-sided scaling
    _a: np.ndarray  # [cap] float: L⁻¹ D⁻¹ r
    _P: np.ndarray  # [cap (cap + 1) / 2] rows of L, the factor of the scaled kernel matrix

    def __init__(self, params: LcmParams, capacity: int = 256) -> None:
        self.params = params
        # Per output, fixed by the artifact: asked for at every update and prediction.
        self._prior_var = [params.prior_var(o) for o in range(params.n_outputs)]
        self._noise = [float(v) for v in params.noise]
        self.n = 0
        self.jitter = 0.0
        self.refactorizations = 0
        cap = max(8, capacity)
        self._t, self._o, self._r, self._d, self._a = self._vectors(cap)
        self._P = np.zeros(_packed(cap))

    def _vectors(self, cap: int) -> tuple[np.ndarray, ...]:
        """Fresh (t, o, r, d, a) buffers of ``cap`` rows."""
        return (np.zeros(cap), np.zeros(cap, dtype=int), np.zeros(cap), np.zeros(cap),
                np.zeros(cap))

    def _alloc(self, cap: int) -> None:
        """Grow the buffers to ``cap`` rows, keeping the first n."""
        n = self.n
        t, o, r, d, a = self._vectors(cap)
        for new, old in ((t, self._t), (o, self._o), (r, self._r), (d, self._d), (a, self._a)):
            new[:n] = old[:n]
        P = np.zeros(_packed(cap))
        P[: _packed(n)] = self._P[: _packed(n)]
        self._t, self._o, self._r, self._d, self._a, self._P = t, o, r, d, a, P

    def _row(self, i: int) -> np.ndarray:
        """L[i, :i] (a view)."""
        start = _packed(i)
        return self._P[start: start + i]

    def _diag(self, i: int) -> float:
        return float(self._P[_packed(i) + i])

    # -- views ------------------------------------------------------------------------
    @property
    def t(self) -> np.ndarray:
        return self._t[: self.n]

    @property
    def o(self) -> np.ndarray:
        return self._o[: self.n]

    @property
    def r(self) -> np.ndarray:
        return self._r[: self.n]

    def _obs_var(self, o: int) -> float:
        return self._prior_var[o] + self._noise[o]

    # -- updates ----------------------------------------------------------------------
    def add(self, t: float, o: int, r: float) -> None:
        """Condition on one more observation (t [h], output o, residual r)."""
        if not (math.isfinite(r) and math.isfinite(t)):  # scalars: math, not numpy's overhead
            raise NumericalError(f"non-finite observation t={t} r={r}")
        n = self.n
        if n == len(self._t):
            self._alloc(2 * n)
        d_new = math.sqrt(self._obs_var(o))
        self._t[n], self._o[n], self._r[n], self._d[n] = t, o, r, d_new
        if n == 0:
            pivot2 = 1.0 + self.jitter
            row = np.zeros(0)
        else:
            k = self.params.k_vec(t, o, self._t[:n], self._o[:n])
            s = k / (self._d[:n] * d_new)
            row = solve_packed_lower(self._P, n, s)
            pivot2 = 1.0 + self.jitter - float(row @ row)
        self.n = n + 1
        # A non-finite entry of row makes row @ row, hence pivot2, NaN or -inf: the one
        # comparison catches it without a pass over the row.
        if not (pivot2 > PIVOT_MIN):
            try:
                self._refactorize()
            except NumericalError:
                self.n = n  # leave the posterior as it was: without this observation
                raise
            return
        piv = math.sqrt(pivot2)
        start = _packed(n)
        self._P[start: start + n] = row
        self._P[start + n] = piv
        self._a[n] = (r / d_new - float(row @ self._a[:n])) / piv

    def index_of(self, t: float, o: int) -> int:
        """The newest observation of output ``o`` at time ``t`` [h]; searched from the end,
        where the window's thinning finds the point it revises."""
        for i in range(self.n - 1, -1, -1):
            if self._o[i] == o and self._t[i] == t:
                return i
        raise KeyError(f"no observation of output {o} at t={t}")

    def revise(self, i: int, r: float) -> None:
        """Replace observation ``i``'s residual by ``r``.

        L depends on the times only and stays; a = L⁻¹ D⁻¹ r changes from row i on, one
        forward-substitution step per row: O((n − i)·n), O(n) for the newest rows.
        """
        if not 0 <= i < self.n:
            raise IndexError(f"no observation {i} of {self.n}")
        if not np.isfinite(r):
            raise NumericalError(f"non-finite residual r={r}")
        self._r[i] = r
        a = self._a
        for j in range(i, self.n):
            a[j] = (self._r[j] / self._d[j] - float(self._row(j) @ a[:j])) / self._diag(j)

    def _refactorize(self) -> None:
        """Full, regularized refactorization (the fallback of a failed extension)."""
        n = self.n
        K = self.params.K(self.t, self.o, self.t, self.o)
        K[np.diag_indices(n)] += self.params.noise[self.o]
        # Regularized from the start: the extension failed because the matrix is (nearly)
        # singular, so an unjittered factor would only succeed by rounding luck.
        f: ScaledCholesky = scaled_cholesky(K, min_jitter=max(self.jitter, JITTER_START))
        self.refactorizations += 1
        self.jitter = f.jitter
        self._P[: _packed(n)] = f.L[np.tril_indices(n)]  # row-major: packed rows
        self._d[:n] = f.d
        self._a[:n] = solve_triangular(f.L, self.r / f.d, lower=True, check_finite=False)

    def set_residuals(self, r: np.ndarray) -> None:
        """Replace all residuals (prior mean moved); one triangular solve, L unchanged."""
        r = np.asarray(r, float)
        if r.shape != (self.n,):
            raise ValueError("one residual per observation expected")
        self._r[: self.n] = r
        if self.n:
            self._a[: self.n] = solve_packed_lower(self._P, self.n, r / self._d[: self.n])

    # -- prediction -------------------------------------------------------------------
    def predict(self, t: float, o: int, include_noise: bool = True) -> tuple[float, float]:
        """Posterior mean residual and variance of output o at time t [h]."""
        var0 = self._prior_var[o] + (self._noise[o] if include_noise else 0.0)
        if self.n == 0:
            return 0.0, var0
        n = self.n
        k = self.params.k_vec(t, o, self._t[:n], self._o[:n])
        v = solve_packed_lower(self._P, n, k / self._d[:n])
        mean = float(v @ self._a[:n])
        var = var0 - float(v @ v)
        if not (math.isfinite(mean) and math.isfinite(var)):
            raise NumericalError("posterior is not finite")
        return mean, max(var, 0.0)
