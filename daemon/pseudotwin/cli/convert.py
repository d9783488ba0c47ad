"""``pseudotwin convert DATASET --out FILE.csv``: a shared dataset as canonical history CSV,
or Parquet with ``--out FILE.parquet`` (the converters are :mod:`pseudotwin.history.convert`)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pseudotwin.cli.util import Parser, UsageError, run_reporting
from pseudotwin.history.convert import DATASETS, convert, find_dataset

PROG = "pseudotwin convert"


def _parser() -> argparse.ArgumentParser:
    p = Parser(
        prog=PROG,
        description="Convert a shared dataset into canonical history CSV (sensor,ts,value) "
                    "or Parquet.",
    )
    p.add_argument("dataset", nargs="?", help="dataset name (see --list)")
    p.add_argument("--source", type=Path, help="dataset folder or file (default: shared data)")
    p.add_argument("--out", type=Path,
                   help="output file (required but with --list): canonical CSV, or Parquet "
                        "when it ends in .parquet or .pq")
    p.add_argument("--raw", action="store_true",
                   help="keep every sample where the converter would average (room-climate-*: "
                        "one reading every ~4 s per node instead of 1-minute means)")
    p.add_argument("--list", action="store_true", help="list the datasets and exit")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``pseudotwin convert``; returns the exit status (0 ok, 2 error)."""
    def body() -> int:
        args = _parser().parse_args(argv)
        if args.list:
            width = max(map(len, DATASETS))
            for name, spec in DATASETS.items():
                print(f"{name:<{width}}  {spec.description}")
            return 0
        if args.dataset is None:
            raise UsageError("a dataset name is required (see --list)")
        spec = find_dataset(args.dataset)
        if args.raw and spec.read_raw is None:
            raise UsageError(f"--raw: {args.dataset} has no samples to keep beyond what it "
                             "converts (only room-climate-* average)")
        if args.out is None:
            raise UsageError("--out FILE.csv (or FILE.parquet) is required")
        t0 = time.perf_counter()
        summary = convert(args.dataset, args.source, args.out, raw=args.raw)
        print(f"{summary.line()} ({time.perf_counter() - t0:.1f} s)")
        return 0

    return run_reporting(PROG, body)


if __name__ == "__main__":
    sys.exit(main())
