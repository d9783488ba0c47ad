"""The project's accuracy report (docs/results.md): runs, tables, verdicts, Markdown.

Runs the evaluation protocol (DESIGN.md §7, the same ``evaluate`` the CLI calls) on
SML2010 (temperature and CO2), Room Climate locations A and B and the Appliances house
(long-term, plus corrgp-triv with the unshifted reference profile), writes every run's CSV
and PNG outputs under ``<out_root>/<run>/`` and renders the tables and verdicts as Markdown.
``scripts/results.py`` is the command; the commissioning report reuses the pieces.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

import pseudotwin
from pseudotwin.analysis.evaluate import (
    ESTIMATE,
    REF_PREFIX,
    Evaluation,
    evaluate,
    write_outputs,
)
from pseudotwin.analysis.validation import BASELINE_LIMIT
from pseudotwin.analysis.validation import TIE_RELATIVE as VALIDATION_TIE
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load
from pseudotwin.live import metrics
from pseudotwin.models.registry import ALL_MODELS, MODELS

PACKAGE = Path(pseudotwin.__file__).resolve().parent
#: The repository root of a source checkout (daemon/pseudotwin/ → ../..).
REPO = PACKAGE.parents[1]
DOCS = REPO / "docs"
COMMAND = ".venv/bin/python scripts/results.py"

PROFILE = "corrgp-triv (profile)"
# Column order of every model table; ref:* pseudo-models follow. ``estimate`` is what the
# daemon publishes (the primary chosen by validation, with its fallbacks).
MODEL_ORDER = (ESTIMATE, "ref", "corrgp-triv", PROFILE, "corrgp-lcm", "triv", "varma")
# GP: the Corr-GP with the TRIV mean, compared with its prior mean TRIV (secondary evidence).
GP, BASE, REF = "corrgp-triv", "triv", "ref"

# The figures for the ``estimate`` rows (Trust I):
FLOOR_RATIO = 1.02  # mean daily NRMSE ≤ this × min(TRIV, best raw reference)
COVER2_RANGE = (90.0, 98.0)  # ±2σ coverage of all scored readings [%]
OK = "✓"


def triv1_label(reference: str) -> str:
    """TRIV on corrgp-triv's single reference (runs with several references)."""
    return f"triv ({reference} only)"

# A model "degrades with the seasons" when its monthly NRMSE rises by more than this share
# of its own mean monthly NRMSE per month (least-squares slope over the month index).
SEASON_REL_SLOPE = 0.10
# Below this mean difference [NRMSE points] two models are called practically equal.
TIE_POINTS = 0.05
TIE_RELATIVE = 2.0  # … or below this share of the baseline's mean daily NRMSE [%]


@dataclass(frozen=True)
class RunSpec:
    """One evaluation of the report."""

    name: str
    title: str
    dataset: str
    references: tuple[str, ...]
    target: str
    quantity: str
    timezone: str
    train_start: dt.date
    about: str
    train_days: int = 5
    long_term: bool = False  # also run corrgp-triv with ref_mean="profile"

    @property
    def twin(self) -> TwinSpec:
        """What the run's twin pseudo-measures (hours 08:00–19:00 in the run's time zone)."""
        return TwinSpec(self.references, self.target, Quantity.parse(self.quantity),
                        OperatingHours(timezone=self.timezone))


RUNS: tuple[RunSpec, ...] = (
    RunSpec(
        "sml2010-temperature", "SML2010 — temperature", "sml2010",
        ("dining/temp",), "room/temp", "temperature", "Europe/Madrid", dt.date(2012, 3, 14),
        "UCI SML2010 house (Valencia, spring 2012, 15-min means, logger clock UTC): reference "
        "`dining/temp` (dining room), target `room/temp` (the other room).",
    ),
    RunSpec(
        "sml2010-co2", "SML2010 — CO2", "sml2010",
        ("dining/co2",), "room/co2", "co2", "Europe/Madrid", dt.date(2012, 3, 14),
        "UCI SML2010 house (Valencia, spring 2012, 15-min means): reference `dining/co2`, "
        "target `room/co2`. The CO2 sensors read ~200 ppm, below outdoor air: uncalibrated "
        "offset, only relative dynamics are meaningful (PROVENANCE).",
    ),
    RunSpec(
        "room-climate-a", "Room Climate — location A", "room-climate-a",
        ("A1/temp", "A3/temp"), "A4/temp", "temperature", "Europe/Berlin",
        dt.date(2016, 3, 15),
        "FAU office A (2016, 1-min means of ~4-s samples, short scripted episodes only): "
        "references `A1/temp` (ceiling centre, 2.88 m) and `A3/temp` (opposite wall, 2.25 m), "
        "target `A4/temp` (wall directly above the desk, 1.18 m). corrgp-triv uses the first "
        "reference (A1) only; corrgp-lcm, triv and varma use both.",
    ),
    RunSpec(
        "room-climate-b", "Room Climate — location B", "room-climate-b",
        ("B1/temp", "B3/temp"), "B2/temp", "temperature", "Europe/Berlin",
        dt.date(2016, 3, 31),
        "FAU office B (2016, 1-min means, short scripted episodes only): references "
        "`B1/temp` (ceiling, 2.8 m) and `B3/temp` (side wall, 2.2 m), target `B2/temp` "
        "(between the two desks, 1.2 m). corrgp-triv uses the first reference (B1) only; "
        "corrgp-lcm, triv and varma use both.",
    ),
    RunSpec(
        "appliances", "Appliances house — long-term (Jan–May 2016)", "appliances",
        ("ironing/temp",), "parents/temp", "temperature", "Europe/Brussels",
        dt.date(2016, 1, 12),
        "UCI Appliances house (Belgium, 11 Jan–27 May 2016, 10-min, house clock fixed UTC+1): "
        "reference `ironing/temp` (T7, ironing room), target `parents/temp` (T9, parents' "
        "room) — the pair with the highest overall r (0.945) in PROVENANCE, most of which is "
        "the common seasonal trend (PROVENANCE: median daily r 0.49 over whole days). "
        "Different rooms, not one room.",
        long_term=True,
    ),
)
RUN_NAMES = tuple(r.name for r in RUNS)


@dataclass
class RunResult:
    spec: RunSpec
    ev: Evaluation
    daily: pd.DataFrame  # all models incl. the extra variants and ref:*
    monthly: pd.DataFrame
    estimates: pd.DataFrame  # ts, model, value, std, truth, quality (all models)
    seconds: float
    notes: list[str] = field(default_factory=list)

    @property
    def primary_ref(self) -> str:
        """corrgp-triv's single reference (the twin's first reference without it)."""
        gp = self.ev.artifact.models.get(GP)
        refs = getattr(gp, "references_", None) or self.ev.artifact.references
        return str(refs[0])


# ---------------------------------------------------------------------------- running


Progress = Callable[[str], None]


