"""Covariates (issue Trust II): other live sensors that a model may use, kept only where
validation on the training days says they help.

Synthetic twins whose truth is known: the desk's temperature follows the reference plus a
term in a CO2 covariate's deviation from its usual day (people warm the desk side of the
room); a second covariate is noise that drives nothing. Then the plumbing: configuration,
artifact round trip, the live twin reading the covariate.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from daemon_support import HandClock, Lockstep, Viewer, wait_for
from pseudotwin.analysis.commissioning.snippet import config_snippet
from pseudotwin.analysis.evaluate import evaluate
from pseudotwin.analysis.replay import ESTIMATE, replay_estimates
from pseudotwin.analysis.training import train_twin
from pseudotwin.cli import _artifact_check
from pseudotwin.config import check_config, load_config
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.edge.replay import replay
from pseudotwin.edge.service import Service
from pseudotwin.errors import ConfigError, DataError
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin
from pseudotwin.models.covariate import MAX_AGE_H, TrivCovModel, _consistent

HOURS = OperatingHours(timezone="UTC")
DAY0 = dt.date(2024, 3, 4)
STEP_H = 0.25
N = 52  # 07:00 … 19:45 on the 15-min grid
GAIN = 0.004  # [°C/ppm] the desk's warming per ppm of CO2 above the usual day


def _smooth(rng: np.random.Generator, days: int, scale: float, length: int) -> np.ndarray:
    raw = rng.normal(size=(days, N + length))
    kernel = np.ones(length) / np.sqrt(length)
    return scale * np.array([np.convolve(r, kernel, mode="valid")[:N] for r in raw])


def _frame(series: dict[str, np.ndarray], days: int) -> pd.DataFrame:
    rows = []
    for d in range(days):
        base = pd.Timestamp(DAY0 + dt.timedelta(days=d), tz="UTC") + pd.Timedelta(hours=7)
        ts = base + pd.to_timedelta(np.arange(N) * STEP_H, unit="h")
        for name, values in series.items():
            rows.append(pd.DataFrame({"sensor": name, "ts": ts, "value": values[d]}))
    return pd.concat(rows, ignore_index=True).sort_values("ts", kind="stable")


def _house(seed: int, days: int) -> pd.DataFrame:
    """ref, desk, co2 (drives the desk), noise (drives nothing)."""
    rng = np.random.default_rng(seed)
    h = 7.0 + np.arange(N) * STEP_H
    ref = 21.0 + np.sin((h - 7) / 12 * np.pi)[None, :] + _smooth(rng, days, 0.2, 8)
    occupied = _smooth(rng, days, 150.0, 10)  # the day's own occupancy pattern [ppm]
    co2 = 600.0 + 200.0 * np.sin((h - 7) / 12 * np.pi)[None, :] + occupied
    noise = 50.0 + _smooth(rng, days, 10.0, 6)
    desk = ref + 0.8 + GAIN * occupied + rng.normal(0.0, 0.03, size=(days, N))
    return _frame({"ref": ref, "desk": desk, "room/co2": co2, "noise": noise}, days)


def _spec(covariates: tuple[str, ...]) -> TwinSpec:
    return TwinSpec(("ref",), "desk", Quantity.TEMPERATURE, HOURS, covariates)


@pytest.fixture(scope="module")
def house() -> pd.DataFrame:
    return _house(3, 12)


@pytest.fixture(scope="module")
def with_co2(house: pd.DataFrame) -> Artifact:
    return train_twin(house, _spec(("noise", "room/co2")), DAY0, 5,
                      models=["ref", "triv", "triv-cov"])


def test_a_covariate_that_drives_the_target_is_picked_by_validation(with_co2: Artifact) -> None:
    model = with_co2.models["triv-cov"]
    assert isinstance(model, TrivCovModel)
    assert model.covariates_ == ("room/co2",)  # the noise was tried and left out
    assert model.beta_[0] == pytest.approx(GAIN, rel=0.25)
    assert with_co2.primary == "triv-cov", with_co2.validation["reason"]
    scores = with_co2.validation["scores"]
    assert scores["triv-cov"]["nrmse_pct"] < 0.7 * scores["triv"]["nrmse_pct"]
    assert "room/co2" in model.fit_summary() and "triv-cov" in with_co2.published


def test_an_irrelevant_covariate_is_not_picked(house: pd.DataFrame) -> None:
    art = train_twin(house, _spec(("noise",)), DAY0, 5, models=["ref", "triv", "triv-cov"])
    model = art.models["triv-cov"]
    assert isinstance(model, TrivCovModel) and model.covariates_ == ()
    assert art.primary == "triv", art.validation["reason"]  # same score, simpler
    assert "triv-cov" in art.withheld and "triv-cov" not in art.published


def test_the_covariate_helps_on_days_after_training(with_co2: Artifact,
                                                    house: pd.DataFrame) -> None:
    rows = replay_estimates(with_co2, house, DAY0 + dt.timedelta(days=5))
    err = {m: float(np.sqrt(np.mean((g["value"] - g["truth"]) ** 2)))
           for m, g in rows.groupby("model")}
    assert err[ESTIMATE] == err["triv-cov"] and err["triv-cov"] < 0.6 * err["triv"]


def test_artifact_round_trip_and_live_twin(with_co2: Artifact, tmp_path: Path,
                                           house: pd.DataFrame) -> None:
    path = tmp_path / "desk.json"
    with_co2.save(path)
    loaded = Artifact.load(path)
    assert loaded.covariates == ("noise", "room/co2")
    a = replay_estimates(with_co2, house, DAY0 + dt.timedelta(days=5))
    b = replay_estimates(loaded, house, DAY0 + dt.timedelta(days=5))
    pd.testing.assert_frame_equal(a, b, check_exact=True)
    # live: the covariate's reading enters the window and moves the estimate
    twin = Twin(loaded, models=["triv-cov"])
    day = DAY0 + dt.timedelta(days=7)
    t = dt.datetime.combine(day, dt.time(10), dt.UTC)
    assert twin.observe("ref", t, 21.5)
    before = twin.estimate(t)["triv-cov"].value
    assert twin.observe("room/co2", t, 1500.0)
    after = twin.estimate(t)["triv-cov"].value
    assert after > before + 0.5 * GAIN * 500
    # a covariate silent for longer than MAX_AGE_H corrects nothing any more
    late = t + dt.timedelta(hours=MAX_AGE_H + 0.5)
    assert twin.observe("ref", late, 21.5)
    triv_only = Twin(loaded, models=["triv"])
    triv_only.observe("ref", late, 21.5)
    assert twin.estimate(late)["triv-cov"].value == triv_only.estimate(late)["triv"].value


def test_a_covariate_far_outside_the_training_days_corrects_no_more_than_they_showed(
        with_co2: Artifact) -> None:
    model = with_co2.models["triv-cov"]
    assert isinstance(model, TrivCovModel)
    (lo, hi), = model.dev_range_
    assert lo < 0 < hi  # the training days' deviations, both ways
    t = dt.datetime.combine(DAY0 + dt.timedelta(days=7), dt.time(10), dt.UTC)
    twin = Twin(with_co2, models=["triv"])
    assert twin.observe("ref", t, 21.5)
    triv = twin.estimate(t)["triv"].value
    corrections = []
    for ppm in (3000.0, 30000.0, -5000.0):  # a drifted or broken CO2 sensor
        twin = Twin(with_co2, models=["triv-cov"])
        twin.observe("ref", t, 21.5)
        twin.observe("room/co2", t, ppm)
        corrections.append(twin.estimate(t)["triv-cov"].value - triv)
    beta = float(model.beta_[0])
    assert corrections[0] == pytest.approx(beta * hi) == pytest.approx(corrections[1])
    assert corrections[2] == pytest.approx(beta * lo)
    assert abs(corrections[1]) < 0.5 * abs(beta * (30000.0 - 1000.0))  # not extrapolated


def test_a_gain_on_average_only_or_a_flipping_relation_is_not_kept() -> None:
    before = np.array([1.0, 1.0, 1.0, 1.0, 1.0])
    steady = np.array([[0.5], [0.4], [0.6], [0.5], [0.5]])  # each fold's β of the covariate
    assert _consistent(before, np.array([0.9, 0.8, 0.9, 0.9, 1.1]), steady)  # one day worse
    # the mean drops by a third, carried by two days; two others get worse
    assert not _consistent(before, np.array([0.2, 0.3, 1.0, 1.1, 1.2]), steady)
    flipping = np.array([[0.5], [0.4], [-0.6], [0.5], [0.5]])
    assert not _consistent(before, np.array([0.9, 0.8, 0.9, 0.9, 0.9]), flipping)
    # an earlier covariate's β may flip: only the one just added is judged
    two = np.column_stack([np.array([1.0, -1.0, 1.0, 1.0, 1.0]), steady[:, 0]])
    assert _consistent(before, np.array([0.9, 0.8, 0.9, 0.9, 0.9]), two)


def test_an_older_artifact_without_deviation_ranges_still_loads(with_co2: Artifact) -> None:
    d = with_co2.to_dict()
    del d["models"]["triv-cov"]["dev_range"]
    model = Artifact.from_dict(d).models["triv-cov"]
    assert isinstance(model, TrivCovModel)
    assert np.all(np.isinf(model.dev_range_))  # unclipped, as it was trained


def test_a_twin_without_covariates_does_not_train_the_model(house: pd.DataFrame) -> None:
    art = train_twin(house, _spec(()), DAY0, 5, models=["triv", "triv-cov"], validate=False)
    assert list(art.models) == ["triv"]
    with pytest.raises(DataError, match="no covariates"):
        train_twin(house, _spec(()), DAY0, 5, models=["triv-cov"], validate=False)


def test_covariates_are_checked() -> None:
    with pytest.raises(ConfigError, match="also listed"):
        _spec(("ref",))
    with pytest.raises(ConfigError, match="listed twice"):
        _spec(("co2", "co2"))
    # a configuration must name the covariates its artifact was trained with
    assert _spec(("noise",)).differences(_spec(()), "the artifact's") == [
        "covariates noise differ from the artifact's (none)"]
    assert _spec(("a", "b")).differences(_spec(("b", "a"))) == []
    with pytest.raises(DataError, match="noise2"):
        train_twin(_house(4, 6), _spec(("noise2",)), DAY0, 5, models=["triv-cov"])


# ------------------------------------------------------------------ through the daemon


def _config(folder: Path, port: int, artifact: Path) -> Path:
    sensors = "".join(f"""
