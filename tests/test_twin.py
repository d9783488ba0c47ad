"""The rolling horizon inside the Twin: midnight rollover, DST days, duplicates, order."""

from __future__ import annotations

import datetime as dt

import pytest

from daemon_support import HOURS, REF
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin


@pytest.fixture(scope="module")
def art(desk_artifact) -> Artifact:
    return Artifact.load(desk_artifact)


def at(day: dt.date, h: float) -> dt.datetime:
    return HOURS.at(day, h)


def test_midnight_rollover_starts_a_fresh_window_with_the_carried_value(art) -> None:
    d1, d2 = dt.date(2012, 3, 20), dt.date(2012, 3, 21)
    a = Twin(art)
    for h in (8.0, 12.0, 18.0):
        a.observe(REF, at(d1, h), 20.0 + h / 10)
    a.observe(REF, at(d1, 23.0), 19.0)  # outside any window: only remembered
    assert a.day == d1 and len(a.window) == 3
    day2 = [(8.0, 18.0), (9.0, 18.5), (10.0, 19.0)]
    for h, v in day2:
        a.observe(REF, at(d2, h), v)
    assert a.day == d2
    assert [(r.hours, r.value) for r in a.window] == [(HOURS.init_start, 19.0), *day2]
    # a twin that only ever saw the last value of day 1 agrees exactly: nothing else leaks
    b = Twin(art)
    b.observe(REF, at(d1, 23.0), 19.0)
    for h, v in day2:
        b.observe(REF, at(d2, h), v)
    assert a.estimate(at(d2, 10.5)) == b.estimate(at(d2, 10.5))


def test_no_estimates_outside_the_window_and_init_before_day_start(art) -> None:
    d = dt.date(2012, 3, 20)
    t = Twin(art)
    t.observe(REF, at(d, 7.0), 17.0)  # like the training mornings (else `uncertain`)
    assert t.estimate(at(d, 7.0)) == {}  # before the init phase
    init = t.estimate(at(d, 7.75))
    assert {e.quality for e in init.values()} == {"init"}
    ok = t.estimate(at(d, 8.0))
    assert ok["corrgp-triv"].quality == "ok"
    assert t.estimate(at(d, 19.5)) == {}  # after day end


@pytest.mark.parametrize("day,utc_hour_of_8", [(dt.date(2012, 3, 25), 6),
                                              (dt.date(2012, 10, 28), 7)])
def test_dst_days_keep_wall_clock_operating_hours(art, day: dt.date, utc_hour_of_8: int) -> None:
    t = Twin(art)
    eight = at(day, 8.0)
    assert eight.astimezone(dt.UTC).hour == utc_hour_of_8
    t.observe(REF, at(day, 7.5), 15.0)
    t.observe(REF, eight, 15.5)
    assert [r.hours for r in t.window] == [7.5, 8.0]
    e = t.estimate(eight)["corrgp-triv"]
    assert e.quality == "ok" and 10 < e.value < 25
    # the last slot of the day still lies in the window on both DST days
    assert t.estimate(at(day, 19.0)) != {}


def test_duplicates_are_dropped_and_late_readings_inserted(art) -> None:
    d = dt.date(2012, 3, 20)
    a, b = Twin(art), Twin(art)
    pts = [(8.0, 20.0), (8.5, 20.4), (8.25, 20.2)]  # the last one arrives late
    for h, v in pts:
        assert a.observe(REF, at(d, h), v)
    assert not a.observe(REF, at(d, 8.0), 20.0)  # duplicate
    for h, v in sorted(pts):
        b.observe(REF, at(d, h), v)
    ea, eb = a.estimate(at(d, 9.0)), b.estimate(at(d, 9.0))
    for kind in ("corrgp-triv", "corrgp-lcm", "triv"):
        assert ea[kind].value == pytest.approx(eb[kind].value, rel=1e-9)
    assert not a.observe("not/a/reference", at(d, 9.0), 1.0)
    assert not a.observe(REF, at(dt.date(2012, 3, 19), 9.0), 1.0)  # a past day's window


def test_stale_reference_marks_estimates_stale(art) -> None:
    d = dt.date(2012, 3, 20)
    t = Twin(art, stale_after=dt.timedelta(minutes=30))
    t.observe(REF, at(d, 8.0), 17.0)  # like the training mornings (else `uncertain`)
    assert t.estimate(at(d, 8.25))["corrgp-triv"].quality == "ok"
    assert {e.quality for e in t.estimate(at(d, 9.0)).values()} == {"stale"}
    t.observe(REF, at(d, 9.0), 17.5)
    assert t.estimate(at(d, 9.0))["corrgp-triv"].quality == "ok"


