"""Causal replay of a history through one :class:`~pseudotwin.live.twin.Twin`: every reading
in time order, exactly as the daemon receives them, and at each true target reading in
operating hours every model's estimate from the references' readings up to that instant.
``evaluate`` scores the days after training with it, the validation the held-out training
days.

A chatty target is scored once per ``min_interval`` bucket (core/thinning.py), at its last
reading, against the mean of the bucket's readings: the truth its 1-minute means would give,
estimated from the references' readings of the same interval (still causal: none after the
instant), and a day's score costs what a reading a minute costs."""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence

import numpy as np
import pandas as pd

from pseudotwin.core.thinning import Thinning
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.failover import NONE_LOST, lost_json
from pseudotwin.live.twin import Twin

REF_PREFIX = "ref:"
# Joins the criteria of a row's ``unlike``: a control character, which sensor ids (and so
# criterion keys) cannot contain, unlike a space.
UNLIKE_SEP = "\x1f"
ESTIMATE = "estimate"  # the rows of what the daemon publishes on <twin>/estimate
COLUMNS = ["ts", "model", "value", "std", "truth", "quality", "slope", "source", "lost"]


def replay_estimates(
    artifact: Artifact,
    history: pd.DataFrame,
    start: dt.date,
    models: Sequence[str] | None = None,
    end: dt.date | None = None,
    thinning: Thinning | None = None,
    stale_after: dt.timedelta | None = None,
    criteria: bool = False,
) -> pd.DataFrame:
    """Estimates at every true target reading in operating hours of days ``start``…``end``.

    Rows (ts, model, value, std, truth, quality, slope, source, lost): one per model that
    answered; rows of model ``estimate``, exactly what the daemon would publish on
    ``<twin>/estimate`` (the primary, with its fallbacks and quality flags; nothing in the
    init phase); and, as pseudo-models ``ref:<sensor>``, the raw reference value held at that
    time, at the instants where some model answered and the reference is in today's window
    (its daily Pearson r with the target is the evidence of how much a reference can tell).
    slope: the references' |slope| [unit/h] the model's σ saw. source, lost: the payload's
    ``model`` (the name of the model that produced the value: a fallback's or a failover's,
    VARMA's own form) and ``lost`` (the silent references a failover answered without, a
    JSON list; ``[]`` otherwise).
    thinning: the window's policy, as the daemon's configuration sets it (default one point
    per sensor and minute). stale_after: the daemon's, to score what it publishes while a
    reference is silent (quality ``stale``, or a failover's ``fallback``); default None: a
    silent reference's last value is held. criteria: add a column ``unlike``, the envelope
    criteria that fired on the row, joined by ``UNLIKE_SEP`` (live/envelope.py; what
    validation judges them on).
    """
    hours = artifact.hours
    thinning = thinning or Thinning()
    twin = Twin(artifact, models=models, thinning=thinning, stale_after=stale_after,
                record_unlike=criteria)
    refs = list(artifact.references)
    primary = artifact.primary
    sub = history[history["sensor"].isin([*artifact.inputs, artifact.target])]
    days, hrs = hours.day_and_hours(sub["ts"])
    keep = np.ones(len(sub), dtype=bool)
    if end is not None:
        keep = days <= np.datetime64(end)
    is_target = (sub["sensor"] == artifact.target).values
    score = is_target & (days >= np.datetime64(start)) & hours.in_operating_hours(hrs) & keep
    # Readings at the same instant: references first, so an estimate at t sees them.
    order = np.lexsort((is_target, pd.DatetimeIndex(sub["ts"]).asi8))
    order = order[keep[order]]
    # An object array: iterating pandas' string array costs a Python call per reading.
    sensors = sub["sensor"].to_numpy(dtype=object)[order]
    stamps = pd.DatetimeIndex(sub["ts"]).tz_convert("UTC")[order]
    values = sub["value"].values[order]
    scored = score[order]
    truths = values.astype(float)
    tgt = np.flatnonzero(sensors == artifact.target)
    if len(tgt):  # one score per target bucket: at its last reading, against its mean
        bucket = thinning.buckets(artifact.target, stamps[tgt])
        first = np.r_[True, bucket[1:] != bucket[:-1]]
        last = np.r_[bucket[1:] != bucket[:-1], True]
        group = np.cumsum(first) - 1
        mean = np.bincount(group, truths[tgt]) / np.bincount(group)
        scored[tgt] &= last
        truths[tgt] = mean[group]
    held: dict[str, float] = {}
    rows: list[tuple[object, ...]] = []
    # one conversion for all: a Timestamp per reading was ~6 % of a raw (chatty) replay
    moments = stamps.to_pydatetime()
    for s, t, v, sc, truth in zip(sensors, moments, values, scored, truths, strict=True):
        if s != artifact.target:
            twin.observe(s, t, float(v))
            held[s] = float(v)
            continue
        if not sc:
            continue
        h = hours.clock_of(t)  # the twin's time of day (live/twin.py)
        answered = False
        for kind, e in twin.estimate(t).items():
            if not e.finite:
                continue
            answered = True
            slope = twin.slope(artifact.models[kind].references_, h)
            fired = (UNLIKE_SEP.join(e.unlike),) if criteria else ()
            said = (e.model, lost_json(e.lost), *fired)
            rows.append((t, kind, e.value, e.std, truth, e.quality.value, slope, *said))
            if kind == primary and e.publishable:
                rows.append((t, ESTIMATE, e.value, e.std, truth, e.quality.value, slope,
                             *said))
        # "Just use the reference" is scored where the twin could answer and the reference
        # is in today's window: one silent for days has no value today for the twin, nor
        # for the desk.
        for r in refs if answered else ():
            if r in held and twin.latest(r, h) is not None:
                rows.append((t, REF_PREFIX + r, held[r], np.nan, truth, "ok", np.nan,
                             REF_PREFIX + r, NONE_LOST, *(("",) if criteria else ())))
    return pd.DataFrame(rows, columns=[*COLUMNS, *(["unlike"] if criteria else [])])
