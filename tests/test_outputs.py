"""The estimate payload is built from cached JSON fragments (edge/outputs.py): it must be
exactly what ``json.dumps`` of the documented fields gives, for every shape of estimate."""

from __future__ import annotations

import datetime as dt
import json
import math

import pytest

from pseudotwin.edge.outputs import estimate_payload
from pseudotwin.live.twin import Quality, TwinEstimate

MADRID = dt.timezone(dt.timedelta(hours=1))
TS = dt.datetime(2012, 3, 20, 8, 5, 7, 123456, tzinfo=MADRID)


def reference(e: TwinEstimate, unit: str) -> bytes:
    def num(x: float) -> float | None:
        return round(x, 6) if math.isfinite(x) else None

    def iso(t: dt.datetime | None) -> str | None:
        return None if t is None else t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")

    return json.dumps({"ts": iso(e.ts), "value": num(e.value), "std": num(e.std),
                       "unit": unit, "model": e.model, "quality": e.quality,
                       "refs": {s: iso(t) for s, t in e.refs.items()}, "lost": list(e.lost)},
                      ensure_ascii=False).encode()


@pytest.mark.parametrize(("estimate", "unit"), [
    (TwinEstimate(TS, 21.123456789, 0.25, "corrgp-triv", Quality.OK,
                  {"room1/wall/temp": TS - dt.timedelta(minutes=3)}), "°C"),
    (TwinEstimate(TS, math.nan, math.inf, "triv", Quality.STALE, {}), "ppm"),
    (TwinEstimate(TS.astimezone(dt.UTC), 1e-7, 123456789.123, "ref", Quality.FALLBACK,
                  {"a": TS, 'odd "id"\\ü\n': None}, ("x",), ("a", 'odd "id"\\ü\n')), "°C"),
    (TwinEstimate(TS, -0.0, 1e21, "corrgp-lcm", Quality.UNCERTAIN, {"a": TS, "b": TS},
                  ("a is unlike training",)), 'unit "q"'),
])
def test_estimate_payload_is_the_json_of_its_fields(estimate: TwinEstimate, unit: str) -> None:
    assert estimate_payload(estimate, unit) == reference(estimate, unit)
    assert json.loads(estimate_payload(estimate, unit))["ts"] == "2012-03-20T07:05:07.123456Z"


def test_same_instant_in_other_zones_gives_the_same_time() -> None:
    other = TS.astimezone(dt.timezone(dt.timedelta(hours=-5)))
    a = TwinEstimate(TS, 1.0, 1.0, "triv", Quality.OK, {"r": TS})
    b = TwinEstimate(other, 1.0, 1.0, "triv", Quality.OK, {"r": other})
    assert estimate_payload(a, "°C") == estimate_payload(b, "°C")
