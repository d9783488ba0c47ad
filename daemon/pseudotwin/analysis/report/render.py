"""The page: code identity and versions, "How to read", the overview, one section per run
and the recorded performance outputs."""

from __future__ import annotations

import datetime as dt
import hashlib
import subprocess
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path

import numpy as np

from pseudotwin.analysis.report.evidence import seasonal_md
from pseudotwin.analysis.report.runs import COMMAND, DOCS, PACKAGE, REPO, RunResult
from pseudotwin.analysis.report.tables import (
    calibration_by_day_md,
    calibration_md,
    daily_md,
    fmt,
    md_table,
    monthly_md,
    selfaware_md,
    summary_md,
    validation_md,
)
from pseudotwin.analysis.report.verdicts import (
    BEAT_TRIV,
    COVER2_RANGE,
    FLOOR_RATIO,
    figures,
    mark,
    raw_name,
    verdict_md,
)
from pseudotwin.analysis.validation import BASELINE_LIMIT
from pseudotwin.analysis.validation import TIE_RELATIVE as VALIDATION_TIE
from pseudotwin.models.registry import MODELS
from pseudotwin.models.triv import WEEKEND_TYPE, TrivWeekModel, day_type


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
_CANDIDATES = " < ".join(k for k, c in MODELS.items() if c.candidate and not c.stacked)

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
  within {VALIDATION_TIE:.0%} of it wins ({_CANDIDATES}; the blend by the rule
  under *Models*). VARMA is a monitoring
  baseline, never primary, and is not published live when its held-out NRMSE exceeds
  {BASELINE_LIMIT:g}× TRIV's. The test days are never looked at for any of this.
* **NRMSE %** (6.10) = the day's RMSE of the estimate against the target's true readings in
  operating hours / the mean of those true readings × 100. **ΔT_max %** (6.14) = the day's
  largest absolute error / the same mean × 100. *Mean daily* = mean over the test days; the
  monthly tables are the monthly means of the daily NRMSE (thesis Tables 6.2–6.4).
* **Models**: `ref` = the raw reference held (the one closest to the target on the training
  days), with a calibrated σ; `corrgp-triv` = Corr-GP ICM with TRIV as the target's prior
  mean (one reference, its prior mean the training profile shifted to the day's level in the
  30-min init phase); `corrgp-multi` = the same over all references (an LCM on the
  deviations of every reference and the target; runs with two references);
  `corrgp-lcm` = zero-mean Corr-GP LCM over all references; `triv` =
  training offset profile (per 15-min slot, from each slot's time-weighted level on the
  training days) + live reference, averaged over references; `triv-shrunk` = TRIV
  with its offset profile shrunk towards the mean offset as far as the training days
  disagree on its shape (James–Stein; the factor is in the artifact); `triv-smooth` = TRIV
  with its offset profile smoothed across the slots (LOWESS, a local straight line through
  the slots within half a span either side, the span 240, 120 or 60 minutes, chosen on the
  training days like VARMA's order: the widest within noise of the lowest held-out error);
  `triv-week` = TRIV
  with an offset profile of its own for Saturdays and Sundays, learnt from the training's
  weekend days (weekdays keep all days' profile; it is TRIV with fewer than two weekend
  days among the training days, which validation could not test); `triv-cov` = TRIV plus
  a linear term in the run's covariates' deviations from their typical day, each covariate
  kept only when it lowers TRIV's held-out error on the training days, on all held-out days
  but one and with a β of one sign, each deviation clipped to the training days' range (it
  is TRIV, and not published, when none is kept; the validation section says which helped);
  `blend` = the weighted mean of the (up to) three candidates with the lowest held-out
  NRMSE, weights ∝ 1/NRMSE² (Bates–Granger); its held-out score combines the members'
  held-out estimates with members and weights chosen on the *other* held-out days, so it is
  as honest as a single model's; it is the primary when that score is more than 3 % below the
  held-out error of choosing one candidate (measured the same way: each held-out day scored
  by the candidate the other days choose);
  `varma` = VAR(p) by least squares
  with trend `n` (no constant, no drift) on the 15-min grid, every series re-levelled each
  day by the references' init-phase shift; the order p (1, 2 or 4) is chosen on the training
  days like a candidate: the smallest whose held-out NRMSE is within 3 % or within one
  standard error of the day-by-day difference of the lowest (each run's validation section
  gives the scores). A p set through the Python API fits VARMAX(p, q) instead, with VAR(p)
  as its fallback.
  `ref:<sensor> (raw)` is the raw reference value held at the reading's time, without σ,
  scored as if it were an estimate: its NRMSE is the error of "just use the reference", and
  its **daily Pearson r** with the target is the evidence of how much that reference can tell
  about the target's within-day course (thesis Fig. 6.6). The r of a model is that of its
  estimate with the truth.
