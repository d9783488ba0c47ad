#!/usr/bin/env python3
"""The project's accuracy results: writes docs/results.md from the shared datasets.

Runs the evaluation protocol (DESIGN.md §7, the same ``evaluate`` the CLI calls) on
SML2010 (temperature and CO2), Room Climate locations A and B and the Appliances house
(long-term, plus corrgp-triv with the unshifted reference profile), writes every run's CSV
and PNG outputs under ``out/results/<run>/`` and renders the tables and verdicts as
Markdown. The report itself is built by ``pseudotwin.analysis.report``.

Usage: .venv/bin/python scripts/results.py [--only RUN[,RUN]] [--out FILE]
(with --only the report goes to out/results-partial.md unless --out is given).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy does any work)
from pseudotwin.analysis.report import RUN_NAMES, RUNS, package_files, progress, render, run_all

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "results.md"
PARTIAL = REPO / "out" / "results-partial.md"
OUT = REPO / "out" / "results"


def _only(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [n for n in names if n not in RUN_NAMES]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown run(s) {', '.join(bad) or '(none)'}; choose from {', '.join(RUN_NAMES)}")
    return names


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--only", type=_only, help=f"comma-separated subset of: {', '.join(RUN_NAMES)}"
                    f" (report then goes to {PARTIAL.relative_to(REPO)})")
    ap.add_argument("--out", type=Path, help=f"report file (default {DOC.relative_to(REPO)})")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    at_start = package_files()
    specs = [r for r in RUNS if a.only is None or r.name in a.only]
    partial = a.only is not None
    target = a.out or (PARTIAL if partial else DOC)
    results = run_all(specs, OUT)
    total = time.perf_counter() - t0
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(render(results, total, partial, at_start), encoding="utf-8")
    progress(f"wrote {target} in {total:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
