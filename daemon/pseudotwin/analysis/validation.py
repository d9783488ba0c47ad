"""Choosing the primary model and calibrating every model's σ from the training days alone.

Leave-one-day-out (LODO) over the training days: each day in turn is held out, every model is
trained on the other days and the held-out day is replayed causally through a
:class:`~pseudotwin.live.twin.Twin`, exactly as the daemon would run it. Per model this gives
honest errors on a day it has not seen:

- the **primary** is the candidate with the lowest mean held-out daily NRMSE, except that the
  simplest candidate within ``TIE_RELATIVE`` of it wins (the registry's order, ref < triv <
  triv-shrunk < triv-smooth < triv-week < triv-cov < corrgp-triv < corrgp-multi < corrgp-lcm):
  five days cannot tell a 3 % difference from noise, and the simpler model fails in simpler
  ways. The blend (models/blend.py) is not refit per fold: its held-out rows combine the
  members' with weights chosen on the other held-out days. It is measured against the held-out
  error of that choice of one candidate, nested the same way (each held-out day scored by the
  candidate the other days choose), not against the lowest single score, which is optimistic
  (the winner's curse of picking the minimum of several noisy scores); it wins when more than
  3 % below it;
- every model's **σ** is calibrated on its held-out errors (:mod:`pseudotwin.live.calibration`).

Days after the training period are never looked at. Every model is refit in each fold, so the
held-out day cannot leak in through parameters fitted on it; with its ``validation_options``
(GP models: one data-initialized start; VARMA: its OLS VAR(p) form).
"""

from __future__ import annotations

import datetime as dt
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pseudotwin.analysis.replay import REF_PREFIX, UNLIKE_SEP, replay_estimates
from pseudotwin.core.series import DayReadings
from pseudotwin.core.spec import TwinSpec
from pseudotwin.core.thinning import Thinning
from pseudotwin.core.twinlog import collapsed
from pseudotwin.errors import DataError, FitError, NumericalError
from pseudotwin.live import metrics
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.calibration import SigmaCalibration
from pseudotwin.live.envelope import Envelope
from pseudotwin.live.twin import Quality
from pseudotwin.models import blend
from pseudotwin.models.base import Estimate, TrainingSet, TwinModel
from pseudotwin.models.registry import MODELS, build

log = logging.getLogger(__name__)
# A child logger: the folds' collapsing filters sit on the loggers above, so its lines (one per
# held-out day: with several references a fold takes minutes) come out as they happen.
progress = logging.getLogger(f"{__name__}.progress")
_FOLD_LOGGERS = ("pseudotwin.gp.train", "pseudotwin.models.varma", "pseudotwin.live.twin", __name__)

TIE_RELATIVE = 0.03
# A monitoring baseline whose held-out NRMSE exceeds this multiple of TRIV's is not published
# live: a baseline far worse than the simple answer only misleads whoever watches it.
BASELINE_LIMIT = 1.5
MIN_DAYS = 3  # fewer training days leave nothing to hold out against
# The held-out rows' column of σ calibrated without each row's day (NaN: fewer than two
# other days to calibrate on): how the commissioning page shows σ on a day it has not seen.
NESTED_STD = "nested_std"


@dataclass(frozen=True)
class CandidateScore:
    """A model's held-out performance on the training days.

    nrmse_pct: mean held-out daily NRMSE [%]; crps [unit] and cover2_pct [%] of the held-out
    rows with σ calibrated without each row's day (nested leave-one-day-out: how well the
    calibration holds on a day it has not seen); days: days held out; candidate: whether it
    may become the primary; error: why it has no score.
    """

    kind: str
    candidate: bool
    nrmse_pct: float = float("nan")
    crps: float = float("nan")
    cover2_pct: float = float("nan")
    days: int = 0
    error: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "candidate": self.candidate, "nrmse_pct": self.nrmse_pct,
                "crps": self.crps, "cover2_pct": self.cover2_pct, "days": self.days,
                "error": self.error}


