"""``pseudotwin`` command line: one entry point, one subcommand per job."""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import logging
import math
import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pseudotwin import __version__
from pseudotwin.cli.util import (
    EX_CONFIG,
    EX_TEMPFAIL,
    STOP_SIGNALS,
    config_error_text,
    load_named_config,
    stop_signal_line,
    whole_number,
)
from pseudotwin.config.model import LOG_LEVELS
from pseudotwin.config.validate import sqlite_file
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.errors import ConfigError, PseudotwinError, StateInUseError
from pseudotwin.gp.kernels import KERNEL_REGISTRY
from pseudotwin.models.registry import ALL_MODELS, MODELS

if TYPE_CHECKING:
    import pandas as pd

    from pseudotwin.config import ServiceConfig, TwinConfig
    from pseudotwin.core.horizon import OperatingHours
    from pseudotwin.core.thinning import Thinning
    from pseudotwin.edge.recorder import Recorder
    from pseudotwin.edge.service import Service
    from pseudotwin.live.artifact import Artifact

log = logging.getLogger("pseudotwin")



def setup_logging(level: str = "INFO") -> None:
    """One line per event on stdout/stderr (systemd and Docker collect it as is)."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    for noisy in ("GP", "paramz", "matplotlib"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    if logging.getLogger().level > logging.DEBUG:
        # The CrateDB client's HTTP pool warns at every retry; the store's own error (or
        # the recorder's outage line) says it once.
        logging.getLogger("urllib3").setLevel(logging.ERROR)


def _csv(text: str) -> list[str]:
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise argparse.ArgumentTypeError("expected a comma-separated list")
    return items


def _shard(text: str) -> Any:
    from pseudotwin.edge.fleet import Shard

    try:
        return Shard.parse(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _date(text: str) -> dt.date:
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a date YYYY-MM-DD") from None


def _dates(text: str) -> frozenset[dt.date]:
    return frozenset(_date(t) for t in _csv(text))


def _add_twin_args(p: argparse.ArgumentParser, train: bool = False) -> None:
    if train:
        src = p.add_mutually_exclusive_group()
        src.add_argument("--history", type=Path,
                         help="canonical history file (CSV or Parquet): sensor,ts,value")
        src.add_argument("--store", metavar="URL",
                         help="history store: SQLite file, postgresql://host/db or "
                              "crate://host:4200")
        p.add_argument("--config", type=Path,
                       help="train for this daemon configuration: its sensors' "
                            "min_interval_seconds, its time zone and operating hours (an "
                            "option below that contradicts them is an error: the artifact "
                            "would not fit it), references and covariates among its sensors; "
                            "the history from its store unless --history or --store is given")
    else:
        src = p.add_mutually_exclusive_group(required=True)
        src.add_argument("--history", type=Path,
                         help="canonical history file (CSV or Parquet): sensor,ts,value")
        src.add_argument("--store", metavar="URL",
                         help="history store (what `record` and `import` wrote): SQLite file, "
                              "postgresql://host/db or crate://host:4200; every stored "
                              "reading of the references, target and covariates is read")
    p.add_argument("--references", required=True, type=_csv,
                   help="reference sensor(s), comma-separated, e.g. hmi/temp,ceiling/temp")
    p.add_argument("--target", required=True, help="the desk sensor to pseudo-measure")
    p.add_argument("--covariates", type=_csv, default=[],
                   help="other live sensors, comma-separated, of any unit (e.g. room/co2 for a "
                        "temperature twin): read by the triv-cov model, kept by validation only "
                        "where they help")
    p.add_argument("--quantity", required=True, choices=("temperature", "co2"),
                   help="selects the default kernel: RQ for temperature, Matérn 5/2 for CO2")
    p.add_argument("--train-start", required=not train, type=_date,
                   help="first candidate training day YYYY-MM-DD (local)"
                        + ("; default: the first full day of the data (not the one it "
                           "begins in after the init phase starts)" if train else ""))
    p.add_argument("--train-days", type=int, default=5,
                   help="training days: the first N days from --train-start on which every "
                        "sensor reports (default 5; at least 3, unless --allow-unvalidated)")
    p.add_argument("--allow-unvalidated", action="store_true",
                   help="allow fewer than three training days: no day can be held out, so "
                        "nothing chooses the primary (--primary, or else the first candidate of "
                        "--models: with the default, ref, the raw reference) and σ is "
                        "each model's own spread, not calibrated on days it did not see: an "
                        "MPC that trusts it is misled. For a first look, not for service")
    p.add_argument("--skip-days", type=_dates, default=frozenset(), metavar="DAY[,DAY...]",
                   help="days YYYY-MM-DD (local) never trained on, even when every sensor "
                        "reports on them: a day of commissioning work, the heating off, a window "
                        "left open; the next usable days are taken instead (evaluate still "
                        "scores such a day when it falls after the training days). train says "
                        "when one training day is unlike the others")
    p.add_argument("--primary", choices=ALL_MODELS,
                   help="pin the model published as the twin's estimate (default: the candidate "
                        "that scores best with each training day held out in turn)")
    p.add_argument("--models", type=_csv, default=list(ALL_MODELS),
                   help=f"comma-separated models: {', '.join(ALL_MODELS)} (default: all)")
    cfg = " (with --config: the configuration's)" if train else ""
    p.add_argument("--timezone",
                   help="IANA time zone of the building; operating hours are local (default "
                        f"UTC{cfg})")
    p.add_argument("--day-start", help=f"start of operating hours (default 08:00{cfg})")
    p.add_argument("--day-end", help=f"end of operating hours (default 19:00{cfg})")
    p.add_argument("--init-minutes", type=_minutes_at_least_zero,
                   help="init phase before day start, collected but not published (default "
                        f"30{cfg})")
    p.add_argument("--slot-minutes", type=float,
                   help=f"time-of-day grid of TRIV, VARMA and GP training (default 15{cfg})")
    p.add_argument("--kernel", choices=tuple(KERNEL_REGISTRY),
                   help="override the Corr-GP kernel")
    p.add_argument("--ref-mean", choices=("shifted", "profile"), default="shifted",
                   help="corrgp-triv/-multi reference prior mean: training profile shifted to "
                        "today's level in the init phase (default), or the unshifted profile")
    p.add_argument("--lcm-terms", type=_lcm_terms, metavar="N",
                   help="LCM terms of corrgp-multi and corrgp-lcm (default: one per reference). "
                        "Their training time grows fast with the terms: with five references "
                        "one fit took ~440 s with five terms, ~55 s with two "
                        "(scripts/bench_gp_references.py); validation refits each model once "
                        "per training day")
    p.add_argument("--varma-p", type=_varma_order, metavar="P",
                   help=f"pin VARMA's order (1..{MAX_VARMA_P}): VARMAX(P, P) by maximum "
                        "likelihood, VAR(P) by least squares if it does not converge (default: "
                        "VAR(p) by least squares, p chosen from 1, 2 and 4 by validation on the "
                        "training days)")
    p.add_argument("--smooth-span", type=_smooth_span, metavar="MIN",
                   help="pin triv-smooth's span in minutes: its offset profile a local straight "
                        "line through the slots within MIN/2 either side (default: 240, 120 "
                        "or 60, chosen by validation on the training days)")


HOURS_OPTIONS = {"day_start": "--day-start", "day_end": "--day-end",
                 "init_minutes": "--init-minutes", "slot_minutes": "--slot-minutes",
                 "timezone": "--timezone"}


def _hours(a: argparse.Namespace) -> OperatingHours:
    """The operating hours from the options given; the others from ``--config`` (train)
    or the defaults. With --config an option may repeat the configuration, not contradict
    it: the artifact is checked against that configuration's hours."""
    import dataclasses

    from pseudotwin.core.horizon import OperatingHours, parse_hhmm

    given: dict[str, Any] = {
        "day_start": None if a.day_start is None else parse_hhmm(a.day_start, "--day-start"),
        "day_end": None if a.day_end is None else parse_hhmm(a.day_end, "--day-end"),
        "init_minutes": a.init_minutes, "slot_minutes": a.slot_minutes,
        "timezone": a.timezone}
    given = {k: v for k, v in given.items() if v is not None}
    if getattr(a, "config", None) is None:
        hours = dataclasses.replace(OperatingHours(), **given)
        if a.timezone is None:  # a building is rarely on UTC: hours and days would shift
            log.warning("no --timezone: the operating hours and the days are in %s (%s); "
                        "give the building's IANA time zone, e.g. Europe/Berlin",
                        hours.timezone, hours.describe())
        return hours
    hours = load_named_config(a.config).hours
    for key, value in given.items():
        if value != getattr(hours, key):
            shown = getattr(a, key)
            raise ConfigError(
                f"{HOURS_OPTIONS[key]} {shown} contradicts {a.config}, whose {key} is "
                f"{_shown(hours, key)}: the artifact would not fit it (leave the option out)")
    return hours


