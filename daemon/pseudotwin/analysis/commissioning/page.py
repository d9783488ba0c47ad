"""The commissioning report as one self-contained HTML page: inline CSS, images as PNG data
URIs, no script and nothing fetched. Every text from data or the user goes through
:func:`html.escape`."""

from __future__ import annotations

import datetime as dt
import html
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pseudotwin import __version__
from pseudotwin.analysis.commissioning.coverage import DataFound, Level
from pseudotwin.analysis.commissioning.heldout import HeldOut
from pseudotwin.analysis.commissioning.oddday import odd_training_day
from pseudotwin.analysis.criteria import NONE_KEPT
from pseudotwin.analysis.replay import REF_PREFIX
from pseudotwin.live import metrics
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.calibration import Z2
from pseudotwin.live.failover import picked
from pseudotwin.live.metrics import COVER2_RANGE

COVER2_AIM = 95.4  # % of truths a calibrated Gaussian ±2σ band holds

CSS = """
body{font-family:system-ui,sans-serif;max-width:72rem;margin:1.5rem auto;padding:0 1rem;
color:#222;line-height:1.4}
h1{font-size:1.6rem;margin-bottom:.2rem}h2{margin-top:2rem;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.6rem 0;font-size:.9rem}
th,td{border:1px solid #ccc;padding:.2rem .5rem;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
th{background:#f2f2f2}tr.primary td{font-weight:bold}
.good{background:#e3f4e1}.thin{background:#fff3cd}.missing{background:#f8d7da}
.verdict{padding:.6rem 1rem;margin:.5rem 0;border-left:.4rem solid #888}
.verdict.good{border-color:#2e7d32}.verdict.thin{border-color:#b8860b}
.verdict.missing{border-color:#c62828}
figure{margin:1rem 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.85rem;color:#555}
pre{background:#f6f6f6;padding:.8rem;overflow-x:auto;font-size:.85rem}
.meta{color:#555;font-size:.9rem}
"""


class Raw(str):
    """Trusted HTML (built here from escaped parts): not escaped again."""


def esc(x: object) -> str:
    return x if isinstance(x, Raw) else html.escape(str(x))


def num(x: object, digits: int = 2) -> str:
    """A score as shown; '—' where there is none (NaN, or null in a saved artifact)."""
    ok = isinstance(x, int | float) and not isinstance(x, bool) and np.isfinite(x)
    return f"{x:.{digits}f}" if ok else "—"


def table(table_id: str, headers: Sequence[str], rows: Iterable[Sequence[object]],
          row_class: Sequence[str] | None = None, numeric: Sequence[int] = ()) -> str:
    """An HTML table; ``numeric``: indices of right-aligned columns."""
    head = "".join(f"<th>{esc(h)}</th>" for h in headers)
    body = []
    for i, row in enumerate(rows):
        cls = f' class="{esc(row_class[i])}"' if row_class and row_class[i] else ""
        cells = "".join(f'<td{" class=num" if j in numeric else ""}>{esc(c)}</td>'
                        for j, c in enumerate(row))
        body.append(f"<tr{cls}>{cells}</tr>")
    return (f'<table id="{esc(table_id)}"><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(body)}</tbody></table>')


def verdict(level: Level, title: str, text: str) -> str:
    return (f'<div class="verdict {level.value}"><strong>{esc(title)}</strong> '
            f"{esc(text)}</div>")


@dataclass(frozen=True)
class Page:
    """Everything the page shows."""

    artifact: Artifact
    twin: str
    artifact_path: Path
    data: DataFound
    held: HeldOut | None
    figures: list[tuple[str, str]]  # (caption, PNG data URI)
    snippet: str
    generated: str = ""


def data_section(p: Page) -> str:
    d = p.data
    rows, classes = [], []
    for r in d.rows:
        rows.append((str(r.day), d.day_status(r.day), r.sensor, r.readings,
                     f"{100 * r.coverage:.0f}", f"{r.longest_gap_min:.0f}", r.verdict))
        classes.append(r.level.value)
    hours = p.artifact.hours
    return (
        "<h2>Data found per sensor and day</h2>"
        f"<p>Readings inside the operating hours ({esc(hours.describe())}), from the first "
        "candidate day to the last training day. Coverage: share of the "
        f"{hours.slot_minutes:g}-minute slots of the operating hours that hold at least one "
        "reading (a change-of-value sensor may be quiet on a steady day and still be "
        "fine).</p>"
        + verdict(d.level, "Is it enough?", d.verdict())
        + table("data", ["day", "day status", "sensor", "readings", "coverage %",
                         "longest gap min", "verdict"], rows, classes, numeric=(3, 4, 5))
    )