@dataclass(frozen=True)
class Validation:
    """The outcome: scores per model, the primary and why, each model's σ calibration."""

    scores: dict[str, CandidateScore]
    primary: str
    reason: str
    calibration: dict[str, SigmaCalibration] = field(default_factory=dict)
    offset_std: float = float("nan")
    seconds: float = 0.0
    withheld: dict[str, str] = field(default_factory=dict)
    # The held-out rows (replay_estimates' columns and ``day``, the models' own std, and
    # NESTED_STD): what the commissioning report plots, so it needs no refit. Not saved in
    # the artifact.
    held_out: pd.DataFrame = field(default_factory=pd.DataFrame, repr=False)
    # The blend's members and weights from all held-out days (models/blend.py; empty: none).
    blend: dict[str, float] = field(default_factory=dict)
    # The nested held-out NRMSE [%] of choosing one candidate, what the blend is measured by.
    selection_nrmse: float = float("nan")
    # Each training day's mean target − reference offset [unit], whose spread is offset_std:
    # the commissioning check of one day unlike the others reads it (commissioning/oddday.py).
    offset_by_day: dict[dt.date, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": f"leave-one-day-out over the training days; tie {TIE_RELATIVE:.0%} "
                      "relative → the simpler model",
            "primary": self.primary,
            "reason": self.reason,
            "offset_std": self.offset_std,
            "offset_by_day": {d.isoformat(): x for d, x in self.offset_by_day.items()},
            "seconds": round(self.seconds, 1),
            "scores": {k: s.to_dict() for k, s in self.scores.items()},
            "withheld": self.withheld,
            **({"blend": self.blend, "selection_nrmse_pct": self.selection_nrmse}
               if self.blend else {}),
        }


def validation_table(v: Mapping[str, Any], unit: str) -> str:
    """An artifact's ``validation`` as the table ``train`` prints."""
    withheld = v.get("withheld", {})
    lines = [f"  {'model':<12} {'held-out NRMSE %':>16} {'CRPS ' + unit:>12} {'±2σ cover %':>11}"
             "  note"]
    for kind, s in v.get("scores", {}).items():
        note = "primary" if kind == v.get("primary") else ("" if s["candidate"] else "baseline")
        if s.get("error"):
            note = s["error"]
        if kind in withheld:
            note = f"not published live: {withheld[kind]}"
        lines.append(f"  {kind:<12} {_num(s['nrmse_pct'], 2):>16} {_num(s['crps'], 3):>12} "
                     f"{_num(s['cover2_pct'], 1):>11}  {note}")
    lines.append(f"  primary {v.get('reason', '')}")
    lines.extend(tuned_lines(v))
    return "\n".join(lines)


def tuned_lines(v: Mapping[str, Any]) -> list[str]:
    """One line per setting validation chose (an artifact's ``validation["tuned"]``)."""
    return [f"  {kind} {t['reason']} (held-out daily NRMSE {tuned_scores(t)}; of the choice, "
            f"nested: {_num(t.get('nested_nrmse_pct'), 2)} %)"
            for kind, t in v.get("tuned", {}).items()]


def tuned_scores(t: Mapping[str, Any]) -> str:
    """Every value's held-out score of one ``validation["tuned"]`` entry, e.g.
    ``p = 1: 0.44 %, p = 2: 0.46 %``."""
    return ", ".join(f"{t['setting']} = {k}: {_num(x, 2)} %" for k, x in t["nrmse_pct"].items())


def _num(x: object, digits: int) -> str:
    """A score as printed; '—' where there is none (NaN, or null once saved as JSON)."""
    return f"{x:.{digits}f}" if isinstance(x, int | float) and np.isfinite(x) else "—"


