"""VARMA baseline on real data (SML2010), real statsmodels.

Training: five days from 2012-03-14, dining-room temperature as the reference, the room
temperature as the target; test days follow. The VARMAX(4, 4) fit is done once per module
(about 15 s for two series); the OLS fallback fits are instant.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from statsmodels.tsa.statespace.varmax import VARMAX

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.series import DayReadings, split_days
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.models.base import TrainingSet, TwinModel
from pseudotwin.models.triv import TrivModel
from pseudotwin.models.varma import VarmaDay, VarmaModel

DATA = Path("/work/shared/data/sml2010/NEW-DATA-1.T15.txt")
REF = "dining/temp"
TARGET = "room/temp"
TRAIN_START = dt.date(2012, 3, 14)
TEST_DAYS = [dt.date(2012, 3, 19) + dt.timedelta(days=i) for i in range(7)]
HOURS = OperatingHours(timezone="Europe/Madrid")

pytestmark = pytest.mark.skipif(not DATA.exists(), reason="SML2010 data not available")


# -- data -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def frame() -> pd.DataFrame:
    """Canonical long frame (sensor, ts UTC, value) of the two temperatures."""
    raw = pd.read_csv(DATA, sep=r"\s+", skiprows=1, header=None)
    local = pd.to_datetime(raw[0] + " " + raw[1], format="%d/%m/%Y %H:%M")
    # The DST night of 2012-03-25 has no 02:xx wall clock; such rows cannot be placed.
    ts = local.dt.tz_localize("Europe/Madrid", ambiguous="NaT", nonexistent="NaT")
    parts = [
        pd.DataFrame({"sensor": name, "ts": ts.dt.tz_convert("UTC"), "value": raw[col]})
        for col, name in ((2, REF), (3, TARGET))
    ]
    df = pd.concat(parts, ignore_index=True).dropna()
    df["value"] = df["value"].astype(float)
    return df.sort_values(["ts", "sensor"], kind="stable").reset_index(drop=True)


@pytest.fixture(scope="module")
def training(frame: pd.DataFrame) -> TrainingSet:
    days = [TRAIN_START + dt.timedelta(days=i) for i in range(5)]
    return TrainingSet(TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS),
                       tuple(split_days(frame, [REF, TARGET], HOURS, days)))


@pytest.fixture(scope="module")
def test_days(frame: pd.DataFrame) -> dict[dt.date, DayReadings]:
    return {d.day: d for d in split_days(frame, [REF, TARGET], HOURS, TEST_DAYS)}


@pytest.fixture(scope="module")
def varma(training: TrainingSet) -> VarmaModel:
    """The default model (VARMAX(4, 4), trend n, target_mode shifted), fitted once."""
    return VarmaModel().fit(training)


@pytest.fixture(scope="module")
def fallback(training: TrainingSet) -> VarmaModel:
    return VarmaModel(force_fallback=True).fit(training)


# -- helpers ----------------------------------------------------------------------------
def run_day(model: VarmaModel, day: DayReadings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replay a day causally: each true target reading in operating hours is predicted from
    the reference readings up to its time. Returns (estimate, std, truth), each [n]."""
    events = [(h, 0, v) for h, v in zip(*day.series[REF], strict=True)]
    events += [
        (h, 1, v) for h, v in zip(*day.series[TARGET], strict=True)
        if HOURS.in_operating_hours(h)
    ]
    events.sort(key=lambda e: (e[0], e[1]))  # a reference reading at t may be used at t
    est = model.start_day(day.day)
    out = []
    for h, kind, v in events:
        if kind == 0:
            est.observe(REF, h, v)
        else:
            e = est.predict(h)
            out.append((e.value, e.std, v))
    a = np.array(out)
    return a[:, 0], a[:, 1], a[:, 2]


def rmse(est: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean((est - truth) ** 2)))


def feed_all(model: VarmaModel, day: DayReadings, sensor: str = REF) -> VarmaDay:
    est = model.start_day(day.day)
    for h, v in zip(*day.series[sensor], strict=True):
        est.observe(sensor, h, v)
    return est


def slot_starts() -> np.ndarray:
    return HOURS.window_slots() * HOURS.slot_hours