def _note(kind: str, s: Mapping[str, Any], v: Mapping[str, Any]) -> str:
    withheld = v.get("withheld", {})
    if kind in withheld:
        return f"not published live: {withheld[kind]}"
    if s.get("error"):
        return str(s["error"])
    if kind == v.get("primary"):
        return "primary: published as the estimate"
    return "candidate" if s.get("candidate") else "monitoring baseline"


def validation_section(p: Page) -> str:
    a = p.artifact
    v = a.validation
    scores: Mapping[str, Mapping[str, Any]] = v.get("scores", {})
    if not scores:
        return ("<h2>Candidates and the primary</h2>"
                + verdict(Level.MISSING, "Not validated.",
                          f"The primary {a.primary} was not chosen on held-out days "
                          "(fewer than three training days, or validation was off); σ is "
                          "each model's own, not calibrated."))
    rows, classes = [], []
    for kind, s in scores.items():
        rows.append((kind, num(s.get("nrmse_pct")), num(s.get("crps"), 3),
                     num(s.get("cover2_pct"), 1), s.get("days", 0), _note(kind, s, v)))
        classes.append("primary" if kind == a.primary else "")
    return (
        "<h2>Candidates and the primary</h2>"
        f"<p>{esc(v.get('method', ''))}. Each training day is held out in turn: every model "
        "is refit on the other days and the held-out day is replayed through the daemon's "
        "twin code. CRPS and ±2σ coverage score each held-out day with a σ calibrated on "
        "the other days only (nested), so they check σ on a day it has not seen.</p>"
        + verdict(Level.GOOD, f"Primary: {a.primary}.", str(v.get("reason", "")))
        + (verdict(Level.THIN, "One training day is unlike the others.",
                   odd.advice(a.unit, len(a.references)))
           if (odd := odd_training_day(v)) else "")
        + table("validation", ["model", "held-out daily NRMSE %", f"CRPS {a.unit}",
                               "±2σ coverage %", "days", "note"], rows, classes,
                numeric=(1, 2, 3, 4))
    )


def _reference_verdict(a: Artifact, ho: HeldOut) -> tuple[Level, str]:
    refs = ho.reference_scores().dropna(subset=["nrmse_pct"])
    prim = ho.daily[ho.daily["model"] == a.primary]["nrmse_pct"].mean()
    if refs.empty or not np.isfinite(prim):
        return Level.THIN, "No held-out scores of the raw references."
    best = refs.loc[refs["nrmse_pct"].idxmin()]
    ref_text = (f"the best raw reference, {best['reference']}, scores "
                f"{best['nrmse_pct']:.2f} % (median daily r {num(best['pearson_r'], 3)})")
    if prim < best["nrmse_pct"] * 0.97:
        gain = 100 * (1 - prim / best["nrmse_pct"])
        return Level.GOOD, (f"The primary {a.primary} scores {prim:.2f} % held out; {ref_text}: "
                            f"the twin is {gain:.0f} % better than reading the reference.")
    if a.primary == "ref":
        return Level.GOOD, (f"The primary is the raw reference held ({prim:.2f} %); "
                            f"{ref_text}. No model beats it on held-out days: the data "
                            "supports no more than that, and the twin publishes it honestly "
                            "with a calibrated σ.")
    return Level.THIN, (f"The primary {a.primary} scores {prim:.2f} % held out; {ref_text}: "
                        "the model does not clearly beat the reference.")


def reference_section(p: Page) -> str:
    if p.held is None or p.held.daily.empty:
        return ""
    a = p.artifact
    level, text = _reference_verdict(a, p.held)
    rs = p.held.reference_scores()
    rows = [(REF_PREFIX + r.reference, num(r.nrmse_pct), num(r.pearson_r, 3), r.days)
            for r in rs.itertuples()]
    return (
        "<h2>The raw reference's own score</h2>"
        "<p>Each reference's raw reading, held and compared with the desk sensor on the "
        "training days: the error of the simplest answer, which a model must beat to be "
        "worth running. Its daily Pearson r with the desk "
        "is the evidence of how much a model can learn from it.</p>"
        + verdict(level, "Reference vs twin:", text)
        + table("references", ["reference", "held-out daily NRMSE %", "median daily r",
                               "days"], rows, numeric=(1, 2, 3))
    )


