"""Choosing training days and training every model of a twin into one artifact."""

from __future__ import annotations

import datetime as dt
import logging
import time
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from pseudotwin.analysis import validation
from pseudotwin.analysis.criteria import select
from pseudotwin.analysis.failover import train_failover
from pseudotwin.analysis.validation import MIN_DAYS
from pseudotwin.core.horizon import OperatingHours, format_hhmm
from pseudotwin.core.series import DayReadings, require_sensors, split_days
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.core.thinning import Thinning, thin_history
from pseudotwin.errors import DataError
from pseudotwin.history.store import Store
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.calibration import SigmaCalibration
from pseudotwin.live.envelope import Envelope
from pseudotwin.models.base import TrainingSet, TwinModel
from pseudotwin.models.blend import BlendModel
from pseudotwin.models.registry import ALL_MODELS, build, model_class

log = logging.getLogger(__name__)

MIN_READINGS_PER_DAY = 4
SKIPPED_SHOWN = 10  # passed-over days (or runs of them) named in training's warning


def day_is_usable(day: DayReadings, sensors: Sequence[str], hours: OperatingHours) -> bool:
    """All sensors report (at least a few readings) within the operating hours."""
    return not _short_of(day, sensors, hours)


def _short_of(day: DayReadings, sensors: Sequence[str], hours: OperatingHours) -> list[str]:
    """What keeps ``day`` from training: each sensor with fewer than MIN_READINGS_PER_DAY
    readings in operating hours, and how many it has."""
    short = []
    for s in sensors:
        n = (int(np.sum(hours.in_operating_hours(day.series[s][0]))) if day.has(s) else 0)
        if n < MIN_READINGS_PER_DAY:
            short.append(f"{s} {n}")
    return short


def _skipped_days(days: Sequence[DayReadings], chosen: Sequence[DayReadings],
                  sensors: Sequence[str], hours: OperatingHours,
                  skip_days: Collection[dt.date]) -> list[str]:
    """Every calendar day from the first with readings to the last chosen that training
    passes over, and why: the sensors short of readings in operating hours (with their
    count), or no readings at all; consecutive days with the same reason as one range."""
    if not days:
        return []
    by_day = {d.day: d for d in days}
    taken = {d.day for d in chosen}
    runs: list[tuple[dt.date, dt.date, str]] = []
    day = days[0].day
    while day <= chosen[-1].day:
        if day not in taken and day not in skip_days:
            why = (f"{', '.join(_short_of(by_day[day], sensors, hours))} reading(s) in "
                   "operating hours" if day in by_day else "no readings")
            if runs and runs[-1][2] == why and runs[-1][1] == day - dt.timedelta(days=1):
                runs[-1] = (runs[-1][0], day, why)
            else:
                runs.append((day, day, why))
        day += dt.timedelta(days=1)
    return [f"{a}{'' if a == b else f' … {b}'} ({why})" for a, b, why in runs]


PLAUSIBLE = {Quantity.TEMPERATURE: (-40.0, 80.0), Quantity.CO2: (0.0, 10000.0)}
MIN_MEDIAN = {Quantity.CO2: 100.0}  # no air holds less CO2 (outdoors ≈ 420 ppm)
STUCK_TOLERANCE = 1e-9  # relative: one value, up to float rounding
#: A few glitches (a DS18B20's 85 °C) are neither another quantity's sensor nor a stuck one;
#: more of a sensor's training-day readings outside the plausible range are: °F run above
#: 80 on a warm day, ppm trained as °C far above.
MAX_IMPLAUSIBLE_SHARE = 0.01