# -- fit --------------------------------------------------------------------------------
def test_fit_returns_self_and_sets_fitted_attributes(
    training: TrainingSet, varma: VarmaModel
) -> None:
    model = VarmaModel(force_fallback=True)
    assert model.fit(training) is model
    m = varma
    S = len(HOURS.window_slots())
    assert m.profile_.shape == (S, 2) and np.isfinite(m.profile_).all()
    assert m.train_day0_ == TRAIN_START
    assert m.references_ == (REF,) and m.target_ == TARGET
    assert m.model_name_ in ("varma", "var-fallback")
    assert m.converged_ == (m.model_name_ == "varma")
    assert m.order_ == ((4, 4) if m.converged_ else (4, 0))
    assert len(m.params_) == len(m.param_names_) and np.isfinite(m.params_).all()
    assert m.fit_message_
    # statsmodels' identification warning is silenced on the console but kept.
    assert any("identification" in w for w in m.fit_warnings_)
    # The profile is the training days' mean per window slot.
    tgt = np.array([d.slot_values(TARGET, HOURS) for d in training.days])
    np.testing.assert_allclose(m.profile_[:, 1], tgt.mean(axis=0))


def test_init_stores_settings_only() -> None:
    m = VarmaModel(p=2, q=1, trend="c", maxiter=5)
    assert (m.p, m.q, m.trend, m.maxiter) == (2, 1, "c", 5)
    assert not [k for k in vars(m) if k.endswith("_")]


def test_fallback_ols_recovers_known_var(training: TrainingSet) -> None:
    """The OLS VAR lands in the right VARMAX parameter slots (A[0, 1] is 'L1.y2.y1')."""
    rng = np.random.default_rng(3)
    a = np.array([[0.8, 0.15], [-0.1, 0.5]])
    slots = HOURS.window_slots()
    starts = slots * HOURS.slot_hours
    days = []
    for i in range(40):
        y = np.zeros((len(slots), 2))
        y[0] = rng.normal(size=2)
        for t in range(1, len(slots)):
            y[t] = a @ y[t - 1] + rng.normal(scale=0.1, size=2)
        days.append(DayReadings(
            TRAIN_START + dt.timedelta(days=i),
            {"a": (starts, y[:, 0] + 20.0), "b": (starts, y[:, 1] + 21.0)},
        ))
    ts = TrainingSet(TwinSpec(("a",), "b", Quantity.TEMPERATURE, HOURS), tuple(days))
    m = VarmaModel(p=1, trend="n", force_fallback=True, target_mode="level").fit(ts)
    got = dict(zip(m.param_names_, m.params_, strict=True))
    est = np.array([[got["L1.y1.y1"], got["L1.y2.y1"]], [got["L1.y1.y2"], got["L1.y2.y2"]]])
    np.testing.assert_allclose(est, a, atol=0.06)
    assert got["sqrt.var.y1"] == pytest.approx(0.1, rel=0.15)
    np.testing.assert_allclose(m.ssm_.transition[:2, :2], est)


