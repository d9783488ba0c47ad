"""``pseudotwin`` command line: one entry point, one subcommand per job."""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from . import __version__
from .errors import PseudotwinError

log = logging.getLogger("pseudotwin")

MODELS_HELP = "comma-separated models: corrgp-triv, corrgp-lcm, triv, varma"


def setup_logging(level: str = "INFO") -> None:
    """One line per event on stdout/stderr (systemd and Docker collect it as is)."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    for noisy in ("GP", "paramz", "matplotlib"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def _csv(text: str) -> list[str]:
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise argparse.ArgumentTypeError("expected a comma-separated list")
    return items


def _date(text: str) -> dt.date:
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a date YYYY-MM-DD") from None


def _add_twin_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--history", required=True, type=Path,
                   help="canonical history file (CSV or Parquet): sensor,ts,value")
    p.add_argument("--references", required=True, type=_csv,
                   help="reference sensor(s), comma-separated, e.g. hmi/temp,ceiling/temp")
    p.add_argument("--target", required=True, help="the desk sensor to pseudo-measure")
    p.add_argument("--quantity", required=True, choices=("temperature", "co2"),
                   help="selects the default kernel: RQ for temperature, Matérn 5/2 for CO2")
    p.add_argument("--train-start", required=True, type=_date,
                   help="first candidate training day YYYY-MM-DD (local)")
    p.add_argument("--train-days", type=int, default=5,
                   help="training days: the first N days from --train-start on which every "
                        "sensor reports (default 5)")
    p.add_argument("--models", type=_csv, default=["corrgp-triv", "corrgp-lcm", "triv", "varma"],
                   help=MODELS_HELP + " (default: all)")
    p.add_argument("--timezone", default="UTC",
                   help="IANA time zone of the building; operating hours are local (default UTC)")
    p.add_argument("--day-start", default="08:00", help="start of operating hours (default 08:00)")
    p.add_argument("--day-end", default="19:00", help="end of operating hours (default 19:00)")
    p.add_argument("--init-minutes", type=float, default=30.0,
                   help="init phase before day start, collected but not published (default 30)")
    p.add_argument("--slot-minutes", type=float, default=15.0,
                   help="time-of-day grid of TRIV, VARMA and GP training (default 15)")
    p.add_argument("--kernel", choices=("rq", "matern52", "matern32", "rbf"),
                   help="override the Corr-GP kernel")
    p.add_argument("--ref-mean", choices=("shifted", "profile"), default="shifted",
                   help="corrgp-triv reference prior mean: training profile shifted to today's "
                        "level in the init phase (default), or the unshifted profile")


def _hours(a: argparse.Namespace):
    from .horizon import OperatingHours

    return OperatingHours.from_strings(
        a.day_start, a.day_end, a.init_minutes, a.slot_minutes, a.timezone
    )


def _options(a: argparse.Namespace) -> dict:
    gp = {"kernel": a.kernel} if a.kernel else {}
    return {"corrgp-triv": {**gp, "ref_mean": a.ref_mean}, "corrgp-lcm": dict(gp)}


def cmd_train(a: argparse.Namespace) -> int:
    from .history import read_history
    from .training import train_twin

    hours = _hours(a)
    df = read_history(a.history)
    art = train_twin(df, a.references, a.target, a.quantity, hours, a.train_start,
                     a.train_days, a.models, _options(a))
    path = art.save(a.out)
    days = ", ".join(art.training["days"])
    print(f"trained {', '.join(art.models)} on {days}; artifact written to {path}")
    for kind, m in art.models.items():
        rep = getattr(m, "report_", None)
        if rep is not None:
            print(f"  {kind}: NLML {rep.nlml:.2f}, {rep.seconds:.1f} s, "
                  f"max jitter {rep.jitter_max:.1e}, max condition {rep.condition_max:.2e}")
    return 0


def cmd_evaluate(a: argparse.Namespace) -> int:
    from .evaluate import evaluate, summary_table
    from .history import read_history

    hours = _hours(a)
    df = read_history(a.history)
    ev = evaluate(df, a.references, a.target, a.quantity, hours, a.train_start, a.train_days,
                  a.models, a.out, _options(a), a.plot_day)
    print(f"trained on {', '.join(ev.artifact.training['days'])}; "
          f"scored {ev.daily['day'].nunique()} day(s) in {ev.seconds:.1f} s")
    print(summary_table(ev))
    print(f"written: {a.out}/daily.csv, monthly.csv, estimates.csv, artifact.json, plots")
    return 0


def cmd_convert(argv: list[str]) -> int:
    from .convert import main as convert_main

    return convert_main(argv)


def cmd_check_config(argv: list[str]) -> int:
    from .config import check_config_main

    return check_config_main(argv)


DELEGATED: dict[str, Callable[[list[str]], int]] = {
    "convert": cmd_convert,
    "check-config": cmd_check_config,
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pseudotwin",
        description="Pseudo-measurements of desk temperature and CO2 from room reference "
                    "sensors with a correlated Gaussian process (Corr-GP) digital twin.",
        epilog="Subcommands: train, evaluate, convert, check-config. "
               "'pseudotwin SUBCOMMAND --help' explains each.",
    )
    p.add_argument("--version", action="version", version=f"pseudotwin {__version__}")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    sub = p.add_subparsers(dest="command", metavar="SUBCOMMAND")

    t = sub.add_parser("train", help="train a twin's models and write the model artifact",
                       description="Train Corr-GP, TRIV and VARMA models of one twin on a few "
                                   "days with a temporary desk sensor; write a JSON artifact.")
    _add_twin_args(t)
    t.add_argument("--out", required=True, type=Path, help="artifact file to write (.json)")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("evaluate", help="train, then score the models causally on later days",
                       description="The thesis protocol: train on five days, then estimate the "
                                   "target at every true reading of the following days using "
                                   "only earlier data, and score per day and month.")
    _add_twin_args(e)
    e.add_argument("--out", required=True, type=Path,
                   help="output folder: daily.csv, monthly.csv, estimates.csv, plots")
    e.add_argument("--plot-day", type=_date, help="day to plot in detail (default: median day)")
    e.set_defaults(func=cmd_evaluate)

    sub.add_parser("convert", help="convert a shared dataset into canonical CSV", add_help=False)
    sub.add_parser("check-config", help="validate a daemon configuration file", add_help=False)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    # Subcommands with their own parsers get the rest of the line untouched.
    first = next((i for i, x in enumerate(args) if not x.startswith("-")), None)
    if first is not None and args[first] in DELEGATED:
        setup_logging("INFO")
        return DELEGATED[args[first]](args[first + 1:])
    parser = build_parser()
    a = parser.parse_args(args)
    if not getattr(a, "func", None):
        parser.print_help()
        return 2
    setup_logging(a.log_level)
    try:
        return int(a.func(a))
    except PseudotwinError as exc:
        print(f"pseudotwin {a.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"pseudotwin {a.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