def progress(msg: str) -> None:
    """The default progress line on stdout."""
    print(f"[results {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _shown(path: Path) -> str:
    """``path`` relative to the repository when it lies inside it."""
    p = path.resolve()
    return str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(path)


def run_one(spec: RunSpec, history: pd.DataFrame, out_root: Path,
            say: Progress = progress) -> RunResult:
    """Evaluate one run (and its variants), writing the outputs under ``out_root``."""
    t0 = time.perf_counter()
    twin = spec.twin
    say(f"{spec.name}: training {', '.join(ALL_MODELS)} and replaying …")
    ev = evaluate(history, twin, spec.train_start, spec.train_days, ALL_MODELS)
    out = out_root / spec.name
    write_outputs(ev, history, out)
    say(f"{spec.name}: {ev.daily['day'].nunique()} test day(s) in {ev.seconds:.1f} s; "
              f"outputs in {_shown(out)}/")
    frames: list[tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]] = [
        (ev.daily, ev.monthly, ev.estimates)
    ]
    notes: list[str] = []
    variants: list[tuple[str, str, str, dict[str, Any]]] = []  # label, folder, model, options
    if spec.long_term:
        variants.append((PROFILE, "profile", GP, {GP: {"ref_mean": "profile"}}))
    if len(spec.references) > 1:
        # corrgp-triv uses one reference; TRIV on that same reference is its like-for-like
        # baseline (and exactly its prior mean).
        first = spec.references[0]
        variants.append((triv1_label(first), "triv1", BASE, {BASE: {"references": (first,)}}))
    for label, folder, model, options in variants:
        say(f"{spec.name}: {label} …")
        ev2 = evaluate(history, twin, spec.train_start, spec.train_days, (model,),
                       options=options)
        out2 = out_root / f"{spec.name}-{folder}"
        write_outputs(ev2, history, out2)
        say(f"{spec.name}: {label} in {ev2.seconds:.1f} s; outputs in {_shown(out2)}/")
        if ev2.artifact.training["days"] != ev.artifact.training["days"]:
            notes.append(f"{label} trained on different days: "
                         f"{', '.join(ev2.artifact.training['days'])}")
        d2, m2, e2 = (f[f["model"] == model].assign(model=label)
                      for f in (ev2.daily, ev2.monthly, ev2.estimates))
        frames.append((d2, m2, e2))
    daily, monthly, estimates = (
        pd.concat([f[i] for f in frames], ignore_index=True) for i in range(3)
    )
    quality = estimates.groupby(["model", "quality"]).size()
    for (model, q), n in quality.items():
        if q != "ok" and not str(model).startswith(REF_PREFIX):
            notes.append(f"{n} estimate(s) of {model} had quality `{q}`")
    return RunResult(spec, ev, daily, monthly, estimates, time.perf_counter() - t0, notes)


def run_all(specs: Sequence[RunSpec], out_root: Path,
            say: Progress = progress) -> list[RunResult]:
    """Every run of ``specs`` in order, each shared dataset loaded once."""
    histories: dict[str, pd.DataFrame] = {}
    results: list[RunResult] = []
    for i, spec in enumerate(specs, 1):
        if spec.dataset not in histories:
            say(f"loading {spec.dataset} …")
            histories[spec.dataset] = load(spec.dataset)
        say(f"run {i}/{len(specs)}: {spec.name}")
        results.append(run_one(spec, histories[spec.dataset], out_root, say))
    return results


# ---------------------------------------------------------------------------- formatting


def _f(x: Any, nd: int = 2) -> str:
    """A number to ``nd`` decimals, or an em dash when missing."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "—"
    return "—" if not np.isfinite(v) else f"{v:.{nd}f}"


def _ordered(models: Sequence[str]) -> list[str]:
    ms = set(models)
    head = [m for m in MODEL_ORDER if m in ms]
    extra = sorted(m for m in ms if m.startswith(BASE + " ("))
    if BASE in head:
        i = head.index(BASE) + 1
        head[i:i] = extra
    else:
        head += extra
    return head + sorted(m for m in ms if m not in head)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], left: int = 1,
           text: Sequence[int] = ()) -> str:
    """Markdown table: the first ``left`` columns and those in ``text`` left-aligned."""
    lines = ["| " + " | ".join(header) + " |",
             "|" + "|".join("---" if i < left or i in text else "---:"
                            for i in range(len(header))) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _label(model: str) -> str:
    return f"{model} (raw)" if model.startswith(REF_PREFIX) else model


def _signed(x: float, nd: int = 2) -> str:
    """Signed number; a value that rounds to zero prints as 0.00 (never -0.00)."""
    v = round(float(x), nd)
    return _f(v, nd) if v == 0 or not np.isfinite(v) else f"{v:+.{nd}f}"


def _bias(estimates: pd.DataFrame) -> pd.Series:
    """Mean signed error (estimate − truth) per model over all scored readings."""
    return (estimates["value"] - estimates["truth"]).groupby(estimates["model"]).mean()


def summary_md(res: RunResult) -> str:
    daily = res.daily
    g = daily.groupby("model").agg(
        nrmse=("nrmse_pct", "mean"), dmax=("dmax_pct", "mean"),
        r=("pearson_r", "median"), days=("day", "nunique"),
    )
    bias = _bias(res.estimates)
    unit = res.ev.artifact.unit
    rows = [[_label(m), _f(g.at[m, "nrmse"]), _f(g.at[m, "dmax"]), _f(g.at[m, "r"], 3),
             _signed(bias.get(m, np.nan)), str(int(g.at[m, "days"]))]
            for m in _ordered(list(g.index))]
    return _table(["model", "mean daily NRMSE %", "mean ΔT_max %", "median daily r",
                   f"mean error [{unit}]", "days"], rows)


def calibration_md(res: RunResult) -> str:
    """Per model over all scored readings: does ±σ mean what it says?"""
    unit = res.ev.artifact.unit
    rows = []
    for m in _ordered(list(res.estimates["model"].unique())):
        e = res.estimates[res.estimates["model"] == m]
        s = metrics.score(e["truth"].to_numpy(), e["value"].to_numpy(), e["std"].to_numpy())
        ratio = s.mean_std / s.rmse if s.rmse > 0 else float("nan")
        rows.append([_label(m), _f(s.cover1_pct, 1), _f(s.cover2_pct, 1), _f(s.mean_std, 3),
                     _f(s.rmse, 3), _f(ratio), _f(s.crps, 3), str(s.n)])
    return _table(["model", "±1σ coverage %", "±2σ coverage %", f"mean σ [{unit}]",
                   f"RMSE [{unit}]", "mean σ / RMSE", f"mean CRPS [{unit}]", "n"], rows)


def monthly_md(res: RunResult) -> str:
    piv = res.monthly.pivot(index="month", columns="model", values="nrmse_pct")
    models = _ordered(list(piv.columns))
    d = res.daily.assign(month=res.daily["day"].str[:7])
    days = d[d["model"] == ESTIMATE].groupby("month")["day"].nunique()
    r = d[d["model"].str.startswith(REF_PREFIX)].pivot_table(
        index="month", columns="model", values="pearson_r", aggfunc="median")
    refs = [m for m in models if m.startswith(REF_PREFIX)]
    header = ["month", "days", *[_label(m) for m in models],
              *[f"median r {m[len(REF_PREFIX):]}" for m in refs]]
    rows = []
    for month in piv.index:
        rows.append([month, str(int(days.get(month, 0))),
                     *[_f(piv.at[month, m]) for m in models],
                     *[_f(r.at[month, m], 3) if m in r.columns else "—" for m in refs]])
    return _table(header, rows)


def daily_md(res: RunResult) -> str:
    nr = res.daily.pivot(index="day", columns="model", values="nrmse_pct")
    rr = res.daily.pivot(index="day", columns="model", values="pearson_r")
    n = res.daily[res.daily["model"] == ESTIMATE].set_index("day")["n"]
    models = [m for m in _ordered(list(nr.columns)) if not m.startswith(REF_PREFIX)]
    refs = [REF_PREFIX + s for s in res.ev.artifact.references if REF_PREFIX + s in rr.columns]
    duel_col = GP in nr.columns and BASE in nr.columns
    header = ["day", "n", *models, *(["corrgp-triv vs triv"] if duel_col else []),
              *[f"r {m[len(REF_PREFIX):]}" for m in refs]]
    rows = []
    for day in nr.index:
        marks = []
        if duel_col:
            a, b = nr.at[day, GP], nr.at[day, BASE]
            marks.append("—" if not (np.isfinite(a) and np.isfinite(b)) else (
                "win" if a < b else "loss" if a > b else "tie"))
        rows.append([day, str(int(n.get(day, 0))), *[_f(nr.at[day, m]) for m in models],
                     *marks, *[_f(rr.at[day, m], 3) for m in refs]])
    return _table(header, rows)


# ---------------------------------------------------------------------------- verdicts


@dataclass(frozen=True)
class Duel:
    """corrgp-triv against one baseline on the days both were scored."""

    other: str
    days: int
    wins: int
    mean_primary: float
    mean_other: float
    win_days: list[str]
    loss_days: list[str]

    @property
    def excess(self) -> float:
        """corrgp-triv's mean daily NRMSE minus the baseline's [points]; < 0 = better."""
        return self.mean_primary - self.mean_other

    @property
    def relative(self) -> float:
        """``excess`` in % of the baseline's mean daily NRMSE."""
        return 100.0 * self.excess / self.mean_other if self.mean_other else float("nan")

    @property
    def beats(self) -> bool:
        return self.excess < 0 and 2 * self.wins > self.days

    @property
    def tie(self) -> bool:
        return abs(self.excess) < TIE_POINTS or abs(self.relative) < TIE_RELATIVE

    def sentence(self, name: str) -> str:
        return (
            f"better than {name} on {self.wins} of {self.days} days; mean daily NRMSE "
            f"{_f(self.mean_primary)} % vs {_f(self.mean_other)} % (difference "
            f"{_signed(self.excess)} points, {_signed(self.relative)} %)"
        )


