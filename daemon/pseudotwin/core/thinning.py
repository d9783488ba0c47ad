"""The window's thinning policy: a bounded conditioning set, whatever a sensor's rate.

Room units on KNX or BACnet often report every 2–10 s. Each conditioning point costs the
GP posterior one Cholesky row (O(n²) per reading, O(n²) memory), so a day of such readings
would make every update slower than the one before. The policy (DESIGN.md §2):

* Time is cut into buckets of ``min_interval`` per sensor (default 1 min), aligned to the
  UTC epoch: ``[k·Δ, (k+1)·Δ)``.
* A sensor's window holds **at most one point per bucket**. The first reading of a bucket
  makes the point (at that reading's time); each later reading of the same bucket revises
  the point's value to the **mean of the bucket's readings so far**. The latest reading is
  thus reflected at once, and a closed bucket's point is that minute's mean, which is what
  the converters' 1-minute means are, so a chatty sensor and its 1-minute means condition
  the models alike. Readings already at most one per bucket (1-minute means, COV sensors)
  pass unchanged: thinning changes nothing for them.
* A reading of an earlier bucket (out of order) makes a point of its own if that bucket has
  none yet, and is dropped otherwise; only the newest bucket's point is revised, because a
  revision costs the GP O(n) only while the point is among its last rows. A reading whose
  time is already in its bucket (a duplicate) is dropped.

The daemon, ``evaluate`` and ``backfill`` all thin here, inside :class:`~pseudotwin.live.twin.Twin`.
Training thins its history with :func:`thin_history` (the same buckets, vectorized), so a
chatty sensor's history trains the twin its 1-minute means would: the models learn from the
points the live window will hold, not from single noisy samples.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import pandas as pd

__all__ = ["DEFAULT_MIN_INTERVAL", "MIN_INTERVAL_SECONDS", "Action", "Thinning",
           "WindowThinner", "thin_history"]

#: One conditioning point per reference and minute: the resolution of the converters'
#: means, far finer than the 15-minute slots and the GP's hour-scale lengthscales.
DEFAULT_MIN_INTERVAL = dt.timedelta(minutes=1)
#: The bucket widths a configuration or the CLI may ask for [s]: below a millisecond a
#: timedelta rounds to nothing; above an hour a point would hide the day's course.
MIN_INTERVAL_SECONDS = (0.001, 3600.0)

_EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)


@dataclass(frozen=True)
class Thinning:
    """Per-sensor bucket widths: ``per_sensor`` overrides ``default`` (both > 0)."""

    default: dt.timedelta = DEFAULT_MIN_INTERVAL
    per_sensor: Mapping[str, dt.timedelta] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, width in {"default": self.default, **self.per_sensor}.items():
            if not width > dt.timedelta(0):
                raise ValueError(f"min_interval of {name} must be positive, got {width}")

    def interval(self, sensor: str) -> dt.timedelta:
        return self.per_sensor.get(sensor, self.default)

    def buckets(self, sensor: str, stamps: pd.DatetimeIndex) -> np.ndarray:
        """The bucket of each of ``sensor``'s (aware) times: [N] (WindowThinner's, vectorized)."""
        width = self.interval(sensor) // dt.timedelta(microseconds=1)
        return np.asarray(stamps.as_unit("us").asi8 // width)

    def describe(self) -> str:
        """E.g. ``one point per 60 s (ref_b: 10 s)``."""
        text = f"one point per {self.default.total_seconds():g} s"
        if self.per_sensor:
            extra = ", ".join(f"{s}: {w.total_seconds():g} s"
                              for s, w in sorted(self.per_sensor.items()))
            text += f" ({extra})"
        return text


class Action(Enum):
    """What a reading does to the window: a new point, a new value of the sensor's newest
    point, or nothing."""

    NEW = "new"
    REVISE = "revise"
    DROP = "drop"


@dataclass
class _Bucket:
    index: int
    point_ts: dt.datetime  # the point's time: the bucket's first reading
    # The readings' times as offsets from the epoch: a timedelta hashes without the
    # utcoffset() call an aware datetime's hash makes, and a chatty sensor hashes one each.
    stamps: set[dt.timedelta]
    total: float

    @property
    def mean(self) -> float:
        return self.total / len(self.stamps)


class WindowThinner:
    """One day's bucket bookkeeping for every sensor of a window.

    State per sensor: its newest bucket (readings' times and sum) and the indices of the
    buckets that hold a point; bounded by the number of points, not of readings.
    """

    def __init__(self, policy: Thinning) -> None:
        self.policy = policy
        self._newest: dict[str, _Bucket] = {}
        self._filled: dict[str, set[int]] = {}
        self.dropped = 0  # readings that changed nothing (duplicates, late into a full bucket)
        self.revised = 0

    def offer(self, sensor: str, ts: dt.datetime, value: float
              ) -> tuple[Action, dt.datetime, float]:
        """The action for reading (``ts`` aware, ``value``) and the point it yields:
        (action, point time, point value). For DROP the point is the reading itself."""
        since = ts - _EPOCH
        k = since // self.policy.interval(sensor)
        newest = self._newest.get(sensor)
        if newest is not None and k == newest.index:
            if since in newest.stamps:
                self.dropped += 1
                return Action.DROP, ts, value
            newest.stamps.add(since)
            newest.total += value
            self.revised += 1
            return Action.REVISE, newest.point_ts, newest.mean
        filled = self._filled.setdefault(sensor, set())
        if k in filled:
            self.dropped += 1
            return Action.DROP, ts, value
        filled.add(k)
        if newest is None or k > newest.index:
            self._newest[sensor] = _Bucket(k, ts, {since}, value)
        return Action.NEW, ts, value


def thin_history(history: pd.DataFrame, policy: Thinning) -> pd.DataFrame:
    """The points a live window holds once each bucket has closed, for a whole history.

    history: canonical rows (sensor, ts aware, value). Per sensor and bucket of
    ``policy``: one row at the bucket's first reading's time with the mean of its readings;
    a repeated timestamp counts once (its first value), as the window drops duplicates.
    Returns the rows in time order (per sensor); a history already at most one reading per
    bucket comes back with the same readings.
    """
    if history.empty:
        return history
    # one stable sort by time: the first reading of a bucket and of a timestamp come first
    rows = history.sort_values("ts", kind="stable")
    rows = rows[~rows.duplicated(["sensor", "ts"], keep="first")]
    stamps = pd.DatetimeIndex(rows["ts"])
    bucket = np.empty(len(rows), dtype=np.int64)
    sensors = rows["sensor"].to_numpy(dtype=object)
    for sensor in pd.unique(sensors):
        mine = sensors == sensor
        bucket[mine] = policy.buckets(sensor, stamps[mine])
    keyed = rows.assign(_bucket=bucket)
    groups = keyed.groupby(["sensor", "_bucket"], sort=False)
    if groups.ngroups == len(keyed):  # nothing shares a bucket: nothing to thin
        return rows.reset_index(drop=True)
    thinned = groups.agg(ts=("ts", "first"), value=("value", "mean")).reset_index()
    return (thinned[["sensor", "ts", "value"]].sort_values("ts", kind="stable")
            .reset_index(drop=True))