# -- live -------------------------------------------------------------------------------
def test_estimates_on_first_test_day_beat_a_constant(
    varma: VarmaModel, fallback: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    """The default (trend n) right after training: below the day's spread of the truth."""
    for model in (varma, fallback):
        est, std, truth = run_day(model, test_days[TEST_DAYS[0]])
        assert np.isfinite(est).all() and np.isfinite(std).all() and (std > 0).all()
        assert rmse(est, truth) < 0.8 * truth.std()


def test_the_default_does_not_drift_away_over_a_week_of_test_days(
    varma: VarmaModel, fallback: VarmaModel, training: TrainingSet,
    test_days: dict[dt.date, DayReadings],
) -> None:
    """No trend is extrapolated beyond the training days (issue Trust I, item 5): over the
    week after training the default (trend n, in its VARMAX and its least-squares form, the
    one validation deploys) stays within 1.5× TRIV's mean daily RMSE, the limit beyond which
    VARMA is not published live. The drift term ``ct`` of the thesis's VARMA, extrapolated
    day after day, is far outside it: the same check fails for it."""

    def mean_daily_rmse(model: TwinModel) -> float:
        return float(np.mean([rmse(*run_day(model, test_days[d])[::2]) for d in TEST_DAYS]))

    triv = mean_daily_rmse(TrivModel().fit(training))
    drifting = mean_daily_rmse(VarmaModel(trend="ct", force_fallback=True).fit(training))
    assert drifting > 1.5 * triv
    for model in (varma, fallback):
        assert mean_daily_rmse(model) <= 1.5 * triv, model.model_name


def test_trend_c_tracks_the_target_on_every_test_day(
    training: TrainingSet, test_days: dict[dt.date, DayReadings]
) -> None:
    """Without the drift term, VAR(4) stays well below the truth's daily spread.

    Measured (2012-03-19 … 25): RMSE 0.33–0.85 K; the truth's std is 1.4–2.4 K except on
    the flat 2012-03-20 (0.36 K), where any model's level error dominates.
    """
    m = VarmaModel(trend="c", force_fallback=True).fit(training)
    for day in TEST_DAYS:
        est, std, truth = run_day(m, test_days[day])
        assert np.isfinite(est).all() and np.isfinite(std).all()
        err = rmse(est, truth)
        assert err < 1.0, day
        if truth.std() > 1.0:
            assert err < 0.5 * truth.std(), day


def test_causal_a_later_reading_does_not_change_an_earlier_estimate(
    varma: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    day = test_days[TEST_DAYS[2]]
    hrs, vals = day.series[REF]
    cut = 10.1  # [h] 10:06, between slot starts
    est = varma.start_day(day.day)
    for h, v in zip(hrs, vals, strict=True):
        if h <= cut:
            est.observe(REF, h, v)
    before = [est.predict(h) for h in (7.6, 9.0, 9.99, cut)]
    est.observe(REF, 10.2, vals[hrs <= cut][-1] + 5.0)  # a wild later reading
    after = [est.predict(h) for h in (7.6, 9.0, 9.99, cut)]
    assert before == after
    # …while it does change the next slot's estimate.
    fresh = varma.start_day(day.day)
    for h, v in zip(hrs, vals, strict=True):
        if h <= cut:
            fresh.observe(REF, h, v)
    assert est.predict(10.25) != fresh.predict(10.25)


def test_out_of_order_reading_recomputes_the_cache(
    varma: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    day = test_days[TEST_DAYS[1]]
    hrs, vals = day.series[REF]
    late = int(np.flatnonzero(np.isclose(hrs, 9.5))[0])  # 09:30 arrives last
    in_order = feed_all(varma, day)
    shuffled = varma.start_day(day.day)
    for i, (h, v) in enumerate(zip(hrs, vals, strict=True)):
        if i != late:
            shuffled.observe(REF, h, v)
    probe = [8.0, 9.5, 12.0, 18.9]
    stale = [shuffled.predict(h) for h in probe]  # fills the cache without 09:30
    shuffled.observe(REF, hrs[late], vals[late])
    assert [shuffled.predict(h) for h in probe] == [in_order.predict(h) for h in probe]
    assert stale[2] != in_order.predict(12.0)


def test_predict_is_cached_between_slots(
    varma: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    est = feed_all(varma, test_days[TEST_DAYS[0]])
    est.predict(12.0)
    n = est.n_filtered
    for h in np.linspace(12.0, 12.24, 20):
        est.predict(float(h))
    assert est.n_filtered == n
    # A reading inside the current slot only affects later slots: no refilter.
    est.observe(REF, 12.1, 30.0)
    assert est.n_filtered == n


def test_the_cache_is_bounded_and_earlier_slots_are_filtered_again_alike(
    varma: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    """Estimates of earlier times, asked after the day went on, equal those made live, while
    the cache holds the newest slots and a checkpoint every EVERY slots only. (From day
    start: the init phase's later readings still move today's level shift.)"""
    day = test_days[TEST_DAYS[0]]
    est = varma.start_day(day.day)
    live = {}
    for h, v in zip(*day.series[REF], strict=True):
        est.observe(REF, h, v)
        if h >= HOURS.day_start:
            live[float(h)] = est.predict(float(h))
    slots = est.n_filtered
    assert slots > 4 * VarmaDay.EVERY
    assert est.n_kept <= 2 * VarmaDay.KEEP + slots // VarmaDay.EVERY + 2
    assert {h: est.predict(h) for h in live} == live
    assert est.n_filtered == slots


def test_target_and_unknown_sensors_are_ignored(
    varma: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    day = test_days[TEST_DAYS[0]]
    a = feed_all(varma, day)
    b = feed_all(varma, day)
    b.observe(TARGET, 9.0, 99.0)
    b.observe("elsewhere/temp", 9.0, 99.0)
    b.observe(REF, 9.0, float("nan"))
    assert a.predict(15.0) == b.predict(15.0)


def test_before_the_window_gives_the_prior(
    varma: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    est = feed_all(varma, test_days[TEST_DAYS[0]])
    e = est.predict(HOURS.init_start - 0.5)
    assert math.isfinite(e.value) and e.std > est.predict(HOURS.init_start).std


def _statsmodels_filter(
    model: VarmaModel, est: VarmaDay, day: dt.date
) -> tuple[np.ndarray, np.ndarray]:
    """statsmodels' filtered target (mean incl. profile, std) per window slot: [S] each."""
    endog = est.observations()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mod = VARMAX(
            endog, order=model.order_, trend=model.trend, trend_offset=model.trend_offset(day)
        )
    res = mod.filter(model.params_, cov_type="none")
    t = len(model.sensors_) - 1
    mean = res.filtered_state[t] + model.profile_[:, t] + est.shift
    std = np.sqrt(res.filtered_state_cov[t, t])
    return mean, std


def _varma_with_ma(fallback: VarmaModel) -> VarmaModel:
    """A VARMA(4, 4) with non-zero MA terms whatever the default fit did (via the artifact)."""
    d = json.loads(json.dumps(fallback.to_dict()))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the VARMA identification warning
        names = VARMAX(np.zeros((3, 2)), order=(4, 4), trend="ct").param_names
    given = dict(zip(d["param_names"], d["params"], strict=True))
    rng = np.random.default_rng(0)
    d["params"] = [given.get(n, float(rng.normal(scale=0.05))) for n in names]
    d["param_names"] = names
    d["order"] = [4, 4]
    d["model_name"] = "varma"
    del d["state_space"]  # the fallback's matrices: rebuilt from the new params
    return VarmaModel.from_dict(d, TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS))


@pytest.mark.parametrize("which", ["varma", "fallback", "with-ma"])
def test_incremental_filter_equals_statsmodels(
    which: str, request: pytest.FixtureRequest, test_days: dict[dt.date, DayReadings]
) -> None:
    if which == "with-ma":
        model = _varma_with_ma(request.getfixturevalue("fallback"))
    else:
        model = request.getfixturevalue(which)
    for day_i, silent_until in ((0, None), (4, 9.0)):
        day = test_days[TEST_DAYS[day_i]]
        est = model.start_day(day.day)
        for h, v in zip(*day.series[REF], strict=True):
            if silent_until is None or h >= silent_until:  # NaN slots before the first reading
                est.observe(REF, h, v)
        got = [est.predict(float(h)) for h in slot_starts()]
        mean, std = _statsmodels_filter(model, est, day.day)
        np.testing.assert_allclose([e.value for e in got], mean, rtol=0, atol=1e-8)
        np.testing.assert_allclose([e.std for e in got], std, rtol=0, atol=1e-8)
        # The live sample-and-hold equals history's on the same readings.
        if silent_until is None:
            ref = day.slot_values(REF, HOURS) - model.profile_[:, 0] - est.shift
            np.testing.assert_array_equal(est.observations()[:, 0], ref)
        else:
            assert np.isnan(est.observations()[0, 0])
        assert np.isnan(est.observations()[:, 1]).all()


# -- artifact ---------------------------------------------------------------------------
@pytest.mark.parametrize("which", ["varma", "fallback"])
def test_round_trip_gives_identical_predictions(
    which: str, request: pytest.FixtureRequest, test_days: dict[dt.date, DayReadings]
) -> None:
    model = request.getfixturevalue(which)
    d = json.loads(json.dumps(model.to_dict()))
    assert d["model_name"] == model.model_name_ and d["train_day0"] == "2012-03-14"
    back = VarmaModel.from_dict(d, TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS))
    assert back.model_name_ == model.model_name_ and back.converged_ == model.converged_
    day = test_days[TEST_DAYS[3]]
    a, b = feed_all(model, day), feed_all(back, day)
    probe = np.linspace(7.0, 19.0, 97)
    assert [a.predict(float(h)) for h in probe] == [b.predict(float(h)) for h in probe]


@pytest.mark.parametrize("which", ["varma", "fallback"])
def test_stored_matrices_equal_those_rebuilt_from_params(
    which: str, request: pytest.FixtureRequest, test_days: dict[dt.date, DayReadings]
) -> None:
    """The artifact's state_space (what the daemon loads, without statsmodels) is the model
    its params define (what an older artifact gives)."""
    model = request.getfixturevalue(which)
    d = json.loads(json.dumps(model.to_dict()))
    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    stored = VarmaModel.from_dict(d, spec)
    del d["state_space"]
    rebuilt = VarmaModel.from_dict(d, spec)
    day = test_days[TEST_DAYS[2]]
    a, b = feed_all(stored, day), feed_all(rebuilt, day)
    probe = np.linspace(7.0, 19.0, 49)
    # BLAS may round the Lyapunov solve differently between fit and load: 1e-9, not bits
    np.testing.assert_allclose([a.predict(float(h)).value for h in probe],
                               [b.predict(float(h)).value for h in probe], rtol=0, atol=1e-9)
    np.testing.assert_allclose([a.predict(float(h)).std for h in probe],
                               [b.predict(float(h)).std for h in probe], rtol=0, atol=1e-9)


def test_stored_matrices_are_checked(fallback: VarmaModel) -> None:
    from pseudotwin.errors import ArtifactError

    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    d = json.loads(json.dumps(fallback.to_dict()))
    d["state_space"]["selection"] = d["state_space"]["selection"][:-1]
    with pytest.raises(ArtifactError, match="selection has shape"):
        VarmaModel.from_dict(d, spec)
    d = json.loads(json.dumps(fallback.to_dict()))
    d["state_space"]["transition"] = (1.5 * np.eye(len(d["state_space"]["transition"]))).tolist()
    with pytest.raises(ArtifactError, match="not stationary"):
        VarmaModel.from_dict(d, spec)
    d = json.loads(json.dumps(fallback.to_dict()))
    d["state_space"]["obs_cov"][0][0] = math.inf
    with pytest.raises(ArtifactError, match="non-finite"):
        VarmaModel.from_dict(d, spec)


def test_the_daemon_loads_an_artifact_without_statsmodels(
    desk_artifact: Path,
) -> None:
    """statsmodels (~50 MB) is for fitting: loading a twin for live use does not import it."""
    import subprocess
    import sys

    code = ("import sys; from pseudotwin.live.artifact import Artifact; "
            "from pseudotwin.live.twin import Twin; import pseudotwin.edge.service; "
            f"Twin(Artifact.load({str(desk_artifact)!r})); "
            "print(sorted(m for m in ('statsmodels', 'scipy.stats', 'GPy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"


def test_from_dict_rejects_a_different_slot_grid(fallback: VarmaModel) -> None:
    from pseudotwin.errors import ArtifactError

    d = fallback.to_dict()
    with pytest.raises(ArtifactError, match="slot grid"):
        hours9 = OperatingHours(day_start=9.0, timezone="Europe/Madrid")
        VarmaModel.from_dict(d, TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, hours9))
    with pytest.raises(ArtifactError, match="trained on"):
        VarmaModel.from_dict(d, TwinSpec(("hall/temp",), TARGET, Quantity.TEMPERATURE, HOURS))


# -- fallback ---------------------------------------------------------------------------
def test_forced_fallback_is_labelled_and_sensible(
    fallback: VarmaModel, test_days: dict[dt.date, DayReadings]
) -> None:
    # asked for (as training does with the order validation chose): "var", not a fallback
    assert fallback.model_name_ == "var" and fallback.converged_ is True
    assert fallback.order_ == (4, 0)
    assert "least squares" in fallback.fit_message_
    est, _, truth = run_day(fallback, test_days[TEST_DAYS[0]])
    assert rmse(est, truth) < 0.8 * truth.std()


@pytest.mark.parametrize(
    ("settings", "reason"),
    [({"maxiter": 0}, "did not converge"), ({"max_seconds": 0.0}, "did not finish")],
)
def test_unconverged_varmax_falls_back(
    training: TrainingSet, fallback: VarmaModel, settings: dict, reason: str
) -> None:
    m = VarmaModel(**settings).fit(training)
    assert m.model_name_ == "var-fallback" and not m.converged_
    assert reason in m.fit_message_ and "least squares" in m.fit_message_
    np.testing.assert_array_equal(m.params_, fallback.params_)


def test_no_reference_reading_yet_gives_no_estimate(varma: VarmaModel) -> None:
    """The filter's prior is the typical day, not a measurement: without any reference
    reading (a reference that never reported) VARMA published one as the twin's baseline."""
    est = varma.start_day(TEST_DAYS[0])
    assert math.isnan(est.predict(9.0).value)
    est.observe(REF, 8.5, 17.0)
    assert math.isfinite(est.predict(9.0).value)
