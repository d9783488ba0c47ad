"""The twin: one pseudo-measurement stream, driven reading by reading.

Everything that produces estimates — the daemon, ``evaluate`` and ``backfill`` — feeds a
:class:`Twin` the same way (``observe`` readings in arrival order, ``estimate`` at an instant),
so a live estimate and an offline one for the same readings are identical.

The twin owns the rolling horizon (DESIGN.md §2): a day's window opens at the init start with
the last known value of each reference carried in, it closes at day end, and the next day
starts from scratch. Model state is only ever built from the window's points. Readings are
thinned into points by one policy (core/thinning.py: at most one point per reference and
``min_interval``, its value the mean of that interval's readings so far), so a chatty
sensor costs the models no more than one reading a minute.
"""

from __future__ import annotations

import bisect
import datetime as dt
import logging
import math
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from pseudotwin.core.series import DayReadings
from pseudotwin.core.thinning import Action, Thinning, WindowThinner
from pseudotwin.errors import NumericalError
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.calibration import SLOPE_WINDOW_H, SigmaCalibration
from pseudotwin.live.failover import ranked
from pseudotwin.models.base import DayEstimator, Estimate, TwinModel

log = logging.getLogger(__name__)


#: Ended uncertain/failover spells kept for the monitor between two of its messages.
ENDED_SPELLS_KEPT = 20
#: How old a reading before the day may be to give the day's carry-over.
MAX_CARRY = dt.timedelta(hours=24)


class Quality(StrEnum):
    """How far to trust a published estimate (the payload's ``quality``).

    ok: the model answered from fresh references; init: the init phase before day start
    (never published); stale: a reference it needs has been silent longer than
    ``stale_after``; fallback: the model failed numerically and a simpler one answered, or
    (failover, live/failover.py) a reference it needs is silent or missing and the artifact's
    validated candidate without that reference answered, with its own calibrated σ
    (:attr:`TwinEstimate.lost` names the silent references; ``stale`` then only when no
    failover can answer from fresh references);
    uncertain: a reference it needs is outside its training range by a criterion validation
    kept (level, deviation from its daily profile, or speed; live/envelope.py), so σ is
    widened by the envelope's ``widen`` and :attr:`TwinEstimate.why` says why.

    One estimate has one quality; precedence init > stale > fallback > uncertain > ok: the
    init phase is never published, a silent reference or a failed model is the bigger news.
    """

    OK = "ok"
    INIT = "init"
    STALE = "stale"
    FALLBACK = "fallback"
    UNCERTAIN = "uncertain"

@dataclass(frozen=True)
class TwinEstimate:
    """One model's estimate of the target at ``ts``.

    value, std: [°C] or [ppm]; model: what produced the value (``triv`` on fallback,
    ``var`` for VARMA as VAR(p), ``var-fallback`` when VARMAX did not converge; the
    failover's kind when a reference is
    lost); refs: sensor → time of its last reading; why: what is unlike training when the
    quality is ``uncertain``; lost: the silent references a failover answered without;
    unlike: the keys of every envelope criterion that fired on an ``ok``/``uncertain``
    estimate, kept or not, when the twin records them (``record_unlike``, or a criterion
    acts); what validation judges the criteria on (live/envelope.py).
    """

    ts: dt.datetime
    value: float
    std: float
    model: str
    quality: Quality
    refs: dict[str, dt.datetime | None] = field(default_factory=dict)
    why: tuple[str, ...] = ()
    lost: tuple[str, ...] = ()
    unlike: tuple[str, ...] = ()

    @property
    def finite(self) -> bool:
        return math.isfinite(self.value)

    @property
    def publishable(self) -> bool:
        """What the daemon publishes (and backfill stores): nothing in the init phase, and
        no estimate without a value."""
        return self.quality != Quality.INIT and self.finite


@dataclass(frozen=True)
class WindowReading:
    """A point of today's window: wall-clock hours [h]; value is the mean of the readings
    thinned into it (core/thinning.py)."""

    sensor: str
    ts: dt.datetime
    hours: float
    value: float


