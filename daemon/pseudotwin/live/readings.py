"""Turning one MQTT payload into one validated reading.

A bad payload is never fatal: :func:`parse_payload` raises :class:`Rejected` with a short,
stable reason code (for counters and the monitor topic) and a human message (for the log).

Payload formats (per sensor, see :class:`~pseudotwin.config.SensorConfig`):

* ``"number"``: the UTF-8 text of one decimal number (``21.5``, ``-3``, ``4.2e2``, blanks
  around it allowed). Its timestamp is the arrival time.
* ``"json"``: an object with the value under ``value_key`` and the timestamp under
  ``ts_key`` (arrival time if ``ts_key`` is empty). The value must be a JSON *number*:
  strings such as ``"21.5"``, booleans and null are rejected as ``not-a-number``. Accepting
  quoted numbers would also have to decide about ``"21,5"``, ``" nan "`` and units in the
  string; a producer sending strings is misconfigured and should be told, not guessed at.
  The timestamp is an ISO 8601 string *with* a UTC offset (``Z`` allowed) or epoch
  seconds, or epoch milliseconds when its magnitude exceeds 1e11 (1e11 s is the year 5138,
  1e11 ms is March 1973, so the two cannot be confused for real data).

Checks run in this order and the first failure is reported: size, syntax, value, timestamp,
valid range, future (more than ``max_skew`` after arrival), too old (before ``not_before``,
the start of the current window). Duplicates and out-of-order readings are the window's
business, not this module's.

A timestamp after arrival but within ``max_skew`` is a clock running ahead (the sensor's,
the bridge's, or the daemon's behind). The reading keeps its stamp: raw readings are never
modified, and a redelivery of it is still the duplicate it is. The caller hears of a lead of
``AHEAD_NOTICE_S`` or more (``on_ahead``), to say so; what the daemon publishes never carries
an instant its clock has not reached (edge/service.py).
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, date, datetime, timedelta
from enum import StrEnum
from typing import Any, TypeVar

import pandas as pd

from pseudotwin.config import SensorConfig

__all__ = ["MAX_PAYLOAD_BYTES", "Reading", "Reason", "Rejected", "parse_payload"]

_T = TypeVar("_T")

#: Larger payloads are rejected before decoding: a reading is a few dozen bytes, and the
#: limit bounds the work a misbehaving publisher can cause.
MAX_PAYLOAD_BYTES = 64 * 1024

#: A timestamp this far [s] or more after arrival is told to the caller (clocks kept in step
#: by NTP differ by milliseconds; a clock set by hand or drifting, by seconds to minutes).
AHEAD_NOTICE_S = 1.0

#: Epoch values above this magnitude are milliseconds.
EPOCH_MS_THRESHOLD = 1e11

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)

#: The rejection counted when a payload makes a consumer fail unexpectedly (a bug, not a
#: property of the payload the parser knows): it is logged, counted and acknowledged.
UNPROCESSABLE = "unprocessable"
# Plain decimal numbers only: float() would also accept "1_000", "infinity" and friends.
_DECIMAL = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


class Reason(StrEnum):
    """Why a payload was rejected. The values are stable: counters and dashboards use them."""

    TOO_LARGE = "too-large"
    NOT_JSON = "not-json"
    MISSING_KEY = "missing-key"
    NOT_A_NUMBER = "not-a-number"
    NON_FINITE = "non-finite"
    BAD_TIMESTAMP = "bad-timestamp"
    OUT_OF_RANGE = "out-of-range"
    FUTURE = "future"
    TOO_OLD = "too-old"
    RETAINED = "retained"


class Rejected(Exception):
    """A payload that does not yield a valid reading.

    reason: stable code (a :class:`Reason`, equal to its string value, e.g. ``"future"``).
    message: what was wrong, for the log; never contains more than a short excerpt of the
        payload.
    """

    def __init__(self, reason: Reason, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason
        self.message = message


@dataclass(frozen=True)
class Reading:
    """One (sensor, ts, value): ts is timezone-aware UTC, value in the sensor's unit."""

    sensor: str
    ts: datetime
    value: float

    def __post_init__(self) -> None:
        if self.ts.tzinfo is None or self.ts.utcoffset() is None:
            raise ValueError("Reading.ts must be timezone-aware")


