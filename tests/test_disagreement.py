"""The self-aware indication for twins with several references: references that drift apart
unlike on the training days (DESIGN.md §6 "references decorrelated"; live/envelope.py).

Real parts: a twin trained and validated on synthetic days with two references that share a
daily course and day level, the live Twin, the artifact saved and loaded.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from daemon_support import reference_days
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.envelope import MARGIN, Q_HI, Q_LO, Envelope, pair_criterion
from pseudotwin.live.twin import Quality, Twin

HOURS = OperatingHours(timezone="Europe/Berlin")
R1, R2, TARGET = "office/ceiling/temp", "office/wall/temp", "office/desk/temp"
FIRST = dt.date(2024, 3, 4)
TEST_DAY = FIRST + dt.timedelta(days=5)
PAIR = pair_criterion(R1, R2)


@pytest.fixture(scope="module")
def history() -> pd.DataFrame:
    """References sharing the day's course and level, each with its own offset and noise."""
    return reference_days(HOURS, FIRST, (R1, R2, TARGET), offsets=(0.8, -0.5, 0.2),
                          noise=(0.1, 0.1, 0.05), level_sd=0.4, seed=11)


@pytest.fixture(scope="module")
def trained(history: pd.DataFrame) -> Artifact:
    spec = TwinSpec((R1, R2), TARGET, Quantity.TEMPERATURE, HOURS)
    return train_twin(history, spec, FIRST, 5, ("ref", "triv"), primary="triv")


@pytest.fixture(scope="module")
def art(trained: Artifact) -> Artifact:
    """The trained twin with only the disagreement criterion acting, σ × 2."""
    assert trained.envelope is not None
    return dataclasses.replace(trained, envelope=trained.envelope.keeping(frozenset({PAIR}), 2.0))


def test_training_judges_the_pair_and_its_range_follows_the_documented_rule(
        trained: Artifact, history: pd.DataFrame) -> None:
    env = trained.envelope
    assert env is not None and [p.key for p in env.pairs] == [PAIR]
    assert PAIR in env.criteria and PAIR in env.judged  # validation judged it like the rest
    prof = {s: np.asarray(env.refs[s].profile) for s in (R1, R2)}
    gaps = []
    for day in trained.training["days"]:
        d = history[[HOURS.day_of(t.to_pydatetime()).isoformat() == day for t in history["ts"]]]
        one, two = (d[d["sensor"] == s] for s in (R1, R2))
        for t, v1, v2 in zip(one["ts"], one["value"], two["value"], strict=True):
            h = HOURS.hours_of(t.to_pydatetime())
            if HOURS.in_operating_hours(h):
                i = HOURS.window_slot_index(h)
                gaps.append((v1 - prof[R1][i]) - (v2 - prof[R2][i]))
    lo, hi = np.quantile(gaps, [Q_LO, Q_HI])
    m = MARGIN * (hi - lo)
    assert env.pairs[0].gap == pytest.approx((lo - m, hi + m))


NOON = HOURS.at(TEST_DAY, 12.0)


def _fed_until_noon(art: Artifact, today: pd.DataFrame) -> tuple[Twin, dict[str, float]]:
    """A twin fed the test day's references up to noon; their latest values then."""
    twin = Twin(art)
    latest = {}
    for s, ts, v in zip(today["sensor"], today["ts"], today["value"], strict=True):
        if ts > NOON:
            break
        if s != TARGET:
            twin.observe(s, ts.to_pydatetime(), float(v))
            latest[s] = float(v)
    e = twin.estimate(NOON)["triv"]
    assert e.quality is Quality.OK and PAIR not in e.unlike  # an ordinary morning
    return twin, latest


def _step(art: Artifact) -> float:
    """How far each reference moves: 0.6 × the span of the pair's training range [°C]."""
    assert art.envelope is not None
    lo, hi = art.envelope.pairs[0].gap
    return 0.6 * (hi - lo)


def _then(twin: Twin, values: dict[str, float]) -> dt.datetime:
    """Both references read ``values`` a minute after noon; that instant."""
    t = NOON + dt.timedelta(minutes=1)
    for sensor, v in values.items():
        twin.observe(sensor, t, v)
    return t


def _deviation(art: Artifact, sensor: str, value: float) -> float:
    """``sensor``'s deviation from its training profile at noon."""
    assert art.envelope is not None
    return value - art.envelope.refs[sensor].profile[HOURS.window_slot_index(12.0)]


def test_references_drifting_apart_make_the_estimate_uncertain(
        art: Artifact, history: pd.DataFrame) -> None:
    assert art.envelope is not None
    today = history[history["ts"] >= HOURS.at(TEST_DAY, 0.0)]
    twin, latest = _fed_until_noon(art, today)
    hi, step = art.envelope.pairs[0].gap[1], _step(art)
    # Each reference moves by less than its own training deviation allows, in opposite
    # directions: only their gap is unlike training.
    v1, v2 = latest[R1], latest[R2]
    d1, d2 = _deviation(art, R1, v1 + step), _deviation(art, R2, v2 - step)
    assert d1 - d2 > hi
    assert art.envelope.refs[R1].deviation[1] > d1 and art.envelope.refs[R2].deviation[0] < d2
    moved = {R1: v1 + step, R2: v2 - step}
    t = _then(twin, moved)
    blind = dataclasses.replace(art, envelope=art.envelope.keeping(frozenset(), 1.0))
    twin_blind, _ = _fed_until_noon(blind, today)
    _then(twin_blind, moved)
    e, b = twin.estimate(t)["triv"], twin_blind.estimate(t)["triv"]
    assert e.unlike == (PAIR,)  # neither reference alone is out of its ranges
    assert e.quality is Quality.UNCERTAIN and b.quality is Quality.OK
    assert e.value == b.value and e.std == pytest.approx(2.0 * b.std)
    assert any(R1 in w and R2 in w and "disagree" in w for w in e.why)
    assert twin.uncertain_why == e.why
    # The raw reference reads one sensor: how the two relate says nothing about it.
    assert PAIR not in twin.estimate(t)["ref"].unlike


def test_references_moving_together_stay_like_training(
        art: Artifact, history: pd.DataFrame) -> None:
    twin, latest = _fed_until_noon(art, history[history["ts"] >= HOURS.at(TEST_DAY, 0.0)])
    step = _step(art)  # as above, both the same way
    t = _then(twin, {s: latest[s] + step for s in (R1, R2)})
    e = twin.estimate(t)["triv"]
    assert PAIR not in e.unlike and e.quality is Quality.OK


def test_pairs_survive_the_artifact_and_older_envelopes_load_without(
        trained: Artifact, tmp_path: Path) -> None:
    path = tmp_path / "twin.json"
    trained.save(path)
    back = Artifact.load(path)
    assert back.envelope is not None and trained.envelope is not None
    assert back.envelope.pairs == trained.envelope.pairs
    d = json.loads(path.read_text())["envelope"]
    older = Envelope.from_dict({k: v for k, v in d.items() if k != "pairs"}, HOURS)
    assert older.pairs == () and PAIR not in older.criteria
    d["pairs"][0]["references"] = [R1, "nowhere/temp"]
    with pytest.raises(ValueError, match="nowhere/temp"):
        Envelope.from_dict(d, HOURS)