* **σ calibration**: every model's σ (ref and TRIV included) comes from its held-out errors
  in validation: a day-level part (never below the day-to-day spread of the reference–target
  offset, which no reading of today reveals) plus a within-day part that depends on the time
  of day and on how fast the references move, widened for the few days it is estimated from.
  So σ varies within a day. A time of day stands out only as far as two training days show
  it: one day's wild hour widens every hour alike.
* **Self-aware indication**: which criteria of `uncertain` validation kept on the held-out
  training days, what `ok` and `uncertain` estimates scored on the test days, and every
  criterion on the test days, a dropped one recorded without acting (the evidence whether
  validation's verdicts hold on days it never saw).
* **Calibration tables** (per model, pooled over all scored readings): the share of true
  readings inside the estimate's ±1σ and ±2σ bands (a calibrated Gaussian σ covers 68.3 % and
  95.4 %), the mean and the root-mean-square σ next to the RMSE (RMS σ / RMSE ≈ 1 when σ
  is the right size: a calibrated σ's mean square is the mean squared error, while its mean
  is smaller the more σ varies), and the
  mean **CRPS** (continuous ranked probability score of the Gaussian N(estimate, σ²), in the
  quantity's unit, lower is better: it rewards a small error and a σ of the right size; for
  an estimate without σ, such as a raw reference, it is the absolute error). Computed by
  `pseudotwin.live.metrics`, as in `daily.csv`. In the validation tables, CRPS and ±2σ
  coverage are nested: each held-out training day is scored with a σ calibrated on the
  other training days' held-out errors only, a check of σ on a day it has not seen. Nested
  in the errors, not in the models: those days' errors come from models trained with the
  scored day among their days, so an unusual day still widens, a little, the σ it is scored
  with (removing that would take a leave-one-out inside every fold).
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
        "### What helped where (Trust II)",
        "",
        _helped(results),
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
    ("bench_gp_references.txt", ".venv/bin/python scripts/bench_gp_references.py",
     "Training the Corr-GPs over all references as references are added",
     "One fit of corrgp-lcm and of corrgp-multi (training defaults: one LCM term per "
     "reference, 3 restarts; no validation) on five days of the Appliances house, target "
     "`parents/temp`, with 2 to 5 of its rooms as references. Validation adds one refit "
     "per training day (1 restart each). One fit each: a rerun differs by tens of percent, "
     "as the restarts stop once two agree."),
    ("bench_daemon.txt", ".venv/bin/python scripts/bench_daemon.py",
     "The daemon with 100 twins",
     "100 twins fed 5-minute COV readings at 60× replay speed through a real Mosquitto: "
     "latency from a reading's publish to its estimate's arrival, CPU and peak RSS."),
    ("bench_daemon_nofsync.txt",
     ".venv/bin/python scripts/bench_daemon.py --no-journal-fsync",
     "The daemon with 100 twins, journal not synced",
     "The same with `[service] journal_fsync = false`: readings acknowledged once their "
     "journal lines are in the kernel, without the default's fsync per batch."),
    ("bench_daemon_1000.txt", ".venv/bin/python scripts/bench_daemon.py --twins 1000",
     "The daemon with 1,000 twins",
     "The same at 1,000 twins: the grid work of a thousand twins paced between readings."),
    ("bench_daemon_1000_nofsync.txt",
     ".venv/bin/python scripts/bench_daemon.py --twins 1000 --no-journal-fsync",
     "The daemon with 1,000 twins, journal not synced",
     "The same with `journal_fsync = false`. The other daemon benchmarks below were "
     "recorded before journal_fsync existed: their daemon acknowledged like this one."),
    ("bench_daemon_1000_none.txt",
     ".venv/bin/python scripts/bench_daemon.py --twins 1000 --baselines none",
     "The daemon with 1,000 twins, without baselines",
     "The same with `[service] baselines = \"none\"`: the twins run their primary model "
     "only (here triv-week, validation's choice for this twin: no GP work, so what is left "
     "is the daemon's own cost), no baseline messages."),
    ("bench_mqtt_floor.txt", ".venv/bin/python scripts/bench_mqtt_floor.py",
     "What paho-mqtt alone costs per reading",
     "No twin at all: a QoS 1 reading in, its ack and one QoS 1 estimate out, at the rate of "
     "the 1,000-twin runs (200 readings/s), once with a worker thread as the daemon does it "
     "and once inside `on_message`. The CPU a paho client spends per reading before any "
     "pseudotwin code runs: compare with the daemon's figure just above."),
    ("bench_daemon_1000_day.txt",
     ".venv/bin/python scripts/bench_daemon.py --twins 1000 --hours 11",
     "The daemon with 1,000 twins through a whole operating day",
     "The same from 07:30 to 18:30 of day time: the evening's larger windows (~140 GP points "
     "per twin and model), the day state a thousand twins hold by then (peak RSS), and the "
     "latency by hour of the day."),
    ("bench_daemon_1000_day_none.txt",
     ".venv/bin/python scripts/bench_daemon.py --twins 1000 --hours 11 --baselines none",
     "The daemon with 1,000 twins through a whole operating day, without baselines",
     "The whole day with `[service] baselines = \"none\"`, the configuration for a fleet "
     "whose controllers read only the estimate: the twins run their primary model only, so "
     "no GP baseline's window grows through the day."),
    ("bench_daemon_10000.txt",
     ".venv/bin/python scripts/bench_daemon.py --twins 10000 --hours 0.25 --speed 10",
     "The daemon with 10,000 twins",
     "10,000 twins at 10× replay: what one process still carries (every estimate arrives) "
     "and what it does not (latency behind a 10,000-twin tick)."),
    ("bench_daemon_10000_none.txt",
     ".venv/bin/python scripts/bench_daemon.py --twins 10000 --hours 0.25 --speed 10 "
     "--baselines none",
     "The daemon with 10,000 twins, without baselines",
     "The same with `[service] baselines = \"none\"`: each twin's grid step is its primary "
     "estimate (and the hourly monitor), not every published model."),
    ("bench_day_state.txt", ".venv/bin/python scripts/bench_day_state.py",
     "1,000 twins' day state",
     "The same twin loaded 1,000 times in one process (no MQTT), a reading every 5 minutes "
     "through two operating days: memory of the day state per twin, objects the garbage "
     "collector tracks, and its full collections, which pause every thread of a daemon."),
    ("bench_chatty.txt", ".venv/bin/python scripts/bench_chatty.py",
     "A chatty sensor",
     "Two references reporting every 2 s for a whole operating day through the live twin: "
     "window size, per-reading update latency (all day and the last hour), and the replay of "
     "the raw days against their 1-minute means."),
    ("bench_history.txt", ".venv/bin/python scripts/bench_history.py",
     "Backfill and recorder",
     "Backfill over 7 months of 1-minute readings in SQLite: one twin serial and on all "
     "cores, and 8 twins (days per second, CPU per day, peak RSS), and the recorder's "
     "sustained rate into SQLite."),
    ("bench_store.txt", ".venv/bin/python scripts/bench_store.py",
     "The history store",
     "Bulk write, idempotent rewrite and read of 7 months of 1-minute readings of 3 sensors, "
     "and one twin's estimates for the span: SQLite against PostgreSQL (a throwaway local "
     "cluster, fsync off: the CPU and protocol cost, not the disk's)."),
    ("bench_metrics.txt", ".venv/bin/python scripts/bench_metrics.py",
     "The Prometheus endpoint with 1,000 twins",
     "The daemon's metric set for 1,000 twins with two references each, filled as by a day "
     "of operation: samples and bytes per scrape, and the time of a real scrape over HTTP."),
    ("bench_journal.txt", ".venv/bin/python scripts/bench_journal.py",
     "The journal over a day of a million readings",
     "One UTC day of 1,000,000 readings of 100 sensors appended as the daemon's worker does "
     "(batches of 64): write rate, file size, the resident memory the journal adds, and the "
     "rebuild of a journal deleted under it, from its open files."),
    ("bench_journal_fsync.txt", ".venv/bin/python scripts/bench_journal.py --fsync",
     "The journal synced to disk after every batch",
     "The same day with an fsync after every batch of 64, as the daemon does before it "
     "acknowledges them with journal_fsync (the default): what a power cut that loses no "
     "reading costs on this machine's disk."),
    ("bench_bridge.txt", ".venv/bin/python scripts/bench_bridge.py",
     "The PLC bridge's publisher and its spool",
     "20,000 readings of 10 sensors put on the bridge's queue as fast as it takes them, "
     "into a real Mosquitto: without a spool, with one, and with one synced before paho has "
     "a reading (the default); then the broker stopped, 20,000 more readings, the bridge "
     "restarted against a broker that is back: how many of those reach it."),
    ("bench_claims.txt", ".venv/bin/python scripts/bench_claims.py",
     "Twin claims in a fleet",
     "A daemon's claim of 1,000 to 100,000 twins (edge/ownership.py): its size and parts of "
     "at most 8 kB, its encoding, the time the network thread spends hearing every part of "
     "an echo, a fleet peer's claim and a second owner's, the longest part, and a claim's "
     "trip through a real Mosquitto."),
    ("failover.txt", ".venv/bin/python scripts/failover.py",
     "Reference failover",
     "Each reference of the two-reference runs silenced for every test day, and on Room "
     "Climate A with its three permanent sensors as references (room-climate-a3) each one "
     "and each two of them: the estimate's mean daily NRMSE against the full twin's, and "
     "the instants left unanswered."),
)