[[sensors]]
id = "{s}"
topic = "house/{s}"
unit = "{unit}"
min = {lo}
max = {hi}
""" for s, unit, lo, hi in (("ref", "°C", -10, 50), ("desk", "°C", -10, 50),
                             ("room/co2", "ppm", 0, 5000), ("noise", "lx", -1000, 1000)))
    text = f"""
[broker]
host = "127.0.0.1"
port = {port}
client_id = "pt-covariates-{folder.name}"

[service]
base_topic = "pt"
timezone = "UTC"
state_dir = "state"
{sensors}
[[twins]]
id = "desk"
references = ["ref"]
covariates = ["noise", "room/co2"]
target = "desk"
quantity = "temperature"
artifact = "{artifact}"
"""
    p = folder / "config.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_the_daemon_reads_the_covariates_like_evaluate(
    mosquitto, with_co2: Artifact, house: pd.DataFrame, tmp_path: Path
) -> None:
    """A CO2 covariate of another unit (ppm for a °C twin) is subscribed to, and every live
    estimate equals evaluate's for the same readings."""
    path = with_co2.save(tmp_path / "desk.json")
    cfg = load_config(_config(tmp_path, mosquitto.port, path))
    assert set(cfg.twins["desk"].inputs) == {"ref", "noise", "room/co2"}
    day = DAY0 + dt.timedelta(days=8)
    start = dt.datetime.combine(day, dt.time(7), dt.UTC)
    end = dt.datetime.combine(day, dt.time(12), dt.UTC)
    readings = house[(house["ts"] >= start) & (house["ts"] < end)]
    offline = replay_estimates(Artifact.load(path), readings, day)
    offline = offline[offline["model"] == ESTIMATE]
    want = {t.isoformat().replace("+00:00", "Z"): (round(v, 6), round(sd, 6))
            for t, v, sd in zip(offline["ts"], offline["value"], offline["std"], strict=True)}
    clock = HandClock(start)  # moves with the replay only: no tick overtakes a reading
    viewer = Viewer(mosquitto.port)

    def last_per_instant() -> dict[str, tuple[float, float]]:
        return {e["ts"]: (e["value"], e["std"]) for e in viewer.all()}

    svc = Service(cfg, clock=clock)
    svc.start(wait_connected=15)
    try:
        replay(cfg, readings, start, end, 1.0, clock=Lockstep(clock, svc))
        # Until the last reading's estimate is out: stopping earlier (the first version of
        # this test) left the last instant without its covariates' estimates.
        wait_for(lambda: all(last_per_instant().get(ts) == w for ts, w in want.items()),
                 what="at every instant, a last estimate equal to evaluate's")
    finally:
        svc.stop()
        viewer.close()
    assert all(e["model"] == "triv-cov" for e in viewer.all())
    assert len(want) == readings["ts"].dt.hour.ge(8).groupby(readings["ts"]).any().sum()
    assert last_per_instant().items() >= want.items()


