"""The data found per sensor and day, and whether it is enough to commission a twin.

A sensor-day is judged by the readings that fall in the operating hours: how many, the share
of the slot grid's operating-hours slots that hold at least one reading (coverage), and the
longest silence. ``train`` itself only skips a day when a sensor has fewer than
``MIN_READINGS_PER_DAY`` readings there; the report is stricter, because a day that passes
with a few readings teaches the models little and its held-out score says little.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import pandas as pd

from pseudotwin.analysis.training import MIN_READINGS_PER_DAY
from pseudotwin.analysis.validation import MIN_DAYS
from pseudotwin.core.spec import TwinSpec
from pseudotwin.live.artifact import Artifact

GOOD_COVERAGE = 0.75  # share of operating-hours slots with a reading for a "good" sensor-day
# Training days within this many calendar days see one stretch of weather: held out in turn,
# each is estimated from its neighbours, and validation cannot see the offset between the
# rooms wander over weeks (docs/pairs.txt measures what that does to σ).
ONE_STRETCH_DAYS = 14


class Level(Enum):
    """How good something is, from best to worst; the page colours it."""

    GOOD = "good"
    THIN = "thin"
    MISSING = "missing"


@dataclass(frozen=True)
class SensorDay:
    """One sensor on one local day, within the operating hours.

    readings: count; coverage: share [0, 1] of the operating-hours slots holding a reading;
    longest_gap_min: longest time without a reading [min], the window's edges included.
    """

    day: dt.date
    sensor: str
    readings: int
    coverage: float
    longest_gap_min: float

    @property
    def level(self) -> Level:
        if self.readings < MIN_READINGS_PER_DAY:
            return Level.MISSING
        return Level.GOOD if self.coverage >= GOOD_COVERAGE else Level.THIN

    @property
    def verdict(self) -> str:
        if self.level is Level.MISSING:
            return (f"too few readings (< {MIN_READINGS_PER_DAY} in operating hours): "
                    "train skips the day")
        if self.level is Level.THIN:
            return f"thin: below {GOOD_COVERAGE:.0%} of the slots"
        return "enough"


@dataclass(frozen=True)
class DataFound:
    """Every sensor-day from the first candidate day to the last training day, with the
    days training used, those the engineer left out (--skip-days), and the overall verdict."""

    rows: list[SensorDay]
    training_days: list[dt.date]
    left_out: list[dt.date] = field(default_factory=list)

    def day_status(self, day: dt.date) -> str:
        if day in self.training_days:
            return "training day"
        if day in self.left_out:
            return "left out (--skip-days)"
        missing = [r.sensor for r in self.rows if r.day == day and r.level is Level.MISSING]
        if missing:
            return f"skipped: no data of {', '.join(missing)}"
        return "not used"

    @property
    def level(self) -> Level:
        used = [r for r in self.rows if r.day in self.training_days]
        if len(self.training_days) < MIN_DAYS:
            return Level.MISSING
        return Level.GOOD if all(r.level is Level.GOOD for r in used) else Level.THIN

    @property
    def span_days(self) -> int:
        """Calendar days from the first training day to the last, both counted."""
        return (max(self.training_days) - min(self.training_days)).days + 1

    def verdict(self) -> str:
        """A few sentences a commissioning engineer can act on."""
        n = len(self.training_days)
        if self.level is Level.MISSING:
            return (f"Not enough: {n} training day(s); at least {MIN_DAYS} are needed to hold "
                    "days out, choose the primary and calibrate σ. Leave the desk sensor in "
                    "place longer.")
        thin = [r for r in self.rows if r.day in self.training_days and r.level is not Level.GOOD]
        if not thin:
            said = (f"Enough: {n} training days, and on each every sensor has readings in at "
                    f"least {GOOD_COVERAGE:.0%} of the operating-hours slots.")
        else:
            worst = min(thin, key=lambda r: r.coverage)
            said = (f"Usable, but thin: {len(thin)} sensor-day(s) of the {n} training days "
                    f"cover less than {GOOD_COVERAGE:.0%} of the operating hours (worst: "
                    f"{worst.sensor} on {worst.day}, {worst.coverage:.0%}). The scores below "
                    "rest on less data than they seem to; more days with the desk sensor "
                    "would make them firmer.")
        return f"{said} {self.span_advice()}".strip()

    def span_advice(self) -> str:
        """What training days close together cannot show; empty when they are spread."""
        if len(self.training_days) < 2 or self.span_days > ONE_STRETCH_DAYS:
            return ""
        return (f"The training days lie within {self.span_days} calendar days, one stretch of "
                "weather: σ is measured on days alike, and the offset between the rooms "
                "wanders more over the following weeks, so σ is likely too narrow months later "
                "(docs/pairs.txt). Check it when the desk sensor is back for a day (the "
                "monitor's target figures), and if it can stay longer or come back, more days "
                "further apart let validation see more of that (train takes the first "
                "--train-days days on which every sensor reports).")


def training_data(df: pd.DataFrame, artifact: Artifact, first: dt.date) -> DataFound:
    """:func:`data_found` for the days an artifact was trained on and left out."""
    days = [dt.date.fromisoformat(d) for d in artifact.training.get("days", [])]
    left_out = [dt.date.fromisoformat(d) for d in artifact.training.get("skipped", [])]
    return data_found(df, artifact.spec, min([first, *days]), days, left_out)


def data_found(df: pd.DataFrame, spec: TwinSpec, first: dt.date,
               training_days: Sequence[dt.date],
               left_out: Sequence[dt.date] = ()) -> DataFound:
    """Readings per sensor and local day from ``first`` to the last training day."""
    hours = spec.hours
    last = max(training_days)
    days = [first + dt.timedelta(days=i) for i in range((last - first).days + 1)]
    sub = df[df["sensor"].isin(spec.sensors)]
    day_of, hrs = hours.day_and_hours(sub["ts"])
    inside = hours.in_operating_hours(hrs)
    sensors = sub["sensor"].to_numpy()
    slots = np.arange(int(np.floor(hours.day_start / hours.slot_hours + 1e-9)),
                      int(np.ceil(hours.day_end / hours.slot_hours - 1e-9)))
    rows = []
    for day in days:
        on_day = inside & (day_of == np.datetime64(day))
        for s in spec.sensors:
            h = np.sort(hrs[on_day & (sensors == s)])
            covered = np.isin(slots, hours.slot_of(h)).mean() if len(slots) else 0.0
            edges = np.concatenate([[hours.day_start], h, [hours.day_end]])
            rows.append(SensorDay(day, s, len(h), float(covered),
                                  float(np.max(np.diff(edges))) * 60.0))
    return DataFound(rows, sorted(training_days), sorted(left_out))