def _performance() -> list[str]:
    """The benchmark outputs kept in docs/ (each produced by the command shown; they are
    not rerun here because they take minutes and measure time, not accuracy)."""
    out = ["## Performance", "",
           "Recorded outputs of the benchmark commands below (rerun a command to refresh its "
           "file: `CMD > docs/FILE`). Figures are from a 2-core machine on the date in each "
           "file's header. The machines of different days differ in speed: compare figures "
           "of the same date, with a bare paho client's CPU per reading "
           "(`bench_mqtt_floor.txt`) as the yardstick.", ""]
    for name, cmd, title, what in PERFORMANCE:
        path = DOCS / name
        if not path.exists():
            continue
        text = "\n".join(line for line in path.read_text(encoding="utf-8").splitlines()
                         if "approaches 1e6" not in line)
        out += [f"### {title}", "", what, "", f"`{cmd} > docs/{name}`:", "", "```",
                text.strip(), "```", ""]
    return out


# TRIV and the models that try to beat it with information TRIV does not use.
_TRIED = ("triv", "triv-shrunk", "triv-smooth", "triv-week", "triv-cov", "corrgp-triv",
          "corrgp-multi", "corrgp-lcm", "blend")


def _helped(results: Sequence[RunResult]) -> str:
    """Per run and model: mean daily NRMSE on the test days, and held-out on the training
    days (what validation saw), next to TRIV's."""
    rows = []
    for res in results:
        test = res.daily.groupby("model")["nrmse_pct"].mean()
        scores = res.ev.artifact.validation.get("scores", {})
        cells = [res.spec.name, f"`{res.ev.artifact.primary}`"]
        for kind in _TRIED:
            if kind not in test:
                cells.append("—")
                continue
            held = scores.get(kind, {}).get("nrmse_pct")
            cells.append(f"{fmt(test[kind])} ({fmt(held)})"
                         + (f" {test[kind] / test['triv']:.2f}×" if kind != "triv" else ""))
        rows.append(cells)
    table = md_table(["run", "primary", *_TRIED], rows, left=2)
    return table + (
        "\n\nMean daily NRMSE % on the test days (in brackets: held out on the training days, "
        "what validation chose from), and the ratio to TRIV's on the test days. `—`: the model "
        "cannot serve the run's twin (corrgp-multi needs two references; triv-cov is TRIV "
        "where no covariate was kept, see each run's validation section; triv-week is TRIV "
        "with fewer than two weekend days among the training days; blend needs two "
        "validated candidates, its members are in the validation note). Only the primary is "
        "published as `estimate`; the others are scored here whether or not they run live."
    ) + _by_day_type(results)


