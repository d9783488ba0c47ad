"""Configured sensors that fall silent in operating hours, as the recorder sees them.

During commissioning the recorder is all that runs: the twins are not trained yet, so no
estimate goes stale and nothing else notices a dead desk sensor. Its days were then missing
at ``train`` time, days after the fact. A sensor that sends no valid reading for longer than
``stale_after_minutes`` (the daemon's own measure of a silent reference) while the clock is
in operating hours is told, once per silence, and again when it reports; at most
``LINES_PER_DAY`` silences per sensor and local day, then that it flaps. Silence is counted
from the day start at the earliest (a sensor may rest at night) and from the latest
(re)connect of the listener (while it was away from the broker, nothing could be heard).
"""

from __future__ import annotations

import datetime as dt
import logging
from collections import Counter
from collections.abc import Iterable

from pseudotwin.core.horizon import OperatingHours

log = logging.getLogger(__name__)

LINES_PER_DAY = 3  # silences told per sensor and local day


class SilenceWatch:
    """sensors: the configured sensor ids; after: how long without a valid reading is
    silent; start: when listening began (a sensor unheard of since is silent from there)."""

    def __init__(self, sensors: Iterable[str], hours: OperatingHours, after: dt.timedelta,
                 start: dt.datetime, who: str = "recorder") -> None:
        self.hours = hours
        self.after = after
        self.who = who
        self._last: dict[str, dt.datetime] = dict.fromkeys(sensors, start)
        self._listening = start  # the latest (re)connect
        self._silent: dict[str, bool] = {}  # silent sensor → whether its silence was told
        self._day: dt.date | None = None
        self._told: Counter[str] = Counter()

    def heard(self, sensor: str, at: dt.datetime) -> None:
        """A valid reading of ``sensor`` arrived at ``at``."""
        if sensor not in self._last:
            return
        since = self._last[sensor]
        self._last[sensor] = max(since, at)
        if (told := self._silent.pop(sensor, None)) is not None and told:
            log.info("%s: sensor %s reports again after %.0f min without a reading", self.who,
                     sensor, (at - since).total_seconds() / 60.0)

    def listening(self, since: dt.datetime) -> None:
        """The listener (re)connected at ``since``: silence counts from there."""
        self._listening = since

    def check(self, now: dt.datetime) -> list[str]:
        """Tell the sensors newly silent at ``now`` (only in operating hours: outside them
        a sensor may rest); returns them. Call only while connected."""
        day, hours = self.hours.day_and_hours_of(now)
        if not self.hours.day_start <= hours <= self.hours.day_end:
            return []
        floor = max(self._listening, self.hours.at(day, self.hours.day_start))
        went = [s for s, last in self._last.items()
                if s not in self._silent and now - max(last, floor) > self.after]
        if not went:
            return []
        if day != self._day:
            self._day, self._told = day, Counter()
        self._told.update(went)
        told = [s for s in went if self._told[s] <= LINES_PER_DAY]
        self._silent.update((s, s in told) for s in went)
        if told:
            flapping = [s for s in told if self._told[s] == LINES_PER_DAY]
            last = {s: self._last[s].astimezone(self.hours.tz).strftime("%Y-%m-%d %H:%M")
                    for s in told}
            log.warning(
                "%s: no reading of %s for more than %g min in operating hours (last one, or "
                "the start: %s): nothing of it is stored. Check the sensor, its bridge and "
                "the broker's ACL; a desk sensor silent on a commissioning day leaves that "
                "day out of training%s", self.who, ", ".join(told),
                self.after.total_seconds() / 60.0,
                ", ".join(f"{s} {t}" for s, t in last.items()),
                f". {', '.join(flapping)}: silent {LINES_PER_DAY} times today; further "
                "silences today are not logged" if flapping else "")
        return went
