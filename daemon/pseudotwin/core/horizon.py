"""Operating hours, wall-clock time of day, the slot grid and the rolling-horizon day.

Time inputs of every model are *wall-clock* hours of the local day (``08:30`` → 8.5), so a
DST change (which happens at night) never shifts the operating hours. Days are local
calendar days.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from dataclasses import dataclass
from functools import cached_property, lru_cache
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import numpy as np
import pandas as pd

from pseudotwin.errors import ConfigError

_MINUTE = dt.timedelta(minutes=1)

_HHMM = re.compile(r"(\d{1,2}):(\d{2})")


def zone_hint(name: str) -> str:
    """What to say after "unknown time zone": the IANA zone a name is but for its letter
    case ("utc" → 'UTC'), else the closest one's name, else an example of the form. Empty
    of suggestions without tzdata."""
    import difflib
    from zoneinfo import available_timezones

    zones = available_timezones()
    same = sorted(z for z in zones if z.lower() == name.strip().lower())
    # Only a Region/City name is spelt like its zone: "CEST" is not "EST", "UTC+1" not "UTC".
    close = same or ("/" in name
                     and difflib.get_close_matches(name, list(zones), n=1, cutoff=0.6))
    if close:
        return f" (did you mean {close[0]!r}?)"
    return (" (an IANA name such as 'Europe/Berlin' or 'UTC', not an abbreviation or a UTC "
            "offset: a zone's offset changes with daylight saving time)")


@lru_cache(maxsize=64)
def _folds(timezone: str, day: dt.date) -> tuple[tuple[float, float, float], ...]:
    """The DST folds of local ``day`` (the wall-clock interval a fall-back shows twice), as
    (first pass start [epoch s], length [s], wall-clock hours of its start): none on a day of
    24 h or less. The transition is found by bisection on the UTC offset."""
    tz = ZoneInfo(timezone)
    start = dt.datetime.combine(day, dt.time(0), tzinfo=tz).timestamp()
    end = dt.datetime.combine(day + dt.timedelta(days=1), dt.time(0), tzinfo=tz).timestamp()
    if end - start <= 86400.0:
        return ()

    def offset(u: float) -> float:
        off = dt.datetime.fromtimestamp(u, tz).utcoffset()
        return 0.0 if off is None else off.total_seconds()

    lo, hi = start, end  # offset(lo) is the day's first; the change lies in (lo, hi]
    first = offset(lo)
    while hi - lo > 0.5:
        mid = (lo + hi) / 2.0
        lo, hi = (mid, hi) if offset(mid) == first else (lo, mid)
    t = float(round(hi))  # transitions fall on whole seconds (whole minutes, in practice)
    length = first - offset(t)
    if length <= 0:
        return ()
    loc = dt.datetime.fromtimestamp(t - length, tz)
    return ((t - length, length, loc.hour + loc.minute / 60.0 + loc.second / 3600.0),)


def parse_hhmm(text: str, what: str = "time of day") -> float:
    """Wall-clock hours [h] of ``"HH:MM"`` (``"08:30"`` → 8.5), 00:00..24:00.

    The one HH:MM parser (operating hours, the configuration); raises ConfigError naming
    ``what``.
    """
    m = _HHMM.fullmatch(text)
    if not m:
        raise ConfigError(f"{what}: expected HH:MM, got {text!r}")
    h, mi = int(m[1]), int(m[2])
    if h > 24 or mi >= 60 or (h == 24 and mi):
        raise ConfigError(f"{what}: {text!r} is not a time of day")
    return h + mi / 60.0


def format_hhmm(hours: float) -> str:
    """``"HH:MM"`` of wall-clock ``hours`` [h] (8.5 → ``"08:30"``): :func:`parse_hhmm`'s
    inverse."""
    m = int(round(hours * 60))
    return f"{m // 60:02d}:{m % 60:02d}"


@dataclass(frozen=True)
class OperatingHours:
    """When a twin works each day.

    day_start, day_end: wall-clock hours [h] of the published window (default 08:00–19:00).
    init_minutes: collection phase before ``day_start`` [min]; nothing is published in it.
    slot_minutes: width of the time-of-day grid used by TRIV and VARMA [min].
    timezone: IANA zone name of the building.
    """

    day_start: float = 8.0
    day_end: float = 19.0
    init_minutes: float = 30.0
    slot_minutes: float = 15.0
    timezone: str = "UTC"

    def __post_init__(self) -> None:
        if not (0.0 <= self.day_start < self.day_end <= 24.0):
            raise ConfigError(
                f"operating hours: day_start {format_hhmm(self.day_start)} must be before "
                f"day_end {format_hhmm(self.day_end)}"
            )
        if not self.init_minutes >= 0.0:
            raise ConfigError(f"init_minutes {self.init_minutes:g}: must be ≥ 0")
        if not self.init_minutes <= 60.0 * self.day_start:
            raise ConfigError(
                f"operating hours: init phase of {self.init_minutes:g} min does not fit before "
                "day_start on the same day"
            )
        if not (1.0 <= self.slot_minutes <= 120.0) or (24 * 60) % self.slot_minutes:
            raise ConfigError(
                f"slot_minutes {self.slot_minutes:g}: must divide a day and lie in 1..120"
            )
        try:
            ZoneInfo(self.timezone)
        except (ZoneInfoNotFoundError, ValueError, OSError):  # OSError: "Europe", a folder
            raise ConfigError(f"unknown time zone {self.timezone!r}"
                              f"{zone_hint(self.timezone)}") from None

    @classmethod
    def from_strings(
        cls,
        day_start: str = "08:00",
        day_end: str = "19:00",
        init_minutes: float = 30.0,
        slot_minutes: float = 15.0,
        timezone: str = "UTC",
    ) -> OperatingHours:
        return cls(
            parse_hhmm(day_start, "day_start"),
            parse_hhmm(day_end, "day_end"),
            float(init_minutes),
            float(slot_minutes),
            timezone,
        )

    # Cached: the per-reading paths (Twin.observe, a model's slot lookup) ask for these
    # thousands of times a second; a frozen dataclass never changes them.
    @cached_property
    def tz(self) -> ZoneInfo:
        return ZoneInfo(self.timezone)

    @cached_property
    def init_start(self) -> float:
        """Start of the init phase [h, wall clock]."""
        return self.day_start - self.init_minutes / 60.0

    @cached_property
    def _window_slot_bounds(self) -> tuple[int, int]:
        slots = self.window_slots()
        return int(slots[0]), len(slots)

    def window_slot_index(self, hours: float) -> int:
        """Index into :meth:`window_slots` of wall-clock ``hours`` [h], clamped to the window
        (a scalar :meth:`slot_of` without numpy's per-call cost)."""
        slot = min(max(math.floor(hours / self.slot_hours + 1e-9), 0), self.n_slots - 1)
        first, count = self._window_slot_bounds
        return min(max(slot - first, 0), count - 1)

    def is_in_window(self, hours: float) -> bool:
        """Scalar :meth:`in_window`."""
        return self.init_start <= hours <= self.day_end

    @property
    def slot_hours(self) -> float:
        return self.slot_minutes / 60.0

    @property
    def n_slots(self) -> int:
        """Number of slots in a whole day."""
        return int(round(24.0 / self.slot_hours))

    def window_slots(self) -> np.ndarray:
        """Indices of the slots from init start to day end: [S]."""
        first = int(np.floor(self.init_start / self.slot_hours + 1e-9))
        last = int(np.ceil(self.day_end / self.slot_hours - 1e-9))
        return np.arange(first, last)

    def slot_of(self, hours: np.ndarray | float) -> np.ndarray:
        """Slot index of wall-clock hours [h]."""
        idx = np.floor(np.asarray(hours, dtype=float) / self.slot_hours + 1e-9).astype(int)
        return np.clip(idx, 0, self.n_slots - 1)

    def slot_index_of(self, hours: float) -> int:
        """Scalar :meth:`slot_of` (the same arithmetic, without numpy's per-call cost)."""
        return min(max(math.floor(hours / self.slot_hours + 1e-9), 0), self.n_slots - 1)

    # -- timestamps -------------------------------------------------------------------
    def local(self, ts: pd.Series | pd.DatetimeIndex) -> pd.DatetimeIndex:
        idx = pd.DatetimeIndex(ts)
        if idx.tz is None:
            raise ConfigError("timestamps must be timezone-aware")
        return idx.tz_convert(self.timezone)

    def day_and_hours(self, ts: pd.Series | pd.DatetimeIndex) -> tuple[np.ndarray, np.ndarray]:
        """Local calendar day (datetime64[D]) and wall-clock hours [h] of each timestamp."""
        loc = self.local(ts)
        days = loc.tz_localize(None).normalize().values.astype("datetime64[D]")
        hours = (
            loc.hour.values + loc.minute.values / 60.0 + loc.second.values / 3600.0
            + loc.microsecond.values / 3.6e9
        )
        return days, np.asarray(hours, dtype=float)

    def day_of(self, ts: dt.datetime) -> dt.date:
        return ts.astimezone(self.tz).date()

    def hours_of(self, ts: dt.datetime) -> float:
        loc = ts.astimezone(self.tz)
        return loc.hour + loc.minute / 60.0 + loc.second / 3600.0 + loc.microsecond / 3.6e9

    def day_and_hours_of(self, ts: dt.datetime) -> tuple[dt.date, float]:
        """:meth:`day_of` and :meth:`hours_of` with one time-zone conversion."""
        loc = ts.astimezone(self.tz)
        hours = loc.hour + loc.minute / 60.0 + loc.second / 3600.0 + loc.microsecond / 3.6e9
        return loc.date(), hours

    # -- the twins' time of day: wall clock, in time order through a DST fold ------------------
    def clock_of(self, ts: dt.datetime) -> float:
        """The hours [h] every twin's models see for ``ts``: its wall-clock hours
        (:meth:`hours_of`), except in a DST fold, whose wall-clock interval the day shows twice
        (02:00–03:00 on an autumn night in Berlin): both passes are mapped onto it in time
        order at half speed, so the day's hours never go back. By wall clock the second pass
        lies before the first one's end, and every model (sample-and-hold, the GP's inputs,
        VARMA's slots) took its readings as older than the first pass's: an hour long the
        estimate held the reference's value from before the change."""
        return self.day_and_clock_of(ts)[1]

    def day_and_clock_of(self, ts: dt.datetime) -> tuple[dt.date, float]:
        """:meth:`day_of` and :meth:`clock_of`."""
        day, hours = self.day_and_hours_of(ts)
        for first, length, wall in _folds(self.timezone, day):
            into = ts.timestamp() - first
            if 0.0 <= into < 2.0 * length:
                return day, wall + into / 7200.0
        return day, hours

    def day_and_clock(self, ts: pd.Series | pd.DatetimeIndex) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`day_and_hours` with the hours of :meth:`clock_of`."""
        days, hours = self.day_and_hours(ts)
        if len(days) == 0:
            return days, hours
        secs = None
        for day in np.unique(days):
            folds = _folds(self.timezone, day.astype(object))
            if not folds:
                continue
            if secs is None:
                secs = pd.DatetimeIndex(ts).as_unit("ns").asi8 / 1e9
                hours = hours.copy()
            for first, length, wall in folds:
                into = secs - first
                m = (days == day) & (into >= 0.0) & (into < 2.0 * length)
                hours[m] = wall + into[m] / 7200.0
        return days, hours

    def at(self, day: dt.date, hours: float) -> dt.datetime:
        """The aware instant of wall-clock ``hours`` on local ``day``.

        A wall-clock time inside a DST gap does not exist: it is the gap's end, the first
        instant after it (02:15 on a spring-forward night is 03:00, not 03:15, which a window
        opening then would have missed); in a fold the first occurrence is taken.
        """
        base = dt.datetime.combine(day, dt.time(0), tzinfo=self.tz)
        secs = round(hours * 3600.0, 6)
        naive = dt.datetime.combine(day, dt.time(0)) + dt.timedelta(seconds=secs)
        aware = naive.replace(tzinfo=self.tz, fold=0)
        if not self._exists(aware):
            # Gaps end on a whole minute: the first existing one after the time.
            wall = naive.replace(second=0, microsecond=0)
            while not self._exists(aware := (wall := wall + _MINUTE).replace(tzinfo=self.tz)):
                pass
        return aware if aware >= base else base

    def _exists(self, aware: dt.datetime) -> bool:
        """Whether ``aware``'s wall time exists in the zone (a time in a DST gap round-trips
        through UTC to another wall time)."""
        return aware.astimezone(dt.UTC).astimezone(self.tz).replace(tzinfo=None) \
            == aware.replace(tzinfo=None)

    def grid(self, day: dt.date, step_hours: float) -> list[dt.datetime]:
        """The publish grid of one local day: the multiples of ``step_hours`` since local
        midnight from day start to day end, before the next midnight (wall clock, so a DST
        day has the same instants on the clock). Anchored at midnight, a 15-min grid is on
        the quarter hours whatever the day start: what an MPC samples). The instants a DST
        gap swallows are not on it: the clock never shows them; those of a fold are on it
        twice, the second pass's at its fixed UTC offset (so that every comparison of two
        instants is in UTC: two of one ZoneInfo compare by wall clock), in time order. The
        fold's second hour had no instant: its baselines and monitor skipped 75 minutes."""
        first = math.ceil(self.day_start / step_hours - 1e-9)
        last = math.floor(min(self.day_end, 24.0 - 1e-6) / step_hours + 1e-9)
        instants = [(k * step_hours, self.at(day, k * step_hours)) for k in range(first, last + 1)]
        out = []
        for h, t in instants:
            if abs(self.hours_of(t) - h) >= 1e-6:
                continue  # in a gap
            out.append(t)
            second = t.replace(fold=1)
            if (offset := second.utcoffset()) != t.utcoffset() and offset is not None:
                out.append(second.astimezone(dt.timezone(offset)))
        return sorted(out, key=lambda t: t.timestamp()) if len(out) > len(instants) else out

    def in_operating_hours(self, hours: np.ndarray | float) -> np.ndarray:
        h = np.asarray(hours, dtype=float)
        return (h >= self.day_start) & (h <= self.day_end)

    def in_window(self, hours: np.ndarray | float) -> np.ndarray:
        h = np.asarray(hours, dtype=float)
        return (h >= self.init_start) & (h <= self.day_end)

    def describe(self) -> str:
        """One readable line: ``08:00–19:00 Europe/Madrid, init 30 min, slots 15 min``."""
        return (f"{format_hhmm(self.day_start)}–{format_hhmm(self.day_end)} {self.timezone}, "
                f"init {self.init_minutes:g} min, slots {self.slot_minutes:g} min")

    def to_dict(self) -> dict:
        return {
            "day_start": self.day_start,
            "day_end": self.day_end,
            "init_minutes": self.init_minutes,
            "slot_minutes": self.slot_minutes,
            "timezone": self.timezone,
        }

    @classmethod
    def from_dict(cls, d: dict) -> OperatingHours:
        return cls(
            float(d["day_start"]), float(d["day_end"]), float(d["init_minutes"]),
            float(d["slot_minutes"]), str(d["timezone"]),
        )
