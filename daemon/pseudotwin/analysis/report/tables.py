"""Markdown tables of one run: number formatting, summary, calibration, monthly, daily and
the validation on the training days."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from pseudotwin.analysis.commissioning.oddday import odd_training_day
from pseudotwin.analysis.criteria import MIN_DAYS, MIN_RATIO, MIN_ROWS
from pseudotwin.analysis.evaluate import ESTIMATE, REF_PREFIX
from pseudotwin.analysis.report.runs import BASE, GP, MODEL_ORDER, RunResult
from pseudotwin.analysis.selfaware import selfaware
from pseudotwin.analysis.validation import tuned_scores
from pseudotwin.live import metrics


def fmt(x: Any, nd: int = 2) -> str:
    """A number to ``nd`` decimals, or an em dash when missing."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "—"
    return "—" if not np.isfinite(v) else f"{v:.{nd}f}"


def _ordered(models: Sequence[str]) -> list[str]:
    ms = set(models)
    head = [m for m in MODEL_ORDER if m in ms]
    extra = sorted(m for m in ms if m.startswith(BASE + " ("))
    if BASE in head:
        i = head.index(BASE) + 1
        head[i:i] = extra
    else:
        head += extra
    return head + sorted(m for m in ms if m not in head)


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]], left: int = 1,
           text: Sequence[int] = ()) -> str:
    """Markdown table: the first ``left`` columns and those in ``text`` left-aligned. A "|"
    in a cell (a pair criterion's key) is escaped: even inside backticks it ends the cell."""
    def line(cells: Sequence[str]) -> str:
        return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"

    lines = [line(header),
             "|" + "|".join("---" if i < left or i in text else "---:"
                            for i in range(len(header))) + "|"]
    lines += [line(r) for r in rows]
    return "\n".join(lines)


def _label(model: str) -> str:
    return f"{model} (raw)" if model.startswith(REF_PREFIX) else model


def signed(x: float, nd: int = 2) -> str:
    """Signed number; a value that rounds to zero prints as 0.00 (never -0.00)."""
    v = round(float(x), nd)
    return fmt(v, nd) if v == 0 or not np.isfinite(v) else f"{v:+.{nd}f}"


def mean_bias(estimates: pd.DataFrame) -> pd.Series:
    """Mean signed error (estimate − truth) per model over all scored readings."""
    return (estimates["value"] - estimates["truth"]).groupby(estimates["model"]).mean()


def summary_md(res: RunResult) -> str:
    daily = res.daily
    g = daily.groupby("model").agg(
        nrmse=("nrmse_pct", "mean"), dmax=("dmax_pct", "mean"),
        r=("pearson_r", "median"), days=("day", "nunique"),
    )
    bias = mean_bias(res.estimates)
    unit = res.ev.artifact.unit
    rows = [[_label(m), fmt(g.at[m, "nrmse"]), fmt(g.at[m, "dmax"]), fmt(g.at[m, "r"], 3),
             signed(bias.get(m, np.nan)), str(int(g.at[m, "days"]))]
            for m in _ordered(list(g.index))]
    return md_table(["model", "mean daily NRMSE %", "mean ΔT_max %", "median daily r",
                   f"mean error [{unit}]", "days"], rows)


def calibration_md(res: RunResult) -> str:
    """Per model over all scored readings: does ±σ mean what it says?"""
    unit = res.ev.artifact.unit
    rows = []
    for m in _ordered(list(res.estimates["model"].unique())):
        e = res.estimates[res.estimates["model"] == m]
        s = metrics.score(e["truth"].to_numpy(), e["value"].to_numpy(), e["std"].to_numpy())
        ratio = s.rms_std / s.rmse if s.rmse > 0 else float("nan")
        rows.append([_label(m), fmt(s.cover1_pct, 1), fmt(s.cover2_pct, 1), fmt(s.mean_std, 3),
                     fmt(s.rms_std, 3), fmt(s.rmse, 3), fmt(ratio), fmt(s.crps, 3), str(s.n)])
    return md_table(["model", "±1σ coverage %", "±2σ coverage %", f"mean σ [{unit}]",
                   f"RMS σ [{unit}]", f"RMSE [{unit}]", "RMS σ / RMSE", f"mean CRPS [{unit}]",
                   "n"], rows)