def _excerpt(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _require_aware(name: str, value: datetime | None) -> None:
    if value is not None and (value.tzinfo is None or value.utcoffset() is None):
        raise ValueError(f"{name} must be timezone-aware")


def _number_text(text: str) -> float:
    stripped = text.strip()
    if _NON_FINITE.fullmatch(stripped):
        raise Rejected(Reason.NON_FINITE, f"value {_excerpt(stripped)} is not finite")
    if not _DECIMAL.fullmatch(stripped):
        raise Rejected(Reason.NOT_A_NUMBER, f"payload {_excerpt(stripped)} is not a number")
    value = float(stripped)
    if not math.isfinite(value):  # e.g. 1e999
        raise Rejected(Reason.NON_FINITE, f"value {_excerpt(stripped)} is not finite")
    return value


def _json_number(raw: Any, key: str) -> float:
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        kind = "null" if raw is None else type(raw).__name__
        raise Rejected(Reason.NOT_A_NUMBER,
                       f"{key!r} is {kind} {_excerpt(raw)}, expected a JSON number")
    try:
        value = float(raw)
    except OverflowError:  # an integer beyond float range
        raise Rejected(Reason.NON_FINITE, f"{key!r} does not fit a float") from None
    if not math.isfinite(value):
        raise Rejected(Reason.NON_FINITE, f"{key!r} is {value}, not a finite number")
    return value


def _timestamp(raw: Any, key: str) -> datetime:
    if isinstance(raw, str):
        try:
            ts = datetime.fromisoformat(raw)
        except ValueError:
            raise Rejected(Reason.BAD_TIMESTAMP,
                           f"{key!r} {_excerpt(raw)} is not an ISO 8601 time") from None
        if ts.tzinfo is None or ts.utcoffset() is None:
            # Guessing a zone would shift readings by hours around DST; refuse instead.
            raise Rejected(Reason.BAD_TIMESTAMP,
                           f"{key!r} {_excerpt(raw)} has no UTC offset")
        try:  # 0001-01-01T00:00+01:00 and 9999-12-31T23:59-01:00 have no UTC equivalent
            return ts.astimezone(UTC)
        except OverflowError:
            raise Rejected(Reason.BAD_TIMESTAMP,
                           f"{key!r} {_excerpt(raw)} is not a representable time") from None
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        kind = "null" if raw is None else type(raw).__name__
        raise Rejected(Reason.BAD_TIMESTAMP,
                       f"{key!r} is {kind}, expected ISO 8601 text or epoch seconds/ms")
    try:
        seconds = float(raw)
        if not math.isfinite(seconds):
            raise OverflowError
        if abs(seconds) > EPOCH_MS_THRESHOLD:
            seconds /= 1000.0
        return _EPOCH + timedelta(seconds=seconds)
    except OverflowError:
        raise Rejected(Reason.BAD_TIMESTAMP,
                       f"{key!r} {_excerpt(raw)} is not a representable time") from None


def parse_payload(
    sensor: SensorConfig,
    payload: bytes,
    arrival: datetime,
    *,
    max_skew: timedelta,
    not_before: datetime | None,
    on_ahead: Callable[[float], None] | None = None,
    retained: bool = False,
) -> Reading:
    """The reading in ``payload`` for ``sensor``, or :class:`Rejected`.

    arrival: when the message arrived (aware); the timestamp of payloads without one.
    max_skew: how far the timestamp may lie after ``arrival``.
    not_before: the start of the current window (aware); older readings are rejected.
        None accepts any age.
    on_ahead: called with how far [s] the timestamp lay after ``arrival`` when that was
        ``AHEAD_NOTICE_S`` or more (less is the jitter of clocks kept in step).
    retained: the broker kept the message and delivered it on subscribing: a payload
        without a timestamp is then an old value of unknown time, not a reading now
        (rejected as ``retained``; every reconnect would otherwise take it in again).
    """
    _require_aware("arrival", arrival)
    _require_aware("not_before", not_before)
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise Rejected(Reason.TOO_LARGE,
                       f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")

    ts: datetime | None = None
    if sensor.format == "number":
        try:
            text = payload.decode("utf-8")
        except UnicodeDecodeError:
            raise Rejected(Reason.NOT_A_NUMBER, "payload is not UTF-8 text") from None
        value = _number_text(text)
    else:
        try:
            doc = json.loads(payload.decode("utf-8"))
        except UnicodeDecodeError:
            raise Rejected(Reason.NOT_JSON, "payload is not UTF-8 text") from None
        except (ValueError, RecursionError) as exc:
            raise Rejected(Reason.NOT_JSON, f"payload is not JSON ({_excerpt(str(exc))})") \
                from None
        if not isinstance(doc, dict):
            raise Rejected(Reason.NOT_JSON,
                           f"expected a JSON object, got {type(doc).__name__} {_excerpt(doc)}")
        if sensor.value_key not in doc:
            raise Rejected(Reason.MISSING_KEY, f"no {sensor.value_key!r} in the payload")
        if sensor.ts_key and sensor.ts_key not in doc:
            raise Rejected(Reason.MISSING_KEY, f"no {sensor.ts_key!r} in the payload")
        value = _json_number(doc[sensor.value_key], sensor.value_key)
        if sensor.ts_key:
            ts = _timestamp(doc[sensor.ts_key], sensor.ts_key)
    if ts is None:
        if retained:
            raise Rejected(Reason.RETAINED, "a retained message without a timestamp: sent at "
                                            "some earlier, unknown time (publish readings "
                                            "unretained, or with a timestamp)")
        ts = arrival.astimezone(UTC)

    if not sensor.accepts(value):
        raise Rejected(Reason.OUT_OF_RANGE,
                       f"{value:g} {sensor.unit} outside {sensor.min:g}..{sensor.max:g}")
    if ts > arrival + max_skew:
        raise Rejected(Reason.FUTURE, f"timestamp {ts.isoformat()} is "
                                      f"{(ts - arrival).total_seconds():.0f} s after arrival "
                                      f"(max skew {max_skew.total_seconds():g} s)")
    if on_ahead is not None and (lead := (ts - arrival).total_seconds()) >= AHEAD_NOTICE_S:
        on_ahead(lead)
    if not_before is not None and ts < not_before:
        raise Rejected(Reason.TOO_OLD, f"timestamp {ts.isoformat()} is before "
                                       f"{not_before.astimezone(UTC).isoformat()}, the oldest "
                                       "reading taken")
    return Reading(sensor.id, ts, value)


def in_range(frame: pd.DataFrame, sensors: Mapping[str, SensorConfig],
             others: bool = False) -> pd.DataFrame:
    """The rows of a canonical frame whose sensor is in ``sensors`` and whose value lies in
    that sensor's configured range: stored readings as the daemon would have taken them
    (the store also holds what ``import`` took, which knows no configuration). others: keep
    the rows of sensors not in ``sensors`` too (training's desk sensor need not be)."""
    if frame.empty:
        return frame
    lo = frame["sensor"].map({k: s.min for k, s in sensors.items()})
    hi = frame["sensor"].map({k: s.max for k, s in sensors.items()})
    keep = (frame["value"] >= lo) & (frame["value"] <= hi)  # NaN bounds: not configured
    if others:
        keep |= lo.isna()
    return frame if bool(keep.all()) else frame[keep.to_numpy()]


class RejectionCounter:
    """Counts rejected readings per (sensor, reason) and local day, and logs each one —
    up to ``log_limit`` per key and day, then only counts (a broken sensor must not flood
    the log). Shared by the daemon and the recorder so both treat bad input alike.
    ``on_reject(sensor, reason)`` is called for each one (the Prometheus counter).

    The last ``KEEP_DAYS`` days are kept apart: a batch straddling midnight, or a clock set
    back across it, counts each rejection on its own day without resetting another's."""

    KEEP_DAYS = 2

    def __init__(self, logger: logging.Logger, log_limit: int = 10,
                 on_reject: Callable[[str, str], None] | None = None) -> None:
        self.log = logger
        self.log_limit = log_limit
        self.on_reject = on_reject
        self._counts: dict[date, Counter[tuple[str, str]]] = {}
        self._ahead: dict[date, set[str]] = {}  # sensors whose clock ran ahead, per day
        self._behind: dict[date, set[str]] = {}  # sensors whose readings came late, per day
        self.run_total = 0  # since the start, every day

    @property
    def counts(self) -> Counter[tuple[str, str]]:
        """The latest day's counts by (sensor, reason)."""
        return self._counts[max(self._counts)] if self._counts else Counter()

    def add(self, sensor: str, rej: Rejected, day: date) -> None:
        self.add_reason(sensor, str(rej.reason), rej.message, day)

    def add_reason(self, sensor: str, reason: str, message: str, day: date) -> None:
        """Count a rejection for a reason outside :class:`Reason` (e.g. the daemon's
        ``unprocessable``: a payload that made it fail unexpectedly)."""
        counts = _of_day(self._counts, day, Counter, self.KEEP_DAYS)
        key = (sensor, reason)
        counts[key] += 1
        self.run_total += 1
        if self.on_reject is not None:
            self.on_reject(sensor, reason)
        n = counts[key]
        if n <= self.log_limit:
            self.log.warning("rejected reading of %s (%s): %s", sensor, reason, message)
        if n == self.log_limit:
            self.log.warning("further %s rejections of %s today are only counted",
                             reason, sensor)

    def ahead(self, sensor: str, seconds: float, day: date) -> None:
        """A reading of ``sensor`` stamped ``seconds`` after its arrival (within max_skew):
        logged once per sensor and day."""
        if self._first_today(self._ahead, sensor, day):
            self.log.warning("reading of %s stamped %.0f s after its arrival: its clock (or its "
                             "bridge's) runs ahead of this process's, or this one's behind; "
                             "kept at its stamp, within max_skew (said once a day per sensor)",
                             sensor, seconds)

    def behind(self, sensor: str, seconds: float, day: date) -> None:
        """A reading of ``sensor`` that arrived ``seconds`` after its stamp, later than the
        silence that makes an estimate stale: logged once per sensor and day."""
        if self._first_today(self._behind, sensor, day):
            self.log.warning("reading of %s arrived %.0f min after its stamp: its clock (or its "
                             "bridge's) runs behind or is set to another time zone, or it was "
                             "held up on its way; until such readings come, the sensor looks "
                             "silent (said once a day per sensor)", sensor, seconds / 60.0)

    def _first_today(self, book: dict[date, set[str]], sensor: str, day: date) -> bool:
        """Whether ``sensor`` is noted in ``book`` for the first time on ``day`` (and note it)."""
        noted = _of_day(book, day, set, self.KEEP_DAYS)
        first = sensor not in noted
        noted.add(sensor)
        return first

    def of_day(self, day: date) -> Mapping[tuple[str, str], int]:
        """Readings rejected on local ``day`` by (sensor, reason) (none: no rejection that
        day, or it is older than the days kept)."""
        return self._counts.get(day, {})


def _of_day(book: dict[date, _T], day: date, new: Callable[[], _T], keep: int) -> _T:
    """``book``'s entry of ``day``, made with ``new`` when missing; only the ``keep`` latest
    days stay in ``book``."""
    if day not in book:
        book[day] = new()
        for old in sorted(book)[:-keep]:
            del book[old]
    return book.get(day, new())
