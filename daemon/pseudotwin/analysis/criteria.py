"""Which criteria of the self-aware indication act live (quality ``uncertain``,
live/envelope.py): those the training days show to flag larger errors.

Validation replays every held-out training day through a Twin whose envelope was fitted on
that fold's other days only, none of its criteria acting; each row records which criteria
fired (``unlike``). On the primary's held-out rows, a criterion is **kept** when

- it fired on at least ``MIN_DAYS`` held-out days and ``MIN_ROWS`` readings (support fixed a
  priori: a criterion seen once proves nothing), and
- the mean absolute error of the readings it fired on is at least ``MIN_RATIO`` × that of the
  readings on which no criterion fired (the issue's figure for ``uncertain`` vs ``ok``).

Every other criterion is dropped: it still shows in ``TwinEstimate.unlike`` but never makes an
estimate uncertain. The primary's errors decide because its estimate is what a controller
reads; the kept criteria then act on every published model alike.

The σ of an uncertain estimate is widened by the ratio of the RMS error of the held-out
readings a kept criterion fired on to the RMS of their calibrated σ, never below 1 (the
calibration, fitted on all held-out readings, underrates exactly these).

A model-aware candidate, the primary disagreeing with TRIV (or, for a TRIV primary, the raw
reference) by more than z × √(σ₁² + σ₂²), was measured the same way on the five shared runs
(z = 0.5, 1, 2): where it had the support, its held-out MAE ratio stayed at 0.2–1.4, so it is
not a criterion.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pseudotwin.analysis.replay import UNLIKE_SEP
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.live.calibration import SigmaCalibration
from pseudotwin.live.envelope import Envelope

MIN_DAYS = 2
MIN_ROWS = 20
MIN_RATIO = 2.0
# Said when nothing was kept: a criterion may well have fired on larger errors, on too few
# days or readings to count (the rule above).
NONE_KEPT = (f"no criterion kept (none fired on ≥ {MIN_DAYS} held-out days and ≥ {MIN_ROWS} "
             f"readings with a mean absolute error ≥ {MIN_RATIO:g}× that where none fired)")


@dataclass(frozen=True)
class Judged:
    """One criterion on the held-out rows: readings and days it fired on, MAE there and on
    the readings where nothing fired [unit], their ratio, kept or not and why."""

    key: str
    n: int
    days: int
    mae: float
    mae_quiet: float
    kept: bool
    reason: str

    @property
    def ratio(self) -> float:
        return self.mae / self.mae_quiet if self.mae_quiet > 0 else float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "days": self.days, "mae": self.mae, "mae_quiet": self.mae_quiet,
                "ratio": self.ratio, "kept": self.kept, "reason": self.reason}


def judge(key: str, fired: np.ndarray, quiet: np.ndarray, err: np.ndarray,
          day: np.ndarray) -> Judged:
    """Criterion ``key`` fired on rows ``fired`` (bool); ``quiet``: rows where nothing fired;
    err: absolute errors; day: held-out day per row."""
    n, days = int(fired.sum()), len(set(day[fired].tolist()))
    mae = float(err[fired].mean()) if n else float("nan")
    mae_quiet = float(err[quiet].mean()) if quiet.any() else float("nan")
    ratio = mae / mae_quiet if mae_quiet > 0 else float("nan")
    if n < MIN_ROWS or days < MIN_DAYS:
        return Judged(key, n, days, mae, mae_quiet, False,
                      f"fired on {n} held-out readings of {days} day(s); needs ≥ {MIN_ROWS} "
                      f"on ≥ {MIN_DAYS} days")
    if not ratio >= MIN_RATIO:
        return Judged(key, n, days, mae, mae_quiet, False,
                      f"MAE where it fired {ratio:.2f}× that where nothing fired "
                      f"(< {MIN_RATIO:g}×): out of range is not a larger error here")
    return Judged(key, n, days, mae, mae_quiet, True,
                  f"MAE where it fired {ratio:.2f}× that where nothing fired, "
                  f"{n} readings on {days} days")


def fired_sets(rows: pd.DataFrame) -> list[set[str]]:
    """The criteria that fired on each of ``rows`` (their ``unlike`` column)."""
    return [set(str(u).split(UNLIKE_SEP)) - {""} for u in rows.get("unlike", pd.Series(dtype=str))]


def abs_errors(rows: pd.DataFrame) -> np.ndarray:
    """|value − truth| of ``rows`` [n] [unit]."""
    return (rows["value"] - rows["truth"]).abs().to_numpy(dtype=float) if len(rows) else \
        np.zeros(0)


def judge_rows(keys: Iterable[str], rows: pd.DataFrame, fired_on: Sequence[set[str]],
               err: np.ndarray) -> dict[str, Judged]:
    """Each criterion of ``keys`` judged on ``rows`` (their ``day``), whose criteria fired
    are ``fired_on`` (:func:`fired_sets`) and absolute errors ``err`` (:func:`abs_errors`)."""
    day = rows["day"].astype(str).to_numpy() if len(rows) else np.zeros(0, dtype=str)
    quiet = np.array([not f for f in fired_on], dtype=bool)
    return {key: judge(key, np.array([key in f for f in fired_on], dtype=bool), quiet, err, day)
            for key in keys}


def select(envelope: Envelope, held_out: pd.DataFrame, primary: str,
           calibration: SigmaCalibration | None, hours: OperatingHours) -> Envelope:
    """``envelope`` with only the criteria the primary's held-out rows (validation's, with
    their ``unlike`` column) show to flag larger errors, and the σ widening of those rows."""
    rows = held_out[(held_out["model"] == primary) & (held_out["quality"] == "ok")] \
        if not held_out.empty and "unlike" in held_out else held_out.iloc[0:0]
    fired_on, err = fired_sets(rows), abs_errors(rows)
    judged = judge_rows(envelope.criteria, rows, fired_on, err)
    kept = frozenset(k for k, j in judged.items() if j.kept)
    widen = 1.0
    flagged = np.array([bool(f & kept) for f in fired_on], dtype=bool)
    if kept and calibration is not None and flagged.any():
        r = rows[flagged]
        sigma = np.array([calibration.sigma(hours.clock_of(t), s)
                          for t, s in zip(r["ts"], r["slope"], strict=True)])
        widen = max(1.0, float(np.sqrt(np.mean(err[flagged] ** 2) / np.mean(sigma ** 2))))
    return envelope.keeping(kept, widen, {k: j.to_dict() for k, j in judged.items()})


def criteria_table(envelope: dict[str, Any] | None, unit: str) -> str:
    """An artifact's ``envelope`` judgement as the table ``train`` prints."""
    if not envelope or envelope.get("kept") is None:
        return "  uncertain: every training-range criterion acts (not judged on held-out days)"
    judged = envelope.get("judged") or {}
    lines = [f"  {'criterion':<28} {'readings':>8} {'days':>4} {'MAE ' + unit:>10} "
             f"{'ratio':>6}  verdict"]
    for key, j in judged.items():
        mae = j.get("mae")
        ratio = j.get("ratio")
        lines.append(f"  {key:<28} {j['n']:>8} {j['days']:>4} "
                     f"{_num(mae, 3):>10} {_num(ratio, 2):>6}  "
                     f"{'kept' if j['kept'] else 'dropped'}: {j['reason']}")
    kept = envelope.get("kept") or []
    widen = envelope.get("rule", {}).get("widen", 1.0)
    lines.append(f"  uncertain: {', '.join(kept)} (σ × {widen:.2f})" if kept else
                 f"  uncertain: {NONE_KEPT}; never uncertain")
    return "\n".join(lines)


def _num(x: object, digits: int) -> str:
    return f"{x:.{digits}f}" if isinstance(x, int | float) and np.isfinite(x) else "—"
