"""The TRIV-mean Corr-GP over several references (corrgp-multi, issue 10 "Trust II").

Synthetic twin whose truth is known: two references share the season's daily level and each
carries its own smooth deviation from the typical day (independent GP draws, zero in the
init phase: the day's deviations build up once the building opens); the desk follows them
with known weights, target deviation = 0.7·dev1 + 0.3·dev2 + noise. corrgp-triv reads the
first reference only, so the 0.3·dev2 part is invisible to it; corrgp-multi must learn both
weights from five training days and use both references live.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import normalize, split_days
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin
from pseudotwin.models.base import TrainingSet, TwinModel
from pseudotwin.models.corrgp import CorrGpMulti, CorrGpTriv
from pseudotwin.models.registry import ALL_MODELS

HOURS = OperatingHours(timezone="UTC")  # 08:00–19:00, init from 07:30, 15-min slots
REFS = ("wall/temp", "ceiling/temp")
TARGET = "desk/temp"
SPEC = TwinSpec(REFS, TARGET, Quantity.TEMPERATURE, HOURS)
DAY0 = dt.date(2024, 3, 4)
TRAIN_DAYS, TEST_DAYS = 4, 3
WEIGHTS = np.array([0.7, 0.3])  # the known coupling: target deviation on dev1, dev2
GRID = 7.5 + 0.25 * np.arange(47)  # 07:30 … 19:00 [h]


def _deviations(rng: np.random.Generator, n_days: int) -> np.ndarray:
    """[n_days, 2, len(GRID)] smooth deviations: squared-exponential GP draws (ℓ = 1.5 h,
    σ = 0.5 K), ramped in from 08:00 to 09:00 so that they vanish in the init phase."""
    d = GRID[:, None] - GRID[None, :]
    K = 0.25 * np.exp(-0.5 * (d / 1.5) ** 2) + 1e-8 * np.eye(len(GRID))
    L = np.linalg.cholesky(K)
    ramp = np.clip(GRID - 8.0, 0.0, 1.0)
    return np.einsum("ij,dkj->dki", L, rng.standard_normal((n_days, 2, len(GRID)))) * ramp


def _history(seed: int = 3, n_days: int = TRAIN_DAYS + TEST_DAYS) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    dev = _deviations(rng, n_days)
    shape = 1.2 * np.sin((GRID - 7.5) / 11.5 * np.pi)  # the typical day's course
    rows = []
    for k in range(n_days):
        day = DAY0 + dt.timedelta(days=k)
        level = 21.0 + rng.normal(0.0, 1.0)  # the season: every sensor alike
        refs = [level + shape + dev[k, 0], level - 0.8 + 0.6 * shape + dev[k, 1]]
        desk = level + 0.5 + 0.8 * shape + WEIGHTS @ dev[k] + rng.normal(0.0, 0.02, len(GRID))
        ts = [HOURS.at(day, float(h)) for h in GRID]
        for sensor, values in ((REFS[0], refs[0]), (REFS[1], refs[1]), (TARGET, desk)):
            noisy = values + (0.0 if sensor == TARGET else rng.normal(0.0, 0.01, len(GRID)))
            rows += [(sensor, t, float(v)) for t, v in zip(ts, noisy, strict=True)]
    return normalize(pd.DataFrame(rows, columns=["sensor", "ts", "value"]))


def _days(df: pd.DataFrame, first: int, n: int, spec: TwinSpec = SPEC) -> list:
    days = [DAY0 + dt.timedelta(days=first + k) for k in range(n)]
    return split_days(df, list(spec.sensors), spec.hours, days)


def _replay_rmse(model: TwinModel, test_days: list) -> float:
    """RMSE of the causal live estimate at every desk reading of the test days [K]: each
    reference reading is observed in time order and the desk estimated right after."""
    errs = []
    for day in test_days:
        est = model.start_day(day.day)
        th = day.series[TARGET][0]
        truth = day.series[TARGET][1]
        readings = sorted((h, s, v) for s in model.references_
                          for h, v in zip(*day.series[s], strict=True))
        i = 0
        for h, y in zip(th, truth, strict=True):
            while i < len(readings) and readings[i][0] <= h:
                est.observe(readings[i][1], readings[i][0], readings[i][2])
                i += 1
            if HOURS.day_start <= h <= HOURS.day_end:
                errs.append(est.predict(float(h)).value - y)
    return float(np.sqrt(np.mean(np.square(errs))))


@pytest.fixture(scope="module")
def history() -> pd.DataFrame:
    return _history()


@pytest.fixture(scope="module")
def training(history: pd.DataFrame) -> TrainingSet:
    return TrainingSet(SPEC, tuple(_days(history, 0, TRAIN_DAYS)))


@pytest.fixture(scope="module")
def multi(training: TrainingSet) -> CorrGpMulti:
    # RBF: the kernel the deviations are drawn from (the RQ default only fits slower here)
    return CorrGpMulti(kernel="rbf", restarts=1).fit(training)


def test_registered_after_corrgp_triv_before_corrgp_lcm() -> None:
    # the registry's order decides validation's ties: the simpler model first
    order = list(ALL_MODELS)
    assert order.index("corrgp-triv") < order.index("corrgp-multi") < order.index("corrgp-lcm")


def test_a_multi_reference_model_recovers_a_known_coupling(
    multi: CorrGpMulti, training: TrainingSet, history: pd.DataFrame,
) -> None:
    # The target's prior mean is TRIV, which weighs both references 1/2; the GP's coupling β
    # is the rest: the learnt weights are 1/2 + β.
    weights = 0.5 + multi.coupling()
    assert weights == pytest.approx(WEIGHTS, abs=0.1), weights
    single = CorrGpTriv(kernel="rbf", restarts=1).fit(training)  # the first reference only
    test = _days(history, TRAIN_DAYS, TEST_DAYS)
    rmse_multi, rmse_single = _replay_rmse(multi, test), _replay_rmse(single, test)
    # corrgp-triv cannot see 0.3·dev2 (σ 0.15 K); corrgp-multi is left with the noise
    assert rmse_multi < 0.5 * rmse_single, (rmse_multi, rmse_single)
    assert rmse_multi < 0.08, rmse_multi


def test_with_one_reference_it_is_exactly_corrgp_triv(history: pd.DataFrame) -> None:
    spec = TwinSpec(REFS[:1], TARGET, Quantity.TEMPERATURE, HOURS)
    ts = TrainingSet(spec, tuple(_days(history, 0, 3, spec)))
    a, b = CorrGpTriv(restarts=1).fit(ts), CorrGpMulti(restarts=1).fit(ts)
    assert b.params_.to_dict() == a.params_.to_dict()
    (day,) = _days(history, TRAIN_DAYS, 1, spec)
    ea, eb = a.start_day(day.day), b.start_day(day.day)
    for h, v in zip(*day.series[REFS[0]], strict=True):
        ea.observe(REFS[0], float(h), float(v))
        eb.observe(REFS[0], float(h), float(v))
        assert eb.predict(float(h)) == ea.predict(float(h))


def test_artifact_round_trip_gives_identical_estimates(
    multi: CorrGpMulti, history: pd.DataFrame, tmp_path: Path,
) -> None:
    art = Artifact(SPEC, {"corrgp-multi": multi}, "corrgp-multi")
    loaded = Artifact.load(art.save(tmp_path / "desk.json"))
    m = loaded.models["corrgp-multi"]
    assert isinstance(m, CorrGpMulti) and m.references_ == REFS
    assert np.array_equal(m.coupling(), multi.coupling())
    day = history[history["ts"] >= pd.Timestamp(DAY0 + dt.timedelta(days=TRAIN_DAYS), tz="UTC")]
    a, b = Twin(art), Twin(loaded)
    seen = 0
    for r in day.itertuples():
        if r.sensor == TARGET:
            continue
        t = r.ts.to_pydatetime()
        a.observe(r.sensor, t, r.value)
        b.observe(r.sensor, t, r.value)
        ea, eb = a.estimate(t), b.estimate(t)
        assert ea == eb
        seen += "corrgp-multi" in ea
    assert seen > 100  # the model answered, not only its fallbacks


def test_bad_settings_are_refused_clearly(training: TrainingSet) -> None:
    from pseudotwin.errors import DataError

    with pytest.raises(DataError, match=r"corrgp-multi references nowhere/temp are not"):
        CorrGpMulti(references=("nowhere/temp",)).fit(training)
    with pytest.raises(DataError, match=r"ref_mean must be"):
        CorrGpMulti(ref_mean="level").fit(training)
