"""Reference failover (Issue 10, item 3): a silent reference does not stop the estimate.

Real parts throughout: twins trained and validated on synthetic days with two references, the
live Twin, artifacts saved and loaded, and the daemon on the real Mosquitto of conftest.py.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
from pathlib import Path

import pandas as pd
import pytest

from daemon_support import HandClock, Lockstep, Viewer, reference_days, wait_for
from pseudotwin.analysis.failover import FAILOVER_KINDS
from pseudotwin.analysis.replay import ESTIMATE, replay_estimates
from pseudotwin.analysis.training import train_twin
from pseudotwin.cli import main
from pseudotwin.config import load_config
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import write_history
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.edge.outputs import estimate_payload
from pseudotwin.edge.replay import replay
from pseudotwin.edge.service import Service
from pseudotwin.errors import ArtifactError
from pseudotwin.history.backfill import backfill
from pseudotwin.history.store import open_store
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.failover import Failover, picked
from pseudotwin.live.twin import Quality, Twin

TZ = "Europe/Madrid"
HOURS = OperatingHours(timezone=TZ)
R1, R2, TARGET = "room/wall/temp", "room/ceiling/temp", "room/desk/temp"
FIRST = dt.date(2024, 3, 4)
TEST_DAY = FIRST + dt.timedelta(days=5)
STALE = dt.timedelta(minutes=30)


@pytest.fixture(scope="module")
def history() -> pd.DataFrame:
    """Each reference with its own offset and noise, so TRIV on both beats either alone and
    each alone still answers."""
    return reference_days(HOURS, FIRST, (R1, R2, TARGET), offsets=(0.6, -0.9, 0.2),
                          noise=(0.2, 0.2, 0.03), level_sd=0.3, seed=7)


@pytest.fixture(scope="module")
def today(history: pd.DataFrame) -> pd.DataFrame:
    """The test day's readings (the day after the five training days)."""
    return history[history["ts"] >= HOURS.at(TEST_DAY, 0.0)]


@pytest.fixture(scope="module")
def artifact(history: pd.DataFrame) -> Artifact:
    spec = TwinSpec((R1, R2), TARGET, Quantity.TEMPERATURE, HOURS)
    # Pinned: the primary must read both references for failover to matter.
    return train_twin(history, spec, FIRST, 5, ("ref", "triv"), primary="triv")


def feed(twin: Twin, df: pd.DataFrame, until: dt.datetime, skip: str | None = None,
         after: dt.datetime | None = None) -> None:
    """Observe ``df``'s references in order up to ``until``; ``skip``'s readings after
    ``after`` are left out (the silenced sensor)."""
    for s, ts, v in zip(df["sensor"], df["ts"], df["value"], strict=True):
        if ts > until:
            break
        if s == TARGET or (s == skip and after is not None and ts > after):
            continue
        twin.observe(s, ts.to_pydatetime(), float(v))


def alone(art: Artifact, lost: str) -> Twin:
    """A twin whose only model is the failover for ``lost``, as a standalone artifact: what
    the failover must publish, value and σ."""
    return standalone(art, art.failover[lost])


def standalone(art: Artifact, f: Failover) -> Twin:
    """A twin whose only model is the failover ``f``, as a standalone artifact."""
    spec = dataclasses.replace(art.spec, references=f.model.references_)
    calib = {f.kind: f.calibration} if f.calibration else {}
    return Twin(Artifact(spec, {f.kind: f.model}, f.kind, calibration=calib))


def test_training_keeps_a_validated_failover_per_reference(artifact: Artifact) -> None:
    assert set(artifact.failover) == {R1, R2}
    # with two references, the failover without one reads the other alone
    assert artifact.failover_alone == {}
    for lost, f in artifact.failover.items():
        assert lost not in f.model.references_ and f.model.references_
        assert f.kind in FAILOVER_KINDS and f.calibration is not None
        assert math.isfinite(f.nrmse_pct) and f.reason


