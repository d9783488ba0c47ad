"""Live conditioning: today's GP posterior, grown by one Cholesky row per observation.

The kernel matrix of today's observations is kept two-sided scaled, S = D⁻¹ K D⁻¹, as its
Cholesky factor L, stored as packed rows (row i at offset i(i+1)/2): half the memory of a
square buffer, and a new row goes at the end without moving the others. A new observation
appends one row to L (a triangular solve, O(n²)) instead of re-factorizing (O(n³)) or
rebuilding a GPy model. Observation order does not matter to a GP posterior, so
out-of-order readings are simply appended.

Lazy: ``add`` only records an observation; the pending ones get their rows when a
prediction is asked (:meth:`IncrementalPosterior.flush`), and a = L⁻¹ D⁻¹ r is solved anew
(one O(n²) solve) at a prediction after any change. So the state a prediction reads is a
function of the observations alone (their times, outputs, residuals and order), not of
when predictions were asked in between: a baseline asked only on the publish grid gives,
to the last bit, the numbers it gives when asked at every reading, and the daemon,
``evaluate`` and ``backfill`` agree however their predictions fall. A revised residual
(the window's thinning) costs O(1); a point that moves (merged GP points, gp/points.py)
re-solves the rows from its own on at the next prediction, a few when it is among the
newest.
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
    normalized units). State: t, o, r, d: [n]; L: [m, m] lower, where the first m ≤ n
    observations have their rows and the rest are pending (lazy); a = L⁻¹ D⁻¹ r: [n], valid
    only while ``_a_fresh``.
    """

    # Buffers of ``capacity`` rows; the first n are in use. They start small and grow by a
    # quarter when full, the packed factor by a quarter of its size when a row does not fit
    # (_reserve_rows): it grows with the square of its rows (doubling would hold up to 4×
    # the rows' memory), and a buffer is resident in full once the allocator hands out
    # reused memory, every day of every twin.
    _t: np.ndarray  # [cap] float: times [h]
    _o: np.ndarray  # [cap] int: output indices
    _r: np.ndarray  # [cap] float: residuals
    _d: np.ndarray  # [cap] float: two-sided scaling
    _a: np.ndarray  # [cap] float: L⁻¹ D⁻¹ r
    _P: np.ndarray  # [≥ m (m + 1) / 2] rows of L, the factor of the scaled kernel matrix

    def __init__(self, params: LcmParams, capacity: int = 32) -> None:
        self.params = params
        # Per output, fixed by the artifact: asked for at every update and prediction.
        self._prior_var = [params.prior_var(o) for o in range(params.n_outputs)]
        self._noise = [float(v) for v in params.noise]
        self.n = 0  # observations, pending ones included
        self._m = 0  # observations with their row of L
        self._a_fresh = False  # a holds L⁻¹ D⁻¹ r of all n observations
        self.jitter = 0.0
        self.refactorizations = 0
        cap = max(8, capacity)
        self._t, self._o, self._r, self._d, self._a = self._vectors(cap)
        self._P = np.empty(_packed(cap))  # rows are written before they are read

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
        self._t, self._o, self._r, self._d, self._a = t, o, r, d, a

    def _reserve_rows(self, rows: int) -> None:
        """Room in the packed factor for ``rows`` rows, keeping the m rows it has. It grows by
        a quarter of its *size*, not with the vectors' rows: grown by rows, its
        quadratic size carried up to 56 % of spare room by the evening (two
        posteriors per twin)."""
        need = _packed(rows)
        if need <= len(self._P):
            return
        P = np.empty(max(need, len(self._P) + len(self._P) // 4))
        P[: _packed(self._m)] = self._P[: _packed(self._m)]
        self._P = P

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
        """Record one more observation (t [h], output o, residual r); it is conditioned on
        at the next prediction or :meth:`flush`."""
        if not (math.isfinite(r) and math.isfinite(t)):  # scalars: math, not numpy's overhead
            raise NumericalError(f"non-finite observation t={t} r={r}")
        n = self.n
        if n == len(self._t):
            self._alloc(n + max(32, n // 4))
        self._t[n], self._o[n], self._r[n] = t, o, r
        self._d[n] = math.sqrt(self._obs_var(o))
        self.n = n + 1

    def flush(self) -> None:
        """Give the pending observations their rows of L, one after the other.

        A loss of positive definiteness falls back to a regularized refactorization of all
        observations; if that fails too, NumericalError, and the posterior is left without
        the pending observations.
        """
        m, n = self._m, self.n
        if n == m:
            return
        self._a_fresh = False
        try:
            for i in range(m, n):
                if not self._append_row(i):
                    self._refactorize()
                    break
                self._m = i + 1
        except NumericalError:
            self.n = self._m = m
            raise
        self._m = n

    def _append_row(self, i: int) -> bool:
        """Row i of L for observation i (rows 0 … i−1 in place); False: the matrix is not
        positive definite any more."""
        self._reserve_rows(i + 1)
        if i == 0:
            pivot2 = 1.0 + self.jitter
            row = np.zeros(0)
        else:
            k = self.params.k_vec(float(self._t[i]), int(self._o[i]), self._t[:i], self._o[:i])
            row = solve_packed_lower(self._P, i, k / (self._d[:i] * self._d[i]))
            pivot2 = 1.0 + self.jitter - float(row @ row)
        # A non-finite entry of row makes row @ row, hence pivot2, NaN or -inf: the one
        # comparison catches it without a pass over the row.
        if not (pivot2 > PIVOT_MIN):
            return False
        start = _packed(i)
        self._P[start: start + i] = row
        self._P[start + i] = math.sqrt(pivot2)
        return True

    def index_of(self, t: float, o: int) -> int:
        """The newest observation of output ``o`` at time ``t`` [h]; searched from the end,
        where the window's thinning finds the point it revises."""
        for i in range(self.n - 1, -1, -1):
            if self._o[i] == o and self._t[i] == t:
                return i
        raise KeyError(f"no observation of output {o} at t={t}")

    def revise(self, i: int, r: float) -> None:
        """Replace observation ``i``'s residual by ``r`` (L depends on the times only)."""
        if not 0 <= i < self.n:
            raise IndexError(f"no observation {i} of {self.n}")
        # A scalar: math, not numpy's overhead (every reading of a chatty sensor revises).
        if not math.isfinite(r):
            raise NumericalError(f"non-finite residual r={r}")
        self._r[i] = r
        self._a_fresh = False

    def move(self, i: int, t: float, r: float) -> None:
        """Give observation ``i`` the time ``t`` [h] and residual ``r`` (its output stays): a
        GP point that merges several readings (gp/points.py) moves with each of them.

        Same time: :meth:`revise`. Otherwise the rows from i on no longer hold: they become
        pending again and get their rows anew at the next prediction, O(n²) each, a few
        when ``i`` is among the newest (the usual case).
        """
        if not 0 <= i < self.n:
            raise IndexError(f"no observation {i} of {self.n}")
        if t == self._t[i]:
            self.revise(i, r)
            return
        if not (math.isfinite(r) and math.isfinite(t)):
            raise NumericalError(f"non-finite observation t={t} r={r}")
        self._m = min(self._m, i)
        self._t[i], self._r[i] = t, r
        self._a_fresh = False

    def _refactorize(self) -> None:
        """Full, regularized refactorization of all n observations (the fallback of a failed
        extension)."""
        n = self.n
        K = self.params.K(self.t, self.o, self.t, self.o)
        K[np.diag_indices(n)] += self.params.noise[self.o]
        # Regularized from the start: the extension failed because the matrix is (nearly)
        # singular, so an unjittered factor would only succeed by rounding luck.
        f: ScaledCholesky = scaled_cholesky(K, min_jitter=max(self.jitter, JITTER_START))
        self.refactorizations += 1
        self.jitter = f.jitter
        self._reserve_rows(n)  # keeps the m old rows: flush restores them should this fail
        self._P[: _packed(n)] = f.L[np.tril_indices(n)]  # row-major: packed rows
        self._d[:n] = f.d
        self._a[:n] = solve_triangular(f.L, self.r / f.d, lower=True, check_finite=False)
        self._a_fresh = True

    def set_residuals(self, r: np.ndarray) -> None:
        """Replace all residuals (prior mean moved); L unchanged."""
        r = np.asarray(r, float)
        if r.shape != (self.n,):
            raise ValueError("one residual per observation expected")
        self._r[: self.n] = r
        self._a_fresh = False

    # -- prediction -------------------------------------------------------------------
    def predict(self, t: float, o: int, include_noise: bool = True) -> tuple[float, float]:
        """Posterior mean residual and variance of output o at time t [h]."""
        var0 = self._prior_var[o] + (self._noise[o] if include_noise else 0.0)
        if self.n == 0:
            return 0.0, var0
        self.flush()
        n = self.n
        if not self._a_fresh:
            self._a[:n] = solve_packed_lower(self._P, n, self._r[:n] / self._d[:n])
            self._a_fresh = True
        k = self.params.k_vec(t, o, self._t[:n], self._o[:n])
        v = solve_packed_lower(self._P, n, k / self._d[:n])
        mean = float(v @ self._a[:n])
        var = var0 - float(v @ v)
        if not (math.isfinite(mean) and math.isfinite(var)):
            raise NumericalError("posterior is not finite")
        return mean, max(var, 0.0)