def calibration_by_day_md(res: RunResult) -> str:
    """Per model, its days' ±2σ coverage and CRPS (daily.csv's ``cover2_pct`` and ``crps``):
    whether σ holds day by day or only pooled, a wide day making up for a narrow one."""
    unit = res.ev.artifact.unit
    lo, hi = metrics.COVER2_RANGE  # the band the verdicts judge the estimate's σ by
    rows = []
    for m in _ordered(list(res.daily["model"].unique())):
        d = res.daily[res.daily["model"] == m]
        cover = d["cover2_pct"].to_numpy(float)
        if not np.isfinite(cover).any():  # a raw reference: no σ
            continue
        cover = cover[np.isfinite(cover)]
        rows.append([_label(m), str(len(cover)), fmt(float(np.median(cover)), 1),
                     fmt(float(np.min(cover)), 1),
                     str(int(np.sum(cover < lo))), str(int(np.sum((cover >= lo) & (cover <= hi)))),
                     str(int(np.sum(cover > hi))), fmt(float(d["crps"].mean()), 3)])
    return md_table(["model", "days", "median daily ±2σ cover %", "lowest %",
                     f"days < {lo:.0f} %", f"days {lo:.0f}–{hi:.0f} %", f"days > {hi:.0f} %",
                     f"mean daily CRPS [{unit}]"], rows) + (
        "\n\nEach test day's ±2σ coverage of its own scored readings (`daily.csv`, "
        "`cover2_pct`, `crps`): whether σ holds day by day or only pooled, a wide day making "
        "up for a narrow one.")


def selfaware_md(res: RunResult) -> str:
    """The published estimate's ``ok`` vs ``uncertain`` readings (live/envelope.py): how often
    it fires on the test and the training days, MAE and ±2σ coverage of each."""
    sa = selfaware(res.ev.estimates, res.train_uncertain)
    unit = res.ev.artifact.unit
    return md_table(
        ["uncertain % (test)", "uncertain % (training days)", f"MAE ok [{unit}]",
         f"MAE uncertain [{unit}]", "MAE ratio", "±2σ coverage ok %",
         "±2σ coverage uncertain %", "n ok", "n uncertain"],
        [[fmt(100 * sa.share, 1), fmt(100 * sa.train_share, 1), fmt(sa.mae_ok, 3),
          fmt(sa.mae_uncertain, 3), fmt(sa.mae_ratio), fmt(sa.cover2_ok, 1),
          fmt(sa.cover2_uncertain, 1), str(sa.n_ok), str(sa.n_uncertain)]], left=0) \
        + "\n\n" + criteria_md(res)


def criteria_md(res: RunResult) -> str:
    """Which criteria of ``uncertain`` validation kept, with the held-out numbers it judged
    them on (analysis/criteria.py)."""
    env = res.ev.artifact.envelope
    if env is None:
        return "No training ranges (artifact older than format 3): never `uncertain`."
    if env.kept is None:
        return "Criteria not judged on held-out days (artifact of format 3–5): every one acts."
    rows = [[f"`{k}`", str(j["n"]), str(j["days"]), fmt(j["ratio"]),
             "kept" if j["kept"] else "dropped"] for k, j in env.judged.items()]
    kept = (f"σ of an uncertain estimate × {env.widen:.2f}." if env.kept else
            "No criterion kept: the estimate is never `uncertain` on this run.")
    return md_table(["criterion (held-out training days)", "readings fired", "days",
                     "MAE fired / MAE where nothing fired", "verdict"], rows, text=(4,)) \
        + "\n\n" + kept + on_test_criteria_md(res)


def on_test_criteria_md(res: RunResult) -> str:
    """Every criterion on the test days (a dropped one recorded, never acting), after a blank
    line: the evidence whether validation's verdicts above hold on days it never saw."""
    if not res.test_criteria:
        return ""
    rows = [[f"`{k}`", fmt(t.share_pct, 1), str(t.judged.days), fmt(t.judged.ratio),
             fmt(t.cover2_pct, 1), "would be kept" if t.judged.kept else "would be dropped"]
            for k, t in res.test_criteria.items()]
    table = md_table(["criterion (test days)", "estimates fired %", "days",
                      "MAE fired / MAE where nothing fired", "±2σ cover where fired %",
                      "the same rule on the test days"], rows, text=(5,))
    return (f"\n\n{table}\n\nThe same criteria on the test days (a dropped one is recorded "
            "but never acts): the share of the published estimates each fired on, the error "
            "there against the error where none fired, and ±2σ coverage there with σ as "
            f"published. The last column applies validation's rule (fired on ≥ {MIN_ROWS} "
            f"readings of ≥ {MIN_DAYS} days, MAE ratio ≥ {MIN_RATIO:g}) to the test days: the "
            "verdict validation would have given had it seen them.")


def monthly_md(res: RunResult) -> str:
    piv = res.monthly.pivot(index="month", columns="model", values="nrmse_pct")
    models = _ordered(list(piv.columns))
    d = res.daily.assign(month=res.daily["day"].str[:7])
    days = d[d["model"] == ESTIMATE].groupby("month")["day"].nunique()
    r = d[d["model"].str.startswith(REF_PREFIX)].pivot_table(
        index="month", columns="model", values="pearson_r", aggfunc="median")
    refs = [m for m in models if m.startswith(REF_PREFIX)]
    header = ["month", "days", *[_label(m) for m in models],
              *[f"median r {m[len(REF_PREFIX):]}" for m in refs]]
    rows = []
    for month in piv.index:
        rows.append([month, str(int(days.get(month, 0))),
                     *[fmt(piv.at[month, m]) for m in models],
                     *[fmt(r.at[month, m], 3) if m in r.columns else "—" for m in refs]])
    return md_table(header, rows)