class Twin:
    """Runs every model of an artifact over the live window.

    models: the kinds to run (default: the artifact's published ones); its primary model is
    reported under ``"estimate"`` by the service, the others as baselines.
    stale_after: a reference silent for longer makes its estimates ``stale`` (None: never).
    max_carry: how old the carried-over value from before the init phase may be.
    thinning: how readings become window points (default: one per sensor and minute).
    """

    def __init__(
        self,
        artifact: Artifact,
        models: Sequence[str] | None = None,
        stale_after: dt.timedelta | None = None,
        max_carry: dt.timedelta = MAX_CARRY,
        thinning: Thinning | None = None,
        record_unlike: bool = False,
    ) -> None:
        """record_unlike: fill :attr:`TwinEstimate.unlike` even when no criterion of the
        envelope acts (validation judges the criteria on it); otherwise such a twin skips the
        checks, which change nothing it publishes."""
        self.artifact = artifact
        self.record_unlike = record_unlike
        self.hours = artifact.hours
        kinds = list(models) if models is not None else artifact.published
        missing = [k for k in kinds if k not in artifact.models]
        if missing:
            raise ValueError(f"artifact has no model(s) {', '.join(missing)}")
        self.kinds = kinds
        # What runs on the window: every kind asked for, a stacked one (models/blend.py) as
        # its members (one state per kind, shared with the member's own kind if asked).
        self._models: dict[str, TwinModel] = {}
        for k in kinds:
            for kind, model in self._running(k, artifact.models[k]):
                self._models.setdefault(kind, model)
        self.stale_after = stale_after
        self.max_carry = max_carry
        self.thinning = thinning or Thinning()
        self.references = artifact.references
        self.inputs = artifact.inputs  # references, then covariates
        self.day: dt.date | None = None
        # Today's window points as plain tuples (sensor, ts, hours [h], value): the cyclic
        # garbage collector stops tracking them, where a thousand twins' objects made every
        # full collection of an evening take hundreds of ms. ``window`` shows them.
        self._points: list[tuple[str, dt.datetime, float, float]] = []
        self.last: dict[str, tuple[dt.datetime, float]] = {}
        self._window_start: dt.datetime | None = None  # the open window's init start
        self._thinner = WindowThinner(self.thinning)
        self._est: dict[str, DayEstimator] = {}
        # The primary's failovers' live state: the references each does without → its
        # estimator (live/failover.py).
        self._failover: dict[tuple[str, ...], DayEstimator] = {}
        self._broken: set[str] = set()
        # Today's window per input in time order: sensor → (hours, values), arrays of doubles
        # (not lists: the garbage collector never traverses them).
        self._series: dict[str, tuple[array[float], array[float]]] = {}
        self.fallbacks = 0
        # The primary's current uncertain spell: since when, and why (for <twin>/monitor).
        self.uncertain_since: dt.datetime | None = None
        self.uncertain_why: tuple[str, ...] = ()
        # The primary's current failover spell: since when, and which references it lost.
        self.failover_since: dt.datetime | None = None
        self.failover_lost: tuple[str, ...] = ()
        self._spells_at: dt.datetime | None = None  # the latest instant they were judged at
        # Spells that ended since the monitor last took them (take_ended_spells): one that
        # begins and ends between two grid instants is told all the same.
        self._ended_spells: list[dict[str, object]] = []

    def _ended(self, kind: str, since: dt.datetime, until: dt.datetime,
               **why: list[str]) -> None:
        if len(self._ended_spells) == ENDED_SPELLS_KEPT:  # a flapping reference: the latest
            del self._ended_spells[0]
        self._ended_spells.append({"kind": kind, "since": since, "until": until, **why})

    @property
    def spells_ended(self) -> bool:
        """Whether a spell ended since take_ended_spells was last called."""
        return bool(self._ended_spells)

    def take_ended_spells(self) -> list[dict[str, object]]:
        """The uncertain and failover spells that ended since the last call (at most
        ENDED_SPELLS_KEPT, the latest), oldest first: ``{"kind", "since", "until"}`` and
        ``why`` or ``lost``."""
        out, self._ended_spells = self._ended_spells, []
        return out

    def _running(self, kind: str, model: TwinModel) -> list[tuple[str, TwinModel]]:
        """The (kind, model) pairs whose day states ``kind`` needs: itself, or a stacked
        model's members (the artifact's models of those kinds where it has them)."""
        if not model.stacked:
            return [(kind, model)]
        return [pair for k, m in model.parts().items()
                for pair in self._running(k, self.artifact.models.get(k, m))]

    # -- the window -------------------------------------------------------------------
    def _needs(self, kind: str) -> tuple[str, ...]:
        return self.artifact.models[kind].references_

    def _open(self, day: dt.date) -> None:
        """Start ``day``'s window: fresh model state, carried-over reference values."""
        self.day = day
        self._points = []
        self._thinner = WindowThinner(self.thinning)
        self._broken = set()
        self._series = {s: (array("d"), array("d")) for s in self.inputs}
        self._est = {k: m.start_day(day) for k, m in self._models.items()}
        self._failover = ({f.lost: f.model.start_day(day) for f in self.artifact.failovers}
                          if self.artifact.primary in self.kinds else {})
        self.uncertain_since, self.uncertain_why = None, ()
        self.failover_since, self.failover_lost = None, ()
        self._spells_at = None
        init_ts = self._window_start = self.hours.at(day, self.hours.init_start)
        for s in self.inputs:
            last = self.last.get(s)
            if last and last[0] < init_ts and init_ts - last[0] <= self.max_carry:
                self._feed(WindowReading(s, last[0], self.hours.init_start, last[1]))

    @property
    def window(self) -> list[WindowReading]:
        """Today's window points in arrival order (built on each call)."""
        return [WindowReading(*p) for p in self._points]

    @property
    def window_size(self) -> int:
        return len(self._points)

    def _feed(self, r: WindowReading) -> None:
        self._points.append((r.sensor, r.ts, r.hours, r.value))
        hs, vs = self._series[r.sensor]
        i = bisect.bisect_right(hs, r.hours)
        hs.insert(i, r.hours)
        vs.insert(i, r.value)
        for kind, est in self._est.items():
            if kind in self._broken:
                continue
            try:
                est.observe(r.sensor, r.hours, r.value)
            except NumericalError as exc:
                self._break(kind, exc)
        if self._failover:  # no closure per reading when none runs (the usual case)
            self._each_failover(lambda est: est.observe(r.sensor, r.hours, r.value))

    def _each_failover(self, step: Callable[[DayEstimator], None]) -> None:
        """``step`` on every running failover. Failovers are cheap models: one that fails
        anyway (or lost a point: KeyError) sits out the rest of the day."""
        for lost, est in list(self._failover.items()):
            try:
                step(est)
            except (NumericalError, KeyError) as exc:
                log.warning("failover for %s: numerical failure (%s); unavailable today",
                            ", ".join(lost), exc)
                del self._failover[lost]

    def _break(self, kind: str, exc: Exception) -> None:
        log.warning("%s: numerical failure (%s); publishing TRIV with quality fallback", kind, exc)
        self._broken.add(kind)
        self.fallbacks += 1

    def _repair(self) -> None:
        """Rebuild broken models from the window (the recovery at the next reading)."""
        if self.day is None:
            return
        for kind in list(self._broken):
            est = self._models[kind].start_day(self.day)
            try:
                for sensor, _, hours, value in self._points:
                    est.observe(sensor, hours, value)
                if self._points:  # GP posteriors condition when asked: ask, or fail here
                    est.predict(self._points[-1][2])
            except NumericalError:
                continue
            self._est[kind] = est
            self._broken.discard(kind)
            log.info("%s: recovered after a numerical failure", kind)

    def _window_for(self, ts: dt.datetime) -> bool:
        """Make the window of ``ts``'s day current if ``ts`` lies in it; False otherwise."""
        day, h = self.hours.day_and_clock_of(ts)
        if not self.hours.is_in_window(h):
            return False
        if day != self.day:
            if self.day is not None and day < self.day:
                return False
            self._open(day)
        return True

    def observe(self, sensor: str, ts: dt.datetime, value: float) -> bool:
        """Take one reading (already validated). False when it does not enter the window:
        not an input (reference or covariate), a duplicate, outside the operating window, or
        from a past day."""
        if sensor not in self.inputs or not math.isfinite(value):
            return False
        # Open the day first: its carry-over is the last value from *before* this reading.
        in_window = self._window_for(ts)
        last = self.last.get(sensor)
        if last is None or ts > last[0]:
            self.last[sensor] = (ts, value)
        if not in_window:
            return False
        action, point_ts, point_value = self._thinner.offer(sensor, ts, value)
        if action is Action.DROP:
            return False
        if self._broken:
            self._repair()
        if action is Action.NEW:
            self._feed(WindowReading(sensor, point_ts, self.hours.clock_of(point_ts), point_value))
        else:
            self._revise(sensor, point_ts, point_value)
        return True

    def before_window(self, ts: dt.datetime) -> bool:
        """Whether a reading at ``ts`` comes too late for any use: today's window is open and
        ``ts`` lies before it (its carry-over was taken when the window opened)."""
        return self._window_start is not None and ts < self._window_start

    def newest(self) -> dt.datetime | None:
        """The latest reading time of any input (reference or covariate), None before any.

        The daemon's per-reading estimate is of this instant: a reading that arrives late
        revises the current estimate rather than publishing one of its own, older time."""
        return max((ts for ts, _ in self.last.values()), default=None)

    def _revise(self, sensor: str, ts: dt.datetime, value: float) -> None:
        """Give ``sensor``'s newest point (at ``ts``) the value ``value``."""
        i = len(self._points) - 1
        while self._points[i][0] != sensor or self._points[i][1] != ts:
            i -= 1  # the newest point is among the last few: one per reference and interval
        hours = self._points[i][2]
        self._points[i] = (sensor, ts, hours, value)
        hs, vs = self._series[sensor]
        j = bisect.bisect_right(hs, hours) - 1
        vs[j] = value  # the newest point is the last at its time
        for kind, est in self._est.items():
            if kind in self._broken:
                continue
            try:
                est.revise(sensor, hours, value)
            except (NumericalError, KeyError) as exc:
                # KeyError: the estimator lost the point (never expected); rebuilt from the
                # window at the next reading like a numerical failure.
                self._break(kind, exc)
        if self._failover:
            self._each_failover(lambda est: est.revise(sensor, hours, value))

    # -- monitoring -------------------------------------------------------------------
    def slot_values(self) -> dict[str, np.ndarray]:
        """Today's window per reference on the slot grid (sample-and-hold): sensor → [S]."""
        series = {s: (np.array(hs), np.array(vs))
                  for s, (hs, vs) in self._series.items() if hs}
        day = DayReadings(self.day or dt.date.min, series)
        return {s: day.slot_values(s, self.hours) for s in self.references}

    def numerics(self) -> dict[str, float | int]:
        """Live numerical health of the GP posteriors: jitter used, refactorizations."""
        found = [e.numerics() for e in self._est.values()]
        nums = [n for n in found if n is not None]
        return {
            "jitter": max((n.jitter for n in nums), default=0.0),
            "refactorizations": sum(n.refactorizations for n in nums),
            "gp_points": max((n.points for n in nums), default=0),
        }

    # -- estimates --------------------------------------------------------------------
    def _stale(self, kind: str, ts: dt.datetime) -> bool:
        return any(self._silent(s, ts) for s in self._needs(kind))

    def silent_references(self, kind: str, ts: dt.datetime) -> tuple[str, ...]:
        """The sensors ``kind`` needs that are silent at ``ts`` (as :meth:`_silent`)."""
        return tuple(s for s in self._needs(kind) if self._silent(s, ts))

    def _silent(self, sensor: str, ts: dt.datetime) -> bool:
        """Never reported, or silent longer than ``stale_after`` at ``ts``."""
        last = self.last.get(sensor)
        if last is None:
            return True
        return self.stale_after is not None and ts - last[0] > self.stale_after

    def slope(self, sensors: Sequence[str], hours: float) -> float:
        """|net change| [unit/h] of ``sensors`` over the last ``SLOPE_WINDOW_H`` of today's
        window up to ``hours``, averaged over the sensors: from the value held at the
        window's start to the latest (0 with fewer than two readings). A net change, not a
        mean |slope| within the half hour: a spike that returns within it counts as nothing,
        and it counts once its start leaves the half hour. Validation sizes σ with the same
        rule (envelope and calibration), so the two agree."""
        found = []
        for s in sensors:
            hs, vs = self._series.get(s, ([], []))
            i1 = bisect.bisect_right(hs, hours) - 1
            if i1 < 0:
                continue
            i0 = max(bisect.bisect_right(hs, hours - SLOPE_WINDOW_H) - 1, 0)
            span = max(hs[i1] - hs[i0], SLOPE_WINDOW_H)
            found.append(abs(vs[i1] - vs[i0]) / span)
        return sum(found) / len(found) if found else 0.0  # plain floats: per estimate

    def _calibrated(self, kind: str, hours: float, std: float,
                    slopes: dict[tuple[str, ...], float]) -> float:
        """The σ of ``kind``'s estimate: its training-day calibration where the artifact has
        one (older artifacts: the model's own spread). slopes: the references' slopes at
        ``hours`` found so far in this estimate (models share references)."""
        model = self.artifact.models.get(kind) or self._fallback_model()
        refs = model.references_ if model is not None else tuple(self.references)
        return self._sigma(self.artifact.calibration.get(kind), refs, hours, std, slopes)

    def _sigma(self, calib: SigmaCalibration | None, refs: tuple[str, ...], hours: float,
               std: float, slopes: dict[tuple[str, ...], float]) -> float:
        """``calib``'s σ at ``hours`` for a model reading ``refs`` (None: ``std``, the model's
        own spread); slopes caches the references' slopes within one estimate."""
        if calib is None:
            return std
        if refs not in slopes:
            slopes[refs] = self.slope(refs, hours)
        return calib.sigma(hours, slopes[refs])

    def estimate(self, ts: dt.datetime,
                 kinds: Sequence[str] | None = None) -> dict[str, TwinEstimate]:
        """Every model's estimate at ``ts`` from the window's readings up to now (only
        ``kinds``' when given: the daemon's per-reading update needs just the primary).

        Empty outside the operating window (before init start, after day end).
        """
        if kinds is not None and (unknown := set(kinds) - set(self.kinds)):
            raise ValueError(f"the twin does not run {', '.join(sorted(unknown))}")
        if not self._window_for(ts):
            return {}
        h = self.hours.clock_of(ts)
        out: dict[str, TwinEstimate] = {}
        triv = None
        predicted: dict[str, Estimate] = {}  # kind → its prediction at h (members are shared)
        slopes: dict[tuple[str, ...], float] = {}
        unlike: dict[str, list[tuple[str, str]]] = {}  # reference → (criterion, why), at h
        for kind in self.kinds if kinds is None else kinds:
            refs = {s: (self.last[s][0] if s in self.last else None) for s in self._needs(kind)}
            name = self.artifact.models[kind].model_name
            quality = Quality.OK
            try:
                e = self._predict(kind, h, predicted)
                value, std = e.value, self._calibrated(kind, h, e.std, slopes)
            except NumericalError:
                triv = triv or self._triv_fallback(h)
                value, name, quality = triv[0], "triv", Quality.FALLBACK
                std = self._calibrated("triv", h, triv[1], slopes)
            # init (never published) before stale before fallback: a model that failed
            # in the init phase must not publish early, nor hide a silent reference.
            why: tuple[str, ...] = ()
            lost: tuple[str, ...] = ()
            fired: tuple[str, ...] = ()
            if h < self.hours.day_start:
                quality = Quality.INIT
            elif self._stale(kind, ts):
                quality = Quality.STALE
                if kind == self.artifact.primary and (answer := self._answer_without(ts, h,
                                                                                     slopes)):
                    value, std, name, lost = answer
                    quality = Quality.FALLBACK
                else:
                    # Made from a silent reference's last value: how far the desk has moved
                    # since is not known, and the calibrated σ (smallest when nothing moves)
                    # would say the opposite. No σ: an honest "I don't know".
                    std = math.nan
            elif quality is Quality.OK:
                fired, why = self._unlike_training(self._needs(kind), h, unlike)
                if why and (env := self.artifact.envelope) is not None:
                    quality, std = Quality.UNCERTAIN, std * env.widen
            # The spells move forward in time only: an estimate at an earlier instant (the
            # daemon's score of a desk reading stamped a little behind) ended and restarted
            # them, and with them the monitor's `since`.
            if kind == self.artifact.primary and (self._spells_at is None
                                                  or ts >= self._spells_at):
                self._spells_at = ts
                if self.uncertain_since is not None and not why:
                    self._ended("uncertain", self.uncertain_since, ts,
                                why=list(self.uncertain_why))
                if self.failover_since is not None and not lost:
                    self._ended("failover", self.failover_since, ts,
                                lost=list(self.failover_lost))
                self.uncertain_why = why
                self.uncertain_since = (self.uncertain_since or ts) if why else None
                self.failover_lost = lost
                self.failover_since = (self.failover_since or ts) if lost else None
            out[kind] = TwinEstimate(ts, float(value), float(std), name, quality, refs, why,
                                     lost, fired)
        return out

    def _predict(self, kind: str, h: float, predicted: dict[str, Estimate]) -> Estimate:
        """``kind``'s raw estimate at ``h`` (a stacked model's from its members'); raises
        NumericalError when it, or a member, failed (and marks that model broken)."""
        if kind in predicted:
            return predicted[kind]
        model = self._models.get(kind) or self.artifact.models[kind]
        if model.stacked:
            e = model.combine({k: self._predict(k, h, predicted) for k in model.parts()})
        elif kind in self._broken:
            raise NumericalError("model state lost")
        else:
            try:
                e = self._est[kind].predict(h)
            except NumericalError as exc:
                self._break(kind, exc)
                raise
        predicted[kind] = e
        return e

    def _answer_without(self, ts: dt.datetime, h: float, slopes: dict[tuple[str, ...], float]
                        ) -> tuple[float, float, str, tuple[str, ...]] | None:
        """The failover's (value, σ, model name, lost references) at ``ts`` when the primary
        cannot answer for a silent reference; None when no failover has fresh references."""
        running = [f for f in self.artifact.failovers if f.lost in self._failover]
        for f in ranked(running, lambda s: not self._silent(s, ts)):
            try:  # a GP posterior conditions on its pending points when asked
                e = self._failover[f.lost].predict(h)
            except NumericalError as exc:
                log.warning("failover for %s: numerical failure (%s); unavailable today",
                            f.name, exc)
                del self._failover[f.lost]
                continue
            if not math.isfinite(e.value):
                continue  # its references have no point in today's window yet
            std = self._sigma(f.calibration, f.model.references_, h, e.std, slopes)
            lost = self.silent_references(self.artifact.primary, ts)
            return e.value, std, f.model.model_name, lost
        return None

    def _unlike_training(self, sensors: Sequence[str], h: float,
                         cache: dict[str, list[tuple[str, str]]]
                         ) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """The criteria by which the latest values of ``sensors`` at ``h`` are unlike the
        training days, and why for those that act (both empty: like them, or the artifact
        records no training ranges)."""
        env = self.artifact.envelope
        if env is None or (env.kept is not None and not env.kept and not self.record_unlike):
            return (), ()
        for s in sensors:
            if s in cache or s not in env.refs:
                continue
            value = self.latest(s, h)
            cache[s] = [] if value is None else env.refs[s].unlike(s, self.hours, h, value,
                                                                   self.slope([s], h))
        found = [kw for s in sensors for kw in cache.get(s, [])]
        for pair in env.pairs:
            if pair.a not in sensors or pair.b not in sensors:
                continue
            if pair.key not in cache:
                va, vb = self.latest(pair.a, h), self.latest(pair.b, h)
                slot = self.hours.window_slot_index(h)
                cache[pair.key] = [] if va is None or vb is None else pair.unlike(
                    va - env.refs[pair.a].profile[slot], vb - env.refs[pair.b].profile[slot])
            found += cache[pair.key]
        return (tuple(k for k, _ in found),
                tuple(w for k, w in found if env.acts(k)))

    def latest(self, sensor: str, h: float) -> float | None:
        """``sensor``'s latest value in today's window at or before ``h`` [h], the carried-over
        one included (None: none yet)."""
        hs, vs = self._series.get(sensor, ([], []))
        i = bisect.bisect_right(hs, h) - 1
        return vs[i] if i >= 0 else None

    def _fallback_model(self) -> TwinModel | None:
        """TRIV of the artifact, or else the first simpler model a model offers."""
        if "triv" in self.artifact.models:
            return self.artifact.models["triv"]
        offered = (m.fallback() for m in self.artifact.models.values())
        return next((m for m in offered if m is not None), None)

    def _triv_fallback(self, h: float) -> tuple[float, float]:
        est = self._est.get("triv")
        if est is None:
            # The twin was not asked to run TRIV: a private one keeps the fallback available.
            model = self._fallback_model()
            if model is None or self.day is None:
                return float("nan"), float("nan")
            est = model.start_day(self.day)
            for sensor, _, hours, value in self._points:
                est.observe(sensor, hours, value)
        e = est.predict(h)
        return e.value, e.std
