"""The live bookkeeping behind ``<twin>/monitor`` (DESIGN.md §6): one :class:`TwinMonitor`
per twin collects today's published σ and (truth, estimate) pairs of the live target sensor
and renders the day's figures. Scores come from :mod:`pseudotwin.live.metrics`, the same as
``evaluate``'s; MQTT, threads and the life cycle stay in the service.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Collection, Mapping
from typing import Any

import numpy as np

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.live import metrics
from pseudotwin.live.twin import Twin


class TwinMonitor:
    """Today's monitor figures of one twin; the lists start afresh with every new day."""

    def __init__(self, twin_id: str, twin: Twin, artifact_hash: str, hours: OperatingHours,
                 sensors: Collection[str]) -> None:
        """sensors: the twin's configured sensors (references and, if live, the target)."""
        self.twin_id = twin_id
        self.twin = twin
        self.sensors = frozenset(sensors)
        self.artifact_hash = artifact_hash
        self.hours = hours
        self.day: dt.date | None = None
        self.stds: list[float] = []  # σ of every published primary estimate today
        # (truth, estimate, σ) of the live target and the published primary at its time, today
        self.pairs: list[tuple[float, float, float]] = []

    def roll(self, day: dt.date) -> None:
        """Start the bookkeeping of ``day`` if it is not today's already."""
        if day != self.day:
            self.day, self.stds, self.pairs = day, [], []

    def record_estimate(self, std: float) -> None:
        """A published primary estimate's σ (call :meth:`roll` for its day first); a stale
        one has none."""
        if math.isfinite(std):
            self.stds.append(std)

    def record_truth(self, truth: float, estimate: float, std: float) -> None:
        """A live target reading, and the primary estimate and its σ at its time."""
        self.pairs.append((truth, estimate, std))

    def snapshot(self, now: dt.datetime,
                 rejected: Mapping[tuple[str, str], int] | None = None) -> dict[str, Any]:
        """The ``<twin>/monitor`` payload fields at ``now``.

        rejected: readings rejected today by (sensor, reason); only the twin's sensors count.
        """
        tw = self.twin
        out: dict[str, Any] = {
            "ts": now, "day": str(self.hours.day_of(now)), "twin": self.twin_id,
            "artifact": self.artifact_hash[:16],
            "window_readings": tw.window_size,
            "mean_std": float(np.mean(self.stds)) if self.stds else None,
            "fallbacks": tw.fallbacks,
            "rejected": {f"{s}:{why}": n for (s, why), n in (rejected or {}).items()
                         if s in self.sensors},
            "refs_pearson_r": ref_correlations(tw),
            # The self-aware indication (DESIGN.md §6): why the estimate is `uncertain` now.
            "uncertain": ({"since": tw.uncertain_since, "why": list(tw.uncertain_why)}
                          if tw.uncertain_since is not None else None),
            # Reference failover (live/failover.py): which references the estimate does without.
            "failover": ({"since": tw.failover_since, "lost": list(tw.failover_lost)}
                         if tw.failover_since is not None else None),
            # σ was measured on the training days, and over months after them it has measured
            # too narrow (README, Unseen pairs): how old they are, for whoever plans the check.
            "training": ({"end": str(end), "age_days": (self.hours.day_of(now) - end).days}
                         if (end := tw.artifact.training_end) is not None else None),
        }
        out.update(tw.numerics())
        if self.pairs:
            truth, est, std = np.array(self.pairs).T
            s = metrics.score(truth, est, std)
            # σ is a promise (DESIGN.md §6): a desk sensor put back for a day checks it too,
            # with daily.csv's figures over the estimates that had a σ (the payload writes a
            # figure without any as null). CRPS without a σ would be the mean absolute error;
            # mean σ is NaN exactly when no estimate had one.
            out["target"] = {
                "n": s.n, "nrmse_pct": s.nrmse_pct, "dmax_pct": s.dmax_pct,
                "pearson_r": _or_none(s.pearson_r), "rmse": s.rmse,
                "mean_std": s.mean_std, "cover1_pct": s.cover1_pct,
                "cover2_pct": s.cover2_pct, "crps": s.crps if np.isfinite(s.mean_std) else None,
            }
        return out


def _or_none(x: float) -> float | None:
    return x if np.isfinite(x) else None


def ref_correlations(tw: Twin) -> dict[str, float | None]:
    """Daily Pearson r between the references on today's slot grid (sample-and-hold)."""
    refs = tw.references
    if len(refs) < 2 or not tw.window_size:
        return {}
    grid = tw.slot_values()
    out = {}
    for i in range(len(refs)):
        for j in range(i + 1, len(refs)):
            a, b = grid[refs[i]], grid[refs[j]]
            ok = np.isfinite(a) & np.isfinite(b)
            out[f"{refs[i]}|{refs[j]}"] = _or_none(metrics.pearson_r(a[ok], b[ok]))
    return out