def day_offsets(spec: TwinSpec, days: Sequence[DayReadings]) -> dict[dt.date, float]:
    """Each day's mean target − reference offset [unit] over the operating hours (mean over
    the references and the slots from day start, each slot's time-weighted level, as TRIV
    learns its offsets); a day without a pair of values is left out."""
    hours = spec.hours
    scored = hours.window_slots() * hours.slot_hours >= hours.day_start - 1e-9
    means = {}
    for d in days:
        tgt = d.slot_means(spec.target, hours)[scored]
        diffs = np.array([tgt - d.slot_means(r, hours)[scored] for r in spec.references])
        ok = np.isfinite(diffs)
        if ok.any():
            means[d.day] = float(np.mean(diffs[ok]))
    return means


def offset_variance(spec: TwinSpec, days: Sequence[DayReadings]) -> float:
    """Variance across days of the day's mean target − reference offset [unit²]: the part of
    the error no reading of a new day can reveal."""
    means = list(day_offsets(spec, days).values())
    return float(np.var(means, ddof=1)) if len(means) > 1 else 0.0


def _fold(df: pd.DataFrame, spec: TwinSpec, train: Sequence[DayReadings], held: dt.date,
          kinds: Sequence[str], options: Mapping[str, Mapping[str, Any]],
          failures: dict[str, str], thinning: Thinning | None = None,
          refs: dict[str, tuple[str, ...]] | None = None) -> pd.DataFrame:
    """Train ``kinds`` on ``train``, replay the held-out day; rows as replay_estimates.
    refs, when given, gets each fitted kind's references."""
    ts = TrainingSet(spec, tuple(train))
    fitted: dict[str, TwinModel] = {}
    for kind in kinds:
        if kind in failures:
            continue
        try:
            settings = {**options.get(kind, {}), **MODELS[kind].validation_options}
            fitted[kind] = build(kind, settings).fit(ts)
        except (DataError, FitError, NumericalError, ValueError) as exc:
            failures[kind] = f"fails on {len(train)} days: {exc}"
            log.warning("validation: %s cannot be trained without %s (%s)", kind, held, exc)
    if not fitted:
        return pd.DataFrame()
    if refs is not None:
        refs.update({k: m.references_ for k, m in fitted.items()})
    # The fold's own training ranges, none acting: the rows only record which criteria fired
    # (column ``unlike``), so analysis/criteria.py can judge them on a day they have not seen.
    envelope = Envelope.fit(ts).keeping(frozenset(), 1.0)
    art = Artifact(spec, fitted, next(iter(fitted)), envelope=envelope)
    days, _ = spec.hours.day_and_hours(df["ts"])
    near = (days >= np.datetime64(held - dt.timedelta(days=1))) & (days <= np.datetime64(held))
    est = replay_estimates(art, df[near], held, end=held, thinning=thinning, criteria=True)
    # The fold's ``estimate`` rows follow an arbitrary primary: dropped. The raw references
    # stay, for their own score.
    keep = est["model"].isin(list(fitted)) | est["model"].str.startswith(REF_PREFIX)
    return est[keep].assign(day=held)


