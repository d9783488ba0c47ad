"""The report's runs: RunSpec, the RUNS list and their evaluation (run_one, run_all).

Also the constants the other modules of the report share: paths, model names and the
column order of the model tables.
"""

from __future__ import annotations

import datetime as dt
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

import pseudotwin
from pseudotwin.analysis.evaluate import (
    ESTIMATE,
    REF_PREFIX,
    Evaluation,
    evaluate,
    write_outputs,
)
from pseudotwin.analysis.selfaware import OnTest, criteria_on_test, training_share
from pseudotwin.analysis.training import plausible_readings
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load
from pseudotwin.models.registry import ALL_MODELS

PACKAGE = Path(pseudotwin.__file__).resolve().parent
#: The repository root of a source checkout (daemon/pseudotwin/ → ../..).
REPO = PACKAGE.parents[1]
DOCS = REPO / "docs"
COMMAND = ".venv/bin/python scripts/results.py"

PROFILE = "corrgp-triv (profile)"
# Column order of every model table; ref:* pseudo-models follow. ``estimate`` is what the
# daemon publishes (the primary chosen by validation, with its fallbacks).
MODEL_ORDER = (ESTIMATE, "ref", "corrgp-triv", "corrgp-multi", PROFILE, "corrgp-lcm", "triv",
               "triv-cov", "blend", "varma")
# GP: the Corr-GP with the TRIV mean, compared with its prior mean TRIV (secondary evidence).
GP, BASE, REF = "corrgp-triv", "triv", "ref"


def triv1_label(reference: str) -> str:
    """TRIV on corrgp-triv's single reference (runs with several references)."""
    return f"triv ({reference} only)"


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
    # Other live sensors for triv-cov, chosen before looking at any result: what a room's
    # permanent sensors would offer (people: CO2 or occupancy; lamps, sun, outdoor air).
    covariates: tuple[str, ...] = ()

    @property
    def twin(self) -> TwinSpec:
        """What the run's twin pseudo-measures (hours 08:00–19:00 in the run's time zone)."""
        return TwinSpec(self.references, self.target, Quantity.parse(self.quantity),
                        OperatingHours(timezone=self.timezone), self.covariates)


RUNS: tuple[RunSpec, ...] = (
    RunSpec(
        "sml2010-temperature", "SML2010 — temperature", "sml2010",
        ("dining/temp",), "room/temp", "temperature", "Europe/Madrid", dt.date(2012, 3, 14),
        "UCI SML2010 house (Valencia, spring 2012, 15-min means, logger clock UTC): reference "
        "`dining/temp` (dining room), target `room/temp` (the other room).",
        covariates=("dining/co2", "dining/light", "outdoor/temp", "outdoor/irradiance"),
    ),
    RunSpec(
        "sml2010-co2", "SML2010 — CO2", "sml2010",
        ("dining/co2",), "room/co2", "co2", "Europe/Madrid", dt.date(2012, 3, 14),
        "UCI SML2010 house (Valencia, spring 2012, 15-min means): reference `dining/co2`, "
        "target `room/co2`. The CO2 sensors read ~200 ppm, below outdoor air: uncalibrated "
        "offset, only relative dynamics are meaningful (PROVENANCE).",
        covariates=("dining/temp", "dining/humidity", "dining/light"),
    ),
    RunSpec(
        "room-climate-a", "Room Climate — location A", "room-climate-a",
        ("A1/temp", "A3/temp"), "A4/temp", "temperature", "Europe/Berlin",
        dt.date(2016, 3, 15),
        "FAU office A (2016, 1-min means of ~4-s samples, short scripted episodes only): "
        "references `A1/temp` (ceiling centre, 2.88 m) and `A3/temp` (opposite wall, 2.25 m), "
        "target `A4/temp` (wall directly above the desk, 1.18 m). corrgp-triv uses the first "
        "reference (A1) only; corrgp-lcm, triv and varma use both.",
        covariates=("A/occupancy", "A/window", "A/door", "A1/light1"),
    ),
    RunSpec(
        "room-climate-b", "Room Climate — location B", "room-climate-b",
        ("B1/temp", "B3/temp"), "B2/temp", "temperature", "Europe/Berlin",
        dt.date(2016, 3, 31),
        "FAU office B (2016, 1-min means, short scripted episodes only): references "
        "`B1/temp` (ceiling, 2.8 m) and `B3/temp` (side wall, 2.2 m), target `B2/temp` "
        "(between the two desks, 1.2 m). corrgp-triv uses the first reference (B1) only; "
        "corrgp-lcm, triv and varma use both.",
        covariates=("B/occupancy", "B/window", "B/door", "B1/light1"),
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
        long_term=True, covariates=("weather/temp", "house/lights", "ironing/humidity"),
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
    train_uncertain: float = float("nan")  # share of `uncertain` replaying the training days
    # every criterion of `uncertain` on the test days, kept or not (selfaware.criteria_on_test)
    test_criteria: dict[str, OnTest] = field(default_factory=dict)

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
    history = plausible_readings(history, twin, warn=False)  # what evaluate scored
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
    train_uncertain = training_share(ev.artifact, history)
    test_criteria = criteria_on_test(ev.artifact, history, ev.test_start)
    return RunResult(spec, ev, daily, monthly, estimates, time.perf_counter() - t0, notes,
                     train_uncertain, test_criteria)


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