def days_section(p: Page) -> str:
    if p.held is None or p.held.daily.empty:
        return ""
    a = p.artifact
    d = p.held.primary_days()
    est = p.held.evaluation.estimates
    mine = est[est["model"] == a.primary]
    # pooled over the held-out readings, as validation's table gives it
    cover = metrics.coverage_pct(mine["truth"], mine["value"], mine["std"], Z2)
    lo, hi = COVER2_RANGE  # the report's band for the published estimate's coverage
    ok = np.isfinite(cover) and lo <= cover <= hi
    level = Level.GOOD if ok else Level.THIN
    side = ("" if ok or not np.isfinite(cover) else
            " σ was wider than the errors needed on these days." if cover > hi else
            " σ was narrower than the errors needed on these days.")
    text = (f"the ±{Z2:g}σ band of {a.primary}, calibrated on the other training days, held "
            f"{num(cover, 1)} % of the held-out days' desk readings (a calibrated band "
            f"holds about {COVER2_AIM:g} %; {lo:g}–{hi:g} % counts as good).{side}")
    refs = {r: p.held.daily[p.held.daily["model"] == REF_PREFIX + r].set_index("day")
            for r in a.references}
    rows = []
    for r in d.itertuples():
        ref_cells = [num(refs[x]["nrmse_pct"].get(r.day, np.nan)) for x in a.references]
        rows.append((r.day, num(r.nrmse_pct), num(r.rmse, 3), num(r.dmax_pct),
                     num(r.pearson_r, 3), num(r.cover2_pct, 1), num(r.mean_std, 3), *ref_cells))
    figs = "".join(
        f'<figure><img alt="{esc(cap)}" src="{esc(uri)}"><figcaption>{esc(cap)}</figcaption>'
        "</figure>" for cap, uri in p.figures)
    return (
        "<h2>Held-out training days</h2>"
        f"<p>The primary {esc(a.primary)} on each training day, estimated by models trained "
        "on the other days, best day first.</p>"
        + verdict(level, "σ:", text)
        + table("days", ["day", f"{a.primary} NRMSE %", f"RMSE {a.unit}", "ΔT_max %", "r",
                         "±2σ coverage %", f"mean σ {a.unit}",
                         *(f"raw {x} NRMSE %" for x in a.references)], rows,
                numeric=tuple(range(1, 7 + len(a.references))))
        + figs
    )


def selfaware_section(p: Page) -> str:
    """Which training-range criteria make the live estimate ``uncertain`` (live/envelope.py),
    with the held-out numbers validation kept or dropped each on (analysis/criteria.py)."""
    env = p.artifact.envelope
    head = ("<h2>Self-aware indication</h2>"
            "<p>Live, a reference outside what it did on the training days (its level, its "
            "deviation from its daily profile, how fast it moves) can make the estimate "
            "<code>uncertain</code>, with a wider σ, and <code>&lt;twin&gt;/monitor</code> says "
            "why. A criterion acts only where the held-out training days show that it flags "
            "larger errors.</p>")
    if env is None:
        return head + verdict(Level.MISSING, "No training ranges.",
                              "The artifact predates them: the estimate is never uncertain.")
    if env.kept is None:
        return head + verdict(Level.THIN, "Not judged.",
                              f"An artifact of an older format: every criterion acts and σ of "
                              f"an uncertain estimate is × {env.widen:g}. Train again to judge "
                              "them on held-out days.")
    if not env.judged:
        return head + verdict(Level.MISSING, "Not judged.",
                              "Without held-out days (fewer than three training days, or "
                              "validation off) no criterion could show that it flags larger "
                              "errors: none acts, and the estimate is never uncertain.")
    rows = [(key, j.get("n", 0), j.get("days", 0), num(j.get("mae"), 3), num(j.get("ratio")),
             "kept" if j.get("kept") else "dropped", j.get("reason", ""))
            for key, j in env.judged.items()]
    if env.kept:
        level, text = Level.GOOD, (f"{', '.join(sorted(env.kept))} act(s) live; σ of an "
                                   f"uncertain estimate × {env.widen:.2f}.")
    else:
        level, text = Level.THIN, (f"{NONE_KEPT[0].upper()}{NONE_KEPT[1:]}: the estimate is "
                                   "never uncertain live, and σ alone says how far to trust "
                                   "it. A criterion dropped for too few days may still have "
                                   "fired on larger errors (table).")
    return (head + verdict(level, "Criteria:", text)
            + table("criteria", ["criterion", "readings fired", "days",
                                 f"MAE fired {p.artifact.unit}",
                                 "MAE fired / MAE where none fired", "verdict", "why"], rows,
                    numeric=(1, 2, 3, 4)))


