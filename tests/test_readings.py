"""Payload parsing: accepted shapes and every rejection reason."""

from __future__ import annotations

import json
import logging
from datetime import UTC, date, datetime, timedelta, timezone
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pseudotwin.config import SensorConfig
from pseudotwin.live.readings import (
    MAX_PAYLOAD_BYTES,
    Reading,
    Reason,
    Rejected,
    RejectionCounter,
    parse_payload,
)

ARRIVAL = datetime(2024, 5, 13, 8, 15, 0, tzinfo=UTC)
WINDOW_START = datetime(2024, 5, 13, 5, 30, 0, tzinfo=UTC)  # 07:30 Europe/Berlin
SKEW = timedelta(seconds=300)

JSON_SENSOR = SensorConfig(id="room1/hmi/temp", topic="b/room1/hmi/temp", unit="°C",
                           min=-10, max=50)
NUMBER_SENSOR = SensorConfig(id="room1/hmi/co2", topic="b/room1/hmi/co2", unit="ppm",
                             min=0, max=5000, format="number")


def parse(payload: bytes | dict[str, Any] | str, sensor: SensorConfig = JSON_SENSOR,
          arrival: datetime = ARRIVAL, not_before: datetime | None = WINDOW_START) -> Reading:
    if isinstance(payload, dict):
        payload = json.dumps(payload)
    if isinstance(payload, str):
        payload = payload.encode()
    return parse_payload(sensor, payload, arrival, max_skew=SKEW, not_before=not_before)


def rejected(payload: bytes | dict[str, Any] | str, **kwargs: Any) -> Rejected:
    with pytest.raises(Rejected) as info:
        parse(payload, **kwargs)
    return info.value


# -- accepted -------------------------------------------------------------------------------


def test_json_with_iso_offset_is_converted_to_utc() -> None:
    r = parse({"ts": "2024-05-13T10:14:30+02:00", "value": 21.5})
    assert r == Reading("room1/hmi/temp", datetime(2024, 5, 13, 8, 14, 30, tzinfo=UTC), 21.5)
    assert r.ts.utcoffset() == timedelta(0)


def test_json_with_iso_z_and_fraction() -> None:
    r = parse({"ts": "2024-05-13T08:14:30.250Z", "value": 21})
    assert r.ts == datetime(2024, 5, 13, 8, 14, 30, 250000, tzinfo=UTC)
    assert r.value == 21.0 and isinstance(r.value, float)


def test_epoch_seconds_int_and_float() -> None:
    epoch = int(ARRIVAL.timestamp()) - 60
    assert parse({"ts": epoch, "value": 20}).ts == ARRIVAL - timedelta(seconds=60)
    r = parse({"ts": epoch + 0.5, "value": 20})
    assert r.ts == ARRIVAL - timedelta(seconds=59.5)


def test_epoch_milliseconds_detected_by_magnitude() -> None:
    ms = int(ARRIVAL.timestamp() * 1000) - 60_123
    r = parse({"ts": ms, "value": 20})
    assert r.ts == ARRIVAL - timedelta(seconds=60.123)


def test_epoch_threshold_separates_seconds_from_milliseconds() -> None:
    # 1e11 is still seconds (year 5138: far future), just above it is milliseconds (1973).
    assert rejected({"ts": 99_999_999_999, "value": 20}).reason == "future"
    r = parse({"ts": 100_000_000_001, "value": 20}, not_before=None)
    assert r.ts == datetime(1973, 3, 3, 9, 46, 40, 1000, tzinfo=UTC)


def test_bare_number_uses_arrival_time_in_utc() -> None:
    arrival = datetime(2024, 5, 13, 10, 15, tzinfo=timezone(timedelta(hours=2)))
    for payload, value in ((b"612", 612.0), (b" 4.125e2\n", 412.5), (b"+0.5", 0.5),
                           (b".5", 0.5), (b"0", 0.0)):
        r = parse(payload, sensor=NUMBER_SENSOR, arrival=arrival)
        assert (r.sensor, r.value) == ("room1/hmi/co2", value)
        assert r.ts == ARRIVAL and r.ts.tzinfo == UTC