def duel(daily: pd.DataFrame, other: str) -> Duel | None:
    piv = daily.pivot(index="day", columns="model", values="nrmse_pct")
    if GP not in piv.columns or other not in piv.columns:
        return None
    d = piv[[GP, other]].dropna()
    if d.empty:
        return None
    win = d[GP] < d[other]
    return Duel(other, len(d), int(win.sum()), float(d[GP].mean()),
                float(d[other].mean()), list(d.index[win]), list(d.index[d[GP] > d[other]]))


def _median_r(daily: pd.DataFrame, ref_model: str, days: Sequence[str]) -> float:
    s = daily[(daily["model"] == ref_model) & daily["day"].isin(list(days))]["pearson_r"]
    return float(s.median()) if s.notna().any() else float("nan")


@dataclass(frozen=True)
class Evidence:
    """Daily Pearson r of corrgp-triv's raw reference vs the target, split by outcome."""

    ref: str
    r_all: float
    r_win: float
    r_loss: float
    n_win: int
    n_loss: int
    rho: float  # Spearman: daily r vs corrgp-triv's daily gain over TRIV

    def sentence(self) -> str:
        split = []
        if self.n_win:
            split.append(f"{_f(self.r_win, 3)} on the {self.n_win} days corrgp-triv wins")
        if self.n_loss:
            split.append(f"{_f(self.r_loss, 3)} on the {self.n_loss} days it loses")
        return (
            f"Evidence — daily Pearson r of the raw reference `{self.ref}` vs the target: "
            f"median {_f(self.r_all, 3)} over all days, " + ", ".join(split)
            + f"; Spearman rank correlation of the daily r with corrgp-triv's daily gain over "
            f"TRIV {_f(self.rho, 2)}."
        )

    @property
    def separates(self) -> bool:
        """The days lost have a clearly lower r than the days won."""
        return bool(self.n_win and self.n_loss and self.r_loss < self.r_win - 0.1)


def evidence(res: RunResult, t: Duel) -> Evidence:
    daily = res.daily
    ref_model = REF_PREFIX + res.primary_ref
    piv = daily.pivot(index="day", columns="model", values="nrmse_pct")
    rr = daily[daily["model"] == ref_model].set_index("day")["pearson_r"]
    gain = (piv[BASE] - piv[GP]).dropna()
    both = pd.concat([gain.rename("gain"), rr.rename("r")], axis=1).dropna()
    rho = float(both["gain"].corr(both["r"], method="spearman")) if len(both) > 3 else np.nan
    return Evidence(
        res.primary_ref, _median_r(daily, ref_model, daily["day"].unique()),
        _median_r(daily, ref_model, t.win_days), _median_r(daily, ref_model, t.loss_days),
        len(t.win_days), len(t.loss_days), rho,
    )