def plausible_readings(df: pd.DataFrame, spec: TwinSpec,
                       ranges: Mapping[str, tuple[float, float]] | None = None,
                       warn: bool = True) -> pd.DataFrame:
    """The rows of ``df`` without the references' and the desk sensor's readings outside
    their range: ``ranges[sensor]`` (a configuration's min..max [unit]) or else the plausible
    range of the twin's quantity (:data:`PLAUSIBLE`), which is what the configuration
    ``train --report`` proposes gives them. The daemon rejects such readings live, so a
    −127 °C of a disconnected probe or an 850 °C glitch would otherwise set a profile, a σ or
    a day's score that the live twin never sees. warn: log how many per sensor. DataError when
    a sensor is left without any reading (another quantity's sensor)."""
    sensor = df["sensor"]
    value = df["value"].to_numpy(dtype=float)
    outside = np.zeros(len(df), dtype=bool)
    said = []
    for s in spec.sensors:
        lo, hi = (ranges or {}).get(s, PLAUSIBLE[spec.quantity])
        own = (sensor == s).to_numpy()
        v = value[own]
        out = (v < lo) | (v > hi)  # NaN is neither: the series' reader drops it
        if not out.any():
            continue
        if out.all():
            raise _implausible(s, spec, float(np.nanmedian(v)), 1.0, lo, hi)
        outside[own] = out
        first = df[own][out].iloc[0]
        said.append(f"{s}: {int(out.sum())} outside {lo:g} … {hi:g} {spec.unit} (e.g. "
                    f"{first['value']:g} at {first['ts']})")
    if not outside.any():
        return df
    if warn:
        log.warning("left out %d reading(s) outside their sensor's range, as the daemon leaves "
                    "them out: %s (without train --config the plausible range of a %s, which "
                    "the configuration train --report proposes gives them)",
                    int(outside.sum()), "; ".join(said), spec.quantity.value)
    return df[~outside]


def _implausible(sensor: str, spec: TwinSpec, median: float, outside: float, lo: float,
                 hi: float, when: str = "") -> DataError:
    """The error of a sensor whose readings are not the twin's quantity; ``outside``: their
    share outside lo..hi [unit]."""
    hint = ("" if outside >= 1.0 else " (A probe that failed then: --skip-days leaves those "
            "days out; train --config applies the sensor's own min..max.)")
    return DataError(f"sensor {sensor}: readings implausible for the quantity "
                     f"{spec.quantity.value} (median {median:.4g} {spec.unit}, "
                     f"{100 * outside:.0f} % outside {lo:g} … {hi:g} {spec.unit}{when}); is it "
                     f"another quantity's sensor, or the wrong --quantity?{hint}")


def check_plausible(df: pd.DataFrame, spec: TwinSpec) -> None:
    """DataError naming the sensor and the quantity when a reference's or the target's
    readings ``df`` (those of the training days, before any is left out) do not look like
    that quantity (CO2 data trained as temperature writes °C; °F are not °C: more than
    :data:`MAX_IMPLAUSIBLE_SHARE` outside the plausible range), or when they never change
    (a stuck sensor: nothing about its coupling to the others can be learnt, and every live
    reading that moves would lie outside what training saw)."""
    lo, hi = PLAUSIBLE[spec.quantity]
    for s in spec.sensors:
        rows = df[df["sensor"] == s]
        v = rows["value"].to_numpy(dtype=float)
        v = v[np.isfinite(v)]
        if not len(v):
            continue
        inside = (v >= lo) & (v <= hi)
        outside, med = 1.0 - float(np.mean(inside)), float(np.median(v))
        if outside > MAX_IMPLAUSIBLE_SHARE or med < MIN_MEDIAN.get(spec.quantity, lo):
            raise _implausible(s, spec, med, outside, lo, hi, " on the training days")
        rows, v_all, v = rows[rows["value"].between(lo, hi)], v, v[inside]  # glitches out
        med = float(np.median(v))
        # Judged on the 1st–99th percentiles, as a few glitches inside the range remain;
        # with a tolerance because a value's float sums (minute means) differ in the last bits.
        q_lo, q_hi = np.quantile(v, [MAX_IMPLAUSIBLE_SHARE, 1 - MAX_IMPLAUSIBLE_SHARE])
        tol = STUCK_TOLERANCE * max(1.0, abs(med))
        if len(v) > 1 and q_hi - q_lo <= tol:
            share = float(np.mean(np.abs(v_all - med) <= tol))
            raise DataError(
                f"sensor {s}: reads {med:.6g} {spec.unit} throughout the training days "
                f"({100 * share:.1f} % of its readings); is it stuck or disconnected? Nothing "
                f"can be learnt from it: train on other days (--train-start, --skip-days) or "
                f"with another sensor"
            )
        _warn_stuck_days(rows, s, spec, tol)