def test_the_commissioning_config_names_the_covariates(with_co2: Artifact,
                                                       tmp_path: Path) -> None:
    path = with_co2.save(tmp_path / "desk.json")
    toml = tmp_path / "twin.toml"
    toml.write_text(config_snippet(with_co2, path, "desk"), encoding="utf-8")
    cfg = check_config(toml, artifact_check=_artifact_check)  # raises on any problem
    assert cfg.twins["desk"].covariates == ("noise", "room/co2")
    assert {"noise", "room/co2"} <= set(cfg.sensors)


def test_evaluate_scores_the_models_that_serve_the_twin(house: pd.DataFrame) -> None:
    """Asked for every kind, evaluate scores those training kept (the last stop's results
    run failed on a one-reference twin without covariates)."""
    ev = evaluate(house, _spec(()), DAY0, 5, ("triv", "triv-cov", "corrgp-multi"))
    assert list(ev.artifact.models) == ["triv"]
    assert set(ev.daily["model"]) == {"triv", ESTIMATE, "ref:ref"}


def test_backfill_skips_a_day_whose_references_are_missing_though_its_covariates_report(
    with_co2: Artifact, house: pd.DataFrame, tmp_path: Path, capsys
) -> None:
    """Covariates alone give nothing the daemon publishes: such a day is skipped and not
    marked done, so readings of the reference imported later are backfilled (it was marked
    done with stale rows only, and a rerun called it 'already backfilled')."""
    from pseudotwin.cli import main
    from pseudotwin.history.store import open_store

    path = with_co2.save(tmp_path / "desk.json")
    cfg = _config(tmp_path, 1883, path)
    db = tmp_path / "history.db"
    day = DAY0 + dt.timedelta(days=8)
    of_day = house["ts"].dt.date == day
    with open_store(str(db)) as store:
        store.write_readings(house[of_day & (house["sensor"] != "ref")])
    text = cfg.read_text(encoding="utf-8").replace('state_dir = "state"',
                                                   f'state_dir = "state"\nstore = "{db}"')
    cfg.write_text(text, encoding="utf-8")
    args = ["backfill", "--config", str(cfg), "--twin", "desk", "--from", str(day), "--to",
            str(day), "--quiet"]
    assert main(args) == 0
    assert f"skipped 1 day(s), no reference readings: {day}" in capsys.readouterr().out
    with open_store(str(db)) as store:
        assert store.read_estimates("desk").empty
        store.write_readings(house[of_day & (house["sensor"] == "ref")])
    assert main(args) == 0
    assert "backfilled 1 day(s)" in capsys.readouterr().out
    with open_store(str(db)) as store:
        assert set(store.read_estimates("desk")["quality"]) == {"ok"}