def gp_md(res: RunResult) -> str:
    """Secondary evidence: the Corr-GP with the TRIV mean against TRIV (the thesis's claim),
    with the daily r of its reference and the reasons read off it."""
    daily, art = res.daily, res.ev.artifact
    t = duel(daily, BASE)
    if t is None:
        return "No common days of corrgp-triv and triv: no comparison."
    if t.beats:
        head = "corrgp-triv beats TRIV"
    elif t.tie:
        head = "corrgp-triv does not beat TRIV (practically equal)"
    else:
        head = "corrgp-triv does not beat TRIV"
    parts = [f"*Secondary — the Corr-GP against TRIV (the thesis's claim):* {head}: "
             f"{t.sentence('TRIV')}."]
    # The TRIV that is corrgp-triv's own prior mean: the baseline on the same reference.
    own = triv1_label(res.primary_ref) if len(art.references) > 1 else BASE
    t1 = duel(daily, own) if own != BASE else None
    if t1 is not None:
        parts.append(
            f"TRIV here averages {len(art.references)} references, corrgp-triv uses "
            f"`{res.primary_ref}` only; against TRIV on `{res.primary_ref}` alone (its own "
            f"prior mean) it is {t1.sentence('that TRIV')}."
        )
    v = duel(daily, "varma")
    if v is not None:
        vm = art.models.get("varma")
        name = getattr(vm, "model_name_", "varma")
        fell = (f" (here the fallback `{name}`: {getattr(vm, 'fit_message_', '')})"
                if name != "varma" else "")
        parts.append(f"Against VARMA{fell}: {v.sentence('VARMA')}.")
    lcm = duel(daily, "corrgp-lcm")
    if lcm is not None:
        parts.append(f"Against the zero-mean corrgp-lcm: {lcm.sentence('corrgp-lcm')}.")
    ev = evidence(res, t)
    parts.append(ev.sentence())
    bias = _bias(res.estimates)
    if not t.beats:
        why = _why(t, t1, ev, bias, art.unit, own)
        if why[5].isupper() and why[6].islower():  # "Why: The …" → "Why: the …"
            why = why[:5] + why[5].lower() + why[6:]
        parts.append(why)
    elif ev.rho > 0.2:
        parts.append("Its gain is larger on days with a higher reference–target r, as the "
                     "method expects.")
    elif not ev.separates:
        parts.append(
            f"The daily r does not separate the days won from those lost ({_f(ev.r_win, 3)} vs "
            f"{_f(ev.r_loss, 3)}): the gain is not confined to days on which the reference "
            "co-varies strongly with the target."
        )
    med_r = daily.groupby("model")["pearson_r"].median()
    r_p, r_b = med_r.get(GP, np.nan), med_r.get(BASE, np.nan)
    if t.beats and r_p < r_b - 0.1:
        parts.append(
            f"Its estimate follows the target's within-day course less well than TRIV's "
            f"(median daily r with the truth {_f(r_p, 3)} vs {_f(r_b, 3)}): the gain is in the "
            "level of the estimate, not in tracking the day's shape."
        )
    raw = daily[daily["model"] == REF_PREFIX + res.primary_ref]["nrmse_pct"].mean()
    if np.isfinite(raw) and raw < t.mean_other:
        parts.append(
            f"Note: the raw reference alone scores {_f(raw)} % mean daily NRMSE, lower than "
            "TRIV: the offset profile learnt on the five training days does not carry over to "
            "the test days, and corrgp-triv inherits it as its prior mean."
        )
    return " ".join(parts)


def _why(t: Duel, t1: Duel | None, ev: Evidence, bias: pd.Series, unit: str, own: str) -> str:
    """Why corrgp-triv does not beat TRIV, read off the r evidence (rules stated in the text)."""
    why = "Why: "
    if t1 is not None:
        one_ref = t1.mean_other - t.mean_other
        gp = t1.excess
        why += (
            f"of the {_signed(t.excess)} points, {_signed(one_ref)} come from using one "
            f"reference instead of all (TRIV on `{ev.ref}` alone vs TRIV) and {_signed(gp)} "
            "from the GP's correction on top of that prior mean. "
        )
        if gp <= 0:
            return why + (
                "The GP itself does not make the estimate worse; the loss is the price of "
                "corrgp-triv using a single reference where TRIV averages several."
            )
        if t1.tie or gp < 0.5 * one_ref:
            return why + (
                f"The GP's correction is small next to that ({_signed(gp)} points, better "
                f"than its prior mean on {t1.wins} of {t1.days} days); most of the loss is the "
                "price of corrgp-triv using a single reference where TRIV averages several. "
                f"The reference tracks the target closely (median r {_f(ev.r_all, 3)}), so "
                "TRIV's offset plus the live reference already carries the target's course and "
                "the GP has little to add."
            )
    b_p, b_t = bias.get(GP, np.nan), bias.get(own, np.nan)
    errs = (f"mean signed error of corrgp-triv {_signed(b_p)} {unit} vs "
            f"{_signed(b_t)} {unit} of {own}")
    if ev.separates:
        return why + (
            f"It loses mainly on days when the reference tells less about the target "
            f"(median r {_f(ev.r_loss, 3)} on lost vs {_f(ev.r_win, 3)} on won days). The GP "
            "transfers the reference's deviation from its typical day to the target through "
            "the coupling learnt on the training days; when the two do not move together "
            "that day, the transfer adds error that TRIV (offset + reference) does not make."
        )
    if t.tie:
        if np.isfinite(ev.r_all) and ev.r_all >= 0.9:
            return why + (
                f"Within each day the reference tracks the target closely (median r "
                f"{_f(ev.r_all, 3)}), so TRIV's offset profile plus the live reference already "
                "carries the target's course; the GP's correction of the reference's deviation "
                "from its typical day has almost nothing left to add, and the two end up "
                "practically equal."
            )
        return why + (
            f"The within-day co-variation of reference and target is moderate to weak "
            f"(median r {_f(ev.r_all, 3)}) and the daily r does not separate the days won from "
            "those lost; the GP's correction stays small, so corrgp-triv ends up practically "
            "equal to its TRIV prior mean."
        )
    if np.isfinite(ev.r_all) and ev.r_all >= 0.9:
        return why + (
            f"Not for lack of information: the reference tracks the target closely on all "
            f"kinds of day (median r {_f(ev.r_all, 3)}), so TRIV's offset profile plus the "
            "live reference already carries the target's course. The GP adds a correction "
            "from the reference's deviation from its (shifted) training-day profile through "
            "the coupling learnt on five days, and on the test days that correction moves the "
            f"estimate away from the truth ({errs})."
        )
    if np.isfinite(ev.r_all) and ev.r_all < 0.5:
        return why + (
            f"The within-day co-variation of reference and target is weak (median r "
            f"{_f(ev.r_all, 3)}), so there is little for the correlated GP to exploit beyond "
            f"TRIV's offset; what it transfers from the reference is largely noise ({errs})."
        )
    return why + (
        f"The daily r does not explain it: it does not separate the days won from those lost "
        f"(rank correlation with the gain {_f(ev.rho, 2)}); {errs}."
    )


def _varma_drift(daily: pd.DataFrame, trend: str) -> str:
    """A sentence when VARMA's error grows with the distance from the training days."""
    v = daily[daily["model"] == "varma"].sort_values("day")["nrmse_pct"].to_numpy()
    if len(v) < 6:
        return ""
    k = len(v) // 3
    first, last = float(np.mean(v[:k])), float(np.mean(v[-k:]))
    if last <= 2 * first:
        return ""
    why = (
        "consistent with a trend with drift: the drift fitted on five days is extrapolated to "
        "every later day (the caveat documented in `models/varma.py`)"
        if "t" in trend else
        f"with trend `{trend}` no drift is extrapolated, so this is the training days' "
        "dynamics carrying over less well to later days"
    )
    return (
        f"Its error grows with the distance from the training days (mean daily NRMSE "
        f"{_f(first)} % over the first third of the test days, {_f(last)} % over the last "
        f"third), {why}."
    )


# ---------------------------------------------------------------------------- the targets