def _warn_stuck_days(readings: pd.DataFrame, sensor: str, spec: TwinSpec, tol: float) -> None:
    """Warn of training days on which ``sensor`` reads one value throughout the operating
    hours, up to 1 % of glitches (at least one, as a day has few readings): stuck for a
    while, or a change-of-value sensor's quiet day; either way those days show nothing of its
    coupling. Not refused: the other days may carry enough."""
    values = readings["value"].to_numpy(dtype=float)
    ok = np.isfinite(values)
    day, hours = spec.hours.day_and_hours(readings.loc[ok, "ts"])
    inside = spec.hours.in_operating_hours(hours)
    day, values = day[inside], values[ok][inside]
    days = sorted(set(day))
    flat = []
    for d in days:
        v = values[day == d]
        glitches = int(np.sum(np.abs(v - np.median(v)) > tol))
        allowed = max(1, int(MAX_IMPLAUSIBLE_SHARE * len(v)))
        if len(v) >= MIN_READINGS_PER_DAY and glitches <= allowed:
            flat.append(str(d))
    if flat:
        log.warning(
            "sensor %s reads one value throughout the operating hours of %s (%d of %d "
            "training days): stuck or disconnected then? Those days show nothing of how it "
            "moves with the others; --skip-days %s leaves them out (a sensor that reports "
            "only on change may just have had a quiet day)", sensor, ", ".join(flat),
            len(flat), len(days), ",".join(flat))


def choose_training_days(
    df: pd.DataFrame,
    sensors: Sequence[str],
    hours: OperatingHours,
    start: dt.date,
    n_days: int = 5,
    extra: Sequence[str] = (),
    skip_days: Collection[dt.date] = (),
) -> tuple[list[DayReadings], list[dt.date]]:
    """The first ``n_days`` days on or after ``start`` on which every sensor reports, none of
    ``skip_days`` (days the engineer leaves out, e.g. of commissioning work); the days also
    carry the ``extra`` sensors' readings (covariates), whether or not they report. Returns
    the days and those of ``skip_days`` left out that would have been training days (every
    sensor reports on them, and they come before the last one chosen)."""
    if n_days < 1:
        raise DataError("--train-days must be at least 1")
    days = [d for d in split_days(df, [*sensors, *extra], hours) if d.day >= start]
    usable = [d for d in days if day_is_usable(d, sensors, hours)]
    left_out = [d.day for d in usable if d.day in skip_days]
    usable = [d for d in usable if d.day not in skip_days]
    if len(usable) < n_days:
        raise DataError(
            f"too little training data: {len(usable)} day(s) from {start} on have at least "
            f"{MIN_READINGS_PER_DAY} readings of each of {', '.join(sensors)} in operating "
            f"hours ({hours.describe()}){_not_counting(left_out)}, {n_days} needed"
            f"{_fewer_days_hint(n_days, len(usable))}"
        )
    chosen = usable[:n_days]
    if skipped := _skipped_days(days, chosen, sensors, hours, skip_days):
        more = f"; and {len(skipped) - SKIPPED_SHOWN} more" if len(skipped) > SKIPPED_SHOWN else ""
        log.warning("training skips days without %d readings of every sensor in operating "
                    "hours: %s%s", MIN_READINGS_PER_DAY, "; ".join(skipped[:SKIPPED_SHOWN]),
                    more)
    left_out = [d for d in left_out if d <= chosen[-1].day]
    if left_out:
        log.info("training leaves out %s, as asked", ", ".join(map(str, left_out)))
    if unused := sorted(set(skip_days) - set(left_out)):
        log.warning("--skip-days %s: would not have been a training day (before %s, after %s, "
                    "or without data of every sensor): nothing left out",
                    ", ".join(map(str, unused)), start, chosen[-1].day)
    return chosen, left_out


def _fewer_days_hint(n_days: int, usable: int) -> str:
    """How to train on fewer days, when ``usable`` ones (≥ 1) would do (--train-days)."""
    if n_days <= 1 or usable < 1:
        return ""
    return (f" (--train-days sets how many; the primary is chosen and σ calibrated by "
            f"validation from {MIN_DAYS} days on, the more days the surer)")


def _not_counting(left_out: Sequence[dt.date]) -> str:
    return f", not counting {len(left_out)} left out by --skip-days" if left_out else ""