@pytest.mark.parametrize("lost", [R1, R2])
def test_silent_reference_switches_to_its_failover_and_back(
    artifact: Artifact, today: pd.DataFrame, lost: str
) -> None:
    silent_from = HOURS.at(TEST_DAY, 10.0)
    twin = Twin(artifact, stale_after=STALE)
    t_ok = HOURS.at(TEST_DAY, 10.0)
    feed(twin, today, t_ok)
    before = twin.estimate(t_ok)["triv"]
    assert before.quality in (Quality.OK, Quality.UNCERTAIN) and before.lost == ()

    t = HOURS.at(TEST_DAY, 11.0 + 2.5 / 60)  # 62 min after the last reading of ``lost``
    feed(twin, today[today["ts"] > t_ok], t, skip=lost, after=silent_from)
    got = twin.estimate(t)["triv"]
    f = artifact.failover[lost]
    assert got.quality is Quality.FALLBACK
    assert got.lost == (lost,) and got.model == f.model.model_name
    assert set(got.refs) == {R1, R2}  # the lost reference's last reading is still reported
    ref_twin = alone(artifact, lost)
    feed(ref_twin, today, t, skip=lost, after=silent_from)
    expected = ref_twin.estimate(t)[f.kind]
    assert got.value == expected.value and got.std == expected.std
    assert f.calibration is not None
    h = HOURS.hours_of(t)
    assert got.std == f.calibration.sigma(h, twin.slope(f.model.references_, h))
    # the primary's own σ differs: the failover's is published, not the primary's
    assert got.std != artifact.calibration["triv"].sigma(h, twin.slope((R1, R2), h))

    back = HOURS.at(TEST_DAY, 11.1)
    twin.observe(lost, back, float(today.loc[today["sensor"] == lost, "value"].iloc[0]))
    again = twin.estimate(back)["triv"]
    assert again.quality is not Quality.FALLBACK and again.lost == ()


def test_missing_reference_fails_over_and_all_silent_is_stale(
    artifact: Artifact, today: pd.DataFrame
) -> None:
    twin = Twin(artifact, stale_after=STALE)
    t = HOURS.at(TEST_DAY, 9.0)
    feed(twin, today[today["sensor"] != R1], t)
    e = twin.estimate(t)["triv"]
    assert e.quality is Quality.FALLBACK and e.lost == (R1,) and math.isfinite(e.value)
    # both silent: no failover can answer
    late = t + dt.timedelta(hours=1)
    e = twin.estimate(late)["triv"]
    assert e.quality is Quality.STALE and e.lost == ()


def test_single_reference_twin_still_goes_stale(history: pd.DataFrame,
                                                today: pd.DataFrame) -> None:
    spec = TwinSpec((R1,), TARGET, Quantity.TEMPERATURE, HOURS)
    art = train_twin(history[history["sensor"] != R2], spec, FIRST, 5, ("ref", "triv"))
    assert art.failover == {}
    twin = Twin(art, stale_after=STALE)
    t = HOURS.at(TEST_DAY, 10.0)
    feed(twin, today, t)
    e = twin.estimate(t + dt.timedelta(hours=1))[art.primary]
    assert e.quality is Quality.STALE and e.lost == ()
    # made from an hour-old reading: its value, but no σ (the calibrated one, smallest when
    # the references do not move, was the day's most confident)
    assert math.isfinite(e.value) and math.isnan(e.std)
    assert json.loads(estimate_payload(e, "°C"))["std"] is None


def test_artifact_round_trip_keeps_failover(artifact: Artifact, today: pd.DataFrame,
                                            tmp_path: Path) -> None:
    path = artifact.save(tmp_path / "a.json")
    d = json.loads(path.read_text(encoding="utf-8"))
    assert d["version"] >= 4 and set(d["failover"]) == {R1, R2}
    loaded = Artifact.load(path)
    for lost, f in artifact.failover.items():
        g = loaded.failover[lost]
        assert (g.kind, g.model.references_, g.nrmse_pct) == (f.kind, f.model.references_,
                                                             f.nrmse_pct)
        assert g.calibration == f.calibration
    # the loaded artifact fails over exactly as the trained one
    t = HOURS.at(TEST_DAY, 11.5)
    a, b = Twin(artifact, stale_after=STALE), Twin(loaded, stale_after=STALE)
    for twin in (a, b):
        feed(twin, today, t, skip=R2, after=HOURS.at(TEST_DAY, 10.0))
    ea, eb = a.estimate(t)["triv"], b.estimate(t)["triv"]
    assert ea.quality is Quality.FALLBACK and (ea.value, ea.std, ea.lost) == (eb.value, eb.std,
                                                                             eb.lost)