def validate(
    df: pd.DataFrame,
    spec: TwinSpec,
    days: Sequence[DayReadings],
    models: Sequence[str],
    options: Mapping[str, Mapping[str, Any]] | None = None,
    primary: str | None = None,
    thinning: Thinning | None = None,
) -> Validation:
    """Hold out each training day, score and calibrate ``models``; choose the primary among
    the candidates (``primary`` pins it). Raises DataError with fewer than MIN_DAYS days.
    thinning: the live window's policy the held-out days are replayed through."""
    t0 = time.perf_counter()
    if len(days) < MIN_DAYS:
        raise DataError(f"validation needs at least {MIN_DAYS} training days, got {len(days)}")
    opts = options or {}
    failures: dict[str, str] = {}
    frames = []
    trained = [k for k in models if not MODELS[k].stacked]
    refs: dict[str, tuple[str, ...]] = {}  # kind → the references its fitted models read
    # Each fold refits every model: the same fit warning would otherwise appear per fold.
    with collapsed(_FOLD_LOGGERS, f"validation's {len(days)} folds"):
        for i, d in enumerate(days, start=1):
            fold_start = time.perf_counter()
            rest = [x for x in days if x.day != d.day]
            frames.append(_fold(df, spec, rest, d.day, trained, opts, failures, thinning,
                                refs))
            progress.info("validation: %s held out (%d of %d) in %.1f s", d.day, i, len(days),
                          time.perf_counter() - fold_start)
    frames = [f for f in frames if not f.empty]
    if not frames:
        raise DataError("no model could be validated on the training days: "
                        + ("; ".join(f"{k} {why}" for k, why in failures.items())
                           or "nothing to validate"))
    held = pd.concat(frames, ignore_index=True)
    offset_var = offset_variance(spec, days)
    offset_var_without = {d.day: offset_variance(spec, [x for x in days if x.day != d.day])
                          for d in days}
    scores: dict[str, CandidateScore] = {}
    calibration: dict[str, SigmaCalibration] = {}
    blend_weights: dict[str, float] = {}
    for kind in [*trained, *(k for k in models if MODELS[k].stacked)]:
        if MODELS[kind].stacked:
            members = _distinct(held, [k for k in trained if MODELS[k].candidate
                                       and k in scores and not scores[k].error])
            blend_weights = blend.weights({k: scores[k].nrmse_pct for k in members})
            extra = _blend_rows(held, members, refs)
            if not blend_weights or extra.empty:
                failures[kind] = "needs two or more validated candidates"
                blend_weights = {}
            else:
                held = pd.concat([held, extra.assign(model=kind)], ignore_index=True)
        rows = held[held["model"] == kind] if not held.empty else held
        if kind in failures or rows.empty:
            why = failures.get(kind, "no held-out estimate")
            scores[kind] = CandidateScore(kind, MODELS[kind].candidate, error=why)
            continue
        scores[kind], calibration[kind], nested = _score(kind, rows, spec, offset_var,
                                                         offset_var_without)
        held.loc[rows.index, NESTED_STD] = nested
    selection = _selection_nrmse(held, scores)
    chosen, reason = _choose(scores, primary, selection)
    return Validation(scores, chosen, reason, calibration, float(np.sqrt(offset_var)),
                      time.perf_counter() - t0, _withheld(scores, chosen), held, blend_weights,
                      selection, day_offsets(spec, days))


@dataclass(frozen=True)
class SettingChoice:
    """A model setting chosen by validation (the model's ``tuned``).

    scores: value → mean held-out daily NRMSE [%] over the days every scored value has (NaN:
    its fit failed on a fold, or it left days unscored); chosen: the value fitted; reason:
    why; nested: the held-out NRMSE [%] of the choice itself, each day scored by the value
    the other days choose (reported: far above the chosen value's own score, it says the
    choice rests on which days were held out; the live-baseline limit stays on the chosen
    value's own score, as for every baseline, a little optimistic as the lowest of a few).
    """

    kind: str
    name: str
    scores: dict[int, float]
    chosen: int
    reason: str
    nested: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {"setting": self.name, "chosen": self.chosen, "reason": self.reason,
                "nrmse_pct": {str(k): v for k, v in self.scores.items()},
                "nested_nrmse_pct": self.nested}


