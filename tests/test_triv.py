"""TRIV offsets and live estimates on a constructed, exactly known case."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pandas as pd
import pytest

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import normalize, split_days
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.models.base import TrainingSet
from pseudotwin.models.triv import TrivModel, TrivShrunkModel


def training_set(offset_fn, days=3, refs=("r1", "r2")) -> TrainingSet:
    h = OperatingHours()
    rows = []
    rng = np.random.default_rng(0)
    for d in range(days):
        day = dt.date(2020, 1, 6) + dt.timedelta(days=d)
        for k in range(46):
            hours = 7.5 + 0.25 * k
            ts = h.at(day, hours).isoformat()
            base = 20 + rng.normal()
            for i, r in enumerate(refs):
                rows.append((r, ts, base + i))
            rows.append(("tgt", ts, base + offset_fn(hours)))
    df = normalize(pd.DataFrame(rows, columns=["sensor", "ts", "value"]))
    ds = split_days(df, [*refs, "tgt"], h)
    return TrainingSet(TwinSpec(tuple(refs), "tgt", Quantity.TEMPERATURE, h), tuple(ds))


def test_offsets_are_mean_target_minus_reference_per_slot() -> None:
    ts = training_set(lambda h: 0.1 * (h - 8))
    m = TrivModel().fit(ts)
    assert m is not None and m.offsets_.shape == (2, 46)
    slot_h = ts.hours.window_slots() * ts.hours.slot_hours
    np.testing.assert_allclose(m.offsets_[0], 0.1 * (slot_h - 8), atol=1e-9)
    np.testing.assert_allclose(m.offsets_[1], 0.1 * (slot_h - 8) - 1.0, atol=1e-9)
    assert np.all(m.std_ < 1e-6 + 1e-9)  # the offset explains the target exactly


def test_live_estimate_is_mean_over_references_of_offset_plus_held_value() -> None:
    m = TrivModel().fit(training_set(lambda h: 0.5))
    day = m.start_day(dt.date(2020, 2, 1))
    assert np.isnan(day.predict(9.0).value)
    day.observe("r1", 8.0, 21.0)
    assert day.predict(9.0).value == pytest.approx(21.5)
    day.observe("r2", 8.5, 25.0)  # offset of r2 is 0.5 - 1 = -0.5
    assert day.predict(9.0).value == pytest.approx(((21.0 + 0.5) + (25.0 - 0.5)) / 2)
    day.observe("r1", 7.9, 0.0)  # a late reading of an earlier time never overwrites
    assert day.predict(9.0).value == pytest.approx(((21.0 + 0.5) + (25.0 - 0.5)) / 2)


def test_round_trip() -> None:
    ts = training_set(lambda h: np.sin(h))
    m = TrivModel().fit(ts)
    m2 = TrivModel.from_dict(m.to_dict(), ts.spec)
    a, b = m.start_day(dt.date(2020, 3, 1)), m2.start_day(dt.date(2020, 3, 1))
    for x in (a, b):
        x.observe("r1", 8.0, 20.0)
    assert a.predict(12.3) == b.predict(12.3)


def test_shrunk_profile_keeps_a_shape_the_days_agree_on() -> None:
    rng = np.random.default_rng(5)
    ts = training_set(lambda h: 0.1 * (h - 8) + rng.normal(0.0, 0.02), days=5)
    m = TrivShrunkModel().fit(ts)
    assert all(lam > 0.95 for lam in m.shrink_)
    np.testing.assert_allclose(m.offsets_, TrivModel().fit(ts).offsets_, atol=0.02)


def test_shrunk_profile_falls_back_to_the_mean_offset_when_the_days_disagree() -> None:
    rng = np.random.default_rng(6)
    # every day and slot its own offset: the mean profile's shape is sampling noise
    ts = training_set(lambda h: 0.5 + rng.normal(0.0, 0.4), days=5)
    m = TrivShrunkModel().fit(ts)
    raw = TrivModel().fit(ts)
    assert all(lam < 0.3 for lam in m.shrink_), m.shrink_
    flat = m.offsets_.std(axis=1)
    assert np.all(flat < 0.3 * raw.offsets_.std(axis=1))
    np.testing.assert_allclose(m.offsets_.mean(axis=1), raw.offsets_.mean(axis=1), atol=1e-9)
    assert "λ" in m.fit_summary()
    again = TrivShrunkModel.from_dict(m.to_dict(), ts.spec)
    assert again.shrink_ == m.shrink_
    np.testing.assert_array_equal(again.offsets_, m.offsets_)