def train_twin(
    df: pd.DataFrame,
    spec: TwinSpec,
    train_start: dt.date,
    train_days: int = 5,
    models: Sequence[str] = ALL_MODELS,
    options: dict[str, dict[str, Any]] | None = None,
    primary: str | None = None,
    validate: bool = True,
    thinning: Thinning | None = None,
    skip_days: Collection[dt.date] = (),
) -> Artifact:
    """Train the requested models of one twin on the chosen days; returns the artifact.
    See :func:`train_validated`."""
    return train_validated(df, spec, train_start, train_days, models, options, primary,
                           validate, thinning, skip_days)[0]


def train_validated(
    df: pd.DataFrame,
    spec: TwinSpec,
    train_start: dt.date,
    train_days: int = 5,
    models: Sequence[str] = ALL_MODELS,
    options: dict[str, dict[str, Any]] | None = None,
    primary: str | None = None,
    validate: bool = True,
    thinning: Thinning | None = None,
    skip_days: Collection[dt.date] = (),
    ranges: Mapping[str, tuple[float, float]] | None = None,
) -> tuple[Artifact, validation.Validation | None]:
    """Train the requested models of one twin on the chosen days; returns the artifact
    and the validation it came from (None when not validated), whose held-out estimates the
    commissioning report shows. Readings of the references and the desk outside their
    range (``ranges``, a configuration's, else the quantity's plausible one) are left out
    (:func:`plausible_readings`).

    options: kind → settings of that model (see each model's ``options``). validate: hold
    out each training day to choose the primary (unless ``primary`` pins it) and calibrate
    every model's σ (:mod:`pseudotwin.analysis.validation`); without it, or with fewer than
    three days, the primary is ``primary`` or the first candidate and σ is each model's own.
    Validated twins with several references also get a failover per reference the primary
    reads, and with three or more one per reference alone
    (:mod:`pseudotwin.analysis.failover`). thinning: the live window's policy (default
    one point per sensor and minute): the models learn from the points it holds
    (:func:`~pseudotwin.core.thinning.thin_history`), and the held-out days are replayed
    reading by reading through it, as the daemon would. skip_days: days never used for
    training, even when every sensor reports on them.
    """
    for kind in models:
        model_class(kind)  # an unknown kind fails before any training
    skipped = {k: why for k in models if (why := model_class(k).not_applicable(spec))}
    for kind, why in skipped.items():
        log.info("%s is not trained: %s", kind, why)
    models = [k for k in models if k not in skipped]
    if not models:
        raise DataError("none of the models asked for can serve this twin: "
                        + "; ".join(f"{k}: {w}" for k, w in skipped.items()))
    if all(model_class(k).stacked for k in models):
        raise DataError(f"{', '.join(models)} is made from other models: ask for at least two "
                        "candidates too (e.g. --models ref,triv,blend)")
    sensors = list(spec.sensors)
    require_sensors(df, [*sensors, *spec.covariates])
    raw = df[df["sensor"].isin(sensors)]
    df = plausible_readings(df, spec, ranges)
    policy = thinning or Thinning()
    # The models learn from the points the live window will hold (one per sensor and
    # interval), so a chatty sensor's history trains the twin its interval means would.
    points = thin_history(df[df["sensor"].isin([*sensors, *spec.covariates])], policy)
    days, left_out = choose_training_days(points, sensors, spec.hours, train_start,
                                          train_days, spec.covariates, skip_days)
    # Judged on the training days only (a sensor broken some other week must not stop this),
    # on their readings as they came: a share left out above may say it is not this quantity.
    local_day, _ = spec.hours.day_and_hours(raw["ts"])
    check_plausible(raw[np.isin(local_day, [np.datetime64(d.day) for d in days])], spec)
    ts = TrainingSet(spec, tuple(days))
    fitted: dict[str, TwinModel] = {}
    opts = dict(options or {})
    validated = validate and len(days) >= MIN_DAYS
    # A setting a model leaves to validation (VARMA's order) is chosen before the model is
    # fit, so the fit, its validation and the artifact all have the chosen value.
    opts, tuned = validation.choose_settings(df, spec, days, models if validated else (), opts,
                                             policy)
    for kind, choice in tuned.items():
        log.info("%s: %s (validation on the training days)", kind, choice.reason)
    if too_few := [k for k in models if model_class(k).min_days > len(days)]:
        for kind in too_few:
            log.info("%s is not trained: it needs at least %d training days, %d given", kind,
                     model_class(kind).min_days, len(days))
        models = [k for k in models if k not in too_few]
        if not models:
            raise DataError(f"none of the models asked for can learn from {len(days)} "
                            "training day(s): ask for more days")
        if primary in too_few:
            raise DataError(f"primary {primary!r} needs at least "
                            f"{model_class(primary).min_days} training days")
    for kind in models:
        if model_class(kind).stacked:
            continue  # made from the others after validation
        t0 = time.perf_counter()
        fitted[kind] = build(kind, opts.get(kind)).fit(ts)
        log.info("trained %s in %.1f s", kind, time.perf_counter() - t0)
    if primary is not None and primary not in models:
        raise DataError(f"primary {primary!r} is not among the trained models")
    if primary is not None and model_class(primary).stacked and not validated:
        raise DataError(f"primary {primary!r} is made from validation's held-out scores; "
                        f"it needs validation on at least {MIN_DAYS} training days")
    calibration: dict[str, SigmaCalibration] = {}
    checked: dict[str, Any] = {}
    v: validation.Validation | None = None
    stacked = [k for k in models if model_class(k).stacked]
    if validated:
        v = validation.validate(df, spec, days, [*fitted, *stacked], opts, primary, policy)
        primary, calibration, checked = v.primary, v.calibration, v.to_dict()
        if tuned:
            checked["tuned"] = {k: c.to_dict() for k, c in tuned.items()}
        log.info("validated on the training days in %.1f s; primary %s", v.seconds, v.reason)
        if v.blend and "blend" in stacked:
            fitted["blend"] = BlendModel({k: fitted[k] for k in v.blend}, v.blend).fit(ts)
        elif "blend" in stacked:
            log.info("blend is not built: %s", v.scores["blend"].error)
        if primary not in fitted:  # pinned, but it could not be made
            raise DataError(f"primary {primary!r} could not be built: "
                            f"{v.scores[primary].error}")
    else:
        if stacked:
            log.info("%s not built: made from validation's held-out scores, and there is no "
                     "validation", ", ".join(stacked))
        if primary is None:
            primary = next((k for k, m in fitted.items() if m.candidate), next(iter(fitted)))
    withheld = dict(checked.get("withheld", {}))
    for kind, m in fitted.items():
        if (problem := m.publish_problem()) and kind != primary:
            withheld[kind] = problem
    for kind, why in withheld.items():
        log.warning("%s is not published live: %s", kind, why)
    for kind, m in fitted.items():
        if not m.live_baseline and kind != primary and kind not in withheld:
            # Every published model costs the daemon its work and a message per grid step.
            withheld[kind] = f"a variant, run live only as the primary (validation chose {primary})"
            log.info("%s is not published live: %s", kind, withheld[kind])
    if validated:
        for kind in fitted:
            if kind not in calibration and kind not in withheld:
                log.warning("%s has no σ calibration (it failed validation); it publishes its "
                            "own spread, which is not calibrated", kind)
    if checked or withheld:
        checked = {**checked, "withheld": withheld}
    # `uncertain` acts only by criteria the held-out days show to flag larger errors; without
    # validation nothing shows that, so no criterion acts.
    envelope = Envelope.fit(ts)
    envelope = (select(envelope, v.held_out, primary, calibration.get(primary), spec.hours)
                if v is not None else envelope.keeping(frozenset(), 1.0))
    log.info("self-aware indication (quality uncertain): %s",
             ", ".join(sorted(envelope.kept or ())) or "no criterion kept")
    # Failover needs validated σ, like the primary it stands in for.
    # the user's options: a setting validation chose for the full twin is chosen anew for
    # each reduced one
    failover, alone = (train_failover(df, spec, days, fitted[primary].references_,
                                      options=options, thinning=policy)
                       if v is not None else ({}, {}))
    return Artifact(
        spec, fitted, primary, calibration=calibration, validation=checked,
        envelope=envelope, failover=failover, failover_alone=alone,
        training={
            "start": str(days[0].day),
            "end": str(days[-1].day),
            "days": [str(d.day) for d in days],
            # what the engineer left out (--skip-days) where it would have been a training day
            **({"skipped": [str(d) for d in left_out]} if left_out else {}),
            "sensors": [*sensors, *spec.covariates],
            "thinning": policy.describe(),
            # per sensor read live: what check-config compares the configuration's with
            "min_interval_seconds": {s: policy.interval(s).total_seconds()
                                     for s in spec.inputs},
        },
    ), v


