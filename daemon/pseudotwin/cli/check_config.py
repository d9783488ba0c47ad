"""``pseudotwin check-config FILE``: validate a configuration, its artifacts included."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pseudotwin.config import ArtifactCheck, ConfigProblems, check_config
from pseudotwin.errors import ConfigError


def _bridge_problems(path: str) -> list[str]:
    """The problems of a [plc] / [bridge] part the file shares with the bridge, as
    ``pseudotwin bridge --check`` finds them offline (the daemon's loader only lets those
    tables be, so a broken one passed here and failed only when the bridge started)."""
    from pseudotwin.config.loader import read_toml
    from pseudotwin.edge.bridge import load_bridge_config

    if not {"plc", "bridge"} & set(read_toml(Path(path))):
        return []
    try:
        load_bridge_config(path)
    except ConfigProblems as exc:
        return [p for p in exc.problems if p.startswith(("plc", "bridge"))]
    return []


def main(argv: list[str] | None = None, *, artifact_check: ArtifactCheck | None = None,
         notes: list[str] | None = None) -> int:
    """``pseudotwin check-config FILE``: 0 valid, 1 problems found, 2 unreadable/not TOML.
    notes: filled by ``artifact_check`` with what is worth saying but no problem."""
    parser = argparse.ArgumentParser(
        prog="pseudotwin check-config",
        description=(
            "Validate a pseudotwin configuration file: unknown or missing keys, types, MQTT "
            "topics, sensor ranges and units, twins' references, operating hours and time "
            "zone, and that every twin's model artifact and the MQTT password source "
            "(password_env / password_file) are available. Prints every problem with its "
            "location, e.g. 'sensors[2].topic: ...'."
        ),
        epilog="Exit status: 0 valid, 1 problems found, 2 file unreadable or not valid TOML.",
    )
    parser.add_argument("file", metavar="FILE", help="the TOML configuration file")
    args = parser.parse_args(argv)
    try:
        config = check_config(args.file, artifact_check=artifact_check)
        problems: list[str] = []
    except ConfigProblems as exc:
        config, problems = None, list(exc.problems)
    except ConfigError as exc:
        # read_toml already prefixes the path.
        print(str(exc), file=sys.stderr)
        return 2
    problems += _bridge_problems(args.file)
    if problems or config is None:
        for problem in problems:
            print(f"{args.file}: {problem}", file=sys.stderr)
        return 1
    print(f"{args.file}: OK ({len(config.sensors)} sensors, {len(config.twins)} twins)")
    for note in notes or ():
        print(f"{args.file}: note: {note}")
    return 0