def test_a_failover_reading_a_sensor_the_twin_lacks_is_refused(
    artifact: Artifact, tmp_path: Path
) -> None:
    d = json.loads(json.dumps(artifact.to_dict(), allow_nan=True))
    model = d["failover"][R2]["model"]
    assert model.get("references") == [R1], model.keys()  # triv reads the other reference
    model["references"] = ["hall/temp"]
    p = tmp_path / "foreign.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ArtifactError, match=rf"^{p}: failover for {R2} reads hall/temp"):
        Artifact.load(p)


def test_older_artifact_without_failover_loads_and_goes_stale(
    artifact: Artifact, today: pd.DataFrame
) -> None:
    d = artifact.to_dict()
    del d["failover"]
    d["version"] = 3
    old = Artifact.from_dict(d)
    assert old.failover == {}
    twin = Twin(old, stale_after=STALE)
    t = HOURS.at(TEST_DAY, 11.5)
    feed(twin, today, t, skip=R2, after=HOURS.at(TEST_DAY, 10.0))
    e = twin.estimate(t)["triv"]
    assert e.quality is Quality.STALE and e.lost == ()


# ------------------------------------------------------------- three references
R3 = "room/door/temp"


@pytest.fixture(scope="module")
def three_days() -> pd.DataFrame:
    """Three references of equal noise (TRIV on any two beats any one alone), six days."""
    return reference_days(HOURS, FIRST, (R1, R2, R3, TARGET), offsets=(0.6, -0.9, 0.3, 0.2),
                          noise=(0.2, 0.2, 0.2, 0.03), level_sd=0.3, seed=7)


@pytest.fixture(scope="module")
def three(three_days: pd.DataFrame) -> Artifact:
    spec = TwinSpec((R1, R2, R3), TARGET, Quantity.TEMPERATURE, HOURS)
    return train_twin(three_days, spec, FIRST, 5, ("ref", "triv"), primary="triv")


def silenced(df: pd.DataFrame, lost: tuple[str, ...], after: dt.datetime) -> pd.DataFrame:
    return df[~(df["sensor"].isin(lost) & (df["ts"] > after))]


def test_three_references_keep_a_failover_per_reference_alone(three: Artifact) -> None:
    assert set(three.failover) == {R1, R2, R3}
    assert set(three.failover_alone) == {R1, R2, R3}
    for kept, f in three.failover_alone.items():
        assert f.model.references_ == (kept,) and set(f.lost) == {R1, R2, R3} - {kept}
        assert f.kind in FAILOVER_KINDS and f.calibration is not None
        assert math.isfinite(f.nrmse_pct)


def test_two_silent_of_three_fall_over_to_the_one_left_and_all_silent_is_stale(
    three: Artifact, three_days: pd.DataFrame
) -> None:
    today = three_days[three_days["ts"] >= HOURS.at(TEST_DAY, 0.0)]
    silent_from, t = HOURS.at(TEST_DAY, 10.0), HOURS.at(TEST_DAY, 11.0 + 2.5 / 60)
    both = silenced(today, (R1, R2), silent_from)
    twin = Twin(three, stale_after=STALE)
    feed(twin, both, t)
    got = twin.estimate(t)["triv"]
    f = three.failover_alone[R3]
    assert got.quality is Quality.FALLBACK and got.lost == (R1, R2)
    assert got.model == f.model.model_name
    expected = standalone(three, f)
    feed(expected, both, t)
    e = expected.estimate(t)[f.kind]
    assert (got.value, got.std) == (e.value, e.std)
    # one silent: two references left beat one (the held-out errors say so), and answer
    one = silenced(today, (R1,), silent_from)
    twin = Twin(three, stale_after=STALE)
    feed(twin, one, t)
    got = twin.estimate(t)["triv"]
    f = three.failover[R1]
    assert f.nrmse_pct < min(a.nrmse_pct for a in three.failover_alone.values())
    expected = standalone(three, f)
    feed(expected, one, t)
    e = expected.estimate(t)[f.kind]
    assert got.lost == (R1,) and (got.value, got.std) == (e.value, e.std)
    # all three silent: nothing can answer
    twin = Twin(three, stale_after=STALE)
    feed(twin, silenced(today, (R1, R2, R3), silent_from), t)
    e = twin.estimate(t)["triv"]
    assert e.quality is Quality.STALE and e.lost == ()


