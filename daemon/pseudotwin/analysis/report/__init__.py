"""The project's accuracy report (docs/results.md): runs, tables, verdicts, Markdown.

Runs the evaluation protocol (DESIGN.md §7, the same ``evaluate`` the CLI calls) on
SML2010 (temperature and CO2), Room Climate locations A and B and the Appliances house
(long-term, plus corrgp-triv with the unshifted reference profile), writes every run's CSV
and PNG outputs under ``<out_root>/<run>/`` and renders the tables and verdicts as Markdown.
``scripts/results.py`` is the command; the commissioning report reuses the pieces.

Modules, each importing only those before it: ``runs`` (RunSpec, RUNS, run_one/run_all),
``tables`` (Markdown tables), ``evidence`` (corrgp-triv against its baselines, seasons),
``verdicts`` (the figures against the targets, the verdict texts), ``render`` (the page).
"""

from __future__ import annotations

from pseudotwin.analysis.report.render import package_files, render
from pseudotwin.analysis.report.runs import RUN_NAMES, RUNS, progress, run_all

__all__ = ["RUN_NAMES", "RUNS", "package_files", "progress", "render", "run_all"]
