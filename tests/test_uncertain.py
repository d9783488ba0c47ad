"""The self-aware indication: quality ``uncertain`` when a reference is unlike training
(live/envelope.py), on the SML2010 desk twin (tests/conftest.py ``desk_artifact``)."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math

import numpy as np
import pandas as pd
import pytest

from daemon_support import DAY, HOURS, REF, day_readings, sml
from pseudotwin.analysis.selfaware import selfaware, training_share
from pseudotwin.edge.outputs import monitor_payload
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.envelope import MARGIN, Q_HI, Q_LO, WIDEN, Envelope
from pseudotwin.live.monitor import TwinMonitor
from pseudotwin.live.twin import Quality, Twin


@pytest.fixture(scope="module")
def art(desk_artifact) -> Artifact:
    return Artifact.load(desk_artifact)


@pytest.fixture(scope="module")
def history() -> pd.DataFrame:
    return sml()


def _first_ok(twin: Twin, readings: pd.DataFrame) -> dt.datetime:
    """Feed ``readings`` until the primary publishes ``ok`` after them; that instant."""
    for ts, v in zip(readings["ts"], readings["value"], strict=True):
        t = ts.to_pydatetime()
        twin.observe(REF, t, float(v))
        e = twin.estimate(t).get(twin.artifact.primary)
        if e is not None and e.quality is Quality.OK:
            return t
    raise AssertionError("the primary never published ok on the test day")


def _hot_reading(art: Artifact, twin: Twin, t: dt.datetime) -> tuple[dt.datetime, float]:
    """A reading well above the training range of the reference, a minute after ``t``."""
    assert art.envelope is not None
    hi = art.envelope.refs[REF].level[1]
    return t + dt.timedelta(minutes=1), hi + 5.0


def test_training_range_follows_the_documented_rule(art, history) -> None:
    env = art.envelope
    assert env is not None and set(env.refs) == {REF}
    days = art.training["days"]
    local_day, h = HOURS.day_and_hours(history["ts"])
    sel = ((history["sensor"] == REF).to_numpy() & HOURS.in_operating_hours(h)
           & np.isin(local_day.astype("datetime64[D]"), np.array(days, dtype="datetime64[D]")))
    lo, hi = np.quantile(history.loc[sel, "value"].to_numpy(float), [Q_LO, Q_HI])
    m = MARGIN * (hi - lo)
    assert env.refs[REF].level == pytest.approx((lo - m, hi + m))
    dlo, dhi = env.refs[REF].deviation
    assert dlo < 0 < dhi and env.refs[REF].slope_hi > 0


def test_an_out_of_range_reference_makes_ok_estimates_uncertain_with_widened_sigma(
        art, history) -> None:
    readings = day_readings(history)
    twin = Twin(art)
    blind = Twin(dataclasses.replace(art, envelope=None))  # same twin, no training ranges
    t = _first_ok(twin, readings)
    _first_ok(blind, readings[readings["ts"] <= t])
    t2, hot = _hot_reading(art, twin, t)
    twin.observe(REF, t2, hot)
    blind.observe(REF, t2, hot)
    e, b = twin.estimate(t2), blind.estimate(t2)
    for kind in art.published:
        assert b[kind].quality is Quality.OK, kind  # without ranges nothing is unlike training
        assert e[kind].quality is Quality.UNCERTAIN, kind
        assert e[kind].value == b[kind].value
        assert e[kind].std == pytest.approx(WIDEN * b[kind].std)
        assert any("level" in w and REF in w for w in e[kind].why)
    assert twin.uncertain_since == t2 and twin.uncertain_why == e[art.primary].why


def test_stale_takes_precedence_over_uncertain(art, history) -> None:
    twin = Twin(art, stale_after=dt.timedelta(minutes=30))
    t = _first_ok(twin, day_readings(history))
    t2, hot = _hot_reading(art, twin, t)
    twin.observe(REF, t2, hot)
    later = t2 + dt.timedelta(hours=1)
    e = twin.estimate(later)[art.primary]
    assert e.quality is Quality.STALE and e.why == ()
    assert twin.uncertain_since is None


def test_the_monitor_says_why_and_since_when(art, history) -> None:
    twin = Twin(art)
    mon = TwinMonitor("desk", twin, "0" * 64, HOURS, {REF})
    t = _first_ok(twin, day_readings(history))
    assert mon.snapshot(t)["uncertain"] is None
    t2, hot = _hot_reading(art, twin, t)
    twin.observe(REF, t2, hot)
    twin.estimate(t2)
    twin.estimate(t2 + dt.timedelta(minutes=5))
    payload = json.loads(monitor_payload(mon.snapshot(t2 + dt.timedelta(minutes=5))))
    since = dt.datetime.fromisoformat(payload["uncertain"]["since"])
    assert since == t2
    assert any("level" in w and REF in w for w in payload["uncertain"]["why"])


def test_the_training_days_themselves_are_rarely_uncertain(art, history) -> None:
    share = training_share(art, history)
    assert 0.0 <= share <= 0.10


def test_the_envelope_survives_a_round_trip(art, tmp_path) -> None:
    again = Artifact.load(art.save(tmp_path / "a.json"))
    assert again.envelope == art.envelope
    d = art.to_dict()
    d["envelope"]["references"][REF]["level"] = [None, None]  # open bounds are stored as null
    opened = Artifact.from_dict(d).envelope
    assert opened is not None and opened.refs[REF].level == (-math.inf, math.inf)


def test_an_older_artifact_loads_without_ranges_and_is_never_uncertain(art, history) -> None:
    d = art.to_dict()
    d["version"] = 2
    del d["envelope"]
    old = Artifact.from_dict(d)
    assert old.envelope is None
    twin = Twin(old)
    t = _first_ok(twin, day_readings(history))
    t2, hot = _hot_reading(art, twin, t)
    twin.observe(REF, t2, hot)
    assert all(e.quality is Quality.OK for e in twin.estimate(t2).values())


def test_selfaware_scores_split_ok_and_uncertain() -> None:
    ts = pd.Timestamp("2012-03-20T12:00Z")
    rows = pd.DataFrame({
        "ts": [ts] * 4, "model": ["estimate"] * 3 + ["triv"],
        "value": [20.0, 21.0, 25.0, 99.0], "std": [1.0, 1.0, 1.0, 1.0],
        "truth": [20.5, 20.0, 20.0, 20.0],
        "quality": ["ok", "ok", "uncertain", "uncertain"], "slope": [0.0] * 4,
    })
    sa = selfaware(rows, 0.05)
    assert (sa.n_ok, sa.n_uncertain) == (2, 1)
    assert sa.share == pytest.approx(1 / 3)
    assert sa.mae_ok == pytest.approx(0.75) and sa.mae_uncertain == pytest.approx(5.0)
    assert sa.cover2_ok == 100.0 and sa.cover2_uncertain == 0.0
    assert sa.mae_ratio == pytest.approx(5.0 / 0.75) and sa.train_share == 0.05


def test_an_envelope_with_a_wrong_slot_grid_is_a_corrupt_artifact(art) -> None:
    from pseudotwin.errors import ArtifactError

    d = art.to_dict()
    d["envelope"]["references"][REF]["profile"] = [20.0, 21.0]
    with pytest.raises(ArtifactError, match="slot grid"):
        Artifact.from_dict(d)
    assert isinstance(art.envelope, Envelope)
    assert DAY > dt.date.fromisoformat(art.training["end"])
