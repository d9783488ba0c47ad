"""Command-line plumbing shared by the subcommands that own their parsers."""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from pseudotwin.edge.clock import EX_TEMPFAIL as EX_TEMPFAIL  # the CLI's too
from pseudotwin.errors import ConfigError, PseudotwinError

if TYPE_CHECKING:
    from pseudotwin.config import ServiceConfig

EX_CONFIG = 78  # sysexits: systemd's RestartPreventExitStatus keys on it

#: Signals that stop a long-running process cleanly. SIGHUP too: a terminal closed under a
#: foreground run killed it without a line or a clean stop; it reloads nothing.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


def stop_signal_line(signum: int) -> str:
    """The log line of a stop signal."""
    name = signal.Signals(signum).name
    return f"received {name}; stopping" + (" (SIGHUP reloads nothing: the configuration is "
                                           "read at start)" if signum == signal.SIGHUP else "")


def config_error_text(path: Path, exc: ConfigError) -> str:
    """The problems of the configuration at ``path``: one line when it is one problem, else a
    heading and one line per problem."""
    sep = "\n" if "\n" in str(exc) else " "
    return f"configuration error in {path}:{sep}{exc}"


def load_named_config(path: Path) -> ServiceConfig:
    """The configuration at ``path`` for a command that only reads it (train, backfill): its
    problems name the file, as those of ``run`` do."""
    from pseudotwin.config import ConfigProblems, load_config

    try:
        return load_config(path)
    except ConfigProblems as exc:
        raise ConfigError(config_error_text(path, exc)) from None


def whole_number(lo: int, hi: int | None = None, what: str = "a whole number"
                 ) -> Callable[[str], int]:
    """An argparse type: an integer in lo..hi (no upper bound when ``hi`` is None)."""
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if n < lo or hi is not None and n > hi:
            raise argparse.ArgumentTypeError(f"{n} is not in {lo}..{hi}" if hi is not None
                                             else f"must be at least {lo}, not {n}")
        return n

    return parse


class UsageError(Exception):
    """Bad command-line arguments, reported by the subcommand as one error line."""


class Parser(argparse.ArgumentParser):
    # argparse would print its usage block and exit; the CLI contract is one error line and
    # exit status 2, so its complaints become an exception the subcommand's main() reports.
    def error(self, message: str) -> NoReturn:
        raise UsageError(message)


def run_reporting(prog: str, body: Callable[[], int]) -> int:
    """Run a subcommand's body; every expected failure becomes one error line and status 2,
    never a traceback."""
    try:
        return body()
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0
    except (UsageError, PseudotwinError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        raise  # the reader went away, not a failure: cli.main ends quietly
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"{prog}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
