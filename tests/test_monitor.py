"""<twin>/monitor while the desk sensor is live: the day's accuracy *and* σ's calibration of
the published primary, the figures evaluate writes into daily.csv."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest

from daemon_support import DAY, HOURS, REF
from pseudotwin.edge.outputs import monitor_payload
from pseudotwin.live import metrics
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.monitor import TwinMonitor
from pseudotwin.live.twin import Twin


def test_a_live_desk_sensor_checks_sigma_too(desk_artifact: Path) -> None:
    mon = TwinMonitor("desk", Twin(Artifact.load(desk_artifact)), "0" * 64, HOURS, {REF})
    now = HOURS.at(DAY, 12.0)
    mon.roll(DAY)
    assert "target" not in mon.snapshot(now)
    # errors of 0.5, 1.5, 2.5 and 0.2 σ (σ = 0.4): 2 of 4 inside ±1σ, 3 of 4 inside ±2σ
    truth = np.array([21.0, 22.0, 20.5, 21.5])
    std = np.full(4, 0.4)
    est = truth + np.array([0.5, -1.5, 2.5, -0.2]) * std
    for y, m, s in zip(truth, est, std, strict=True):
        mon.record_truth(float(y), float(m), float(s))
    target = json.loads(monitor_payload(mon.snapshot(now)))["target"]
    assert target["n"] == 4
    assert target["cover1_pct"] == pytest.approx(50.0)
    assert target["cover2_pct"] == pytest.approx(75.0)
    assert target["mean_std"] == pytest.approx(0.4)
    # the payload carries 6 decimals
    crps = float(np.mean(metrics.gaussian_crps(truth, est, std)))
    assert target["crps"] == pytest.approx(crps, abs=1e-6)
    assert target["nrmse_pct"] == pytest.approx(metrics.nrmse_pct(truth, est), abs=1e-6)
    assert target["rmse"] == pytest.approx(metrics.rmse(truth, est), abs=1e-6)
    # the next day starts afresh
    mon.roll(DAY + dt.timedelta(days=1))
    assert "target" not in mon.snapshot(now + dt.timedelta(days=1))
    # a stale estimate has no σ: the day's mean σ is that of the others, not NaN
    for s in (0.2, float("nan"), 0.4):
        mon.record_estimate(s)
    snap = json.loads(monitor_payload(mon.snapshot(now + dt.timedelta(days=1))))
    assert snap["mean_std"] == pytest.approx(0.3)


def test_the_monitor_says_how_old_the_training_days_are(desk_artifact: Path) -> None:
    art = Artifact.load(desk_artifact)
    end = dt.date.fromisoformat(art.training["end"])
    mon = TwinMonitor("desk", Twin(art), "0" * 64, HOURS, {REF})
    # a local day, not a UTC one: 00:30 in Madrid is still the evening before in UTC
    late = HOURS.at(end + dt.timedelta(days=40), 0.5)
    assert late.astimezone(dt.UTC).date() == end + dt.timedelta(days=39)
    got = json.loads(monitor_payload(mon.snapshot(late)))["training"]
    assert got == {"end": str(end), "age_days": 40}
    # an artifact that does not say when it was trained: nothing made up
    bare = Artifact(art.spec, art.models, art.primary)
    assert TwinMonitor("desk", Twin(bare), "0" * 64, HOURS, {REF}).snapshot(late)["training"] \
        is None


def test_estimates_without_sigma_leave_the_sigma_figures_null(desk_artifact: Path) -> None:
    mon = TwinMonitor("desk", Twin(Artifact.load(desk_artifact)), "0" * 64, HOURS, {REF})
    mon.roll(DAY)
    for y, m in ((21.0, 21.5), (22.0, 21.0)):
        mon.record_truth(y, m, float("nan"))
    target = json.loads(monitor_payload(mon.snapshot(HOURS.at(DAY, 12.0))))["target"]
    assert target["n"] == 2 and target["rmse"] == pytest.approx(np.sqrt((0.25 + 1.0) / 2))
    # no σ, nothing to check: not a coverage of 0 %, not the absolute error as a CRPS
    assert {target[k] for k in ("mean_std", "cover1_pct", "cover2_pct", "crps")} == {None}
