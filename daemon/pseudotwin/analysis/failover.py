"""Training the failover candidates: per reference the primary reads, the best model that does
without it, and, with three references or more, per reference the best model on it alone
(live/failover.py says how the twin uses them).

For each such reduced twin (reference r removed, or every reference but r), the candidates
``FAILOVER_KINDS`` are trained and validated exactly like the twin's own candidates
(leave-one-day-out over the training days, the same tie rule, σ calibrated on the held-out
errors: analysis/validation.py).
Only cheap kinds by default: the raw reference and the TRIV family (TRIV, its shrunk or
smoothed offset profile, its weekend profile, TRIV with covariates) need no GP fit, so
failover adds seconds to ``train``, not minutes; a kind that cannot serve the reduced twin
(triv-cov without covariates) is skipped.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import pandas as pd

from pseudotwin.analysis import validation
from pseudotwin.core.series import DayReadings
from pseudotwin.core.spec import TwinSpec
from pseudotwin.core.thinning import Thinning
from pseudotwin.errors import DataError
from pseudotwin.live.failover import Failover, label
from pseudotwin.models.base import TrainingSet
from pseudotwin.models.registry import build, model_class

log = logging.getLogger(__name__)

# Cheap candidates (no GP fit): a failover answers for hours at most, until the sensor is back.
FAILOVER_KINDS: tuple[str, ...] = ("ref", "triv", "triv-shrunk", "triv-smooth", "triv-week",
                                   "triv-cov")


def train_failover(
    df: pd.DataFrame,
    spec: TwinSpec,
    days: Sequence[DayReadings],
    needed: Sequence[str],
    kinds: Sequence[str] = FAILOVER_KINDS,
    options: Mapping[str, Mapping[str, Any]] | None = None,
    thinning: Thinning | None = None,
) -> tuple[dict[str, Failover], dict[str, Failover]]:
    """(lost reference → its validated failover, for each of ``needed``, the references the
    primary reads; kept reference → the validated failover reading it alone, for each
    reference of a twin with three or more, which answers when two or more are silent).
    Both empty for a single-reference twin, the second for a two-reference one (a failover
    without one reads the other alone); a reduced twin whose candidates cannot be validated
    gets none (logged): losing what it does without makes the estimate stale, as before."""
    refs = spec.references
    if len(refs) < 2:
        return {}, {}
    # A model option naming the lost reference (say ref's ``reference``) cannot apply.
    opts = {k: {o: v for o, v in (options or {}).get(k, {}).items()
                if o not in ("reference", "references")} for k in kinds}
    without = {lost: f for lost in needed
               if (f := _best_without(df, spec, days, (lost,), kinds, opts, thinning))}
    alone = ({kept: f for kept in refs if (f := _best_without(
        df, spec, days, tuple(r for r in refs if r != kept), kinds, opts, thinning))}
             if len(refs) >= 3 else {})
    return without, alone


def _best_without(
    df: pd.DataFrame,
    spec: TwinSpec,
    days: Sequence[DayReadings],
    lost: tuple[str, ...],
    kinds: Sequence[str],
    opts: Mapping[str, Mapping[str, Any]],
    thinning: Thinning | None,
) -> Failover | None:
    """The best validated candidate of the twin without ``lost`` (None, logged, when none
    can be validated)."""
    others = replace(spec, references=tuple(r for r in spec.references if r not in lost))
    name = label(lost, others.references)
    usable = [k for k in kinds if not model_class(k).not_applicable(others)]
    try:
        # a setting left to validation (triv-smooth's span) is chosen for the reduced twin
        settings, _ = validation.choose_settings(df, others, days, usable, opts, thinning)
        v = validation.validate(df, others, days, usable, settings, thinning=thinning)
    except DataError as exc:
        log.warning("no failover %s: %s", name, exc)
        return None
    if not math.isfinite(v.scores[v.primary].nrmse_pct):  # nothing to rank it by
        log.warning("no failover %s: its held-out error is not finite", name)
        return None
    model = build(v.primary, settings.get(v.primary)).fit(TrainingSet(others, tuple(days)))
    log.info("failover %s: %s on %s (held-out %.2f %%)", name, v.primary,
             ", ".join(model.references_), v.scores[v.primary].nrmse_pct)
    return Failover(lost, v.primary, model, v.calibration.get(v.primary),
                    v.scores[v.primary].nrmse_pct, v.reason)