def test_custom_keys_and_json_without_timestamp() -> None:
    sensor = SensorConfig(id="z2m", topic="z2m/desk", unit="°C", min=-10, max=50,
                          ts_key="", value_key="temperature")
    r = parse({"temperature": 22.25, "humidity": 40, "ts": "ignored"}, sensor=sensor)
    assert (r.value, r.ts) == (22.25, ARRIVAL)
    timed = SensorConfig(id="t", topic="t", unit="°C", min=-10, max=50, ts_key="time",
                         value_key="v")
    assert parse({"time": "2024-05-13T08:00:00Z", "v": 1}, sensor=timed).ts == datetime(
        2024, 5, 13, 8, tzinfo=UTC)


def test_range_bounds_are_inclusive() -> None:
    assert parse({"ts": "2024-05-13T08:00:00Z", "value": -10}).value == -10.0
    assert parse({"ts": "2024-05-13T08:00:00Z", "value": 50}).value == 50.0


def test_time_limits_are_inclusive() -> None:
    at_skew = (ARRIVAL + SKEW).isoformat()
    assert parse({"ts": at_skew, "value": 20}).ts == ARRIVAL + SKEW
    assert parse({"ts": WINDOW_START.isoformat(), "value": 20}).ts == WINDOW_START


@pytest.mark.parametrize(("lead_s", "told"), [(0.001, False), (0.999, False), (1, True),
                                              (240, True), (300, True)])
def test_a_reading_stamped_after_its_arrival_keeps_its_stamp(lead_s: float, told: bool) -> None:
    """Within max_skew a lead is a clock running ahead: the reading is kept as sent (raw
    readings are never modified; a redelivery stays a duplicate), and the caller learns of a
    lead of a second or more (clocks in step by NTP differ by milliseconds)."""
    leads: list[float] = []
    stamped = ARRIVAL + timedelta(seconds=lead_s)
    r = parse_payload(JSON_SENSOR, json.dumps({"ts": stamped.isoformat(), "value": 21.5})
                      .encode(), ARRIVAL, max_skew=SKEW, not_before=WINDOW_START,
                      on_ahead=leads.append)
    assert (r.ts, r.value) == (stamped, 21.5)
    assert leads == ([pytest.approx(lead_s)] if told else [])


def test_no_window_start_accepts_old_readings() -> None:
    assert parse({"ts": "2001-01-01T00:00:00Z", "value": 20}, not_before=None).ts.year == 2001


def test_payload_of_exactly_the_limit_is_accepted() -> None:
    body = b'{"ts": "2024-05-13T08:00:00Z", "value": 20}'
    payload = body + b" " * (MAX_PAYLOAD_BYTES - len(body))
    assert len(payload) == MAX_PAYLOAD_BYTES
    assert parse(payload).value == 20.0


@given(value=st.floats(min_value=-10, max_value=50),
       offset_ms=st.integers(min_value=0, max_value=int(2.75 * 3600 * 1000)))
def test_any_valid_json_reading_round_trips(value: float, offset_ms: int) -> None:
    ts = WINDOW_START + timedelta(milliseconds=offset_ms)
    epoch_ms = int(WINDOW_START.timestamp()) * 1000 + offset_ms  # exact, no float rounding
    r = parse({"ts": epoch_ms, "value": value})
    assert r.value == value
    assert r.ts == ts


# -- rejected -------------------------------------------------------------------------------

