"""The self-aware indication: quality ``uncertain`` when a reference is unlike training
(live/envelope.py) by a criterion the held-out training days kept (analysis/criteria.py), on
the SML2010 desk twin (tests/conftest.py ``desk_artifact``)."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math

import numpy as np
import pandas as pd
import pytest

from daemon_support import DAY, HOURS, REF, day_readings, sml
from pseudotwin.analysis.criteria import MIN_DAYS, MIN_RATIO, MIN_ROWS, criteria_table, select
from pseudotwin.analysis.replay import UNLIKE_SEP
from pseudotwin.analysis.selfaware import criteria_on_test, selfaware, training_share
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.edge.outputs import monitor_payload
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.envelope import MARGIN, Q_HI, Q_LO, WIDEN, Envelope
from pseudotwin.live.monitor import TwinMonitor
from pseudotwin.live.twin import Quality, Twin, TwinEstimate

LEVEL = f"level:{REF}"


@pytest.fixture(scope="module")
def trained(desk_artifact) -> Artifact:
    return Artifact.load(desk_artifact)


@pytest.fixture(scope="module")
def art(trained) -> Artifact:
    """The desk twin with its level criterion acting and σ × 3 (whatever validation kept on
    SML2010): the live mechanism under test."""
    assert trained.envelope is not None
    return dataclasses.replace(trained, envelope=trained.envelope.keeping(frozenset({LEVEL}), 3.0))


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
        assert e[kind].std == pytest.approx(3.0 * b[kind].std)
        assert any("level" in w and REF in w for w in e[kind].why)
        assert LEVEL in e[kind].unlike
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


def test_a_criterion_not_kept_is_reported_but_changes_nothing(art, history) -> None:
    assert art.envelope is not None
    dropped = dataclasses.replace(art, envelope=art.envelope.keeping(frozenset(), 1.0))
    twin, e, b = _hot_against_blind(dropped, history, record_unlike=True)
    assert e.quality is Quality.OK and e.why == () and e.std == b.std
    assert LEVEL in e.unlike  # what validation judges it on
    assert twin.uncertain_since is None
    # the daemon's twin does not record them: with no criterion acting it skips the checks
    _, e, b = _hot_against_blind(dropped, history)
    assert e.quality is Quality.OK and e.unlike == () and e.std == b.std


def _hot_against_blind(art: Artifact, history: pd.DataFrame, record_unlike: bool = False
                       ) -> tuple[Twin, TwinEstimate, TwinEstimate]:
    """A twin of ``art`` and one without training ranges, fed the same day up to its first
    ok estimate and then an out-of-range reference reading: the twin and both primaries'
    estimates at that reading."""
    readings = day_readings(history)
    twin = Twin(art, record_unlike=record_unlike)
    blind = Twin(dataclasses.replace(art, envelope=None))
    t = _first_ok(twin, readings)
    _first_ok(blind, readings[readings["ts"] <= t])
    t2, hot = _hot_reading(art, twin, t)
    twin.observe(REF, t2, hot)
    blind.observe(REF, t2, hot)
    return twin, twin.estimate(t2)[art.primary], blind.estimate(t2)[art.primary]


def test_the_training_days_themselves_are_rarely_uncertain(art, trained, history) -> None:
    assert 0.0 <= training_share(art, history) <= 0.10
    assert 0.0 <= training_share(trained, history) <= 0.10


def _held_out(errors: dict[str, tuple[float, int, int]]) -> pd.DataFrame:
    """Synthetic held-out rows of the primary ``triv``: per criterion key (or "" for rows
    where nothing fired) (absolute error, readings per day, days); truth 20, slope 0."""
    rows = []
    t0 = pd.Timestamp("2012-03-14T10:00Z")
    for key, (err, per_day, days) in errors.items():
        for d in range(days):
            for i in range(per_day):
                ts = t0 + pd.Timedelta(days=d, minutes=i)
                rows.append({"ts": ts, "model": "triv", "value": 20.0 + err * (-1) ** i,
                             "std": 1.0, "truth": 20.0, "quality": "ok", "slope": 0.0,
                             "day": str(ts.date()), "unlike": key})
    return pd.DataFrame(rows)


def test_criteria_of_a_sensor_id_with_a_space_are_judged(trained) -> None:
    """Sensor ids may contain spaces; the held-out rows' criteria must still be told apart."""
    env = trained.envelope
    assert env is not None
    spaced = dataclasses.replace(env, refs={"desk wall/temp": env.refs[REF]})
    level, speed = "level:desk wall/temp", "speed:desk wall/temp"
    rows = _held_out({"": (0.2, 30, 5), UNLIKE_SEP.join([level, speed]): (1.0, 10, 3)})
    sel = select(spaced, rows, "triv", trained.calibration["triv"], HOURS)
    assert sel.kept == frozenset({level, speed})


