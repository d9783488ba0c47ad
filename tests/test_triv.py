"""TRIV offsets and live estimates on a constructed, exactly known case."""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pandas as pd
import pytest

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import DayReadings, normalize, split_days
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.models.base import TrainingSet
from pseudotwin.models.triv import TrivModel, TrivShrunkModel, TrivWeekModel


def training_set(offset_fn, days=3, refs=("r1", "r2"), weekend_extra=0.0,
                 day_levels=None) -> TrainingSet:
    """``days`` days from Monday 2020-01-06; the target is the first reference plus
    offset_fn(hours), plus ``weekend_extra`` on Saturdays and Sundays, plus day d's
    ``day_levels[d]``."""
    h = OperatingHours()
    rows = []
    rng = np.random.default_rng(0)
    for d in range(days):
        day = dt.date(2020, 1, 6) + dt.timedelta(days=d)
        extra = weekend_extra if day.weekday() >= 5 else 0.0
        extra += day_levels[d] if day_levels is not None else 0.0
        for k in range(46):
            hours = 7.5 + 0.25 * k
            ts = h.at(day, hours).isoformat()
            base = 20 + rng.normal()
            for i, r in enumerate(refs):
                rows.append((r, ts, base + i))
            rows.append(("tgt", ts, base + offset_fn(hours) + extra))
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


def test_shrunk_profile_keeps_a_shape_the_days_agree_on_at_different_levels() -> None:
    """A day's level cancels out of the profile's shape: days with one offset course at
    levels 0.6 °C apart agree on the shape, which is kept (the level's spread is σ's)."""
    rng = np.random.default_rng(7)
    ts = training_set(lambda h: 0.1 * (h - 8) + rng.normal(0.0, 0.02), days=5,
                      day_levels=[-0.3, 0.1, 0.3, -0.1, 0.0])
    m = TrivShrunkModel().fit(ts)
    assert all(lam > 0.95 for lam in m.shrink_), m.shrink_


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


def test_slot_means_weigh_each_value_by_how_long_it_held() -> None:
    """The slot's level is the time-weighted mean of the held signal: a COV value counts
    for as long as it held, 1-minute readings give the slot's mean, a reading at the slot's
    start held all slot gives itself, and a slot wholly before the first reading is NaN."""
    h = OperatingHours()  # slots of 15 min from 07:30
    day = DayReadings(dt.date(2020, 1, 6), {
        # COV: 20.0 from 08:00, 23.0 from 08:12 (the last 3 of the slot's 15 minutes)
        "cov": (np.array([8.0, 8.2]), np.array([20.0, 23.0])),
        # one reading a minute in 09:00–09:15: 0, 1, …, 14
        "minute": (9.0 + np.arange(15) / 60, np.arange(15, dtype=float)),
    })
    slots = h.window_slots() * h.slot_hours
    cov, minute = day.slot_means("cov", h), day.slot_means("minute", h)
    k8 = int(np.flatnonzero(np.isclose(slots, 8.0))[0])
    k9 = int(np.flatnonzero(np.isclose(slots, 9.0))[0])
    assert cov[k8] == pytest.approx((12 * 20.0 + 3 * 23.0) / 15)
    assert cov[k8 + 1] == pytest.approx(23.0)  # held on through the next slot
    assert np.isnan(cov[:k8]).all()  # no reading yet
    assert minute[k9] == pytest.approx(np.mean(np.arange(15)))
    # sample-and-hold at the slot's start would have taken the first minute only
    assert day.slot_values("minute", h)[k9] == 0.0


def test_triv_learns_the_offset_of_the_whole_slot_from_dense_readings() -> None:
    """Readings every minute whose offset wanders within each slot (±0.3 around 1.0): the
    offset learnt is the slot's mean 1.0, not the value of its first minute (1.3)."""
    h = OperatingHours()
    rows = []
    for d in range(3):
        day = dt.date(2020, 1, 6) + dt.timedelta(days=d)
        for minute in range(int(7.5 * 60), 19 * 60):
            ts = h.at(day, minute / 60).isoformat()
            wiggle = 0.3 * np.cos(2 * np.pi * (minute % 15) / 15)  # mean 0 over a slot
            rows += [("r", ts, 20.0 + d), ("tgt", ts, 21.0 + d + wiggle)]
    df = normalize(pd.DataFrame(rows, columns=["sensor", "ts", "value"]))
    ts = TrainingSet(TwinSpec(("r",), "tgt", Quantity.TEMPERATURE, h),
                     tuple(split_days(df, ["r", "tgt"], h)))
    m = TrivModel().fit(ts)
    np.testing.assert_allclose(m.offsets_[0], 1.0, atol=0.02)


