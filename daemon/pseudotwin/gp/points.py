"""The GP models' conditioning points: at most one per output and ``interval`` of the day.

The window (core/thinning.py) keeps one point per reference and minute; every one of them
costs a GP posterior one Cholesky row, so a day conditions on ~700 rows per reference and
the day's conditioning costs O(n³). The kernels' lengthscales are hours: points a minute
apart carry nearly the same information. A GP model may therefore merge the window's points
of one output into buckets of ``interval`` hours of the local day, ``[k·Δ, (k+1)·Δ)``: the
bucket's point sits at the mean time of its window points and has their mean value. The
newest point moves with each window point that joins its bucket, so the latest reading is
still reflected at once (the posterior re-conditions only that point's row and the few
after it, lazily). ``interval=None`` keeps every window point (no merging).

Only the newest bucket of each output remembers its members (a window revision only ever
targets a sensor's newest point, core/thinning.py); a window point that joins an older
bucket (out of order) updates that bucket's sums.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["INTERVAL_H", "PointBuckets", "merging"]

#: The GP models' point interval [h] (None: one GP point per window point, no merging).
#: Five minutes: a day's GP conditioning costs ~1/100 of one point per minute (O(n³)),
#: and the mean daily NRMSE of corrgp-triv and corrgp-lcm on Room Climate A and B was
#: the same or lower than with every 1-minute point (``scripts/bench_gp_points.py``).
INTERVAL_H: float | None = 5 / 60


@dataclass(slots=True)
class _Bucket:
    """The newest bucket of an output: the only one a window revision can reach."""

    k: int  # bucket number: floor(hours / interval)
    index: int  # the posterior's observation index of the bucket's point
    hours_sum: float
    value_sum: float
    count: int
    members: dict[float, float] = field(default_factory=dict)  # hours → value

    @property
    def point(self) -> tuple[float, float]:
        return self.hours_sum / self.count, self.value_sum / self.count


#: An older bucket: (index, hours_sum, value_sum, count). A plain tuple of numbers, which the
#: cyclic garbage collector stops tracking: a thousand twins hold ~300 buckets each by the
#: evening, and every full collection would traverse them all (hundreds of ms).
_Sums = tuple[int, float, float, int]


class PointBuckets:
    """Which GP point each window point of an output goes to (one day's state)."""

    def __init__(self, interval_h: float) -> None:
        if not interval_h > 0:
            raise ValueError(f"GP point interval must be positive, got {interval_h} h")
        self.interval_h = interval_h
        self._older: dict[tuple[int, int], _Sums] = {}  # (output, k) → an older bucket
        self._newest: dict[int, _Bucket] = {}  # output → its newest bucket

    def _k(self, hours: float) -> int:
        # A hair of slack: hours-of-day on a bucket boundary may come out 1 ulp below it.
        return math.floor(hours / self.interval_h + 1e-9)

    def offer(self, o: int, hours: float, value: float, next_index: int
              ) -> tuple[int | None, float, float]:
        """A new window point of output ``o``: (None, hours, value) when it makes a new GP
        point (which the caller adds as observation ``next_index``), else (index of the GP
        point it joins, that point's new time, its new value)."""
        k = self._k(hours)
        newest = self._newest.get(o)
        if newest is not None and newest.k == k:
            newest.hours_sum += hours
            newest.value_sum += value
            newest.count += 1
            newest.members[hours] = value
            return (newest.index, *newest.point)
        sums = self._older.get((o, k))
        if sums is not None:  # out of order: joins an older bucket
            index, h_sum, v_sum, count = sums
            h_sum, v_sum, count = h_sum + hours, v_sum + value, count + 1
            self._older[(o, k)] = (index, h_sum, v_sum, count)
            return index, h_sum / count, v_sum / count
        if newest is None or k > newest.k:
            if newest is not None:
                self._older[(o, newest.k)] = (newest.index, newest.hours_sum,
                                              newest.value_sum, newest.count)
            self._newest[o] = _Bucket(k, next_index, hours, value, 1, {hours: value})
        else:  # a new bucket before the newest (out of order): never revised
            self._older[(o, k)] = (next_index, hours, value, 1)
        return None, hours, value

    def revise(self, o: int, hours: float, value: float) -> tuple[int, float, float]:
        """Window point (``o``, ``hours``) has a new value: (index, time, value) of its GP
        point. KeyError when it is not a member of the output's newest bucket."""
        b = self._newest.get(o)
        if b is None or hours not in b.members:
            raise KeyError(f"no newest GP point of output {o} holds the window point at "
                           f"{hours} h")
        b.value_sum += value - b.members[hours]
        b.members[hours] = value
        return (b.index, *b.point)


def merging() -> PointBuckets | None:
    """A fresh day's buckets at :data:`INTERVAL_H` (None when GP points are not merged)."""
    return PointBuckets(INTERVAL_H) if INTERVAL_H else None