def test_a_criterion_that_flags_larger_held_out_errors_is_kept_one_that_does_not_dropped(
        trained, history) -> None:
    env = trained.envelope
    assert env is not None
    dev, speed = f"deviation:{REF}", f"speed:{REF}"
    rows = _held_out({"": (0.2, 30, 5),  # nothing fired: MAE 0.2
                      LEVEL: (1.0, 10, 3),  # 5× the error, 30 readings on 3 days: kept
                      dev: (0.3, 30, 3),  # 1.5× only: dropped
                      speed: (2.0, 30, 1)})  # large, but on one day only: dropped
    calib = trained.calibration["triv"]
    sel = select(env, rows, "triv", calib, HOURS)
    assert sel.kept == frozenset({LEVEL})
    assert sel.judged[LEVEL]["ratio"] == pytest.approx(5.0) and sel.judged[LEVEL]["kept"]
    assert sel.judged[LEVEL]["n"] == 30 and sel.judged[LEVEL]["days"] == 3
    assert not sel.judged[dev]["kept"] and f"< {MIN_RATIO:g}×" in sel.judged[dev]["reason"]
    assert not sel.judged[speed]["kept"] and f"≥ {MIN_DAYS} days" in sel.judged[speed]["reason"]
    # σ of an uncertain estimate: RMS error of the flagged rows over their calibrated σ
    flagged = rows[rows["unlike"] == LEVEL]
    sigma = np.array([calib.sigma(HOURS.hours_of(t), 0.0) for t in flagged["ts"]])
    assert sel.widen == pytest.approx(max(1.0, 1.0 / float(np.sqrt(np.mean(sigma ** 2)))))
    # live, the kept criterion fires on an out-of-range reference, with the judged widening
    _, e, b = _hot_against_blind(dataclasses.replace(trained, envelope=sel), history)
    assert e.quality is Quality.UNCERTAIN and e.std == pytest.approx(sel.widen * b.std)
    # too few readings: dropped
    few = select(env, _held_out({"": (0.2, 30, 5), LEVEL: (1.0, (MIN_ROWS - 1) // 3, 3)}),
                 "triv", calib, HOURS)
    assert few.kept == frozenset() and few.widen == 1.0
    assert "never uncertain" in criteria_table(
        {**env.keeping(few.kept, few.widen, few.judged).to_dict()}, "°C")
    assert f"uncertain: {LEVEL}" in criteria_table(sel.to_dict(), "°C")


def test_the_trained_artifact_keeps_only_criteria_its_held_out_days_support(trained) -> None:
    env = trained.envelope
    assert env is not None and env.kept is not None and env.widen >= 1.0
    assert set(env.judged) == set(env.criteria) == {LEVEL, f"deviation:{REF}", f"speed:{REF}"}
    for key, j in env.judged.items():
        supported = j["n"] >= MIN_ROWS and j["days"] >= MIN_DAYS and j["ratio"] >= MIN_RATIO
        assert j["kept"] == supported == (key in env.kept), key


def test_the_envelope_survives_a_round_trip(art, trained, tmp_path) -> None:
    again = Artifact.load(art.save(tmp_path / "a.json"))
    assert again.envelope == art.envelope
    assert again.envelope is not None and again.envelope.kept == frozenset({LEVEL})
    assert again.envelope.widen == 3.0
    again = Artifact.load(trained.save(tmp_path / "t.json"))
    assert again.envelope is not None and trained.envelope is not None
    assert again.envelope.judged == trained.envelope.judged
    d = art.to_dict()
    d["envelope"]["references"][REF]["level"] = [None, None]  # open bounds are stored as null
    opened = Artifact.from_dict(d).envelope
    assert opened is not None and opened.refs[REF].level == (-math.inf, math.inf)


def test_a_format_5_envelope_keeps_every_criterion_with_sigma_doubled(art, history) -> None:
    d = art.to_dict()
    d["version"] = 5
    for k in ("kept", "judged"):
        del d["envelope"][k]
    d["envelope"]["rule"]["widen"] = WIDEN
    old = Artifact.from_dict(d)
    assert old.envelope is not None and old.envelope.kept is None
    _, e, b = _hot_against_blind(old, history)
    assert e.quality is Quality.UNCERTAIN and e.std == pytest.approx(WIDEN * b.std)


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


def test_the_criteria_are_scored_on_the_test_days_by_validations_rule(trained, history) -> None:
    """criteria_on_test: the reference pushed out of its training range on two test days
    (13–16 h) while the target stays: the level criterion fires there, the estimate errs
    there, and validation's rule would keep it; on the untouched days it fires less."""
    quiet = dataclasses.replace(trained, envelope=trained.envelope.keeping(frozenset(), 1.0)) \
        if trained.envelope is not None else trained
    end = HOURS.at(DAY + dt.timedelta(days=2), 0.0)
    days = history[history["ts"] < end]
    local, at = HOURS.day_and_hours(days["ts"])
    hot = ((days["sensor"] == REF).to_numpy() & (local >= np.datetime64(DAY))
           & (at >= 13.0) & (at < 16.0))
    pushed = days.assign(value=days["value"].where(~hot, days["value"] + 15.0))
    level = criteria_on_test(quiet, pushed, DAY)[LEVEL]
    assert level.judged.kept and level.judged.days == 2 and level.judged.ratio >= MIN_RATIO
    assert 0.0 < level.share_pct < 50.0 and level.cover2_pct < 50.0
    assert criteria_on_test(quiet, days, DAY)[LEVEL].share_pct < level.share_pct
    assert criteria_on_test(dataclasses.replace(trained, envelope=None), days, DAY) == {}


def test_training_keeps_a_criterion_its_held_out_days_prove_and_it_fires_live() -> None:
    """End to end, nothing switched on by hand (issue Trust II, tests): the desk's offset grows
    with the room's level (a radiator under the desk), so a held-out day warmer or colder
    than the others is one TRIV gets wrong, and validation keeps the level criterion; replayed,
    the training days are never uncertain; live, a reference far above any training day makes
    the primary's estimates uncertain with σ widened by what the held-out days measured."""
    hours = pd.Series(7.0 + np.arange(52) * 0.25)
    spec = TwinSpec(("ref",), "desk", Quantity.TEMPERATURE, OperatingHours(timezone="UTC"))
    day0 = dt.date(2024, 3, 4)
    rng = np.random.default_rng(8)
    rows = []
    for d, level in enumerate((21.0, 21.4, 20.7, 25.0, 17.0, 30.0)):
        ref = level + np.cumsum(rng.normal(0.0, 0.03, size=hours.size))
        desk = ref + 0.5 + 0.5 * (level - 21.0) + rng.normal(0.0, 0.05, size=hours.size)
        ts = pd.Timestamp(day0 + dt.timedelta(days=d), tz="UTC") + pd.to_timedelta(hours,
                                                                                   unit="h")
        rows += [pd.DataFrame({"sensor": "ref", "ts": ts, "value": ref}),
                 pd.DataFrame({"sensor": "desk", "ts": ts, "value": desk})]
    history = pd.concat(rows, ignore_index=True).sort_values("ts", kind="stable")
    art = train_twin(history, spec, day0, 5, models=["ref", "triv"])
    assert art.envelope is not None
    assert art.envelope.kept is not None and "level:ref" in art.envelope.kept, \
        art.envelope.judged
    assert art.envelope.widen > 1.0
    assert training_share(art, history) == 0.0
    hot_day = history[history["ts"] >= pd.Timestamp(day0 + dt.timedelta(days=5), tz="UTC")]
    twin = Twin(art)
    blind = Twin(dataclasses.replace(art, envelope=None))
    uncertain = 0
    for ts, v in zip(hot_day.loc[hot_day["sensor"] == "ref", "ts"],
                     hot_day.loc[hot_day["sensor"] == "ref", "value"], strict=True):
        t = ts.to_pydatetime()
        twin.observe("ref", t, float(v))
        blind.observe("ref", t, float(v))
        e, b = twin.estimate(t).get(art.primary), blind.estimate(t).get(art.primary)
        if e is not None and b is not None and b.quality is Quality.OK:
            assert e.quality is Quality.UNCERTAIN and "level:ref" in e.unlike
            assert e.value == b.value
            assert e.std == pytest.approx(art.envelope.widen * b.std)
            uncertain += 1
    assert uncertain > 20
