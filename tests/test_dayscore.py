"""The demo's day score (live/dayscore.py): the same estimates give the same numbers in any
arrival order, with duplicate deliveries and with two estimates sharing an instant."""

from __future__ import annotations

import datetime as dt
import random

import numpy as np
import pytest

from pseudotwin.live import metrics
from pseudotwin.live.dayscore import Published, answered, day_scores, one_per_instant

T0 = dt.datetime(2012, 3, 20, 7, 0, tzinfo=dt.UTC)


def at(minutes: float) -> dt.datetime:
    return T0 + dt.timedelta(minutes=minutes)


def payload(ts: dt.datetime, value: float, ref_ts: dt.datetime) -> dict[str, object]:
    return {"ts": ts.isoformat(), "value": value, "std": 0.2, "unit": "°C", "model": "triv",
            "quality": "ok", "refs": {"dining/temp": ref_ts.isoformat()}}


def day() -> tuple[list[Published], dict[dt.datetime, float], list[tuple[dt.datetime, float]]]:
    rng = np.random.default_rng(7)
    truth = {at(15 * k): 21.0 + 0.1 * k + float(rng.normal(0, 0.1)) for k in range(40)}
    refs = [(t, v - 0.4 + float(rng.normal(0, 0.05))) for t, v in truth.items()]
    estimates = []
    for k, t in enumerate(truth):
        # the reading's estimate, which saw the reference of this instant …
        estimates.append(Published.from_payload(
            "estimate", payload(t, truth[t] + float(rng.normal(0, 0.15)), t)))
        # … a grid estimate of the same instant made before that reading arrived …
        if k % 4 == 0:
            estimates.append(Published.from_payload(
                "estimate", payload(t, truth[t] + 3.0, at(15 * k - 15))))
        # … and one the worker reached late, after the next reading
        if k % 4 == 1:
            estimates.append(Published.from_payload(
                "estimate", payload(t, truth[t] - 3.0, at(15 * k + 15))))
        estimates.append(Published.from_payload(
            "triv", payload(t, truth[t] + float(rng.normal(0, 0.3)), t)))
    return estimates, truth, refs


def test_scores_do_not_depend_on_arrival_order_or_duplicates() -> None:
    estimates, truth, refs = day()
    expected = day_scores(estimates, truth, {"dining/temp": refs})
    rnd = random.Random(3)
    for _ in range(20):
        shuffled = estimates + rnd.sample(estimates, 25)  # redeliveries
        rnd.shuffle(shuffled)
        r = refs + rnd.sample(refs, 5)
        rnd.shuffle(r)
        assert day_scores(shuffled, truth, {"dining/temp": r}) == expected  # bit-identical


def test_the_best_informed_estimate_of_an_instant_is_scored() -> None:
    estimates, truth, refs = day()
    chosen = one_per_instant(reversed(estimates))["estimate"]
    assert len(chosen) == len(truth)
    assert all(abs(e.value - truth[t]) < 1.0 for t, e in chosen.items())  # never ± 3
    scores = {s.model: s for s in day_scores(estimates, truth, {"dining/temp": refs})}
    assert set(scores) == {"estimate", "triv", "ref:dining/temp"}
    t = sorted(truth)
    assert scores["estimate"].nrmse_pct == pytest.approx(
        metrics.nrmse_pct([truth[x] for x in t], [chosen[x].value for x in t]))
    # the raw reference (0.4 °C below the desk), read at the desk's own instants: each
    # instant is scored against the reading made there
    assert scores["ref:dining/temp"].n == len(truth)
    at_instant = dict(refs)
    assert scores["ref:dining/temp"].nrmse_pct == pytest.approx(
        metrics.nrmse_pct([truth[x] for x in t], [at_instant[x] for x in t]))


def test_the_reference_is_held_until_its_next_reading() -> None:
    truth = {at(0): 20.0, at(10): 20.0, at(20): 20.0}
    refs = [(at(-5), 19.0), (at(15), 21.0)]  # 19 is held until 21 arrives at +15 min
    (score,) = day_scores([], truth, {"a": refs})
    assert score.n == 3 and score.max_abs_error == pytest.approx(1.0)
    assert score.nrmse_pct == pytest.approx(100.0 * 1.0 / 20.0)


def test_the_day_is_answered_once_every_model_has_seen_the_last_reading() -> None:
    last = at(60)
    estimate = Published.from_payload("estimate", payload(last, 21.0, last))
    grid_before = Published.from_payload("triv", payload(last, 21.0, at(45)))
    grid_after = Published.from_payload("triv", payload(at(75), 21.0, last))
    assert not answered([], last)
    assert answered([estimate], last)
    # a baseline's grid estimate of the last instant made before that reading is not enough
    assert not answered([estimate, grid_before], last)
    # its next grid estimate, which saw the reading, is
    assert answered([grid_before, estimate, grid_after], last)
    # an estimate that has not seen the last reading leaves the day open
    assert not answered([Published.from_payload("estimate", payload(at(75), 21.0, at(45)))],
                        last)