def choose_setting(
    df: pd.DataFrame,
    spec: TwinSpec,
    days: Sequence[DayReadings],
    kind: str,
    options: Mapping[str, Any] | None = None,
    thinning: Thinning | None = None,
) -> SettingChoice | None:
    """``kind``'s ``tuned`` setting from the training days: each value is scored like a
    candidate (leave-one-day-out, the model refit without the held-out day and the day
    replayed; TRIV alongside, as the twin's fallback is in validation), and
    :func:`pick_setting` chooses. None when the model has no such setting, the user set it
    or a form of their own (``options``), or there are too few days to hold out."""
    tuned = MODELS[kind].tuned
    opts = dict(options or {})
    if tuned is None or tuned.pinned(opts) or len(days) < MIN_DAYS:
        return None
    kinds = [kind, *(["triv"] if kind != "triv" else [])]
    daily: dict[int, dict[dt.date, float]] = {}
    with collapsed(_FOLD_LOGGERS, f"{kind}'s {len(tuned.values)} × {len(days)} folds for "
                                  f"{tuned.name}"):
        for value in tuned.values:
            failures: dict[str, str] = {}
            settings = {kind: {**opts, tuned.name: value}}
            per_day = {}
            for d in days:
                f = _fold(df, spec, [x for x in days if x.day != d.day], d.day, kinds,
                          settings, failures, thinning)
                rows = f[f["model"] == kind] if not f.empty else f
                if not rows.empty:
                    per_day[d.day] = metrics.nrmse_pct(rows["truth"], rows["value"])
            if kind in failures:  # a fit that fails on some days is no choice
                log.warning("validation: %s with %s = %s %s", kind, tuned.name, value,
                            failures[kind])
                continue
            daily[value] = per_day
    return pick_setting(kind, tuned.name, tuned.values, daily)


def choose_settings(
    df: pd.DataFrame,
    spec: TwinSpec,
    days: Sequence[DayReadings],
    kinds: Sequence[str],
    options: Mapping[str, Mapping[str, Any]],
    thinning: Thinning | None = None,
) -> tuple[dict[str, dict[str, Any]], dict[str, SettingChoice]]:
    """``options`` (kind → settings) with the setting each of ``kinds`` leaves to validation
    chosen on the training days (:func:`choose_setting`; the value and what goes with it,
    ``Tuned.fit_with``), so that fit, validation and artifact all have the chosen form; and
    the choices made (kind → SettingChoice)."""
    settings = {k: dict(v) for k, v in options.items()}
    choices: dict[str, SettingChoice] = {}
    for kind in kinds:
        if choice := choose_setting(df, spec, days, kind, options.get(kind), thinning):
            tuned = MODELS[kind].tuned
            assert tuned is not None  # choose_setting answers for tuned models only
            choices[kind] = choice
            settings[kind] = {**options.get(kind, {}), **tuned.fit_with,
                              choice.name: choice.chosen}
    return settings, choices


def pick_setting(kind: str, name: str, values: Sequence[int],
                 daily: Mapping[int, Mapping[dt.date, float]]) -> SettingChoice:
    """The choice among ``values`` (from the simplest) from their held-out daily NRMSE
    (value → day → NRMSE [%]; a value missing could not be fit): compared on the days every
    value has a finite score, the simplest within noise of the lowest
    (:func:`smallest_within_noise`). With fewer than ``MIN_DAYS`` such days, the last value
    (the model's default) is kept and the reason says why."""
    finite = {v: {d: x for d, x in daily[v].items() if np.isfinite(x)}
              for v in values if v in daily}
    common = sorted(set.intersection(*(set(f) for f in finite.values()))) if finite else []
    scored = list(finite)  # in the order of values, from the simplest
    scores = {v: float(np.mean([finite[v][d] for d in common])) if v in finite and common
              else float("nan") for v in values}
    if len(common) < MIN_DAYS:
        return SettingChoice(kind, name, scores, values[-1],
                             f"{name} = {values[-1]}, the default: the training days held out "
                             f"scored every {name} on {len(common)} day(s) only")
    table = np.array([[finite[v][d] for d in common] for v in scored])  # [values, days]
    i, best, why = smallest_within_noise(table)
    chosen = scored[i]
    if i == best:
        reason = f"{name} = {chosen}: lowest held-out daily NRMSE ({scores[chosen]:.2f} %)"
    else:
        reason = (f"{name} = {chosen}: held-out daily NRMSE {scores[chosen]:.2f} % against "
                  f"{scores[scored[best]]:.2f} % for {name} = {scored[best]}, {why}, and "
                  "simpler")
    nested = [table[smallest_within_noise(np.delete(table, j, axis=1))[0], j]
              for j in range(len(common))]
    return SettingChoice(kind, name, scores, chosen, reason, float(np.mean(nested)))