def first_full_day(first: dt.datetime, hours: OperatingHours) -> dt.date:
    """The first local day whose data, beginning at ``first``, covers its init phase: the
    day of ``first``, or the next when the data begins mid-day."""
    day = hours.day_of(first)
    if hours.hours_of(first) <= hours.init_start:
        return day
    log.info("training begins on %s: the data begins on %s at %s local time, after the "
             "init phase (--train-start %s trains on that day too)", day + dt.timedelta(days=1),
             day, format_hhmm(hours.hours_of(first)), day)
    return day + dt.timedelta(days=1)


def require_stored(store: Store, sensors: Sequence[str],
                   name: str = "the history store") -> None:
    """DataError naming those of ``sensors`` without any reading in ``store`` (``name``)."""
    if silent := [s for s in sensors if store.reading_range([s]) is None]:
        raise DataError(f"{name} has no readings of {', '.join(silent)}")


def history_from_store(
    store: Store,
    sensors: Sequence[str],
    hours: OperatingHours,
    start: dt.date | None = None,
    n_days: int = 5,
    skip_days: Collection[dt.date] = (),
    extra: Sequence[str] = (),
) -> tuple[pd.DataFrame, dt.date]:
    """The readings needed to train on the first ``n_days`` usable days in the store (every
    one of ``sensors`` reports in operating hours), none of ``skip_days``; the ``extra``
    sensors' (covariates') readings come along, whether or not they report, as
    :func:`choose_training_days` takes them from a file.

    Streams the store one day at a time from ``start`` (default: the first full day of the
    sensors' readings) and keeps only the usable days and the day before each (its
    carry-over, the day before the first included), and the days between them (so that
    training can say why it passed them over), so a year of history is never loaded.
    A usable day of ``skip_days`` is kept too, so that training can say it left it out.
    Returns the frame and the first usable day, a left-out one included.
    """
    # One sensor without any reading (a typo, a sensor never recorded) is named, rather than
    # counted as too few usable days.
    require_stored(store, sensors)
    span = store.reading_range(list(sensors))
    assert span is not None  # every sensor has readings
    first = start or first_full_day(span[0], hours)
    last = hours.day_of(span[1])
    kept: list[pd.DataFrame] = []
    chosen: list[dt.date] = []
    left_out: list[dt.date] = []
    prev: pd.DataFrame | None = None
    read = [*sensors, *extra]
    # From the day before the first: its evening is the first day's carry-over, as in a file.
    for day, frame in store.iter_days(read, first - dt.timedelta(days=1), last, hours.timezone):
        both = frame if prev is None else pd.concat([prev, frame], ignore_index=True)
        if day >= first and not frame.empty and day_is_usable(
                split_days(both, read, hours, [day])[0], sensors, hours):
            kept.append(both)
            (left_out if day in skip_days else chosen).append(day)
            if len(chosen) == n_days:
                break
        elif kept:  # a day passed over among the training days: why it was, as from a file
            kept.append(frame)
        prev = frame
    if len(chosen) < n_days:
        raise DataError(
            f"too little training data in the store: {len(chosen)} day(s) from {first} on "
            f"have at least {MIN_READINGS_PER_DAY} readings of each of {', '.join(sensors)} "
            f"in operating hours ({hours.describe()}){_not_counting(left_out)}, "
            f"{n_days} needed{_fewer_days_hint(n_days, len(chosen))}"
        )
    df = pd.concat(kept, ignore_index=True).drop_duplicates(["sensor", "ts"])
    # A covariate the store holds, but not on these days, was reported as "not found; file
    # has: ..." (a bare-number sensor replayed through the recorder is stamped on arrival).
    if absent := [c for c in extra if not (df["sensor"] == c).any()]:
        spans = []
        for c in absent:
            got = store.reading_range([c])
            spans.append(f"{c}: no readings in the store" if got is None else
                         f"{c}: stored from {got[0].isoformat()} to {got[1].isoformat()}")
        raise DataError(
            f"covariate(s) {', '.join(absent)} have no readings on the training days "
            f"{min(chosen)} … {max(chosen)} ({'; '.join(spans)}); leave them out of "
            "--covariates, or train on days when they were recorded")
    return df.sort_values("ts", kind="stable").reset_index(drop=True), min([*chosen, *left_out])