# A failover within this factor of the primary's held-out error keeps the estimate useful
# (Trust II's target for one of two references silenced for a day).
FAILOVER_WITHIN = 1.2


def failover_section(a: Artifact) -> str:
    """What answers when references fall silent (live/failover.py): each failover, its
    held-out error against the primary's, and which reference the twin can least afford
    to lose."""
    head = ("<h2>When a reference falls silent</h2>"
            "<p>A reference silent longer than <code>stale_after_minutes</code> makes the "
            "primary's estimate stale. Live, the best validated failover whose references all "
            "report answers instead, with its own calibrated σ, quality "
            "<code>fallback</code>, and the silent references in <code>lost</code>.</p>")
    if len(a.references) < 2:
        return head + verdict(Level.THIN, "One reference:",
                              f"when {a.references[0]} is silent the estimate is stale, "
                              "made from its last value without σ, until it reports again. "
                              "A second permanent sensor as a reference would let the twin "
                              "fail over.")
    if not a.failovers:
        return head + verdict(Level.MISSING, "No failover:",
                              "trained without validation (or none could be validated): "
                              "any silent reference the primary reads makes the estimate "
                              "stale.")
    own = a.validation.get("scores", {}).get(a.primary, {}).get("nrmse_pct")
    own = float(own) if isinstance(own, int | float) and np.isfinite(own) else float("nan")
    rows, classes = [], []
    for f in a.failovers:
        ratio = f.nrmse_pct / own if own > 0 else float("nan")
        rows.append((", ".join(f.lost), f"{f.kind} on {', '.join(f.model.references_)}",
                     num(f.nrmse_pct), num(ratio)))
        classes.append(Level.GOOD.value if ratio <= FAILOVER_WITHIN else Level.THIN.value)
    # each reference the primary reads, by what the twin would pick with it silent
    picks = {r: picked(a.failovers, (r,)) for r in a.models[a.primary].references_}
    bare = [r for r, f in picks.items() if f is None]
    costly = sorted(((f.nrmse_pct / own, r) for r, f in picks.items() if f is not None),
                    reverse=True)
    if bare:
        level, text = Level.MISSING, (f"no failover could be validated without "
                                      f"{', '.join(bare)}: when it is silent the estimate is "
                                      "stale.")
    elif not own > 0:
        level, text = Level.THIN, ("the primary has no held-out error to compare the "
                                   "failovers with.")
    elif costly[0][0] > FAILOVER_WITHIN:
        level, text = Level.THIN, (f"losing {costly[0][1]} costs the most: its failover's "
                                   f"held-out error is {costly[0][0]:.2f} × the primary's "
                                   f"({num(own)} %). Keep that sensor reporting (power, bus, "
                                   "battery).")
    else:
        level, text = Level.GOOD, (f"without any one reference the held-out error stays "
                                   f"within {FAILOVER_WITHIN:g} × the primary's "
                                   f"({num(own)} %).")
    alone = ("" if not a.failover_alone else
             "<p>With three references or more, a failover on each reference alone answers "
             "when two or more are silent.</p>")
    return (head + verdict(level, "Failover:", text) + alone
            + table("failover", ["silent", "answers", "held-out daily NRMSE %",
                                 "× the primary's"], rows, classes, numeric=(2, 3)))


def render(p: Page) -> str:
    a = p.artifact
    tr = a.training
    generated = p.generated or dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    meta = (
        f"<p class=meta>Target (desk) <b>{esc(a.target)}</b> from "
        f"{esc(', '.join(a.references))}; {esc(a.quantity.value)} [{esc(a.unit)}]; "
        f"operating hours {esc(a.hours.describe())}. Training days: "
        f"{esc(', '.join(tr.get('days', [])))}. Artifact: <code>{esc(p.artifact_path)}</code>. "
        f"Generated {esc(generated)} by pseudotwin {esc(__version__)}.</p>"
    )
    snippet = (
        "<h2>Configuration for the twin</h2>"
        "<p>TOML the daemon's configuration loader accepts as it stands (check it with "
        "<code>pseudotwin check-config FILE</code>); the comments say what to copy into an "
        "existing configuration such as <code>config/example.toml</code>.</p>"
        f'<pre id="config"><code>{esc(p.snippet)}</code></pre>'
    )
    body = (f"<h1>Commissioning report: twin {esc(p.twin)}</h1>" + meta
            + data_section(p) + validation_section(p) + reference_section(p)
            + days_section(p) + selfaware_section(p) + failover_section(a) + snippet)
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>pseudotwin commissioning: {esc(p.twin)}</title>"
        f"<style>{CSS}</style></head><body>{body}</body></html>\n"
    )
