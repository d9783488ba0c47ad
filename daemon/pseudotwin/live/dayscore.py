"""A day's score of published estimates (the daemon's MQTT payloads) against the desk sensor.

What a subscriber such as the demo sees is not ordered: a grid estimate and a reading's
estimate can share an instant and arrive in either order, and both may be redelivered. So
the estimate scored at an instant is chosen by content, never by arrival: the one that had
seen the latest reference readings up to that instant (``refs``), as ``evaluate`` scores an
estimate made after the references of that instant (analysis/replay.py). An estimate whose
``refs`` lie after its own instant (a grid tick the worker reached late, after the next
reading) ranks below every causal one; equal ``refs`` and a different value (which the
twin's determinism rules out) would take the larger value. Errors are summed in time order,
so the same estimates give bit-identical scores in any order.

The raw reference is scored like ``evaluate``'s ``ref:<sensor>`` rows: its last reading at
or before each true reading, as if published unchanged.
"""

from __future__ import annotations

import bisect
import datetime as dt
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pseudotwin.live import metrics

REF_PREFIX = "ref:"


def _instant(text: str) -> dt.datetime:
    return dt.datetime.fromisoformat(text.replace("Z", "+00:00"))


@dataclass(frozen=True)
class Published:
    """One received estimate of one model."""

    model: str
    ts: dt.datetime
    value: float
    refs: tuple[tuple[str, dt.datetime], ...] = ()

    @classmethod
    def from_payload(cls, model: str, body: Mapping[str, Any]) -> Published:
        refs = tuple(sorted((s, _instant(t)) for s, t in (body.get("refs") or {}).items()
                            if t is not None))
        return cls(model, _instant(body["ts"]), float(body["value"]), refs)

    def _rank(self) -> tuple[bool, tuple[float, ...], float]:
        seen = [t.timestamp() for _, t in self.refs]
        if all(t <= self.ts.timestamp() for t in seen):
            return True, tuple(seen), self.value
        return False, tuple(-t for t in seen), self.value  # the least of the future first


def one_per_instant(estimates: Iterable[Published]) -> dict[str, dict[dt.datetime, Published]]:
    """model → instant → the estimate scored there (the best-informed one), any order in."""
    out: dict[str, dict[dt.datetime, Published]] = {}
    for e in estimates:
        per = out.setdefault(e.model, {})
        old = per.get(e.ts)
        if old is None or e._rank() > old._rank():
            per[e.ts] = e
    return out


def answered(estimates: Iterable[Published], last: dt.datetime) -> bool:
    """Every model in ``estimates`` has published an estimate that saw the reading at
    ``last``: at that instant (a reading's estimate) or at a later one (a baseline published
    on the grid only, by default, answers at the next grid instant)."""
    models: set[str] = set()
    done: set[str] = set()
    for e in estimates:
        models.add(e.model)
        if e.ts >= last and e.refs and max(t for _, t in e.refs) == last:
            done.add(e.model)
    return bool(models) and done == models


@dataclass(frozen=True)
class DayScore:
    model: str
    n: int
    nrmse_pct: float
    max_abs_error: float


def _score(model: str, truth: np.ndarray, est: np.ndarray) -> DayScore:
    return DayScore(model, int(truth.size), metrics.nrmse_pct(truth, est),
                    float(np.max(np.abs(est - truth))) if truth.size else float("nan"))


def day_scores(
    estimates: Iterable[Published],
    truth: Mapping[dt.datetime, float],
    references: Mapping[str, Sequence[tuple[dt.datetime, float]]] | None = None,
) -> list[DayScore]:
    """Scores per model at the instants with a true reading (``truth``: instant → value),
    then one ``ref:<sensor>`` row per raw reference (its readings: (instant, value))."""
    chosen = one_per_instant(estimates)
    rows = []
    for model in sorted(chosen):
        per = chosen[model]
        at = sorted(t for t in per if t in truth)
        rows.append(_score(model, np.array([truth[t] for t in at]),
                           np.array([per[t].value for t in at])))
    for sensor, readings in sorted((references or {}).items()):
        ordered = sorted(readings)
        stamps = [t for t, _ in ordered]
        y, r = [], []
        for t in sorted(truth):
            i = bisect.bisect_right(stamps, t)
            if i:
                y.append(truth[t])
                r.append(ordered[i - 1][1])
        rows.append(_score(REF_PREFIX + sensor, np.array(y, float), np.array(r, float)))
    return rows


def table(scores: Sequence[DayScore], unit: str) -> str:
    lines = [f"  {'model':<22} {'n':>4} {'NRMSE %':>8} {'max |error|':>14}"]
    lines += [f"  {s.model:<22} {s.n:>4} {s.nrmse_pct:>8.2f} {s.max_abs_error:>10.2f} {unit}"
              for s in scores]
    return "\n".join(lines)
