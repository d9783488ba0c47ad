"""The monitor's health figures (edge/health.py)."""

from __future__ import annotations

import time

import pytest

from pseudotwin.edge.health import Health


def test_ingest_rates_fall_to_zero_when_nothing_arrives() -> None:
    """Rates were computed only when a message was done: with none arriving, the monitor
    kept showing the last busy window's rates."""
    start = time.monotonic()
    h = Health(lambda status: None, queue_max=100)
    for _ in range(600):
        h.received += 1
        h.processed_one(lag_s=0.5, queued=0)
    busy = h.snapshot(now=start + h.report_seconds * 2)["ingest"]
    assert busy["in_per_s"] == pytest.approx(600 / (h.report_seconds * 2), rel=0.05)
    assert busy["done_per_s"] == busy["in_per_s"] and busy["lag_s_median"] == 0.5
    idle = h.snapshot(now=start + h.report_seconds * 4)["ingest"]
    assert idle["in_per_s"] == 0.0 and idle["done_per_s"] == 0.0
    assert idle["lag_s_median"] is None and idle["received"] == 600
