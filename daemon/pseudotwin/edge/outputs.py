"""Payloads the daemon publishes (DESIGN.md §6): JSON, UTF-8.

The estimate payload goes out for every reading and for every model on the grid (tens of
thousands a minute at a thousand twins), so it is assembled from cached JSON fragments
rather than through ``json.dumps`` of a fresh dict; the bytes are the same as
``json.dumps(..., ensure_ascii=False)`` would give (tests/test_outputs.py).
"""

from __future__ import annotations

import datetime as dt
import json
import math
from functools import lru_cache
from typing import Any

from pseudotwin.live.twin import TwinEstimate

# Timestamps repeat: one grid instant is every model's and every twin's ts, and a
# reference's last reading time is in each of its twins' payloads until the next one.
_CACHED_TIMES = 4096


def iso(ts: dt.datetime | None) -> str | None:
    return None if ts is None else _iso(ts)


@lru_cache(maxsize=_CACHED_TIMES)
def _iso(ts: dt.datetime) -> str:
    return ts.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


@lru_cache(maxsize=_CACHED_TIMES)
def _json_time(ts: dt.datetime | None) -> str:
    return "null" if ts is None else f'"{_iso(ts)}"'


@lru_cache(maxsize=1024)
def _json_str(s: str) -> str:
    """A string as JSON: units, model names, sensor ids and qualities are few and repeat."""
    return json.dumps(s, ensure_ascii=False)


def _num(x: float, digits: int = 6) -> float | None:
    return round(float(x), digits) if math.isfinite(x) else None


def _json_num(x: float) -> str:
    return repr(round(float(x), 6)) if math.isfinite(x) else "null"


def estimate_payload(e: TwinEstimate, unit: str) -> bytes:
    """``{"ts", "value", "std", "unit", "model", "quality", "refs", "lost"}``; ``lost``: the
    silent references a failover answered without (empty otherwise)."""
    refs = ", ".join(f"{_json_str(s)}: {_json_time(t)}" for s, t in e.refs.items())
    lost = ", ".join(_json_str(s) for s in e.lost)
    return (f'{{"ts": {_json_time(e.ts)}, "value": {_json_num(e.value)}, '
            f'"std": {_json_num(e.std)}, "unit": {_json_str(unit)}, '
            f'"model": {_json_str(e.model)}, "quality": {_json_str(e.quality)}, '
            f'"refs": {{{refs}}}, "lost": [{lost}]}}').encode()


def monitor_payload(fields: dict[str, Any]) -> bytes:
    def clean(v: Any) -> Any:
        if isinstance(v, float):
            return _num(v)
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list):
            return [clean(x) for x in v]
        if isinstance(v, dt.datetime):
            return iso(v)
        return v

    return json.dumps(clean(fields), ensure_ascii=False).encode()
