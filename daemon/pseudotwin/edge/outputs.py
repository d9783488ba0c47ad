"""Payloads the daemon publishes (DESIGN.md §6): JSON, UTF-8."""

from __future__ import annotations

import datetime as dt
import json
import math
from typing import Any

from pseudotwin.live.twin import TwinEstimate


def iso(ts: dt.datetime | None) -> str | None:
    return None if ts is None else ts.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


def _num(x: float, digits: int = 6) -> float | None:
    return round(float(x), digits) if math.isfinite(x) else None


def estimate_payload(e: TwinEstimate, unit: str) -> bytes:
    """``{"ts", "value", "std", "unit", "model", "quality", "refs", "lost"}``; ``lost``: the
    silent references a failover answered without (empty otherwise)."""
    return json.dumps({
        "ts": iso(e.ts),
        "value": _num(e.value),
        "std": _num(e.std),
        "unit": unit,
        "model": e.model,
        "quality": e.quality,
        "refs": {s: iso(t) for s, t in e.refs.items()},
        "lost": list(e.lost),
    }, ensure_ascii=False).encode()


def monitor_payload(fields: dict[str, Any]) -> bytes:
    def clean(v: Any) -> Any:
        if isinstance(v, float):
            return _num(v)
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, dt.datetime):
            return iso(v)
        return v

    return json.dumps(clean(fields), ensure_ascii=False).encode()