def test_failover_alone_round_trips_and_an_older_artifact_goes_stale(
    three: Artifact, three_days: pd.DataFrame, tmp_path: Path
) -> None:
    path = three.save(tmp_path / "three.json")
    d = json.loads(path.read_text(encoding="utf-8"))
    assert d["version"] >= 8 and set(d["failover_alone"]) == {R1, R2, R3}
    loaded = Artifact.load(path)
    for kept, f in three.failover_alone.items():
        g = loaded.failover_alone[kept]
        assert (g.kind, g.lost, g.model.references_, g.nrmse_pct, g.calibration) == (
            f.kind, f.lost, f.model.references_, f.nrmse_pct, f.calibration)
    today = three_days[three_days["ts"] >= HOURS.at(TEST_DAY, 0.0)]
    t = HOURS.at(TEST_DAY, 11.5)
    both = silenced(today, (R1, R3), HOURS.at(TEST_DAY, 10.0))
    a, b = Twin(three, stale_after=STALE), Twin(loaded, stale_after=STALE)
    for twin in (a, b):
        feed(twin, both, t)
    ea, eb = a.estimate(t)["triv"], b.estimate(t)["triv"]
    assert ea.quality is Quality.FALLBACK and ea.lost == (R1, R3)
    assert (ea.value, ea.std, ea.model) == (eb.value, eb.std, eb.model)
    # version 7 had no failover alone: two silent references make it stale, as they did
    del d["failover_alone"]
    d["version"] = 7
    old = Artifact.from_dict(d)
    twin = Twin(old, stale_after=STALE)
    feed(twin, both, t)
    assert twin.estimate(t)["triv"].quality is Quality.STALE


def test_a_failover_alone_reading_another_reference_is_refused(
    three: Artifact, tmp_path: Path
) -> None:
    d = json.loads(json.dumps(three.to_dict(), allow_nan=True))
    d["failover_alone"][R3] = d["failover_alone"][R1]  # reads R1, filed under R3
    p = tmp_path / "swapped.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ArtifactError,
                       match=rf"^{p}: the failover for {R1}, {R2} reads {R1} itself$"):
        Artifact.load(p)
    d["failover_alone"] = {"hall/temp": d["failover_alone"][R1]}
    p.write_text(json.dumps(d))
    with pytest.raises(ArtifactError, match="hall/temp.*not one of the references"):
        Artifact.load(p)
    with pytest.raises(TypeError, match="tuple of references"):
        dataclasses.replace(three.failover[R1], lost=R1)


