"""triv-smooth (issue Trust II, item 1: the offset profile, smoothing): TRIV whose offset
profile is smoothed across the day's slots, the span chosen on the training days.

The smoother on profiles whose answer is known, then real training on synthetic days (real
replays, real statsmodels LOWESS): where the slots' wiggles are one day's noise validation
keeps the widest span, where the offset really turns within the hour the narrowest.
"""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pandas as pd
import pytest

from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.errors import ArtifactError
from pseudotwin.live.artifact import Artifact
from pseudotwin.models.triv import SMOOTH_SPANS, TrivSmoothModel, smooth_profile

HOURS = OperatingHours(timezone="UTC")
SPEC = TwinSpec(("ref",), "desk", Quantity.TEMPERATURE, HOURS)
DAY0 = dt.date(2024, 3, 4)
GRID_H = 7.0 + np.arange(52) * 0.25  # 15-min readings 07:00–19:45


def test_a_straight_profile_comes_back_unchanged_and_noise_is_smoothed_out() -> None:
    x = np.arange(46, dtype=float)
    line = 0.3 + 0.02 * x
    np.testing.assert_allclose(smooth_profile(line, 4), line, atol=1e-12)
    np.testing.assert_allclose(smooth_profile(np.full(46, -0.4), 8), -0.4, atol=1e-12)
    truth = 0.5 * np.sin(x / 46 * np.pi)
    noisy = truth + np.random.default_rng(1).normal(0.0, 0.1, x.size)
    smoothed = smooth_profile(noisy, 4)
    assert np.sqrt(np.mean((smoothed - truth) ** 2)) < 0.6 * np.sqrt(np.mean((noisy - truth) ** 2))
    # a span that reaches no neighbouring slot: the profile as it is
    np.testing.assert_array_equal(smooth_profile(noisy, 0), noisy)


def test_the_span_reaches_exactly_the_slots_within_half_of_it() -> None:
    """60 min on 15-min slots is ±2 slots: a one-slot spike spreads to them, not beyond."""
    spike = np.zeros(41)
    spike[20] = 1.0
    out = smooth_profile(spike, 2)
    assert np.all(out[18:23] > 0) and out[20] == out.max()
    np.testing.assert_allclose(np.r_[out[:18], out[23:]], 0.0, atol=1e-12)


def test_a_span_covering_the_whole_window_is_one_straight_line() -> None:
    """A span over every slot (a short window, or 240 min on a 4-hour day): one line."""
    x = np.arange(5, dtype=float)
    np.testing.assert_allclose(smooth_profile(0.1 + 0.2 * x, 1), 0.1 + 0.2 * x, atol=1e-12)
    np.testing.assert_allclose(smooth_profile(0.1 + 0.2 * x, 8), 0.1 + 0.2 * x, atol=1e-12)


def _frame(days: int, seed: int, offset: np.ndarray, noise: float) -> pd.DataFrame:
    """A wandering reference and a desk at ``offset`` [per reading of GRID_H] from it, plus
    noise of its own in every reading (standard deviation ``noise``)."""
    rng = np.random.default_rng(seed)
    rows = []
    for d in range(days):
        ref = 21.0 + np.cumsum(rng.normal(0.0, 0.05, size=GRID_H.size))
        desk = ref + offset + rng.normal(0.0, noise, size=GRID_H.size)
        ts = pd.Timestamp(DAY0 + dt.timedelta(days=d), tz="UTC") + pd.to_timedelta(GRID_H,
                                                                                  unit="h")
        rows.append(pd.DataFrame({"sensor": "ref", "ts": ts, "value": ref}))
        rows.append(pd.DataFrame({"sensor": "desk", "ts": ts, "value": desk}))
    return pd.concat(rows, ignore_index=True).sort_values("ts", kind="stable")