REJECTIONS: list[tuple[str, bytes, SensorConfig, str]] = [
    ("1MB", b'{"value": 1, "pad": "' + b"x" * 1_000_000 + b'"}', JSON_SENSOR, "too-large"),
    ("limit+1", b" " * (MAX_PAYLOAD_BYTES + 1), NUMBER_SENSOR, "too-large"),
    ("truncated", b'{"ts": 1715580000, "value": 2', JSON_SENSOR, "not-json"),
    ("empty-json", b"", JSON_SENSOR, "not-json"),
    ("array", b"[1, 2]", JSON_SENSOR, "not-json"),
    ("bare-number-as-json", b"21.5", JSON_SENSOR, "not-json"),
    ("invalid-utf8-json", b'{"value": "\xff"}', JSON_SENSOR, "not-json"),
    ("deeply-nested", b"[" * 60_000, JSON_SENSOR, "not-json"),
    ("no-value", b'{"ts": "2024-05-13T08:00:00Z"}', JSON_SENSOR, "missing-key"),
    ("no-ts", b'{"value": 21.5}', JSON_SENSOR, "missing-key"),
    ("value-string", b'{"ts": "2024-05-13T08:00:00Z", "value": "21.5"}', JSON_SENSOR,
     "not-a-number"),
    ("value-bool", b'{"ts": "2024-05-13T08:00:00Z", "value": true}', JSON_SENSOR,
     "not-a-number"),
    ("value-null", b'{"ts": "2024-05-13T08:00:00Z", "value": null}', JSON_SENSOR,
     "not-a-number"),
    ("value-list", b'{"ts": "2024-05-13T08:00:00Z", "value": [21.5]}', JSON_SENSOR,
     "not-a-number"),
    ("value-object", b'{"ts": "2024-05-13T08:00:00Z", "value": {"v": 1}}', JSON_SENSOR,
     "not-a-number"),
    ("bare-text", b"abc", NUMBER_SENSOR, "not-a-number"),
    ("bare-comma", b"21,5", NUMBER_SENSOR, "not-a-number"),
    ("bare-underscore", b"1_000", NUMBER_SENSOR, "not-a-number"),
    ("bare-empty", b"", NUMBER_SENSOR, "not-a-number"),
    ("bare-bool", b"true", NUMBER_SENSOR, "not-a-number"),
    ("bare-json", b'{"value": 400}', NUMBER_SENSOR, "not-a-number"),
    ("bare-invalid-utf8", b"4\xff00", NUMBER_SENSOR, "not-a-number"),
    ("json-nan", b'{"ts": "2024-05-13T08:00:00Z", "value": NaN}', JSON_SENSOR, "non-finite"),
    ("json-inf", b'{"ts": "2024-05-13T08:00:00Z", "value": Infinity}', JSON_SENSOR,
     "non-finite"),
    ("json-minus-inf", b'{"ts": "2024-05-13T08:00:00Z", "value": -Infinity}', JSON_SENSOR,
     "non-finite"),
    ("json-1e400", b'{"ts": "2024-05-13T08:00:00Z", "value": 1e400}', JSON_SENSOR,
     "non-finite"),
    ("json-huge-int", b'{"ts": "2024-05-13T08:00:00Z", "value": 1' + b"0" * 400 + b"}",
     JSON_SENSOR, "non-finite"),
    ("bare-nan", b"nan", NUMBER_SENSOR, "non-finite"),
    ("bare-inf", b"-Infinity", NUMBER_SENSOR, "non-finite"),
    ("bare-1e999", b"1e999", NUMBER_SENSOR, "non-finite"),
    ("ts-naive", b'{"ts": "2024-05-13T08:00:00", "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-date-only", b'{"ts": "2024-05-13", "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-garbage", b'{"ts": "yesterday", "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-digits-string", b'{"ts": "1715580000", "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-bool", b'{"ts": true, "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-null", b'{"ts": null, "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-nan", b'{"ts": NaN, "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-list", b'{"ts": [2024, 5, 13], "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("ts-unrepresentable", b'{"ts": 1e20, "value": 20}', JSON_SENSOR, "bad-timestamp"),
    ("below-min", b'{"ts": "2024-05-13T08:00:00Z", "value": -10.01}', JSON_SENSOR,
     "out-of-range"),
    ("above-max", b'{"ts": "2024-05-13T08:00:00Z", "value": 85}', JSON_SENSOR, "out-of-range"),
    ("bare-out-of-range", b"-1", NUMBER_SENSOR, "out-of-range"),
    ("far-future", b'{"ts": "2030-01-01T00:00:00Z", "value": 20}', JSON_SENSOR, "future"),
    ("just-past-skew", b'{"ts": "2024-05-13T08:20:00.001Z", "value": 20}', JSON_SENSOR,
     "future"),
    ("too-old", b'{"ts": "2024-05-13T05:29:59Z", "value": 20}', JSON_SENSOR, "too-old"),
    ("yesterday", b'{"ts": "2024-05-12T12:00:00+02:00", "value": 20}', JSON_SENSOR, "too-old"),
]


@pytest.mark.parametrize(("payload", "sensor", "reason"),
                         [pytest.param(p, s, r, id=n) for n, p, s, r in REJECTIONS])
def test_rejections(payload: bytes, sensor: SensorConfig, reason: str) -> None:
    err = rejected(payload, sensor=sensor)
    assert err.reason == reason
    assert isinstance(err.reason, Reason)
    assert err.message and len(err.message) < 300  # a log line, not the payload
    assert str(err) == f"{reason}: {err.message}"


def test_every_reason_code_is_exercised_and_stable() -> None:
    # retained: test_a_retained_message_is_a_reading_only_with_its_own_timestamp
    assert {r for _, _, _, r in REJECTIONS} | {"retained"} == {reason.value for reason in Reason}
    assert {reason.value for reason in Reason} == {
        "not-json", "missing-key", "not-a-number", "non-finite", "out-of-range", "future",
        "too-old", "too-large", "bad-timestamp", "retained"}


def test_a_retained_message_is_a_reading_only_with_its_own_timestamp() -> None:
    """Delivered again at every subscribe: stamped on arrival it would be an old value
    taken in as new; with a timestamp it is the same reading again (a duplicate)."""
    def retained(payload: bytes, sensor: SensorConfig) -> Reading:
        return parse_payload(sensor, payload, ARRIVAL, max_skew=SKEW, not_before=WINDOW_START,
                             retained=True)

    with pytest.raises(Rejected) as info:
        retained(b"612", NUMBER_SENSOR)
    assert info.value.reason == "retained" and "unknown time" in info.value.message
    r = retained(b'{"ts": "2024-05-13T08:14:30Z", "value": 21.5}', JSON_SENSOR)
    assert r.ts == datetime(2024, 5, 13, 8, 14, 30, tzinfo=UTC)
    assert parse(b"612", sensor=NUMBER_SENSOR).ts == ARRIVAL  # not retained: a reading now


def test_messages_name_the_problem() -> None:
    assert "'value'" in rejected(b'{"ts": 1}').message
    assert "str" in rejected({"ts": "2024-05-13T08:00:00Z", "value": "21.5"}).message
    assert "no UTC offset" in rejected({"ts": "2024-05-13T08:00:00", "value": 1}).message
    assert "°C" in rejected({"ts": "2024-05-13T08:00:00Z", "value": 99}).message


def test_size_is_checked_before_decoding() -> None:
    # Not JSON at all, but oversized: the cheaper verdict wins.
    assert rejected(b"\xff" * (MAX_PAYLOAD_BYTES + 1)).reason == "too-large"


def test_naive_times_from_the_caller_are_programming_errors() -> None:
    with pytest.raises(ValueError, match="arrival"):
        parse(b"1", sensor=NUMBER_SENSOR, arrival=datetime(2024, 5, 13, 8))
    with pytest.raises(ValueError, match="not_before"):
        parse(b"1", sensor=NUMBER_SENSOR, not_before=datetime(2024, 5, 13, 8))
    with pytest.raises(ValueError, match="aware"):
        Reading("s", datetime(2024, 5, 13, 8), 1.0)


def test_rejection_counts_are_kept_per_day() -> None:
    """Per local day: a straggler of the day before (a batch straddling midnight, counted by
    its arrival) or a clock set back across midnight counts on its own day and resets no
    other; only the two latest days are kept."""
    counter = RejectionCounter(logging.getLogger("test.rejections"))
    d1, d2, d3 = (date(2024, 5, 13) + timedelta(days=k) for k in range(3))
    bad = Rejected(Reason.OUT_OF_RANGE, "99 °C")
    counter.add("a", bad, d1)
    assert counter.of_day(d1) == {("a", "out-of-range"): 1} and counter.of_day(d2) == {}
    counter.add("a", bad, d2)
    counter.add("b", bad, d2)
    counter.add("a", bad, d1)  # the straggler
    assert counter.of_day(d1) == {("a", "out-of-range"): 2}
    assert counter.of_day(d2) == {("a", "out-of-range"): 1, ("b", "out-of-range"): 1}
    counter.add("c", bad, d3)
    assert counter.of_day(d1) == {} and counter.of_day(d3) == {("c", "out-of-range"): 1}
    assert counter.counts == counter.of_day(d3) and counter.run_total == 5