@dataclass(frozen=True)
class Figures:
    """The issue's figures for one run, computed from its evaluation outputs.

    NRMSE figures are mean daily NRMSE [%] over each model's scored days; cover1/cover2 [%],
    mean_std and rmse [unit] pool all scored readings of the ``estimate`` rows; sigma_cv is
    the mean over days of std(σ)/mean(σ) of those rows (0 = σ constant within each day).
    """

    days: int
    primary: str
    estimate: float
    triv: float
    best_ref: str  # the raw reference with the lowest mean daily NRMSE (`ref` or ref:<sensor>)
    ref: float
    n: int
    cover1: float
    cover2: float
    mean_std: float
    rmse: float
    sigma_cv: float
    varma: float
    varma_withheld: str  # why VARMA is not published live ("" when it is)
    best_model: str  # hindsight: the trained model with the lowest NRMSE on the test days
    best_nrmse: float

    @property
    def floor(self) -> float:
        """The simple answer: the lower of TRIV's and the best raw reference's NRMSE."""
        return float(np.nanmin([self.triv, self.ref])) if np.isfinite(
            [self.triv, self.ref]).any() else float("nan")

    @property
    def ratio(self) -> float:
        return self.estimate / self.floor if self.floor > 0 else float("nan")

    @property
    def floor_met(self) -> bool:
        return bool(self.ratio <= FLOOR_RATIO)

    @property
    def cover_met(self) -> bool:
        return bool(COVER2_RANGE[0] <= self.cover2 <= COVER2_RANGE[1])

    @property
    def sigma_varies(self) -> bool:
        return bool(self.sigma_cv > 1e-9)

    @property
    def varma_ratio(self) -> float:
        return self.varma / self.triv if self.triv > 0 else float("nan")

    @property
    def varma_met(self) -> bool:
        """VARMA within BASELINE_LIMIT × TRIV, or not published live."""
        return bool(self.varma_ratio <= BASELINE_LIMIT) or bool(self.varma_withheld)


def _is_raw(model: str) -> bool:
    return model == REF or model.startswith(REF_PREFIX)


def _raw_name(res: RunResult, model: str) -> str:
    """A raw reference's row named with its sensor: `ref` (sensor) or `sensor` raw."""
    if model.startswith(REF_PREFIX):
        return f"`{model[len(REF_PREFIX):]}` raw"
    refs = getattr(res.ev.artifact.models.get(model), "references_", None)
    return f"`{model}` on {refs[0]}" if refs else f"`{model}`"


def figures(res: RunResult) -> Figures:
    art = res.ev.artifact
    g = res.daily.groupby("model")["nrmse_pct"].mean()
    raw = g[[m for m in g.index if _is_raw(str(m))]].dropna()
    best_ref = str(raw.idxmin()) if len(raw) else "—"
    e = res.estimates[res.estimates["model"] == ESTIMATE]
    s = metrics.score(e["truth"].to_numpy(), e["value"].to_numpy(), e["std"].to_numpy())
    cv = float("nan")
    if len(e):
        days, _ = res.spec.twin.hours.day_and_hours(e["ts"])
        std = e["std"].astype(float)
        per_day = std.groupby(np.asarray(days)).agg(["std", "mean", "count"])
        per_day = per_day[(per_day["count"] > 1) & (per_day["mean"] > 0)]
        if len(per_day):
            cv = float((per_day["std"] / per_day["mean"]).mean())
    trained = g[[m for m in g.index if m in art.models]].dropna()
    best = str(trained.idxmin()) if len(trained) else "—"
    return Figures(
        days=int(res.daily["day"].nunique()), primary=art.primary,
        estimate=float(g.get(ESTIMATE, np.nan)), triv=float(g.get(BASE, np.nan)),
        best_ref=best_ref, ref=float(raw.min()) if len(raw) else float("nan"), n=s.n,
        cover1=s.cover1_pct, cover2=s.cover2_pct, mean_std=s.mean_std, rmse=s.rmse,
        sigma_cv=cv, varma=float(g.get("varma", np.nan)),
        varma_withheld=str(art.withheld.get("varma", "")),
        best_model=best, best_nrmse=float(trained.min()) if len(trained) else float("nan"),
    )


def _mark(ok: bool, value: str) -> str:
    return value if value == "—" else f"{value} {OK if ok else '✗'}"


def validation_md(res: RunResult) -> str:
    """The artifact's leave-one-day-out scores on the training days, and why the primary won."""
    art = res.ev.artifact
    v = art.validation
    if not v or not v.get("scores"):
        return (f"No validation recorded in the artifact: the primary `{art.primary}` was not "
                "chosen by validation.")
    withheld = v.get("withheld", {})
    unit = art.unit
    rows = []
    for kind, sc in v["scores"].items():
        if kind == art.primary:
            note = "**primary** (published as `estimate`)"
        elif sc.get("candidate"):
            note = "candidate"
        else:
            note = "baseline (never primary)"
        if sc.get("error"):
            note += f"; {sc['error']}"
        if kind in withheld:
            note += f"; **not published live**: {withheld[kind]}"
        elif kind != art.primary:
            note += "; published live"
        rows.append([kind, _f(sc.get("nrmse_pct")), _f(sc.get("crps"), 3),
                     _f(sc.get("cover2_pct"), 1), str(sc.get("days", "")), note])
    table = _table(["model", "held-out NRMSE %", f"CRPS [{unit}]", "±2σ cover %", "days",
                    "note"], rows, text=(5,))
    reason = f"Primary: {v.get('reason', '')}."
    if v.get("primary") not in (None, art.primary):
        reason += (f" (Validation chose `{v['primary']}`; `{art.primary}` was pinned by the "
                   "user.)")
    extra = [f"Method: {v.get('method', 'unknown')}"]
    if np.isfinite(float(v.get("offset_std", np.nan))):
        extra.append(f"spread (std) of the daily mean reference–target offset over the "
                     f"training days {_f(v['offset_std'], 3)} {unit}, the floor of every "
                     "model's day-level σ")
    if "seconds" in v:
        extra.append(f"{_f(v['seconds'], 1)} s")
    return "\n\n".join([table, reason + " " + "; ".join(extra) + "."])


