"""σ calibration (live/calibration.py) from held-out errors on the training days."""

from __future__ import annotations

import numpy as np

from pseudotwin.live.calibration import SigmaCalibration


def _held_out_errors(wild_days: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Five held-out days of errors, readings every 6 min 08:00–19:00, within-day noise
    N(0, 0.1²); on ``wild_days`` of them the noon hour's errors are N(0, 1²)."""
    rng = np.random.default_rng(7)
    hours = np.arange(8.0, 19.0, 0.1)
    day = np.repeat(np.arange(5), len(hours))
    at = np.tile(hours, 5)
    error = rng.normal(0.0, 0.1, len(at))
    noon = (at >= 12.0) & (at < 13.0)
    for d in range(wild_days):
        wild = noon & (day == d)
        error[wild] = rng.normal(0.0, 1.0, int(wild.sum()))
    return day, at, error, np.zeros(len(at))


def test_a_time_of_day_stands_out_in_sigma_only_when_two_training_days_show_it() -> None:
    """One training day's wild noon says a wild hour can come, not when: σ widens at every
    hour alike and noon does not stand out; a wild noon on two days is noon's own, and σ
    widens there."""
    calm = SigmaCalibration.fit(*_held_out_errors(0))
    once = SigmaCalibration.fit(*_held_out_errors(1))
    twice = SigmaCalibration.fit(*_held_out_errors(2))
    assert once.sigma(12.5, 0.0) < 1.2 * once.sigma(15.5, 0.0)
    assert once.sigma(15.5, 0.0) > 1.3 * calm.sigma(15.5, 0.0)
    assert twice.sigma(12.5, 0.0) > 2.5 * twice.sigma(15.5, 0.0)


def test_an_hour_seen_on_one_training_day_only_does_not_stand_out() -> None:
    """The 18-h bin exists on one held-out day alone, with wild errors there: that day
    cannot show it is the hour's own spread."""
    day, at, error, slope = _held_out_errors(0)
    lone = (day == 0) & (at >= 18.0)
    others = ~((day > 0) & (at >= 18.0))
    error = np.where(lone, 10.0 * error, error)
    c = SigmaCalibration.fit(day[others], at[others], error[others], slope[others])
    assert c.sigma(18.5, 0.0) < 1.2 * c.sigma(15.5, 0.0)