def _by_day_type(results: Sequence[RunResult]) -> str:
    """triv-week against TRIV on the test days by day type, for the runs whose triv-week
    learnt a weekend profile (two or more weekend training days; elsewhere it is TRIV)."""
    rows = []
    for res in results:
        week = res.ev.artifact.models.get("triv-week")
        if not isinstance(week, TrivWeekModel) or week.weekend_ is None:
            continue
        d = res.daily[res.daily["model"].isin(["triv", "triv-week"])]
        weekend = d["day"].map(lambda day: day_type(dt.date.fromisoformat(day))
                               == WEEKEND_TYPE)
        cells = [res.spec.name, str(week.type_days_["weekend"])]
        for sel in (weekend, ~weekend):
            mean = d[sel].groupby("model")["nrmse_pct"].mean()
            n = d.loc[sel, "day"].nunique()
            cells += [str(n), fmt(mean.get("triv", np.nan)), fmt(mean.get("triv-week", np.nan))]
        rows.append(cells)
    if not rows:
        return ""
    table = md_table(["run", "weekend training days", "weekend test days", "triv",
                      "triv-week", "weekday test days", "triv", "triv-week"], rows, left=1)
    return ("\n\n" + table + "\n\nThe weekend profile by day type: mean daily NRMSE % on "
            "the weekend and the weekday test days. triv-week estimates weekdays as TRIV does "
            "(up to the weekend days' share in its σ); what it changes is the weekend.")