def verdict_md(res: RunResult) -> str:
    """The published estimate against the issue's figures; then the GP-vs-TRIV evidence."""
    f = figures(res)
    unit = res.ev.artifact.unit
    parts: list[str] = []  # the estimate against the figures
    more: list[str] = []  # the primary, VARMA
    if not np.isfinite(f.ratio):
        parts.append("**Estimate vs floor: not measurable** (no `estimate` or no floor rows).")
    else:
        pct = 100.0 * (f.ratio - 1.0)
        where = ("equal to the floor" if abs(pct) < 0.05 else
                 f"{_f(-pct, 1)} % below the floor" if pct < 0 else
                 f"{_f(pct, 1)} % above the floor ({_signed(f.estimate - f.floor)} points)")
        state = ("met" if f.floor_met else "not met")
        limit = f"≤ {FLOOR_RATIO:.2f}" if f.floor_met else f"> {FLOOR_RATIO:.2f}"
        parts.append(
            f"**Estimate vs floor: {state}** — the published estimate scores {_f(f.estimate)} % "
            f"mean daily NRMSE against the floor {_f(f.floor)} % (the lower of TRIV's "
            f"{_f(f.triv)} % and the best raw reference's {_f(f.ref)} %, "
            f"{_raw_name(res, f.best_ref)}): ratio {_f(f.ratio, 3)} ({limit}), {where}."
        )
    lo, hi = COVER2_RANGE
    size = (f"mean σ {_f(f.mean_std, 3)} {unit} vs RMSE {_f(f.rmse, 3)} {unit} "
            f"(ratio {_f(f.mean_std / f.rmse if f.rmse > 0 else np.nan)})")
    if not np.isfinite(f.cover2):
        parts.append("**±2σ coverage: not measurable** (the estimate has no σ).")
    elif f.cover_met:
        parts.append(f"**±2σ coverage: met** — {_f(f.cover2, 1)} % of the {f.n} scored "
                     f"readings lie inside the estimate's ±2σ band (target {lo:.0f}–{hi:.0f} %; "
                     f"±1σ: {_f(f.cover1, 1)} %); {size}.")
    else:
        kind = "too narrow" if f.cover2 < lo else "too wide"
        parts.append(f"**±2σ coverage: not met, σ {kind}** — {_f(f.cover2, 1)} % of the {f.n} "
                     f"scored readings lie inside ±2σ (target {lo:.0f}–{hi:.0f} %; ±1σ: "
                     f"{_f(f.cover1, 1)} %); {size}.")
    if np.isfinite(f.sigma_cv):
        parts.append(
            f"σ varies within the day (mean within-day std/mean of σ {_f(100 * f.sigma_cv, 1)} "
            "%)." if f.sigma_varies else "**σ is constant within each day** (a defect).")
    hind = ("also the best trained model on the test days" if f.best_model == f.primary
            else f"in hindsight `{f.best_model}` was the best trained model on the test days "
                 f"({_f(f.best_nrmse)} %)")
    more.append(f"The estimate is `{f.primary}`'s, chosen on the training days (table above); "
                 f"{hind}.")
    if np.isfinite(f.varma):
        vm = res.ev.artifact.models.get("varma")
        name = getattr(vm, "model_name_", "varma")
        trend = str(getattr(vm, "trend", "?"))
        mode = getattr(vm, "target_mode", None)
        fell = (f", re-levelled each day (target_mode `{mode}`)" if mode == "shifted" else
                f", target_mode `{mode}`" if mode else "")
        fell += f", here the fallback `{name}`" if name != "varma" else ""
        live = (f"not published live ({f.varma_withheld})" if f.varma_withheld
                else "published live")
        within = (f"within the {BASELINE_LIMIT:g}× limit" if f.varma_ratio <= BASELINE_LIMIT
                  else f"above the {BASELINE_LIMIT:g}× limit")
        state = "met" if f.varma_met else "not met"
        sent = (f"**VARMA: {state}** — trend `{trend}`{fell}: {_f(f.varma)} % mean daily "
                f"NRMSE, {_f(f.varma_ratio)}× TRIV's ({within}); {live}.")
        drift = _varma_drift(res.daily, trend)
        more.append(sent + (" " + drift if drift else ""))
    return "\n\n".join([" ".join(parts), " ".join(more), gp_md(res)])


def seasonal_md(res: RunResult) -> str:
    """Appliances: zero-mean LCM vs TRIV-mean corrgp-triv over the months."""
    models = [m for m in ("corrgp-lcm", GP, PROFILE, BASE, "varma")
              if m in set(res.monthly["model"])]
    piv = res.monthly.pivot(index="month", columns="model", values="nrmse_pct")[models]
    d = res.daily.assign(month=res.daily["day"].str[:7])
    days = d[d["model"] == ESTIMATE].groupby("month")["day"].nunique()
    ref_model = REF_PREFIX + res.primary_ref
    r = d[d["model"] == ref_model].groupby("month")["pearson_r"].median()
    names = {GP: "corrgp-triv (shifted)"}
    x = np.arange(len(piv.index), dtype=float)
    slope: dict[str, float] = {}
    rel: dict[str, float] = {}
    for m in models:
        y = piv[m].to_numpy(dtype=float)
        ok = np.isfinite(y)
        if ok.sum() >= 2:
            slope[m] = float(np.polyfit(x[ok], y[ok], 1)[0])
            rel[m] = slope[m] / float(np.mean(y[ok]))
    rows = [[mo, str(int(days.get(mo, 0))), *[_f(piv.at[mo, m]) for m in models],
             _f(r.get(mo, np.nan), 3)] for mo in piv.index]
    rows.append(["slope [points/month]", "", *[_f(slope.get(m, np.nan)) for m in models], ""])
    rows.append(["slope / mean [%/month]", "",
                 *[_f(100 * rel.get(m, np.nan)) for m in models], ""])
    table = _table(["month", "days", *[names.get(m, m) for m in models],
                    f"median r {res.primary_ref}"], rows)

    def trend(m: str) -> str:
        if m not in rel:
            return "unknown"
        return "degrades" if rel[m] > SEASON_REL_SLOPE else "holds"

    first, last = piv.index[0], piv.index[-1]

    def span(m: str) -> str:
        return f"{_f(piv.at[first, m])} % in {first} → {_f(piv.at[last, m])} % in {last}"

    lcm_t, triv_t = trend("corrgp-lcm"), trend(GP)
    rule = (f"Rule: a model *degrades* when the least-squares slope of its monthly NRMSE over "
            f"the month index exceeds {100 * SEASON_REL_SLOPE:.0f} % of its mean monthly NRMSE "
            "per month; otherwise it *holds*.")
    facts = (f"corrgp-lcm (zero mean) {span('corrgp-lcm')}, slope {_f(slope.get('corrgp-lcm'))}"
             f" points/month ({lcm_t}); corrgp-triv (shifted) {span(GP)}, slope "
             f"{_f(slope.get(GP))} points/month ({triv_t})")
    if PROFILE in slope:
        facts += (f"; corrgp-triv (profile) {span(PROFILE)}, slope {_f(slope[PROFILE])} "
                  f"points/month ({trend(PROFILE)})")
    facts += f"; TRIV {span(BASE)} ({trend(BASE)})."
    best = str(piv["corrgp-lcm"].idxmin())
    if best != first:
        facts += (f" corrgp-lcm is not monotonic: its lowest month is {best} "
                  f"({_f(piv.at[best, 'corrgp-lcm'])} %).")
    below = [str(mo) for mo in piv.index if piv.at[mo, GP] < piv.at[mo, BASE]]
    facts += (f" corrgp-triv (shifted) is below TRIV in {len(below)} of {len(piv.index)} "
              f"months ({', '.join(below) or 'none'}).")
    if lcm_t == "degrades" and triv_t == "holds":
        finding = ("**The thesis's finding is reproduced**: the zero-mean LCM degrades with "
                   "the seasons while the TRIV-mean model holds.")
    elif lcm_t == "degrades":
        finding = ("**Only partly reproduced**: the zero-mean LCM degrades with the seasons, "
                   "but corrgp-triv degrades too.")
    else:
        finding = ("**The thesis's finding is not reproduced here**: the zero-mean LCM does "
                   "not degrade with the seasons on this pair of rooms by the rule above.")
        lvl = piv["corrgp-lcm"] - piv[GP]
        if (lvl > 0).all():
            finding += (" It is worse than corrgp-triv in every month, but by a margin that "
                        "does not grow towards May.")
    if PROFILE in piv.columns:
        diff = float((piv[PROFILE] - piv[GP]).mean())
        better = "shifted" if diff > 0 else "profile"
        finding += (f" Shifted vs unshifted reference prior mean: the {better} variant is "
                    f"better on average by {_f(abs(diff))} points of monthly NRMSE.")
    intro = (
        "corrgp-triv (shifted) is the default: the reference's prior mean is its training-day "
        "profile P_ref shifted to the day's level in the init phase. corrgp-triv (profile) is "
        "the same model with the unshifted P_ref (`options={\"corrgp-triv\": {\"ref_mean\": "
        "\"profile\"}}`, CLI `--ref-mean profile`). corrgp-lcm has a zero mean and one shared "
        "normalization of all outputs from the training days. Monthly mean of daily NRMSE %; "
        f"the last column is the median daily r of the raw reference `{res.primary_ref}` vs "
        "the target."
    )
    return "\n\n".join([intro, table, rule, facts + " " + finding])