SATURDAY, MONDAY = dt.date(2020, 2, 1), dt.date(2020, 2, 3)


def test_weekend_days_get_the_weekend_profile_and_weekdays_trivs() -> None:
    # Monday to Sunday: the target stands 1 K higher on Saturday and Sunday
    ts = training_set(lambda h: 0.1 * (h - 8), days=7, weekend_extra=1.0)
    m = TrivWeekModel().fit(ts)
    triv = TrivModel().fit(ts)
    assert m.type_days_ == {"weekday": 5, "weekend": 2}
    assert m.weekend_ is not None
    slot_h = ts.hours.window_slots() * ts.hours.slot_hours
    np.testing.assert_allclose(m.weekend_[0], 0.1 * (slot_h - 8) + 1.0, atol=1e-9)
    np.testing.assert_array_equal(m.offsets_, triv.offsets_)  # weekdays: all days' profile
    # the spread of its own training errors: none at weekends, 2/7 K on the five weekdays
    np.testing.assert_allclose(m.std_, np.sqrt(5 / 7) * 2 / 7, rtol=1e-9)
    assert np.all(m.std_ < triv.std_)
    for day, extra in ((SATURDAY, 1.0), (MONDAY, 2 / 7)):
        live, simple = m.start_day(day), triv.start_day(day)
        for x in (live, simple):
            x.observe("r1", 8.0, 21.0)
        assert live.predict(10.0).value == pytest.approx(21.0 + 0.2 + extra)
        if day == MONDAY:
            assert live.predict(10.0).value == simple.predict(10.0).value
    assert "weekend offset profile from 2 weekend days" in m.fit_summary()


def test_without_a_weekend_day_among_the_training_days_it_is_triv() -> None:
    ts = training_set(lambda h: 0.1 * (h - 8), days=5)  # Monday to Friday
    m = TrivWeekModel().fit(ts)
    assert m.weekend_ is None and m.type_days_ == {"weekday": 5, "weekend": 0}
    live, simple = m.start_day(SATURDAY), TrivModel().fit(ts).start_day(SATURDAY)
    for x in (live, simple):
        x.observe("r2", 8.0, 23.0)
    assert live.predict(11.0) == simple.predict(11.0)
    assert "0 weekend days among the training days" in m.fit_summary()


def test_one_weekend_day_is_not_enough_but_validations_refits_learn_from_it() -> None:
    """Live, a weekend profile needs two weekend days (validation could not test one learnt
    from a single day); validation's refits, holding one of two out, learn it from one."""
    ts = training_set(lambda h: 0.0, days=6, weekend_extra=1.0)  # Monday to Saturday
    live = TrivWeekModel().fit(ts)
    assert live.weekend_ is None and live.type_days_["weekend"] == 1
    assert "1 weekend day among the training days, 2 needed" in live.fit_summary()
    refit = TrivWeekModel(**TrivWeekModel.validation_options).fit(ts)
    assert refit.weekend_ is not None
    np.testing.assert_allclose(refit.weekend_[0], 1.0, atol=1e-9)


def test_week_round_trip_and_a_mismatched_weekend_profile_is_refused() -> None:
    ts = training_set(lambda h: np.sin(h), days=7, weekend_extra=-0.5)
    m = TrivWeekModel().fit(ts)
    again = TrivWeekModel.from_dict(json.loads(json.dumps(m.to_dict())), ts.spec)
    assert again.type_days_ == m.type_days_
    for day in (SATURDAY, MONDAY):
        a, b = m.start_day(day), again.start_day(day)
        for x in (a, b):
            x.observe("r1", 8.0, 20.0)
        assert a.predict(12.3) == b.predict(12.3)
    none = TrivWeekModel.from_dict(TrivWeekModel().fit(training_set(np.cos, days=2)).to_dict(),
                                   ts.spec)
    assert none.weekend_ is None
    bad = m.to_dict()
    bad["weekend"] = bad["weekend"][:1]  # one reference's profile for a twin of two
    with pytest.raises(ValueError, match="weekend offsets"):
        TrivWeekModel.from_dict(bad, ts.spec)
