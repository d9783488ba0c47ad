"""Scores of estimates against true readings: the one implementation behind the daemon's
monitor, ``evaluate`` and the results report (DESIGN.md §7).

Accuracy (thesis 6.5):
- NRMSE (6.10) = RMSE / |mean truth| × 100;
- ΔT_max (6.14) = max |error| / |mean truth| × 100;
- Pearson r of estimate and truth.

Calibration of a Gaussian predictive N(μ, σ²) per estimate:
- coverage of the ±1σ and ±2σ bands [%] (ideal 68.3 / 95.4);
- mean σ, and the root-mean-square σ to set against the RMSE (for a calibrated σ the mean
  squared error is the mean σ², so RMS σ / RMSE ≈ 1; the mean σ is smaller when σ varies);
- CRPS (a proper scoring rule, in the quantity's unit; lower is better):
  σ·[z(2Φ(z) − 1) + 2φ(z) − 1/√π], z = (y − μ)/σ. An estimate without a σ (NaN or 0, e.g.
  a raw reference) is a point forecast: its CRPS is |y − μ| (the σ → 0 limit) and it takes no
  part in coverage or mean and RMS σ.

Every score is NaN when it is undefined (no rows, zero mean truth, constant series, no σ).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import ndtr

_INV_SQRT_PI = 1.0 / np.sqrt(np.pi)
_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)
NAN = float("nan")
#: The band the published estimate's ±2σ coverage should land in [%] (a calibrated Gaussian
#: band holds 95.4 %): what the results report and the commissioning page judge σ by.
COVER2_RANGE = (90.0, 98.0)


def _arrays(truth: ArrayLike, est: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(truth, float)
    m = np.asarray(est, float)
    if y.shape != m.shape:
        raise ValueError(f"truth {y.shape} and estimate {m.shape} differ in shape")
    return y, m


def _mean_scale(y: np.ndarray) -> float:
    """|mean truth|, NaN when there is none or it is zero (NRMSE undefined)."""
    if y.size == 0:
        return NAN
    mean = abs(float(np.mean(y)))
    return mean if mean > 0 else NAN


def rmse(truth: ArrayLike, est: ArrayLike) -> float:
    y, m = _arrays(truth, est)
    return float(np.sqrt(np.mean((m - y) ** 2))) if y.size else NAN


def nrmse_pct(truth: ArrayLike, est: ArrayLike) -> float:
    """NRMSE (thesis 6.10): RMSE / |mean truth| × 100."""
    y, m = _arrays(truth, est)
    return 100.0 * rmse(y, m) / _mean_scale(y)


def dmax_pct(truth: ArrayLike, est: ArrayLike) -> float:
    """ΔT_max (thesis 6.14): largest absolute error / |mean truth| × 100."""
    y, m = _arrays(truth, est)
    if y.size == 0:
        return NAN
    return 100.0 * float(np.max(np.abs(m - y))) / _mean_scale(y)


def pearson_r(a: ArrayLike, b: ArrayLike) -> float:
    """Pearson correlation; NaN with fewer than 3 points or a constant series."""
    x, y = _arrays(a, b)
    # np.ptp, not np.std: a constant series of 22.3 has a std of 4e-15, not 0
    if x.size < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return NAN
    return float(np.corrcoef(x, y)[0, 1])


def _has_std(std: np.ndarray) -> np.ndarray:
    return np.isfinite(std) & (std > 0)


def gaussian_crps(truth: ArrayLike, mean: ArrayLike, std: ArrayLike) -> np.ndarray:
    """CRPS of N(mean, std²) at each truth: [N]. Rows without a σ (NaN/0) → |truth − mean|."""
    y, mu = _arrays(truth, mean)
    s = np.broadcast_to(np.asarray(std, float), y.shape)
    out = np.abs(y - mu)
    ok = _has_std(s)
    if np.any(ok):
        z = (y[ok] - mu[ok]) / s[ok]
        pdf = _INV_SQRT_2PI * np.exp(-0.5 * z * z)
        out[ok] = s[ok] * (z * (2.0 * ndtr(z) - 1.0) + 2.0 * pdf - _INV_SQRT_PI)
    return out


def coverage_pct(truth: ArrayLike, mean: ArrayLike, std: ArrayLike, k: float) -> float:
    """Share of truths inside mean ± k·std [%], over the rows that have a σ (NaN if none)."""
    y, mu = _arrays(truth, mean)
    s = np.broadcast_to(np.asarray(std, float), y.shape)
    ok = _has_std(s)
    if not np.any(ok):
        return NAN
    return 100.0 * float(np.mean(np.abs(y[ok] - mu[ok]) <= k * s[ok]))


def mean_std(std: ArrayLike) -> float:
    """Mean σ over the rows that have one (NaN if none)."""
    s = np.asarray(std, float)
    ok = _has_std(s)
    return float(np.mean(s[ok])) if np.any(ok) else NAN


def rms_std(std: ArrayLike) -> float:
    """Root-mean-square σ over the rows that have one (NaN if none)."""
    s = np.asarray(std, float)
    ok = _has_std(s)
    return float(np.sqrt(np.mean(s[ok] ** 2))) if np.any(ok) else NAN


@dataclass(frozen=True)
class Scores:
    """All scores of one series of estimates (a day of one model, say)."""

    n: int
    nrmse_pct: float
    dmax_pct: float
    pearson_r: float
    cover1_pct: float
    cover2_pct: float
    crps: float
    mean_std: float
    rmse: float
    rms_std: float = NAN  # set against rmse: ≈ rmse when σ is the right size

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def score(truth: ArrayLike, est: ArrayLike, std: ArrayLike | None = None) -> Scores:
    """Accuracy and calibration of estimates ``est`` (± ``std``; None = no σ) vs ``truth``."""
    y, m = _arrays(truth, est)
    s = np.full(y.shape, NAN) if std is None else np.broadcast_to(np.asarray(std, float), y.shape)
    return Scores(
        n=int(y.size),
        nrmse_pct=nrmse_pct(y, m),
        dmax_pct=dmax_pct(y, m),
        pearson_r=pearson_r(m, y),
        cover1_pct=coverage_pct(y, m, s, 1.0),
        cover2_pct=coverage_pct(y, m, s, 2.0),
        crps=float(np.mean(gaussian_crps(y, m, s))) if y.size else NAN,
        mean_std=mean_std(s),
        rmse=rmse(y, m),
        rms_std=rms_std(s),
    )