# ---------------------------------------------------------------------------- document


def _commit() -> str:
    try:
        p = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                           capture_output=True, text=True, timeout=10, check=True)
        return p.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def package_files() -> dict[str, str]:
    """sha256 of every Python source of the package now: relative path → hex digest."""
    pkg = PACKAGE
    return {str(f.relative_to(pkg)): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in sorted(pkg.rglob("*.py"))}


def _loaded_package_files() -> list[str]:
    """Package sources this process imported (relative paths): the code behind the results."""
    pkg = PACKAGE
    out = []
    for mod in list(sys.modules.values()):
        f = getattr(mod, "__file__", None)
        if f and Path(f).resolve().is_relative_to(pkg):
            out.append(str(Path(f).resolve().relative_to(pkg)))
    return sorted(out)


def _code_identity(at_start: dict[str, str]) -> tuple[str, list[str]]:
    """(12-hex hash over the imported sources as they were at the start, those changed since)."""
    now = package_files()
    h = hashlib.sha256()
    changed = []
    for f in _loaded_package_files():
        h.update(f.encode())
        h.update(at_start.get(f, "new").encode())
        if at_start.get(f) != now.get(f):
            changed.append(f)
    return h.hexdigest()[:12], changed


def _versions() -> str:
    out = []
    for pkg in ("pseudotwin", "numpy", "pandas", "GPy", "statsmodels"):
        try:
            out.append(f"{pkg} {metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            continue
    return ", ".join(out)


# The candidates for primary, simplest first (the tie-break order of validation).
_CANDIDATES = " < ".join(k for k, c in MODELS.items() if c.candidate)

HOW_TO_READ = f"""\
## How to read these tables

* **Protocol** (DESIGN.md §7, thesis 6.5): every model is trained on the first five days from
  the stated start on which all sensors report, then every later day is scored. Each day is
  replayed reading by reading through the same `Twin` the daemon runs; at each true reading of
  the target within operating hours 08:00–19:00 local time every model gives its estimate from
  the references' readings up to that instant only (causal; the target is never fed in).
* **`estimate`** is exactly what the daemon publishes on `<twin>/estimate`: the primary
  model's estimate, with its fallbacks and quality flags. It is the product; the other
  rows are the models behind it and the baselines it is judged against.
* **Validation** (training days only): each training day in turn is held out, every model is
  trained on the other days and the held-out day replayed causally. The candidate with the
  lowest mean held-out daily NRMSE becomes the primary, except that the simplest candidate
  within {VALIDATION_TIE:.0%} of it wins ({_CANDIDATES}). VARMA is a monitoring
  baseline, never primary, and is not published live when its held-out NRMSE exceeds
  {BASELINE_LIMIT:g}× TRIV's. The test days are never looked at for any of this.
* **NRMSE %** (6.10) = the day's RMSE of the estimate against the target's true readings in
  operating hours / the mean of those true readings × 100. **ΔT_max %** (6.14) = the day's
  largest absolute error / the same mean × 100. *Mean daily* = mean over the test days; the
  monthly tables are the monthly means of the daily NRMSE (thesis Tables 6.2–6.4).
* **Models**: `ref` = the raw reference held (the one closest to the target on the training
  days), with a calibrated σ; `corrgp-triv` = Corr-GP ICM with TRIV as the target's prior
  mean (one reference, its prior mean the training profile shifted to the day's level in the
  30-min init phase); `corrgp-lcm` = zero-mean Corr-GP LCM over all references; `triv` =
  training offset profile + live reference, averaged over references; `varma` = VARMAX(4, 4)
  with trend `n` (no constant, no drift) on the 15-min grid, every series re-levelled each
  day by the references' init-phase shift (its fallback: VAR(4) by least squares).
  `ref:<sensor> (raw)` is the raw reference value held at the reading's time, without σ,
  scored as if it were an estimate: its NRMSE is the error of "just use the reference", and
  its **daily Pearson r** with the target is the evidence of how much that reference can tell
  about the target's within-day course (thesis Fig. 6.6). The r of a model is that of its
  estimate with the truth.
* **σ calibration**: every model's σ (ref and TRIV included) comes from its held-out errors
  in validation: a day-level part (never below the day-to-day spread of the reference–target
  offset, which no reading of today reveals) plus a within-day part that depends on the time
  of day and on how fast the references move, widened for the few days it is estimated from.
  So σ varies within a day.
* **Calibration tables** (per model, pooled over all scored readings): the share of true
  readings inside the estimate's ±1σ and ±2σ bands (a calibrated Gaussian σ covers 68.3 % and
  95.4 %), the mean σ next to the RMSE (mean σ / RMSE ≈ 1 when σ is the right size), and the
  mean **CRPS** (continuous ranked probability score of the Gaussian N(estimate, σ²), in the
  quantity's unit, lower is better: it rewards a small error and a σ of the right size; for
  an estimate without σ, such as a raw reference, it is the absolute error). Computed by
  `pseudotwin.live.metrics`, as in `daily.csv`.
* **Verdicts** are computed by the script from the test days, against the figures the
  product must reach: the estimate's mean daily NRMSE ≤ {FLOOR_RATIO:.2f} × the *floor*, the
  lower of TRIV's and the best raw reference's (never meaningfully worse than the simple
  answer); ±2σ coverage of the estimate {COVER2_RANGE[0]:.0f}–{COVER2_RANGE[1]:.0f} %, σ not
  constant within a day; VARMA's mean daily NRMSE ≤ {BASELINE_LIMIT:g}× TRIV's, or VARMA not
  published live. Secondary: corrgp-triv *beats* TRIV when its mean daily NRMSE is lower
  **and** it is better on more than half of the days, with the daily r evidence. n = scored
  target readings per day.
* CSV (`daily.csv`, `monthly.csv`, `estimates.csv`), the artifact and plots (daily NRMSE per
  model, one median day) of each run are written to `out/results/<run>/` (not committed).
"""


def render(
    results: Sequence[RunResult], total: float, partial: bool, at_start: dict[str, str]
) -> str:
    """``at_start``: the package's source digests when the run started (code imported)."""
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    source, changed = _code_identity(at_start)
    lines = [
        "# Accuracy results",
        "",
        f"Generated by `{COMMAND}`"
        + (f" `--only {','.join(r.spec.name for r in results)}` (partial)" if partial else "")
        + f" on {now} at commit `{_commit()}` (sha256 of the imported package sources "
        f"`{source}`) in {total / 60:.1f} min ({total:.0f} s).",
        f"Regenerate with `{COMMAND}` (from the repository root). Versions: {_versions()}.",
        *(["", f"**Warning: package source(s) {', '.join(changed)} changed while this ran; "
                "regenerate.**"] if changed else []),
        "",
        HOW_TO_READ,
        "## Overview",
        "",
        _overview(results),
        "",
    ]
    for res in results:
        lines += _section(res)
    if not partial:
        lines += _performance()
    return "\n".join(lines).rstrip() + "\n"


PERFORMANCE = (
    ("gpy_comparison.txt", ".venv/bin/python scripts/compare_gpy_restarts.py",
     "Training the LCM: our fit vs GPy's `optimize_restarts(5)`",
     "Same data (Room Climate A, references A1 and A3, target A4, five training days, 15-min "
     "grid), same 3-term LCM with 30 free parameters, same day-block likelihood. GPy starts "
     "from its default initialization and randomizes each restart. Ours: data-initialized "
     "starts (eigen-directions of the outputs' second moment, lengthscales from fast to slow, "
     "a near-constant daily-level term), stopping once two starts agree, then a tight polish."),
    ("bench_update.txt", ".venv/bin/python scripts/bench_update.py",
     "Live conditioning and training time",
     "Per-reading update (condition + estimate) of the live Cholesky posterior over a real "
     "day with two references, side by side with rebuilding a GPy model per reading; "
     "training times of corrgp-triv and corrgp-lcm (two references, default 15-min grid) on "
     "five days."),
    ("bench_daemon.txt", ".venv/bin/python scripts/bench_daemon.py",
     "The daemon with 100 twins",
     "100 twins fed 5-minute COV readings at 60× replay speed through a real Mosquitto: "
     "latency from a reading's publish to its estimate's arrival, CPU and peak RSS."),
    ("bench_history.txt", ".venv/bin/python scripts/bench_history.py",
     "Backfill and recorder",
     "Backfill of one twin over 7 months of 1-minute readings in SQLite (days per second, "
     "peak RSS of the backfill process) and the recorder's sustained rate into SQLite."),
)


def _performance() -> list[str]:
    """The benchmark outputs kept in docs/ (each produced by the command shown; they are
    not rerun here because they take minutes and measure time, not accuracy)."""
    out = ["## Performance", "",
           "Recorded outputs of the benchmark commands below (rerun a command to refresh its "
           "file: `CMD > docs/FILE`). Figures are from this 2-core machine.", ""]
    for name, cmd, title, what in PERFORMANCE:
        path = DOCS / name
        if not path.exists():
            continue
        text = "\n".join(line for line in path.read_text(encoding="utf-8").splitlines()
                         if "approaches 1e6" not in line)
        out += [f"### {title}", "", what, "", f"`{cmd} > docs/{name}`:", "", "```",
                text.strip(), "```", ""]
    return out


def _overview(results: Sequence[RunResult]) -> str:
    rows = []
    figs = [figures(res) for res in results]
    for res, f in zip(results, figs, strict=True):
        ref = _raw_name(res, f.best_ref)
        rows.append([
            res.spec.name, str(f.days), f"`{f.primary}`", _f(f.estimate), _f(f.triv),
            f"{_f(f.ref)} ({ref})", _f(f.floor), _mark(f.floor_met, _f(f.ratio, 3)),
            _mark(f.cover_met, _f(f.cover2, 1)), _mark(f.sigma_varies, _f(100 * f.sigma_cv, 1)),
            _mark(bool(f.varma_ratio <= BASELINE_LIMIT), _f(f.varma_ratio)),
            "—" if not np.isfinite(f.varma) else ("no" if f.varma_withheld else "yes"),
        ])
    table = _table(["run", "test days", "primary (validation)", "estimate", "triv",
                    "best raw reference", "floor", "estimate / floor", "±2σ cover %",
                    "σ within-day CV %", "varma / triv", "varma live"], rows, left=3)
    n = len(figs)
    met = [
        f"estimate ≤ {FLOOR_RATIO:.2f} × floor on {sum(f.floor_met for f in figs)} of {n}",
        f"±2σ coverage {COVER2_RANGE[0]:.0f}–{COVER2_RANGE[1]:.0f} % on "
        f"{sum(f.cover_met for f in figs)} of {n}",
        f"σ varying within the day on {sum(f.sigma_varies for f in figs)} of {n}",
        f"VARMA within {BASELINE_LIMIT:g}× TRIV or not published live on "
        f"{sum(f.varma_met for f in figs if np.isfinite(f.varma))} of "
        f"{sum(bool(np.isfinite(f.varma)) for f in figs)}",
    ]
    return table + (
        "\n\nMean daily NRMSE % over the test days: `estimate` is what the daemon publishes "
        "(the primary chosen by validation on the training days, with its fallbacks); the "
        "floor is the lower of TRIV's and the best raw reference's (the `ref` model or a "
        "`ref:<sensor>` row). ±2σ coverage pools all scored readings of the estimate; σ "
        "within-day CV = mean over days of std(σ)/mean(σ) of the estimate. ✓/✗: estimate / "
        f"floor ≤ {FLOOR_RATIO:.2f}, coverage {COVER2_RANGE[0]:.0f}–{COVER2_RANGE[1]:.0f} %, "
        f"CV > 0, VARMA / TRIV ≤ {BASELINE_LIMIT:g} (otherwise VARMA must not be published "
        "live). Targets met: " + "; ".join(met) + " runs."
    )


def _section(res: RunResult) -> list[str]:
    spec, art = res.spec, res.ev.artifact
    days = sorted(res.daily["day"].unique())
    varma = art.models.get("varma")
    vname = getattr(varma, "model_name_", None)
    lines = [
        f"## {spec.title} (`{spec.name}`)",
        "",
        f"{spec.about} Time zone {spec.timezone}; training days "
        f"{', '.join(art.training['days'])} (from {spec.train_start}); {len(days)} test days "
        f"{days[0]} … {days[-1]}; quantity {spec.quantity} [{art.unit}]"
        + (f"; VARMA model `{vname}`" if vname else "")
        + f". Run time {res.seconds:.0f} s; outputs in `out/results/{spec.name}/`"
        + (f" and `out/results/{spec.name}-profile/`" if spec.long_term else "") + ".",
        "",
    ]
    if res.notes:
        lines += ["Notes: " + "; ".join(res.notes) + ".", ""]
    lines += ["### Validation on the training days", "", validation_md(res), "",
              "### Summary", "", summary_md(res), "",
              "### Calibration (all scored readings)", "", calibration_md(res), "",
              "### Verdict", "", verdict_md(res), ""]
    if spec.long_term:
        lines += ["### Seasons: zero-mean LCM vs TRIV-mean Corr-GP", "", seasonal_md(res), ""]
    lines += ["### Monthly mean of daily NRMSE %", "", monthly_md(res), "",
              "### Per day (NRMSE %, and daily r of each raw reference vs the target)", "",
              daily_md(res), ""]
    return lines