def _overview(results: Sequence[RunResult]) -> str:
    rows = []
    figs = [figures(res) for res in results]
    for res, f in zip(results, figs, strict=True):
        ref = raw_name(res, f.best_ref)
        rows.append([
            res.spec.name, str(f.days), f"`{f.primary}`", fmt(f.estimate), fmt(f.triv),
            mark(bool(f.estimate <= BEAT_TRIV * f.triv), fmt(f.estimate / f.triv, 3)),
            f"{fmt(f.ref)} ({ref})", fmt(f.floor), mark(f.floor_met, fmt(f.ratio, 3)),
            mark(f.cover_met, fmt(f.cover2, 1)), mark(f.sigma_varies, fmt(100 * f.sigma_cv, 1)),
            mark(bool(f.varma_ratio <= BASELINE_LIMIT), fmt(f.varma_ratio)),
            "—" if not np.isfinite(f.varma) else ("no" if f.varma_withheld else "yes"),
        ])
    table = md_table(["run", "test days", "primary (validation)", "estimate", "triv",
                    "estimate / triv", "best raw reference", "floor", "estimate / floor",
                    "±2σ cover %", "σ within-day CV %", "varma / triv", "varma live"], rows,
                     left=3)
    n = len(figs)
    met = [
        f"estimate ≤ {FLOOR_RATIO:.2f} × floor on {sum(f.floor_met for f in figs)} of {n}",
        f"estimate ≤ {BEAT_TRIV:g} × TRIV on "
        f"{sum(bool(f.estimate <= BEAT_TRIV * f.triv) for f in figs)} of {n} (Trust II asks "
        "for at least 3)",
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
        f"TRIV ≤ {BEAT_TRIV:g} (better than the simple model, the thesis's claim), estimate / "
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
              "### Calibration by day", "", calibration_by_day_md(res), "",
              "### Self-aware indication", "", selfaware_md(res), "",
              "### Verdict", "", verdict_md(res), ""]
    if spec.long_term:
        lines += ["### Seasons: zero-mean LCM vs TRIV-mean Corr-GP", "", seasonal_md(res), ""]
    lines += ["### Monthly mean of daily NRMSE %", "", monthly_md(res), "",
              "### Per day (NRMSE %, and daily r of each raw reference vs the target)", "",
              daily_md(res), ""]
    return lines