def test_arrival_order_never_changes_estimates_even_without_carry_over(art) -> None:
    """The corrgp-triv level shift comes from the init phase: a late init reading counts."""
    d = dt.date(2012, 3, 20)
    pts = [(8.5, 20.0), (7.75, 18.0), (9.0, 20.5)]  # the init reading arrives second
    a, b = Twin(art), Twin(art)
    for h, v in pts:
        a.observe(REF, at(d, h), v)
    for h, v in sorted(pts):
        b.observe(REF, at(d, h), v)
    for kind, e in a.estimate(at(d, 9.5)).items():
        assert e.value == pytest.approx(b.estimate(at(d, 9.5))[kind].value, rel=1e-9), kind


def test_a_model_failing_in_the_init_phase_publishes_nothing_before_day_start(
    art, monkeypatch
) -> None:
    from pseudotwin.errors import NumericalError
    from pseudotwin.gp.posterior import IncrementalPosterior

    def broken(self, t, o, r):  # fault injection: every extension of the factor fails
        raise NumericalError("injected")

    monkeypatch.setattr(IncrementalPosterior, "add", broken)
    d = dt.date(2012, 3, 20)
    t = Twin(art)
    t.observe(REF, at(d, 7.6), 20.0)
    early = t.estimate(at(d, 7.75))
    assert early["corrgp-triv"].quality == "init" and not early["corrgp-triv"].publishable
    t.observe(REF, at(d, 8.0), 20.1)
    later = t.estimate(at(d, 8.1))["corrgp-triv"]
    assert (later.quality, later.model) == ("fallback", "triv") and later.publishable


def test_calibration_of_a_model_without_any_held_out_error_is_finite() -> None:
    import numpy as np

    from pseudotwin.live.calibration import SigmaCalibration

    c = SigmaCalibration.fit(np.array([1, 1, 2, 2]), np.array([8.0, 9.0, 8.0, 9.0]),
                             np.zeros(4), np.zeros(4))
    assert c.factor == 1.0 and 0.0 <= c.sigma(8.5, 0.0) < 1e-3


def test_estimating_a_subset_of_models_equals_estimating_all(art) -> None:
    """The daemon's per-reading estimate computes only the primary: the same value as when
    every model is estimated; a model the twin does not run is refused."""
    day = dt.date(2012, 3, 20)
    t = HOURS.at(day, 9.0)
    twin = Twin(art)
    twin.observe(REF, HOURS.at(day, 8.0), 17.0)
    twin.observe(REF, t, 17.6)
    every = twin.estimate(t)
    alone = twin.estimate(t, kinds=(art.primary,))
    assert list(alone) == [art.primary] and alone[art.primary] == every[art.primary]
    with pytest.raises(ValueError, match="does not run"):
        Twin(art, models=["triv"]).estimate(t, kinds=(art.primary,))


def _tracked_from(root: object, skip: set[int]) -> set[int]:
    """ids of the objects the cyclic garbage collector tracks that ``root`` reaches, not
    entering ``skip``, classes, modules or functions (shared by every twin)."""
    import gc
    import types

    shared = (type, types.ModuleType, types.FunctionType, types.BuiltinFunctionType,
              types.MethodType)
    seen: set[int] = set()
    todo = [root]
    while todo:
        o = todo.pop()
        if id(o) in seen or id(o) in skip or not gc.is_tracked(o) or isinstance(o, shared):
            continue
        seen.add(id(o))
        todo.extend(gc.get_referents(o))
    return seen


def test_a_day_of_points_adds_no_objects_for_the_garbage_collector_to_traverse(art) -> None:
    """A thousand twins' windows once made every full collection walk ~600 objects per twin
    by the evening; the day state now holds its points in tuples and arrays, so the tracked
    objects do not grow with the points (plain tuples are untracked at a collection)."""
    import gc

    d = dt.date(2012, 3, 20)
    twin = Twin(art)
    model_state = _tracked_from(art, set())

    def day_state_after(hours: float) -> int:
        h = 7.5 if not twin.window_size else twin.window[-1].hours + 5 / 60
        while h <= hours:
            twin.observe(REF, at(d, h), 18.0 + h / 10)
            twin.estimate(at(d, h))
            h += 5 / 60
        gc.collect()
        return len(_tracked_from(twin, model_state))

    morning = day_state_after(9.0)
    evening = day_state_after(18.5)
    assert twin.window_size > 120
    assert evening - morning < 10, (morning, evening)