def _trained_span(frame: pd.DataFrame, tmp_path) -> tuple[int, dict[str, object]]:
    art = train_twin(frame, SPEC, DAY0, 5, models=["triv", "triv-smooth"])
    tuned = art.validation["tuned"]["triv-smooth"]
    model = art.models["triv-smooth"]
    assert isinstance(model, TrivSmoothModel) and model.span == tuned["chosen"]
    assert set(tuned["nrmse_pct"]) == {str(s) for s in SMOOTH_SPANS}
    # the fit is the form validation scored, and the artifact keeps it
    assert art.validation["scores"]["triv-smooth"]["nrmse_pct"] == \
        tuned["nrmse_pct"][str(tuned["chosen"])]
    back = Artifact.load(art.save(tmp_path / "a.json"))
    reloaded = back.models["triv-smooth"]
    assert isinstance(reloaded, TrivSmoothModel) and reloaded.span == model.span
    np.testing.assert_array_equal(reloaded.offsets_, model.offsets_)
    assert back.validation["tuned"] == json.loads(json.dumps(art.validation["tuned"]))
    return model.span, tuned


def test_validation_keeps_the_widest_span_when_the_slots_wiggles_are_noise(tmp_path) -> None:
    span, tuned = _trained_span(_frame(6, 21, np.full(GRID_H.size, 0.5), noise=0.3),
                                tmp_path)
    assert span == SMOOTH_SPANS[0], tuned
    scores = tuned["nrmse_pct"]
    assert isinstance(scores, dict)
    # not a tie of spans that change nothing: the widest smooths the noise away
    assert scores[str(SMOOTH_SPANS[0])] < scores[str(SMOOTH_SPANS[-1])]


def test_validation_keeps_the_narrowest_span_when_the_offset_turns_within_the_hour(
    tmp_path,
) -> None:
    # every day the desk is 1 K warmer for half an hour from 12:00 (the sun on it, say)
    bump = np.where((GRID_H >= 12.0) & (GRID_H < 12.5), 1.0, 0.0)
    span, tuned = _trained_span(_frame(6, 22, 0.5 + bump, noise=0.02), tmp_path)
    assert span == SMOOTH_SPANS[-1], tuned


@pytest.mark.parametrize("span", [0, -60, 1.5, "120"])
def test_a_span_that_is_not_a_positive_number_of_minutes_is_refused(span: object) -> None:
    frame = _frame(6, 23, np.full(GRID_H.size, 0.5), noise=0.05)
    with pytest.raises(ValueError, match="span"):
        train_twin(frame, SPEC, DAY0, 5, models=["triv-smooth"],
                   options={"triv-smooth": {"span": span}}, validate=False)


@pytest.mark.parametrize("span", ["120", 60.5, -60, True, None])
def test_an_artifact_with_a_damaged_span_is_refused_at_load(span: object, tmp_path) -> None:
    art = train_twin(_frame(6, 23, np.full(GRID_H.size, 0.5), noise=0.05), SPEC, DAY0, 5,
                     models=["triv-smooth"], validate=False)
    d = json.loads(art.save(tmp_path / "a.json").read_text())
    d["models"]["triv-smooth"]["span"] = span
    with pytest.raises(ArtifactError, match="span"):
        Artifact.from_dict(d, "a.json")


def test_a_short_day_trains_whatever_the_span() -> None:
    """09:00–10:00: 240 min reaches past every slot of the window (and the init phase)."""
    hours = OperatingHours(timezone="UTC", day_start=9.0, day_end=10.0)
    spec = TwinSpec(("ref",), "desk", Quantity.TEMPERATURE, hours)
    frame = _frame(6, 24, np.full(GRID_H.size, 0.5), noise=0.05)
    art = train_twin(frame, spec, DAY0, 5, models=["triv", "triv-smooth"])
    assert "triv-smooth" in art.models
    assert all(np.isfinite(v) for v in art.validation["tuned"]["triv-smooth"]["nrmse_pct"].values())