def daily_md(res: RunResult) -> str:
    nr = res.daily.pivot(index="day", columns="model", values="nrmse_pct")
    rr = res.daily.pivot(index="day", columns="model", values="pearson_r")
    n = res.daily[res.daily["model"] == ESTIMATE].set_index("day")["n"]
    models = [m for m in _ordered(list(nr.columns)) if not m.startswith(REF_PREFIX)]
    refs = [REF_PREFIX + s for s in res.ev.artifact.references if REF_PREFIX + s in rr.columns]
    duel_col = GP in nr.columns and BASE in nr.columns
    header = ["day", "n", *models, *(["corrgp-triv vs triv"] if duel_col else []),
              *[f"r {m[len(REF_PREFIX):]}" for m in refs]]
    rows = []
    for day in nr.index:
        marks = []
        if duel_col:
            a, b = nr.at[day, GP], nr.at[day, BASE]
            marks.append("—" if not (np.isfinite(a) and np.isfinite(b)) else (
                "win" if a < b else "loss" if a > b else "tie"))
        rows.append([day, str(int(n.get(day, 0))), *[fmt(nr.at[day, m]) for m in models],
                     *marks, *[fmt(rr.at[day, m], 3) for m in refs]])
    return md_table(header, rows)


def validation_md(res: RunResult) -> str:
    """The artifact's leave-one-day-out scores on the training days, and why the primary won."""
    art = res.ev.artifact
    v = art.validation
    if not v or not v.get("scores"):
        return (f"No validation recorded in the artifact: the primary `{art.primary}` was not "
                "chosen by validation.")
    withheld = v.get("withheld", {})
    unit = art.unit
    rows = []
    for kind, sc in v["scores"].items():
        if kind == art.primary:
            note = "**primary** (published as `estimate`)"
        elif sc.get("candidate"):
            note = "candidate"
        else:
            note = "baseline (never primary)"
        if sc.get("error"):
            note += f"; {sc['error']}"
        if kind in withheld:
            note += f"; **not published live**: {withheld[kind]}"
        elif kind != art.primary:
            note += "; published live"
        rows.append([kind, fmt(sc.get("nrmse_pct")), fmt(sc.get("crps"), 3),
                     fmt(sc.get("cover2_pct"), 1), str(sc.get("days", "")), note])
    table = md_table(["model", "held-out NRMSE %", f"CRPS [{unit}]", "±2σ cover %", "days",
                    "note"], rows, text=(5,))
    reason = f"Primary: {v.get('reason', '')}."
    if v.get("primary") not in (None, art.primary):
        reason += (f" (Validation chose `{v['primary']}`; `{art.primary}` was pinned by the "
                   "user.)")
    extra = [f"Method: {v.get('method', 'unknown')}"]
    if np.isfinite(float(v.get("offset_std", np.nan))):
        extra.append(f"spread (std) of the daily mean reference–target offset over the "
                     f"training days {fmt(v['offset_std'], 3)} {unit}, the floor of every "
                     "model's day-level σ")
    if odd := odd_training_day(v):
        extra.append(f"one training day unlike the others (Grubbs' test, 5 %): {odd.day}, "
                     f"offset {odd.offset:+.3f} {unit} against {min(odd.others):+.3f} to "
                     f"{max(odd.others):+.3f} {unit} on the other days, the spread "
                     f"{odd.spread_without:.3f} {unit} without it; train says so and offers "
                     "--skip-days, the report's protocol keeps every day")
    if "seconds" in v:
        extra.append(f"{fmt(v['seconds'], 1)} s")
    parts = [table, reason + " " + "; ".join(extra) + "."]
    cov = art.models.get("triv-cov")
    if cov is not None:  # which covariate helped, on the training days (Trust II)
        parts.append(f"Covariates ({', '.join(f'`{c}`' for c in art.covariates)}), each "
                     f"added to TRIV alone and scored leave-one-day-out inside every fold's "
                     f"training days: {cov.fit_summary()}.")
    for kind, t in v.get("tuned", {}).items():  # a setting validation chose (VARMA's order)
        parts.append(f"`{kind}` {t['reason']} (held-out daily NRMSE by {t['setting']}: "
                     f"{tuned_scores(t)}; of the choice itself, each held-out day scored by the "
                     f"{t['setting']} the other days choose: "
                     f"{fmt(t.get('nested_nrmse_pct'))} %: how much the choice itself "
                     "depends on which days are held out).")
    if blend := v.get("blend"):
        parts.append("Blend (members and weights from all held-out training days): "
                     + ", ".join(f"`{k}` {w:.2f}" for k, w in blend.items())
                     + f"; measured against {fmt(v.get('selection_nrmse_pct'))} %, the held-out "
                     "error of choosing one candidate (each held-out day scored by the "
                     "candidate the other days choose).")
    return "\n\n".join(parts)
