"""``pseudotwin bridge --config FILE``: publish PLC symbols (ADS notifications) as MQTT
readings until SIGTERM/SIGINT/SIGHUP (the bridge itself is :mod:`pseudotwin.edge.bridge`)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

from pseudotwin.cli.util import EX_CONFIG, EX_TEMPFAIL, STOP_SIGNALS, stop_signal_line
from pseudotwin.config import ConfigProblems
from pseudotwin.config.model import LOG_LEVELS
from pseudotwin.edge.bridge import Bridge, load_bridge_config
from pseudotwin.errors import ConfigError, StateInUseError

__all__ = ["EX_CONFIG", "build_parser", "main"]

log = logging.getLogger("pseudotwin.edge.bridge")  # the bridge's own log lines


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pseudotwin bridge",
        description=(
            "Publish PLC variables as sensor readings: ADS device notifications (on change) "
            "of the symbols in [[plc.symbols]] go to their sensors' MQTT topics, QoS 1, "
            "time-stamped by the PLC (the values read at each connect: on the PLC's clock as "
            "its notifications showed it). Reconnects by itself when the PLC, the route or the "
            "broker drops; the PLC state is polled every plc.poll_seconds because ADS has no "
            "heartbeat. With bridge.spool_dir (default: the daemon's state_dir, when this "
            "is the daemon's file) every reading is on disk until the broker acknowledged "
            "it: a broker outage or a restart of the bridge loses none. Runs until "
            "SIGTERM/SIGINT/SIGHUP."
        ),
        epilog=(
            "Exit status: 0 stopped by a signal; 75 another bridge runs on the same spool "
            "(systemd retries); 77 the broker refused the credentials; 78 "
            "configuration error (the file, or a symbol the PLC does not have or declares "
            "with another type); every problem is printed with its location, e.g. "
            "'plc.symbols[1].plc_type: ...'."
        ),
    )
    p.add_argument("--config", required=True, type=Path, metavar="FILE",
                   help="TOML configuration: [broker], [[sensors]], [plc], [[plc.symbols]] "
                        "(the daemon's file or one of its own)")
    p.add_argument("--check", action="store_true",
                   help="only validate the configuration file, without connecting to anything")
    p.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS,
                   help="default INFO")
    return p


def _print_problems(path: Path, problems: Sequence[str]) -> None:
    for problem in problems:
        print(f"{path}: {problem}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """``pseudotwin bridge --config FILE``: 0 after a signal, 77 when the broker refuses the
    credentials, 78 on configuration errors."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help and usage errors; callers want an int back
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    if args.log_level:
        logging.getLogger().setLevel(args.log_level)
    try:
        cfg = load_bridge_config(args.config, runtime=True)
    except ConfigProblems as exc:
        _print_problems(args.config, exc.problems)
        return EX_CONFIG
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)  # already names the file
        return EX_CONFIG
    if args.check:
        spool = f"spool {cfg.spool_path}" if cfg.spool_path is not None else \
            "no spool: readings wait in memory only (set bridge.spool_dir)"
        print(f"{args.config}: OK ({len(cfg.plc.symbols)} PLC symbols; {spool})")
        if cfg.unstamped_note:
            print(f"{args.config}: note: {cfg.unstamped_note}")
        return 0
    bridge = Bridge(cfg)

    def on_signal(signum: int, frame: object) -> None:
        log.info("%s", stop_signal_line(signum))
        bridge.request_stop()

    in_main = threading.current_thread() is threading.main_thread()
    previous = {}
    if in_main:
        for sig in STOP_SIGNALS:
            previous[sig] = signal.signal(sig, on_signal)
    try:
        bridge.run()
    except StateInUseError as exc:  # the other one may end: systemd retries (RestartSec)
        print(f"pseudotwin bridge: {exc}", file=sys.stderr)
        return EX_TEMPFAIL
    except ConfigError as exc:  # found only on start: the spool cannot be written
        print(f"pseudotwin bridge: {exc}", file=sys.stderr)
        return EX_CONFIG
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if bridge.refused is not None:
        print(f"pseudotwin bridge: {bridge.refused[1]}", file=sys.stderr)
        return bridge.refused[0]
    if bridge.fatal is not None:
        print(f"pseudotwin bridge: the PLC does not match {args.config}:", file=sys.stderr)
        _print_problems(args.config, bridge.fatal.problems)
        return EX_CONFIG
    return 0
