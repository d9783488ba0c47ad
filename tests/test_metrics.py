"""The scores (live/metrics.py): NRMSE/ΔT_max by hand, CRPS against its definition,
coverage of a calibrated Gaussian."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm

from pseudotwin.live import metrics


def test_nrmse_dmax_and_r_on_a_hand_example() -> None:
    truth = [20.0, 22.0, 24.0, 22.0]  # mean 22
    est = [21.0, 21.0, 25.0, 23.0]  # errors +1, -1, +1, +1 → RMSE 1, max 1
    assert metrics.rmse(truth, est) == pytest.approx(1.0)
    assert metrics.nrmse_pct(truth, est) == pytest.approx(100.0 / 22.0)
    assert metrics.dmax_pct(truth, est) == pytest.approx(100.0 / 22.0)
    est2 = [20.0, 22.0, 24.0, 19.0]  # one error of -3: RMSE 1.5, max 3
    assert metrics.nrmse_pct(truth, est2) == pytest.approx(150.0 / 22.0)
    assert metrics.dmax_pct(truth, est2) == pytest.approx(300.0 / 22.0)
    # a negative mean is taken by its magnitude
    assert metrics.nrmse_pct([-t for t in truth], [-e for e in est]) == pytest.approx(100 / 22)
    assert metrics.pearson_r(truth, [2 * t + 1 for t in truth]) == pytest.approx(1.0)
    # undefined → NaN, never an exception
    assert np.isnan(metrics.nrmse_pct([1.0, -1.0], [0.0, 0.0]))  # zero mean truth
    assert np.isnan(metrics.pearson_r([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]))  # constant
    assert np.isnan(metrics.pearson_r([1.0, 2.0], [1.0, 2.0]))  # too few points
    assert np.isnan(metrics.nrmse_pct([], []))
    # constant series: no correlation (22.3's float std is 4e-15, and r came out 0.0)
    assert np.isnan(metrics.pearson_r(np.arange(7.0), [22.3] * 7))
    assert np.isnan(metrics.pearson_r([21.7] * 7, np.arange(7.0)))


def _crps_by_integral(y: float, mu: float, sigma: float) -> float:
    """∫ (F(x) − 1{x ≥ y})² dx, split at y (the step) for the quadrature."""
    f = lambda x: norm.cdf(x, mu, sigma) ** 2  # noqa: E731
    g = lambda x: (norm.cdf(x, mu, sigma) - 1.0) ** 2  # noqa: E731
    lo = quad(f, -np.inf, y, limit=200)[0]
    hi = quad(g, y, np.inf, limit=200)[0]
    return lo + hi


@pytest.mark.parametrize(("y", "mu", "sigma"), [
    (0.0, 0.0, 1.0), (21.3, 20.0, 0.5), (400.0, 450.0, 30.0), (1.0, 0.9, 2.0), (5.0, 0.0, 0.7),
])
def test_crps_equals_the_integral_of_its_definition(y: float, mu: float, sigma: float) -> None:
    got = metrics.gaussian_crps([y], [mu], [sigma])[0]
    assert got == pytest.approx(_crps_by_integral(y, mu, sigma), rel=1e-6, abs=1e-9)


def test_crps_without_sigma_is_the_absolute_error() -> None:
    y, mu = np.array([1.0, 2.0, 3.0]), np.array([1.5, 1.0, 3.0])
    got = metrics.gaussian_crps(y, mu, [np.nan, 0.0, np.nan])
    np.testing.assert_allclose(got, [0.5, 1.0, 0.0])
    # and a vanishing σ tends to it
    assert metrics.gaussian_crps([1.0], [1.5], [1e-9])[0] == pytest.approx(0.5, abs=1e-6)


def test_coverage_of_a_calibrated_gaussian() -> None:
    rng = np.random.default_rng(7)
    n = 20000
    mu = rng.normal(20.0, 3.0, n)
    sigma = rng.uniform(0.2, 2.0, n)
    y = mu + sigma * rng.standard_normal(n)
    s = metrics.score(y, mu, sigma)
    assert s.cover1_pct == pytest.approx(68.27, abs=1.5)
    assert s.cover2_pct == pytest.approx(95.45, abs=1.0)
    assert s.mean_std == pytest.approx(1.1, abs=0.02)
    # σ of the right size: its root mean square is the RMSE; its mean, σ varying, is less
    assert s.rms_std / s.rmse == pytest.approx(1.0, abs=0.02)
    assert s.mean_std / s.rmse < 0.92
    # a σ three times too wide covers (nearly) everything and scores worse
    wide = metrics.score(y, mu, 3 * sigma)
    assert wide.cover2_pct > 99.9
    assert wide.crps > s.crps
    # rows without a σ take no part in the coverage
    half = sigma.copy()
    half[: n // 2] = np.nan
    assert metrics.coverage_pct(y, mu, half, 2.0) == pytest.approx(95.45, abs=1.5)
    assert np.isnan(metrics.coverage_pct(y, mu, np.full(n, np.nan), 2.0))
    assert np.isnan(metrics.score(y, mu).cover2_pct)