def _shown(hours: OperatingHours, key: str) -> str:
    from pseudotwin.core.horizon import format_hhmm

    value = getattr(hours, key)
    if key in ("day_start", "day_end"):
        return format_hhmm(value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _options(a: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """Each model's settings from the command line: those of its ``options`` that were given."""
    given = {k: v for k, v in (("kernel", a.kernel), ("ref_mean", a.ref_mean),
                               ("n_terms", a.lcm_terms)) if v is not None}
    options = {kind: {k: v for k, v in given.items() if k in cls.options}
               for kind, cls in MODELS.items()}
    if a.varma_p is not None:
        options["varma"]["p"] = a.varma_p  # a p set skips validation's choice of the order
    if a.smooth_span is not None:
        options["triv-smooth"]["span"] = a.smooth_span  # skips validation's choice of it
    return options


def _spec(a: argparse.Namespace) -> TwinSpec:
    return TwinSpec(tuple(a.references), a.target, Quantity.parse(a.quantity), _hours(a),
                    tuple(a.covariates))


def _check_live_sensors(a: argparse.Namespace, cfg: ServiceConfig) -> None:
    """What the twin reads live must be a sensor of the configuration the artifact is for;
    the desk sensor need not be (it is often imported, never fed live)."""
    from pseudotwin.config.validate import suggest

    for option, names in (("--references", a.references), ("--covariates", a.covariates)):
        if unknown := [s for s in names if s not in cfg.sensors]:
            raise ConfigError(
                f"{option}: {', '.join(unknown)} not a sensor of {a.config}"
                f"{suggest(unknown[0], cfg.sensors)}; the twin could not be fed live")


def _check_twin_of_out(a: argparse.Namespace, spec: TwinSpec, cfg: ServiceConfig) -> None:
    """--out naming a configured twin's artifact must be trained as that twin is configured:
    another set of references wrote over the artifact the daemon runs one its configuration
    refuses (the next start exits 78), after minutes of training."""
    for tc in cfg.twins.values():
        if not _same_file(tc.artifact, a.out):
            continue
        # (the hours are checked against the configuration's already)
        if problems := tc.spec(spec.hours, spec.target).differences(spec, "this training's"):
            raise ConfigError(
                f"--out {a.out} is the artifact of twin {tc.id} in {a.config}, and "
                f"{'; '.join(problems)}: the daemon would refuse the artifact at its next "
                "start. Train with that twin's references, covariates and quantity, or "
                "change the twin in the configuration first, or write another file")


def _training_history(a: argparse.Namespace, hours: OperatingHours,
                      cfg: ServiceConfig | None) -> tuple[pd.DataFrame, dt.date]:
    """The history to train on and the first candidate day: --history, else --store, else
    the store of --config's configuration ``cfg``."""
    from pseudotwin.analysis.training import first_full_day
    from pseudotwin.core.series import read_history

    if a.history is not None:
        df = read_history(a.history)
        if a.train_start is None:  # as from the store: a day the data begins in is not full
            own = df.loc[df["sensor"].isin([*a.references, a.target]), "ts"]
            first = (own if len(own) else df["ts"]).min().to_pydatetime()
            return df, first_full_day(first, hours)
        return df, a.train_start
    from pseudotwin.analysis.training import history_from_store
    from pseudotwin.history.store import open_store

    url = a.store
    if url is None:
        assert cfg is not None  # one of --history, --store and --config is required
        url = cfg.store
        if url is None:
            raise ConfigError(f"{a.config}: no store configured in [service] (or give "
                              "--history or --store)")
    with open_store(url, existing=True, migrate=False) as store:  # reads readings only
        return history_from_store(store, [*a.references, a.target], hours, a.train_start,
                                  a.train_days, a.skip_days, a.covariates)


def _train_thinning(a: argparse.Namespace, cfg: ServiceConfig | None) -> Thinning:
    """The window's policy training learns for: the sensors' of --config's configuration
    ``cfg`` (a --min-interval may repeat it, not contradict it), else --min-interval, else
    the default."""
    from pseudotwin.core.thinning import Thinning

    given = None if a.min_interval is None else Thinning(dt.timedelta(seconds=a.min_interval))
    if cfg is None:
        return given or Thinning()
    policy = cfg.thinning
    if given is not None:
        if other := [s for s in [*a.references, *a.covariates]
                     if policy.interval(s) != given.default]:
            raise ConfigError(
                f"--min-interval {a.min_interval:g} contradicts {a.config}, whose "
                f"min_interval_seconds of {other[0]} is "
                f"{policy.interval(other[0]).total_seconds():g}: the artifact would not fit "
                "it (leave the option out)")
    return policy


def _say_unused_skips(skip_days: frozenset[dt.date], art: Artifact) -> None:
    """train's and evaluate's line on --skip-days that left nothing out (a mistyped day, or
    one outside the training days): silence would read as done."""
    left_out = set(art.training.get("skipped", ()))
    if unused := sorted(str(d) for d in skip_days if str(d) not in left_out):
        print(f"--skip-days: {', '.join(unused)} would not have been training days anyway "
              f"(training took {art.training['start']} … {art.training['end']}); nothing "
              "left out for them")


def _say_odd_day(art: Artifact) -> None:
    """train's and evaluate's line on a training day unlike the others, if there is one."""
    from pseudotwin.analysis.commissioning.oddday import odd_training_day

    if odd := odd_training_day(art.validation):
        print(f"training days: {odd.advice(art.unit, len(art.references))}")


def _store_read(a: argparse.Namespace, cfg: ServiceConfig | None) -> str | None:
    """The history store ``train`` read (None: a file), as the configuration names it: a
    SQLite file's absolute path (a relative one was from the working directory), else the
    URL as given."""
    if a.history is not None:
        return None
    if a.store is None:
        return cfg.store if cfg is not None else None  # the loader made a path absolute
    file = sqlite_file(a.store)
    return str(Path(file).resolve()) if file is not None else str(a.store)


def cmd_train(a: argparse.Namespace) -> int:
    from pseudotwin.analysis.training import train_validated
    from pseudotwin.core.twinlog import twin_context

    spec = _spec(a)
    cfg = None if a.config is None else load_named_config(a.config)
    if cfg is not None:  # what contradicts the configuration fails before any reading
        _check_live_sensors(a, cfg)
        _check_twin_of_out(a, spec, cfg)
        if cfg.store and (file := sqlite_file(cfg.store)) and _same_file(Path(file), a.out):
            raise ConfigError(f"--out would overwrite the store of {a.config}, {cfg.store}")
    thinning = _train_thinning(a, cfg)
    df, start = _training_history(a, spec.hours, cfg)
    if cfg is not None:  # as the daemon takes them: a stored 85 °C of a 0..50 °C sensor is not
        from pseudotwin.live.readings import in_range

        kept = in_range(df, cfg.sensors, others=True)
        if dropped := len(df) - len(kept):
            out = df.loc[~df.index.isin(kept.index), "sensor"].value_counts()
            log.warning("training leaves out %d reading(s) outside their sensor's min..max in "
                        "%s (%s)", dropped, a.config,
                        ", ".join(f"{s}: {n}" for s, n in out.items()))
        df = kept
    # The configuration's sensors keep their own min..max: the daemon applies those.
    ranges = ({k: (s.min, s.max) for k, s in cfg.sensors.items()} if cfg is not None
              else None)
    with twin_context(a.out.stem):  # the artifact's name is the twin's id by convention
        art, checked = train_validated(df, spec, start, a.train_days, a.models, _options(a),
                                       a.primary, thinning=thinning, skip_days=a.skip_days,
                                       ranges=ranges)
    from pseudotwin.analysis.training import plausible_readings

    df = plausible_readings(df, spec, ranges, warn=False)  # what training learnt from
    path = art.save(a.out)
    days = ", ".join(art.training["days"])
    print(f"trained {', '.join(art.models)} on {days}; artifact written to {path}")
    from pseudotwin.analysis.commissioning.coverage import training_data

    # The commissioning report's verdict on the data, here too: a thin training day makes
    # every score below rest on less than it seems to.
    print(f"training data: {training_data(df, art, start).verdict()}")
    _say_unused_skips(a.skip_days, art)
    _say_odd_day(art)
    for kind, m in art.models.items():
        if summary := m.fit_summary():
            print(f"  {kind}: {summary}")
    if art.validation.get("scores"):
        from pseudotwin.analysis.validation import validation_table

        print("validation on the training days (each held out in turn):")
        print(validation_table(art.validation, art.unit))
        from pseudotwin.analysis.criteria import criteria_table

        print("self-aware indication: criteria of quality `uncertain`, judged on the held-out "
              "days:")
        print(criteria_table(art.envelope.to_dict() if art.envelope else None, art.unit))
    else:
        print(f"primary: {art.primary} (not validated)")
    for f in art.failovers:
        print(f"  failover {f.label}: {f.kind} on {', '.join(f.model.references_)} "
              f"(held-out {f.nrmse_pct:.2f} %)")
    if a.report is not None:
        import time

        from pseudotwin.analysis.commissioning import write_report

        t0 = time.perf_counter()
        page = write_report(a.report, art, checked, df, start, path, _store_read(a, cfg))
        print(f"commissioning report written to {page} ({page.stat().st_size / 1e3:.0f} kB, "
              f"{time.perf_counter() - t0:.1f} s)")
    return 0


def _stored_history(a: argparse.Namespace) -> pd.DataFrame:
    """Every reading of the twin's sensors in the store --store: what evaluate reads from a
    history file (a site that recorded its commissioning days had no file to give)."""
    from pseudotwin.analysis.training import require_stored
    from pseudotwin.history.store import open_store

    with open_store(a.store, existing=True, migrate=False) as store:  # readings only
        # (covariates are read where there are some, as from a file)
        require_stored(store, [*a.references, a.target], f"the history store {a.store}")
        return store.read_readings([*a.references, a.target, *a.covariates])


def cmd_evaluate(a: argparse.Namespace) -> int:
    from pseudotwin.analysis.evaluate import evaluate, summary_table
    from pseudotwin.core.series import read_history
    from pseudotwin.core.thinning import Thinning
    from pseudotwin.core.twinlog import twin_context

    df = read_history(a.history) if a.history is not None else _stored_history(a)
    with twin_context(a.target):  # evaluate has no twin id: its desk sensor names it
        ev = evaluate(df, _spec(a), a.train_start, a.train_days, a.models, a.out,
                      _options(a), a.plot_day, a.primary,
                      thinning=Thinning(dt.timedelta(seconds=a.min_interval)),
                      stale_after=(dt.timedelta(minutes=a.stale_after)
                                   if a.stale_after is not None else None),
                      skip_days=a.skip_days)
    print(f"trained on {', '.join(ev.artifact.training['days'])}; "
          f"scored {ev.daily['day'].nunique()} day(s) in {ev.seconds:.1f} s")
    _say_unused_skips(a.skip_days, ev.artifact)
    _say_odd_day(ev.artifact)
    print(summary_table(ev))
    print(f"written: {a.out}/daily.csv, monthly.csv, estimates.csv, artifact.json, plots")
    return 0


def _number(text: str, of: str = "") -> float:
    """``text`` as a float, or argparse's error naming what was expected (``of``)."""
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number{of}") from None


def _positive_seconds(text: str) -> float:
    seconds = _number(text, " of seconds")
    from pseudotwin.core.thinning import MIN_INTERVAL_SECONDS

    lo, hi = MIN_INTERVAL_SECONDS  # as a sensor's min_interval_seconds
    if not lo <= seconds <= hi:
        raise argparse.ArgumentTypeError(f"{text} s is not in {lo:g}..{hi:g}")
    return seconds


def _positive_minutes(text: str) -> float:
    minutes = _number(text, " of minutes")
    if not minutes > 0 or minutes == float("inf"):
        raise argparse.ArgumentTypeError(f"{text} min is not a positive number of minutes")
    return minutes


MAX_VARMA_P = 8  # five training days hold ~220 slots: a higher order fits noise


_varma_order = whole_number(1, MAX_VARMA_P)
# (a day at most: a span over the whole window is one straight line already)
_smooth_span = whole_number(1, 24 * 60, what="a whole number of minutes")
_tcp_port = whole_number(1, 65535, "a port number")
# (more terms than a few cost hours of fitting and add nothing the references can tell)
_lcm_terms = whole_number(1, 10, what="a number of terms")


def _minutes_at_least_zero(text: str) -> float:
    minutes = _number(text, " of minutes")
    if not 0 <= minutes < math.inf:
        raise argparse.ArgumentTypeError(f"{text} min: must be ≥ 0")
    return minutes


MAX_SPEED = 1e6  # a day in under a tenth of a second; beyond, the clock's arithmetic overflows


def _speed(text: str) -> float:
    speed = _number(text)
    if not 0 < speed < math.inf:
        raise argparse.ArgumentTypeError(f"{text}: the speed must be positive")
    if speed > MAX_SPEED:
        raise argparse.ArgumentTypeError(f"{text}: at most {MAX_SPEED:g} times real time")
    return speed


def _output(text: str) -> Path:
    """A path to write, checked before any work: its nearest existing folder takes a file."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path")
    path = Path(text)
    parent = next((p for p in path.absolute().parents if p.exists()), None)
    if parent is not None and not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {parent} is not a directory")
    folder = path if path.is_dir() else parent
    if folder is not None:
        import tempfile

        # A file created and dropped, not os.access: root passes permission checks that an
        # immutable folder, a read-only mount or /proc still refuse at the end of training.
        try:
            with tempfile.TemporaryFile(dir=folder):
                pass
        except OSError as exc:
            raise argparse.ArgumentTypeError(
                f"{text}: cannot write in {folder} ({exc.strerror or exc})") from None
    return path


def _artifact_out(text: str) -> Path:
    """An artifact file to write: not a directory, its folder creatable."""
    path = _output(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory; give the artifact's file "
                                         f"name, e.g. {path / 'twin.json'}")
    if path.exists() and not path.is_file():  # a device, a pipe: never replaced by a file
        raise argparse.ArgumentTypeError(f"{text} exists and is not a regular file")
    return path


def _folder_out(text: str) -> Path:
    """An output folder: absent (it is created) or a directory."""
    path = _output(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} exists and is not a directory")
    return path


def _same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file (links and relative paths included)."""
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and a.samefile(b))
    except OSError:
        return False


def _check_training(p: argparse.ArgumentParser, a: argparse.Namespace) -> None:
    from pseudotwin.analysis.evaluate import OUTPUT_FILES
    from pseudotwin.analysis.validation import MIN_DAYS

    if a.command == "train" and a.history is None and a.store is None and a.config is None:
        p.error("one of the arguments --history --store --config is required")
    readers = [k for k, cls in MODELS.items() if cls.reads_covariates]
    if a.covariates and not any(k in readers for k in a.models):
        p.error(f"--covariates {','.join(a.covariates)}: none of the models asked for reads "
                f"covariates (only {', '.join(readers)} does): add it to --models, or leave "
                "--covariates out (the twin would have to be fed sensors nothing reads)")
    if a.primary is not None and a.primary not in a.models:
        p.error(f"--primary {a.primary} is not among --models ({','.join(a.models)}): add it, "
                "or leave --primary out and let validation choose")
    written = [a.out] if a.command == "train" else [a.out / n for n in OUTPUT_FILES]
    inputs = [("--history", a.history), ("--config", getattr(a, "config", None))]
    if (store := getattr(a, "store", None)) and (file := sqlite_file(store)):
        inputs.append(("--store", Path(file)))
    for option, path in inputs:
        if path is not None and any(_same_file(path, w) for w in written):
            p.error(f"--out would overwrite the {option} file {path}")
    if 0 < a.train_days < MIN_DAYS and not a.allow_unvalidated:
        p.error(f"--train-days {a.train_days}: validation holds out each training day in turn "
                f"and needs at least {MIN_DAYS}; with fewer, σ is not calibrated and nothing "
                f"chooses the primary (--allow-unvalidated trains anyway)")


def _check_run(p: argparse.ArgumentParser, a: argparse.Namespace) -> None:
    if a.speed is not None and a.replay_from is None:
        p.error("--speed needs --replay-from (the live clock runs at real time)")


def _check_replay(p: argparse.ArgumentParser, a: argparse.Namespace) -> None:
    if a.end <= a.start:
        p.error(f"--end {a.end.isoformat()} is not after --start {a.start.isoformat()}")


def _aware(text: str) -> dt.datetime:
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an ISO 8601 instant") from None
    if t.tzinfo is None:
        raise argparse.ArgumentTypeError(f"{text!r} needs a UTC offset, e.g. +01:00 or Z")
    if not 2000 <= t.year <= 2200:  # (readings before 2000 are refused; year 1 overflowed)
        raise argparse.ArgumentTypeError(f"{text!r}: expected a year in 2000..2200")
    return t


def _artifact_check(twin: TwinConfig, hours: OperatingHours | None,
                    thinning: Thinning | None) -> list[str]:
    from pseudotwin.live.artifact import check_artifact

    return check_artifact(twin, hours=hours, thinning=thinning)


def _load_service_config(path: Path, only_twins: frozenset[str] | None = None
                         ) -> ServiceConfig:
    from pseudotwin.config import check_config

    return check_config(path, artifact_check=_artifact_check, only_twins=only_twins)


def _serve(process: Service | Recorder) -> int:
    """Start a long-running process (daemon, recorder) and stop it on SIGTERM, SIGINT or
    SIGHUP."""
    import signal
    import threading

    from pseudotwin.core.heap import (
        freeze_long_lived,
        log_long_collections,
        watch_full_collections,
    )

    done = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        log.info("%s", stop_signal_line(signum))
        done.set()

    for sig in STOP_SIGNALS:
        signal.signal(sig, on_signal)
    freeze_long_lived()  # the loaded twins live as long as the process
    watch_full_collections()
    try:
        process.start(wait_connected=None)  # never blocks: a signal is honoured at once
    except StateInUseError as exc:  # the other one may end: systemd retries (RestartSec)
        log.error("%s", exc)
        return EX_TEMPFAIL
    except ConfigError as exc:  # found only on start, e.g. a metrics port already taken
        log.error("configuration error: %s", exc)
        return EX_CONFIG
    while not done.wait(0.2):
        log_long_collections()
        if process.fatal is not None:  # e.g. a wrong password: retrying will not help
            log.error("%s; exiting with status %d", process.fatal[1], process.fatal[0])
            break
    process.stop()
    return process.fatal[0] if process.fatal is not None else 0


def _service_exits(tempfail: str) -> str:
    """The exit statuses of a long-running process (run, record), ``tempfail`` its reasons
    for EX_TEMPFAIL."""
    # 77: edge.mqttconn.EX_NOPERM, not imported here (paho) for a --help
    return (f"Exit status: 0 stopped by a signal; {EX_TEMPFAIL} {tempfail} (systemd "
            f"retries); 77 the broker refused the credentials; {EX_CONFIG} configuration "
            "error (the units do not restart it on either).")


def _config_error(command: str, path: Path, exc: ConfigError) -> int:
    """Report a configuration error of ``run``/``record``: one line when it is one problem,
    else a heading and one line per problem; EX_CONFIG (systemd does not restart on it)."""
    print(f"pseudotwin {command}: {config_error_text(path, exc)}", file=sys.stderr)
    return EX_CONFIG


def _private_files() -> None:
    """Journal, spool and SQLite files 0600, directories 0700, whatever the launcher
    (systemd's UMask=0077 does the same; Docker and a shell do not)."""
    import os

    os.umask(0o077)


def cmd_run(a: argparse.Namespace) -> int:
    _private_files()
    from pseudotwin.config.checks import prepare_state_dir
    from pseudotwin.edge.clock import ReplayClock, SystemClock
    from pseudotwin.edge.service import Service

    fleet = a.shard is not None or a.twins is not None
    try:
        # A fleet instance checks its own twins' artifacts only: one twin's broken artifact
        # must stop its owner, not every instance (78 is not restarted by systemd).
        cfg = _load_service_config(a.config, _owned(a) if fleet else None)
    except ConfigError as exc:
        return _config_error("run", a.config, exc)
    logging.getLogger().setLevel(a.log_level or cfg.log_level)
    member = None
    try:
        if fleet:
            from pseudotwin.edge.fleet import narrow

            cfg, member = narrow(cfg, shard=a.shard, twins=a.twins, metrics_port=a.metrics_port)
        elif a.metrics_port is not None:
            import dataclasses

            cfg = dataclasses.replace(cfg, metrics=dataclasses.replace(cfg.metrics,
                                                                       port=a.metrics_port))
        prepare_state_dir(cfg.state_dir)  # a fleet member's own subfolder
    except ConfigError as exc:
        return _config_error("run", a.config, exc)
    clock = ReplayClock(a.replay_from, a.speed or 1.0) if a.replay_from else SystemClock()
    if a.replay_from:
        log.info("replay mode: clock starts at %s and runs at %g× real time",
                 a.replay_from.isoformat(), a.speed or 1.0)
    return _serve(Service(cfg, clock, member))


def _owned(a: argparse.Namespace) -> frozenset[str]:
    """The twins of ``run --shard/--twins``, from the file's own consistency alone."""
    from pseudotwin.config import load_config
    from pseudotwin.edge.fleet import narrow

    _, member = narrow(load_config(a.config), shard=a.shard, twins=a.twins)
    return frozenset(member.twins)


def cmd_replay(a: argparse.Namespace) -> int:
    from pseudotwin.core.series import read_history
    from pseudotwin.edge.replay import replay

    cfg = load_named_config(a.config)
    df = read_history(a.history)
    n = replay(cfg, df, a.start, a.end, a.speed, hold=True)
    print(f"published {n} readings")
    return 0


def cmd_record(a: argparse.Namespace) -> int:
    _private_files()
    from pseudotwin.config import check_config
    from pseudotwin.config.checks import prepare_state_dir
    from pseudotwin.edge.recorder import Recorder

    try:
        # No twin's artifact: the recorder needs sensors, broker and store only, and it runs
        # before the twins are trained (the commissioning days are what train reads).
        cfg = check_config(a.config, only_twins=frozenset())
        prepare_state_dir(cfg.state_dir)  # its spool lives there
        rec = Recorder(cfg)
    except ConfigError as exc:
        return _config_error("record", a.config, exc)
    logging.getLogger().setLevel(a.log_level or cfg.log_level)  # as run
    return _serve(rec)


def cmd_backfill(a: argparse.Namespace) -> int:
    from pseudotwin.cli.backfill import run

    return run(a)  # each day's log lines name their twin (history.backfill.run_chunk)


def cmd_convert(argv: list[str]) -> int:
    from pseudotwin.cli.convert import main as convert_main

    return convert_main(argv)


def cmd_import(argv: list[str]) -> int:
    from pseudotwin.cli.importer import main as import_main

    return import_main(argv)


def cmd_bridge(argv: list[str]) -> int:
    from pseudotwin.cli.bridge import main as bridge_main

    return bridge_main(argv)


class _NotingCheck:
    """check-config's artifact check, which also notes each twin whose artifact has no σ
    calibration (the artifact loaded once for both)."""

    def __init__(self) -> None:
        self.notes: list[str] = []

    def __call__(self, twin: TwinConfig, hours: OperatingHours | None,
                 thinning: Thinning | None) -> list[str]:
        from pseudotwin.live.artifact import UNVALIDATED, Artifact, check_artifact

        art = Artifact.load(twin.artifact)
        if not art.calibration:
            self.notes.append(f"twins.{twin.id}: {UNVALIDATED}")
        return check_artifact(twin, art, hours, thinning)


def cmd_check_config(argv: list[str]) -> int:
    from pseudotwin.cli.check_config import main as check_config_main

    check = _NotingCheck()
    return check_config_main(argv, artifact_check=check, notes=check.notes)


DELEGATED: dict[str, Callable[[list[str]], int]] = {
    "convert": cmd_convert,
    "check-config": cmd_check_config,
    "import": cmd_import,
    "bridge": cmd_bridge,
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pseudotwin",
        description="Pseudo-measurements of desk temperature and CO2 from room reference "
                    "sensors with a correlated Gaussian process (Corr-GP) digital twin.",
        epilog="Subcommands: train, evaluate, run, record, backfill, bridge, replay, import, "
               "convert, check-config. "
               "'pseudotwin SUBCOMMAND --help' explains each.",
    )
    p.add_argument("--version", action="version", version=f"pseudotwin {__version__}")
    p.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS,
                   help="default INFO (for run and record: the configuration's log_level)")
    sub = p.add_subparsers(dest="command", metavar="SUBCOMMAND")

    t = sub.add_parser("train", help="train a twin's models and write the model artifact",
                       description="Train Corr-GP, TRIV and VARMA models of one twin on a few "
                                   "days with a temporary desk sensor; write a JSON artifact. "
                                   "From a file or the history store; without --train-start "
                                   "the first --train-days days on which every sensor reports "
                                   "in operating hours are chosen (and printed).")
    _add_twin_args(t, train=True)
    t.add_argument("--out", required=True, type=_artifact_out,
                   help="artifact file to write (.json); checked before training")
    t.add_argument("--min-interval", type=_positive_seconds, default=None, metavar="SECONDS",
                   help="the daemon's window keeps at most one point per sensor and interval, "
                        "the mean of its readings in it; training learns from those points, "
                        "not from single samples of a chatty sensor, and replays the held-out "
                        "days through that window (default: with --config, the sensors' "
                        "min_interval_seconds, which a value that contradicts them may not "
                        "override; else 60)")
    t.add_argument("--report", type=_folder_out, metavar="DIR",
                   help="also write a commissioning report, DIR/<twin>.html (<twin>: the "
                        "artifact's file name): one self-contained HTML page with the data "
                        "found per sensor and day and whether it is enough, every candidate's "
                        "held-out score and why the primary won, the raw reference's own "
                        "score, the primary's typical and worst held-out days with the ±2σ "
                        "band, and the TOML configuration for the twin. Uses what training "
                        "computed; nothing is refit")
    t.set_defaults(func=cmd_train, check=functools.partial(_check_training, t))

    e = sub.add_parser("evaluate", help="train, then score the models causally on later days",
                       description="The thesis protocol: train on five days (--train-days), "
                                   "then estimate the "
                                   "target at every true reading of the following days using "
                                   "only earlier data, and score per day and month.")
    _add_twin_args(e)
    e.add_argument("--out", required=True, type=_folder_out,
                   help="output folder: daily.csv, monthly.csv, estimates.csv, plots")
    e.add_argument("--min-interval", type=_positive_seconds, default=60.0, metavar="SECONDS",
                   help="the window keeps at most one point per sensor and interval, the mean "
                        "of its readings in it, and a chatty target is scored once per "
                        "interval, as the daemon's min_interval_seconds (default 60)")
    e.add_argument("--stale-after", type=_positive_minutes, metavar="MINUTES",
                   help="score what the daemon with this stale_after_minutes publishes: a "
                        "reference silent longer makes the estimate stale, or a failover "
                        "answers without it (default: a silent reference's last value is held; "
                        "only a reference that never reported makes the estimate stale)")
    e.add_argument("--plot-day", type=_date,
                   help="day to plot in detail (default: the primary's median day by NRMSE, "
                        "among days with at least half the usual scored readings)")
    e.set_defaults(func=cmd_evaluate, check=functools.partial(_check_training, e))

    r = sub.add_parser("run", help="run the live daemon (MQTT in, pseudo-measurements out)",
                       description="Run the twins of a configuration against the MQTT broker "
                                   "until SIGTERM/SIGINT/SIGHUP. A reading is acknowledged to "
                                   "the broker once it is in the journal in state_dir (on "
                                   "disk with [service] journal_fsync, the default).",
                       epilog=_service_exits("another daemon runs on the same state_dir, "
                                             "or the clock went back"))
    r.add_argument("--config", required=True, type=Path, help="TOML configuration file")
    r.add_argument("--replay-from", type=_aware, metavar="INSTANT",
                   help="replay mode: the daemon's clock starts at this instant "
                        "(ISO 8601 with offset) instead of now")
    r.add_argument("--speed", type=_speed,
                   help="replay mode (needs --replay-from): clock speed-up factor, > 0 "
                        "(default 1)")
    fleet = r.add_mutually_exclusive_group()
    fleet.add_argument("--shard", type=_shard, metavar="I/N",
                       help="fleet: run only shard I of N (0-based), the twins whose "
                            "SHA-256 of the id (its first 8 bytes, big-endian) mod N is I, and "
                            "subscribe only to their sensors; "
                            "client id, state_dir subfolder and status topic "
                            "(<base>/status/shard-I-of-N) become this instance's own")
    fleet.add_argument("--twins", type=_csv, metavar="ID,ID",
                       help="fleet: run only these twins of the configuration (as --shard, "
                            "the instance is named after the set)")
    r.add_argument("--metrics-port", type=_tcp_port, metavar="PORT",
                   help="serve Prometheus metrics on this port instead of [metrics] port "
                        "(one per instance when several run on one host)")
    r.set_defaults(func=cmd_run, check=functools.partial(_check_run, r))

    rp = sub.add_parser("replay", help="publish stored readings through the broker",
                        description="Publish a canonical history's readings of the configured "
                                    "sensors to their topics on an accelerated clock.")
    rp.add_argument("--config", required=True, type=Path,
                    help="the daemon's configuration (broker, sensors and their topics)")
    rp.add_argument("--history", required=True, type=Path, help="canonical history file")
    rp.add_argument("--start", required=True, type=_aware, metavar="INSTANT",
                    help="first instant to replay: ISO 8601 with a UTC offset, "
                         "e.g. 2012-03-20T07:00:00+01:00 (or Z)")
    rp.add_argument("--end", required=True, type=_aware, metavar="INSTANT",
                    help="instant to stop before: ISO 8601 with a UTC offset, "
                         "e.g. 2012-03-20T20:00:00+01:00 (or Z)")
    rp.add_argument("--speed", type=_speed, default=60.0,
                    help="speed-up factor, > 0 (default 60)")
    rp.set_defaults(func=cmd_replay, check=functools.partial(_check_replay, rp))

    rc = sub.add_parser("record", help="record every valid reading into the history store",
                        description="Subscribe to the configured sensor topics and write every "
                                    "valid reading to the store ([service] store) in batches; "
                                    "buffers to disk (state_dir/recorder-spool.jsonl) while the "
                                    "store is unreachable. A reading is acknowledged to the "
                                    "broker once it is stored or spooled (on disk with "
                                    "[service] journal_fsync, the default).",
                        epilog=_service_exits("another recorder runs on the same state_dir"))
    rc.add_argument("--config", required=True, type=Path, help="TOML configuration file")
    rc.set_defaults(func=cmd_record)

    bf = sub.add_parser("backfill", help="write twins' estimates for past days to the store",
                        description="Replay stored readings day by day through the daemon's "
                                    "twin code and write every model's estimates to the "
                                    "estimates table. Idempotent and resumable. Twins, and "
                                    "runs of one twin's days, run in parallel processes "
                                    "(--jobs) with the same results as one process. Exit "
                                    "status 1 when a day failed (each failure names its "
                                    "twin and day; other days stay written), 130 on Ctrl-C.")
    from pseudotwin.cli.backfill import add_arguments as add_backfill_arguments

    add_backfill_arguments(bf)
    bf.set_defaults(func=cmd_backfill)

    sub.add_parser("convert", help="convert a shared dataset into canonical CSV", add_help=False)
    sub.add_parser("check-config", help="validate a daemon configuration file", add_help=False)
    sub.add_parser("import", help="load a canonical history file into the history store",
                   add_help=False)
    sub.add_parser("bridge", help="publish PLC symbols (ADS notifications) as MQTT readings",
                   add_help=False)
    for name, sp in sub.choices.items():
        if name not in DELEGATED:  # after the subcommand too: `pseudotwin run ... --log-level`
            sp.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS,
                            default=argparse.SUPPRESS,
                            help="as before the subcommand: default INFO (for run and record: "
                                 "the configuration's log_level)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    try:
        try:
            return _main(argv)
        finally:
            sys.stdout.flush()  # here, not at exit: a closed pipe is an ordinary end
    except BrokenPipeError:
        # The reader went away (`pseudotwin train … | head`): no traceback, and no second
        # one when the interpreter flushes stdout at exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE


def _main(argv: Sequence[str] | None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    # Subcommands with their own parsers get the rest of the line untouched.
    first = next((i for i, x in enumerate(args) if not x.startswith("-")
                  and (i == 0 or args[i - 1] != "--log-level")), None)  # not its value
    if first is not None and args[first] in DELEGATED:
        # The options before the subcommand are the main parser's: checked by it (a bad
        # --log-level is its usage error, as for the other subcommands).
        head = build_parser().parse_args(args[:first])
        setup_logging(head.log_level or "INFO")
        try:
            return DELEGATED[args[first]](args[first + 1:])
        except KeyboardInterrupt:  # what was written so far stays whole (convert, import)
            print(f"pseudotwin {args[first]}: interrupted", file=sys.stderr)
            return 130
    parser = build_parser()
    a = parser.parse_args(args)
    if check := getattr(a, "check", None):
        check(a)  # what one option alone cannot tell: argparse's error, status 2
    if not getattr(a, "func", None):
        parser.print_help()
        return 2
    setup_logging(a.log_level or "INFO")
    try:
        return int(a.func(a))
    except PseudotwinError as exc:
        print(f"pseudotwin {a.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.filename is None:
            raise
        # A file that could not be read or written after the checks (a disk filled up, a
        # folder made read-only meanwhile): its name and the OS's reason, not a traceback.
        print(f"pseudotwin {a.command}: error: {exc.filename}: {exc.strerror or exc}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"pseudotwin {a.command}: interrupted", file=sys.stderr)
        return 130

