"""Packed-row triangular solves (gp/trsv.py) against scipy's dense solve."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import solve_triangular

from pseudotwin.gp import trsv


@pytest.mark.parametrize("n", [1, 2, 7, 300])
def test_the_packed_solve_equals_the_dense_one(n: int) -> None:
    rng = np.random.default_rng(n)
    A = rng.normal(size=(n, n))
    L = np.linalg.cholesky(A @ A.T + n * np.eye(n))
    b = rng.normal(size=n)
    packed = np.concatenate([L[np.tril_indices(n)], np.full(5, np.nan)])  # spare capacity
    want = solve_triangular(L, b, lower=True)
    assert trsv._dtpsv is not None  # scipy's BLAS pointer was found: the fast path runs
    np.testing.assert_allclose(trsv.solve_packed_lower(packed, n, b), want, rtol=1e-12)
    # the fallback (no BLAS pointer, or an array BLAS cannot take) gives the same
    np.testing.assert_allclose(trsv.solve_packed_lower(packed.astype(np.float32), n, b),
                               want, rtol=1e-5)
    assert np.array_equal(b, b.copy())  # b untouched