def test_train_prints_what_each_failover_answers_for(
    three_days: pd.DataFrame, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    csv = tmp_path / "h.csv"
    write_history(three_days, csv)
    out = tmp_path / "a.json"
    assert main(["--log-level", "WARNING", "train", "--history", str(csv), "--references",
                 f"{R1},{R2},{R3}", "--target", TARGET, "--quantity", "temperature",
                 "--train-start", str(FIRST), "--timezone", TZ, "--models", "ref,triv",
                 "--primary", "triv", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    art = Artifact.load(out)
    for r in (R1, R2, R3):
        f, g = art.failover[r], art.failover_alone[r]
        assert (f"failover without {r}: {f.kind} on {', '.join(f.model.references_)} "
                f"(held-out {f.nrmse_pct:.2f} %)") in printed
        assert f"failover on {r} alone: {g.kind} on {r} (held-out {g.nrmse_pct:.2f} %)" in printed


def test_a_two_reference_artifact_with_a_failover_alone_is_refused(artifact: Artifact) -> None:
    """With two references a failover on one alone would do without the same reference as
    the failover without the other: the live twin could not tell their estimators apart."""
    d = artifact.to_dict()
    d["failover_alone"] = {R2: d["failover"][R1]}
    with pytest.raises(ArtifactError, match="need three references or more; the twin has 2"):
        Artifact.from_dict(d)
    with pytest.raises(ArtifactError, match="do without the same references"):
        dataclasses.replace(artifact, failover={R1: artifact.failover[R1],
                                                R2: dataclasses.replace(artifact.failover[R1])})


def test_evaluate_cli_scores_the_failover_with_stale_after(
    history: pd.DataFrame, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`evaluate --stale-after` publishes what the daemon would: with R2 silent on the test
    day the `estimate` rows are the failover's (fallback), never stale; without the option
    R2's carried-over value is held (no fallback); a bad value is a clear error."""
    silent = history[~((history["sensor"] == R2) & (history["ts"] >= HOURS.at(TEST_DAY, 0.0)))]
    csv = tmp_path / "h.csv"
    write_history(silent, csv)
    base = ["--log-level", "WARNING", "evaluate", "--history", str(csv), "--references",
            f"{R1},{R2}", "--target", TARGET, "--quantity", "temperature", "--train-start",
            str(FIRST), "--timezone", TZ, "--models", "ref,triv", "--primary", "triv"]
    assert main([*base, "--out", str(tmp_path / "fo"), "--stale-after", "30"]) == 0
    est = pd.read_csv(tmp_path / "fo" / "estimates.csv")
    published = est[est["model"] == ESTIMATE]
    assert len(published) > 100 and set(published["quality"]) == {"fallback"}
    # the file says which model answered and which reference it did without
    failover = Artifact.load(tmp_path / "fo" / "artifact.json").failover[R2]
    assert set(published["source"]) == {failover.model.model_name}
    assert set(published["lost"]) == {json.dumps([R2])}
    assert main([*base, "--out", str(tmp_path / "held")]) == 0
    held = pd.read_csv(tmp_path / "held" / "estimates.csv")
    assert "fallback" not in set(held.loc[held["model"] == ESTIMATE, "quality"])
    assert set(held.loc[held["model"] == ESTIMATE, "lost"]) == {"[]"}
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main([*base, "--out", str(tmp_path / "bad"), "--stale-after", "-5"])
    assert exc.value.code == 2
    assert "--stale-after" in capsys.readouterr().err


# ------------------------------------------------------------------ through the daemon


def write_config(folder: Path, port: int, artifact: Path,
                 references: tuple[str, ...] = (R1, R2)) -> Path:
    sensors = "".join(f"""
[[sensors]]
id = "{s}"
topic = "house/{s}"
unit = "°C"
min = -10
max = 50
""" for s in (*references, TARGET))
    text = f"""
[broker]
host = "127.0.0.1"
port = {port}
client_id = "pt-failover-{folder.name}"

[service]
base_topic = "pt"
timezone = "{TZ}"
state_dir = "state"
stale_after_minutes = {STALE.total_seconds() / 60:g}
{sensors}
[[twins]]
id = "desk"
references = {json.dumps(list(references))}
target = "{TARGET}"
quantity = "temperature"
artifact = "{artifact}"
"""
    p = folder / "config.toml"
    p.write_text(text, encoding="utf-8")
    return p


def stamp_of(t: dt.datetime) -> str:
    return t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


@pytest.mark.parametrize("case", ["one of two", "two of three"])
def test_daemon_fails_over_on_silenced_references_like_evaluate(
    mosquitto, case: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    """R2 of two (or R1 and R2 of three) silenced from 10:00: the daemon publishes the
    failover the twin picks, with its σ, names the silent references, and every estimate at
    a reading equals evaluate's (replay with the daemon's stale_after)."""
    art, history, silent = ((request.getfixturevalue("artifact"),
                             request.getfixturevalue("history"), (R2,)) if case == "one of two"
                            else (request.getfixturevalue("three"),
                                  request.getfixturevalue("three_days"), (R1, R2)))
    chosen = picked(art.failovers, silent)
    assert chosen is not None
    assert chosen.lost == silent  # with two of three silent, the failover on the third
    path = art.save(tmp_path / "desk.json")
    cfg = load_config(write_config(tmp_path, mosquitto.port, path, art.references))
    start, end = HOURS.at(TEST_DAY, 7.0), HOURS.at(TEST_DAY, 12.0)
    silent_from = HOURS.at(TEST_DAY, 10.0)
    day = history[(history["ts"] >= start) & (history["ts"] < end)]
    day = day[~(day["sensor"].isin(silent) & (day["ts"] > silent_from))]
    # The daemon's clock moves only with the replay, a reading at a time once the daemon
    # has taken the ones before (Lockstep): on a wall-time clock a grid tick could overtake
    # readings still on their way (a pause of the test process longer than stale_after at
    # the replay's speed made the references look stale), and ticks went on after the
    # replay until svc.stop().
    clock = HandClock(start)
    viewer = Viewer(mosquitto.port)
    monitor = Viewer(mosquitto.port, "pt/desk/monitor")
    svc = Service(cfg, clock=clock)
    svc.start(wait_connected=15)
    try:
        replay(cfg, day, start, end, 1.0,
               clock=Lockstep(clock, svc))
        refs = day[(day["sensor"] != TARGET) & (day["ts"] >= HOURS.at(TEST_DAY, 8.0))]
        wanted = set(refs["ts"])
        stamp = {t: t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z") for t in wanted}
        wait_for(lambda: set(stamp.values()) <= {e["ts"] for e in viewer.all()},
                 what="an estimate at every reference reading")
        last_hourly = stamp_of(HOURS.at(TEST_DAY, 11.0))  # the default cadence: hourly
        wait_for(lambda: any(m["ts"] == last_hourly for m in monitor.all()),
                 what="the monitor of the last full hour")
    finally:
        svc.stop()
        viewer.close()
        monitor.close()
    # <twin>/monitor says which references the estimate does without, from the first tick
    # at which their last reading is older than stale_after (not waiting for the next full
    # hour of the monitor's cadence); before, nothing is lost
    last_each = day.loc[day["sensor"].isin(silent)].groupby("sensor")["ts"].max()
    last_silent = last_each.max()
    assert (last_each == last_silent).all()  # silent together: one spell, losing them all
    first_lost = min(dt.datetime.fromisoformat(m["ts"]) for m in monitor.all() if m["failover"])
    assert (first_lost.minute != 0
            and first_lost - last_silent <= STALE + dt.timedelta(minutes=15))
    for m in monitor.all():
        lost = m["failover"]
        if dt.datetime.fromisoformat(m["ts"]) - last_silent > STALE:
            assert lost is not None and lost["lost"] == list(silent), m["ts"]
            assert dt.datetime.fromisoformat(lost["since"]) - last_silent > STALE
        else:
            assert lost is None, m["ts"]
    live: dict[str, dict] = {}
    for e in viewer.all():  # two readings at an instant: the later estimate saw both
        live[e["ts"]] = e
    offline = replay_estimates(Artifact.load(path), day, TEST_DAY, stale_after=cfg.stale_after)
    offline = offline[(offline["model"] == ESTIMATE) & offline["ts"].isin(wanted)]
    assert len(offline) == len(wanted)
    fallbacks = 0
    for _, row in offline.iterrows():
        e = live[stamp[row["ts"]]]
        assert e["value"] == round(row["value"], 6) and e["std"] == round(row["std"], 6)
        assert e["quality"] == row["quality"]
        # what produced the value and what it lost, as estimates.csv writes them
        assert e["model"] == row["source"] and e["lost"] == json.loads(row["lost"])
        if row["ts"] > silent_from + STALE:
            assert e["quality"] == "fallback" and e["lost"] == list(silent)
            assert e["model"] == chosen.model.model_name
            fallbacks += 1
        else:
            assert e["quality"] in ("ok", "uncertain") and e["lost"] == []
    assert fallbacks >= 10
    assert all(e["quality"] != "stale" for e in viewer.all())
    # backfill of the same readings stores what the daemon published, what answered and
    # what it lost included (the history store's source and lost)
    with open_store(str(tmp_path / "history.db")) as store:
        store.write_readings(day)
        backfill(cfg, "desk", TEST_DAY, TEST_DAY, store, progress=False)
        rows = store.read_estimates("desk", model=art.primary)
    stored = {stamp_of(t): r for t, r in zip(rows["ts"], rows.itertuples(), strict=True)}
    compared = 0
    for ts in stamp.values():
        e, r = live[ts], stored[ts]
        assert (round(r.value, 6), round(r.std, 6), r.quality) == (e["value"], e["std"],
                                                                   e["quality"])
        assert r.source == e["model"] and json.loads(r.lost) == e["lost"]
        compared += bool(e["lost"])
    assert compared >= 10


def test_an_estimate_at_an_earlier_instant_does_not_end_the_failover_spell(
        artifact: Artifact, today: pd.DataFrame) -> None:
    """The daemon scores a desk reading at its own stamp, a little behind the references':
    that estimate ended the spell and the next restarted it, moving the monitor's `since`."""
    twin = Twin(artifact, stale_after=STALE)
    silent_from = HOURS.at(TEST_DAY, 10.0)
    t = HOURS.at(TEST_DAY, 11.0 + 2.5 / 60)
    feed(twin, today, t, skip=R1, after=silent_from)
    assert twin.estimate(t)["triv"].quality is Quality.FALLBACK
    since = twin.failover_since
    assert since == t and twin.failover_lost == (R1,)
    earlier = twin.estimate(t - dt.timedelta(minutes=40))["triv"]  # R1 fresh back then
    assert earlier.quality is not Quality.FALLBACK
    assert twin.failover_since == since and twin.failover_lost == (R1,)
    twin.estimate(t + dt.timedelta(minutes=3))
    assert twin.failover_since == since


def test_a_failover_spell_between_two_grid_instants_is_told_on_the_monitor(
    mosquitto, artifact: Artifact, history: pd.DataFrame, tmp_path: Path
) -> None:
    """R2 silent from 10:02:30 to 10:42:30: the estimate failed over at 10:37:30 and came
    back at 10:42:30, between the 10:30 and 10:45 grid instants. The monitor compared the
    state at grid instants only, so no monitor ever told of the spell."""
    path = artifact.save(tmp_path / "desk.json")
    cfg = load_config(write_config(tmp_path, mosquitto.port, path))
    start, end = HOURS.at(TEST_DAY, 7.0), HOURS.at(TEST_DAY, 10.9)
    day = history[(history["ts"] >= start) & (history["ts"] < end)]
    gap = (day["sensor"] == R2) & (day["ts"] > HOURS.at(TEST_DAY, 10.05)) \
        & (day["ts"] < HOURS.at(TEST_DAY, 10.7))
    day = day[~gap]
    last_r2 = day.loc[(day["sensor"] == R2) & (day["ts"] < HOURS.at(TEST_DAY, 10.5)), "ts"].max()
    back = day.loc[(day["sensor"] == R2) & (day["ts"] > HOURS.at(TEST_DAY, 10.5)), "ts"].min()
    assert HOURS.at(TEST_DAY, 10.5) - last_r2 <= STALE < back - last_r2  # no tick sees it
    assert back < HOURS.at(TEST_DAY, 10.75)
    clock = HandClock(start)
    monitor = Viewer(mosquitto.port, "pt/desk/monitor")
    svc = Service(cfg, clock=clock)
    svc.start(wait_connected=15)
    try:
        replay(cfg, day, start, end, 1.0, clock=Lockstep(clock, svc))
        at = stamp_of(HOURS.at(TEST_DAY, 10.75))
        wait_for(lambda: any(m["ts"] == at for m in monitor.all()),
                 what="a monitor at 10:45 for the ended spell")
    finally:
        svc.stop()
        monitor.close()
    told = [(m["ts"], m["ended"]) for m in monitor.all() if m["ended"]]
    assert len(told) == 1 and told[0][0] == at
    (spell,) = told[0][1]
    assert spell["kind"] == "failover" and spell["lost"] == [R2]
    assert dt.datetime.fromisoformat(spell["since"]) - last_r2 > STALE
    assert dt.datetime.fromisoformat(spell["until"]) == back
    assert all(m["failover"] is None for m in monitor.all())


def test_each_reduced_twin_chooses_its_own_smoothing_span(
    history: pd.DataFrame, monkeypatch: pytest.MonkeyPatch
) -> None:
    """triv-smooth's span is chosen on the training days for the full twin and again for each
    twin without one reference: what suits two references need not suit one (the full twin's
    choice was handed down once, and pinned the failover's)."""
    from pseudotwin.analysis import validation

    asked: list[tuple[tuple[str, ...], dict[str, object]]] = []
    choose = validation.choose_setting

    def spy(df, spec, days, kind, options=None, thinning=None):  # type: ignore[no-untyped-def]
        if kind == "triv-smooth":
            asked.append((spec.references, dict(options or {})))
        return choose(df, spec, days, kind, options, thinning)

    monkeypatch.setattr(validation, "choose_setting", spy)
    spec = TwinSpec((R1, R2), TARGET, Quantity.TEMPERATURE, HOURS)
    art = train_twin(history, spec, FIRST, 5, ("ref", "triv", "triv-smooth"), primary="triv")
    assert [refs for refs, _ in asked] == [(R1, R2), (R2,), (R1,)]
    assert all("span" not in options for _, options in asked)
    assert set(art.failover) == {R1, R2}