def smallest_within_noise(table: np.ndarray) -> tuple[int, int, str]:
    """Of settings ordered from the simplest, each with its held-out daily NRMSE on the same
    days (``table`` [settings, days], finite), the simplest one whose mean is within noise of
    the lowest mean: within ``TIE_RELATIVE`` of it, or within one standard error of the
    paired day-by-day difference (the one-standard-error rule of cross-validation). Five days
    cannot tell a smaller difference from chance, and the simpler setting has fewer
    coefficients to get wrong. Returns (chosen, lowest, why it counts as a tie)."""
    means = table.mean(axis=1)
    best = int(np.argmin(means))
    for i in range(best):
        diff = table[i] - table[best]
        se = float(np.std(diff, ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else 0.0
        if diff.mean() <= means[best] * TIE_RELATIVE:
            return i, best, f"within {TIE_RELATIVE:.0%}"
        if diff.mean() <= se:
            return i, best, (f"within one standard error ({se:.2f} points) of the day-by-day "
                             "difference")
    return best, best, ""


def _score(kind: str, rows: pd.DataFrame, spec: TwinSpec, offset_var: float,
           offset_var_without: Mapping[dt.date, float]
           ) -> tuple[CandidateScore, SigmaCalibration, np.ndarray]:
    """``kind``'s held-out ``rows`` as its score, its σ calibration, and each row's nested σ
    (calibrated without the row's day: what the score's CRPS and coverage use) [n]."""
    hours = np.array([spec.hours.clock_of(t) for t in rows["ts"]])
    err = (rows["value"] - rows["truth"]).to_numpy()
    calibration = SigmaCalibration.fit(rows["day"].to_numpy(), hours, err,
                                       rows["slope"].to_numpy(), offset_var)
    sigma = _nested_sigma(offset_var_without, rows, hours, err)
    daily = [metrics.nrmse_pct(g["truth"], g["value"]) for _, g in rows.groupby("day")]
    return CandidateScore(
        kind, MODELS[kind].candidate,
        nrmse_pct=float(np.mean(daily)),
        crps=float(np.mean(metrics.gaussian_crps(rows["truth"], rows["value"], sigma))),
        cover2_pct=metrics.coverage_pct(rows["truth"], rows["value"], sigma, 2.0),
        days=int(rows["day"].nunique()),
    ), calibration, sigma


def _daily_nrmse(rows: pd.DataFrame) -> dict[tuple[str, Any], float]:
    """(model, held-out day) → that day's NRMSE [%] of the model's held-out ``rows``."""
    return {(k, d): metrics.nrmse_pct(g["truth"], g["value"])
            for (k, d), g in rows.groupby(["model", "day"])}


def _distinct(held: pd.DataFrame, kinds: Sequence[str]) -> list[str]:
    """``kinds`` without any whose held-out estimates equal an earlier one's at every instant
    (triv-cov that kept no covariate is TRIV): a blend must not count one model twice."""
    out: list[str] = []
    values = {k: held.loc[held["model"] == k, ["day", "ts", "value"]].reset_index(drop=True)
              for k in kinds}
    for k in kinds:
        if not any(values[k].equals(values[j]) for j in out):
            out.append(k)
    return out


def _blend_rows(held: pd.DataFrame, members: Sequence[str],
                refs: Mapping[str, tuple[str, ...]] | None = None) -> pd.DataFrame:
    """The blend's held-out rows (models/blend.py): on each held-out day, the members and
    weights its rule picks from the *other* days' held-out daily NRMSE of ``members``, so the
    day it is scored on chose nothing; only members held out on every day take part, so the
    blend is scored on the days the single candidates are. At each instant every member
    answered: value and own std combined with the weights; truth; the worst quality (the
    first not ``ok``); slope that of a member reading every reference the blend reads
    (``refs``: kind → its references), as the live σ takes it, else the members' mean; the
    criteria any member's row fired on."""
    rows = held[held["model"].isin(members)]
    if rows.empty:
        return rows.iloc[0:0]
    daily = _daily_nrmse(rows)
    all_days = sorted(rows["day"].unique())
    complete = [k for k in members if all((k, x) in daily for x in all_days)]
    out = []
    for d in all_days:
        others = [x for x in all_days if x != d]
        inner = {k: float(np.mean([daily[(k, x)] for x in others])) for k in complete
                 if others}
        w = blend.weights(inner)
        if not w:
            continue
        day_rows = rows[(rows["day"] == d) & rows["model"].isin(w)]
        union = {r for k in w for r in (refs or {}).get(k, ())}
        full = next((k for k in w if refs and set(refs.get(k, ())) == union), None)
        for ts, g in day_rows.groupby("ts", sort=True):
            if set(g["model"]) != set(w) or len(g) != len(w):
                continue  # a member without an estimate here: the blend has none either
            e = blend.combine(w, {k: Estimate(v, s) for k, v, s in
                                  zip(g["model"], g["value"], g["std"], strict=True)})
            if (failed := g[g["quality"] == Quality.FALLBACK.value]).shape[0]:
                # A member failed numerically: its row holds TRIV's answer, and the live
                # blend, which cannot combine without it, publishes TRIV's answer alone.
                e = Estimate(float(failed["value"].iloc[0]), float(failed["std"].iloc[0]))
            bad = g.loc[g["quality"] != "ok", "quality"]
            row = {"ts": ts, "value": e.value, "std": e.std,
                   "truth": float(g["truth"].iloc[0]),
                   "quality": str(bad.iloc[0]) if len(bad) else "ok",
                   "slope": float(g.loc[g["model"] == full, "slope"].iloc[0]
                                  if full is not None else g["slope"].mean()), "day": d}
            if "unlike" in g:
                fired = {u for x in g["unlike"] for u in str(x).split(UNLIKE_SEP) if u}
                row["unlike"] = UNLIKE_SEP.join(sorted(fired))
            out.append(row)
    return pd.DataFrame(out)


def _nested_sigma(offset_var_without: Mapping[dt.date, float], rows: pd.DataFrame,
                  hours: np.ndarray, err: np.ndarray) -> np.ndarray:
    """σ [n] of each held-out row from a calibration that never saw the row's day: fit on
    the other days' held-out errors (and their offset spread, ``offset_var_without`` the
    row's day), as the artifact's is fit on all of them. Scored against the rows it is an
    honest check of σ; σ calibrated on the same rows would cover them by construction."""
    sigma = np.full(len(rows), np.nan)
    day = rows["day"].to_numpy()
    slope = rows["slope"].to_numpy()
    for d in np.unique(day):
        test, rest = day == d, day != d
        if len(np.unique(day[rest])) < 2:
            continue  # one day cannot tell a day level from noise
        calib = SigmaCalibration.fit(day[rest], hours[rest], err[rest], slope[rest],
                                     offset_var_without[d])
        sigma[test] = [calib.sigma(h, s) for h, s in zip(hours[test], slope[test], strict=True)]
    return sigma


def _withheld(scores: Mapping[str, CandidateScore], primary: str) -> dict[str, str]:
    """Baselines not to publish live, with the reason (the primary is always published)."""
    triv = scores.get("triv")
    out = {}
    for kind, s in scores.items():
        if kind == primary or s.candidate:
            continue
        if s.error:
            out[kind] = f"could not be validated on the training days ({s.error})"
        # Compared as shown (0.01 %): a target copying its reference has TRIV and VARMA at
        # 0.00 %, and rounding noise must not withhold either.
        elif (triv is not None and not triv.error
              and round(s.nrmse_pct, 2) > BASELINE_LIMIT * round(triv.nrmse_pct, 2)):
            out[kind] = (f"held-out daily NRMSE {s.nrmse_pct:.2f} % on the training days is more "
                         f"than {BASELINE_LIMIT:g}× TRIV's {triv.nrmse_pct:.2f} %")
    return out


def _selection_nrmse(held: pd.DataFrame, scores: Mapping[str, CandidateScore]) -> float:
    """The held-out error of choosing one candidate by validation [%]: the mean over held-out
    days d of the daily NRMSE on d of the candidate :func:`_choose` picks from the *other*
    days' held-out scores. What the blend is measured against: its own score is nested the
    same way, while the lowest of several single scores is optimistic (the winner's curse)."""
    singles = [k for k, s in scores.items()
               if s.candidate and not s.error and not MODELS[k].stacked]
    rows = held[held["model"].isin(singles)] if not held.empty else held
    if rows.empty:
        return float("nan")
    daily = _daily_nrmse(rows)
    days = sorted({d for _, d in daily})
    picked = []
    for d in days:
        others = [x for x in days if x != d]
        inner = {k: CandidateScore(k, True, nrmse_pct=float(np.mean([daily[(k, x)]
                                                                     for x in others])))
                 for k in singles if others and all((k, x) in daily for x in others)}
        if not inner:
            return float("nan")
        kind = _choose(inner, None)[0]
        if (kind, d) not in daily:
            return float("nan")
        picked.append(daily[(kind, d)])
    return float(np.mean(picked))


def _choose(scores: Mapping[str, CandidateScore], pinned: str | None,
            selection_nrmse: float = float("nan")) -> tuple[str, str]:
    """The primary and why: the simplest single candidate within ``TIE_RELATIVE`` of the
    lowest held-out NRMSE; a stacked candidate (the blend) instead when its nested held-out
    NRMSE is more than ``TIE_RELATIVE`` below ``selection_nrmse``, the nested held-out error
    of that very choice (:func:`_selection_nrmse`)."""
    if pinned is not None:
        return pinned, f"pinned by the user ({pinned})"
    ranked = [s for s in scores.values() if s.candidate and not s.error
              and np.isfinite(s.nrmse_pct) and not MODELS[s.kind].stacked]
    if not ranked:
        candidates = ", ".join(k for k, m in MODELS.items() if m.candidate and not m.stacked)
        raise DataError("no model that may be the primary could be validated on the training "
                        f"days (candidates: {candidates}; check --models)")
    order = list(MODELS)  # the registry lists models from the simplest
    best = min(ranked, key=lambda s: s.nrmse_pct)
    tied = [s for s in ranked if s.nrmse_pct <= best.nrmse_pct * (1 + TIE_RELATIVE)]
    chosen = min(tied, key=lambda s: order.index(s.kind))
    if chosen.kind == best.kind:
        reason = (f"{chosen.kind}: lowest held-out daily NRMSE ({chosen.nrmse_pct:.2f} %) on the "
                  "training days")
    else:
        reason = (f"{chosen.kind}: within {TIE_RELATIVE:.0%} of the lowest held-out daily NRMSE "
                  f"({chosen.nrmse_pct:.2f} % vs {best.kind} {best.nrmse_pct:.2f} %) and simpler")
    # Scored on fewer held-out days than the single candidates, it is not comparable.
    stacked = [s for s in scores.values() if s.candidate and not s.error
               and np.isfinite(s.nrmse_pct) and MODELS[s.kind].stacked
               and s.days >= max(r.days for r in ranked)]
    for s in stacked:
        if s.nrmse_pct < selection_nrmse * (1 - TIE_RELATIVE):
            return s.kind, (f"{s.kind}: held-out daily NRMSE {s.nrmse_pct:.2f} %, more than "
                            f"{TIE_RELATIVE:.0%} below the {selection_nrmse:.2f} % of choosing "
                            f"one candidate by validation (both nested: each held-out day "
                            f"scored by what the other days chose); else {reason}")
    return chosen.kind, reason
