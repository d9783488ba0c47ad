"""The verdicts: each run's figures against the issue's targets (Figures) and the verdict
text of the published estimate, VARMA and the GP-vs-TRIV evidence."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from pseudotwin.analysis.evaluate import ESTIMATE, REF_PREFIX
from pseudotwin.analysis.report.evidence import gp_md
from pseudotwin.analysis.report.runs import BASE, REF, RunResult
from pseudotwin.analysis.report.tables import fmt, signed
from pseudotwin.analysis.validation import BASELINE_LIMIT
from pseudotwin.live import metrics
from pseudotwin.live.metrics import COVER2_RANGE

# The figures for the ``estimate`` rows (Trust I):
FLOOR_RATIO = 1.02  # mean daily NRMSE ≤ this × min(TRIV, best raw reference)
BEAT_TRIV = 0.9  # Trust II: mean daily NRMSE ≤ this × TRIV's on at least three runs
OK = "✓"


def _varma_drift(daily: pd.DataFrame, trend: str) -> str:
    """A sentence when VARMA's error grows with the distance from the training days."""
    v = daily[daily["model"] == "varma"].sort_values("day")["nrmse_pct"].to_numpy()
    if len(v) < 6:
        return ""
    k = len(v) // 3
    first, last = float(np.mean(v[:k])), float(np.mean(v[-k:]))
    if last <= 2 * first:
        return ""
    why = (
        "consistent with a trend with drift: the drift fitted on five days is extrapolated to "
        "every later day (the caveat documented in `models/varma.py`)"
        if "t" in trend else
        f"with trend `{trend}` no drift is extrapolated, so this is the training days' "
        "dynamics carrying over less well to later days"
    )
    return (
        f"Its error grows with the distance from the training days (mean daily NRMSE "
        f"{fmt(first)} % over the first third of the test days, {fmt(last)} % over the last "
        f"third), {why}."
    )


@dataclass(frozen=True)
class Figures:
    """The issue's figures for one run, computed from its evaluation outputs.

    NRMSE figures are mean daily NRMSE [%] over each model's scored days; cover1/cover2 [%],
    mean_std, rms_std and rmse [unit] pool all scored readings of the ``estimate`` rows; sigma_cv is
    the mean over days of std(σ)/mean(σ) of those rows (0 = σ constant within each day).
    """

    days: int
    primary: str
    estimate: float
    triv: float
    best_ref: str  # the raw reference with the lowest mean daily NRMSE (`ref` or ref:<sensor>)
    ref: float
    n: int
    cover1: float
    cover2: float
    mean_std: float
    rms_std: float  # set against rmse: ≈ rmse when σ is the right size
    rmse: float
    crps: float  # the estimate's mean CRPS [unit] over the scored readings
    sigma_cv: float
    varma: float
    varma_withheld: str  # why VARMA is not published live ("" when it is)
    best_model: str  # hindsight: the trained model with the lowest NRMSE on the test days
    best_nrmse: float

    @property
    def floor(self) -> float:
        """The simple answer: the lower of TRIV's and the best raw reference's NRMSE."""
        return float(np.nanmin([self.triv, self.ref])) if np.isfinite(
            [self.triv, self.ref]).any() else float("nan")

    @property
    def ratio(self) -> float:
        return self.estimate / self.floor if self.floor > 0 else float("nan")

    @property
    def floor_met(self) -> bool:
        return bool(self.ratio <= FLOOR_RATIO)

    @property
    def cover_met(self) -> bool:
        return bool(COVER2_RANGE[0] <= self.cover2 <= COVER2_RANGE[1])

    @property
    def sigma_varies(self) -> bool:
        return bool(self.sigma_cv > 1e-9)

    @property
    def varma_ratio(self) -> float:
        return self.varma / self.triv if self.triv > 0 else float("nan")

    @property
    def varma_met(self) -> bool:
        """VARMA within BASELINE_LIMIT × TRIV, or not published live."""
        return bool(self.varma_ratio <= BASELINE_LIMIT) or bool(self.varma_withheld)


def _is_raw(model: str) -> bool:
    return model == REF or model.startswith(REF_PREFIX)


def raw_name(res: RunResult, model: str) -> str:
    """A raw reference's row named with its sensor: `ref` (sensor) or `sensor` raw."""
    if model.startswith(REF_PREFIX):
        return f"`{model[len(REF_PREFIX):]}` raw"
    refs = getattr(res.ev.artifact.models.get(model), "references_", None)
    return f"`{model}` on {refs[0]}" if refs else f"`{model}`"


def figures(res: RunResult) -> Figures:
    art = res.ev.artifact
    g = res.daily.groupby("model")["nrmse_pct"].mean()
    raw = g[[m for m in g.index if _is_raw(str(m))]].dropna()
    best_ref = str(raw.idxmin()) if len(raw) else "—"
    e = res.estimates[res.estimates["model"] == ESTIMATE]
    s = metrics.score(e["truth"].to_numpy(), e["value"].to_numpy(), e["std"].to_numpy())
    cv = float("nan")
    if len(e):
        days, _ = res.spec.twin.hours.day_and_hours(e["ts"])
        std = e["std"].astype(float)
        per_day = std.groupby(np.asarray(days)).agg(["std", "mean", "count"])
        per_day = per_day[(per_day["count"] > 1) & (per_day["mean"] > 0)]
        if len(per_day):
            cv = float((per_day["std"] / per_day["mean"]).mean())
    trained = g[[m for m in g.index if m in art.models]].dropna()
    best = str(trained.idxmin()) if len(trained) else "—"
    return Figures(
        days=int(res.daily["day"].nunique()), primary=art.primary,
        estimate=float(g.get(ESTIMATE, np.nan)), triv=float(g.get(BASE, np.nan)),
        best_ref=best_ref, ref=float(raw.min()) if len(raw) else float("nan"), n=s.n,
        cover1=s.cover1_pct, cover2=s.cover2_pct, mean_std=s.mean_std, rms_std=s.rms_std,
        rmse=s.rmse,
        crps=s.crps,
        sigma_cv=cv, varma=float(g.get("varma", np.nan)),
        varma_withheld=str(art.withheld.get("varma", "")),
        best_model=best, best_nrmse=float(trained.min()) if len(trained) else float("nan"),
    )


def mark(ok: bool, value: str) -> str:
    return value if value == "—" else f"{value} {OK if ok else '✗'}"


def verdict_md(res: RunResult) -> str:
    """The published estimate against the issue's figures; then the GP-vs-TRIV evidence."""
    f = figures(res)
    unit = res.ev.artifact.unit
    parts: list[str] = []  # the estimate against the figures
    more: list[str] = []  # the primary, VARMA
    if not np.isfinite(f.ratio):
        parts.append("**Estimate vs floor: not measurable** (no `estimate` or no floor rows).")
    else:
        pct = 100.0 * (f.ratio - 1.0)
        where = ("equal to the floor" if abs(pct) < 0.05 else
                 f"{fmt(-pct, 1)} % below the floor" if pct < 0 else
                 f"{fmt(pct, 1)} % above the floor ({signed(f.estimate - f.floor)} points)")
        state = ("met" if f.floor_met else "not met")
        limit = f"≤ {FLOOR_RATIO:.2f}" if f.floor_met else f"> {FLOOR_RATIO:.2f}"
        parts.append(
            f"**Estimate vs floor: {state}** — the published estimate scores {fmt(f.estimate)} % "
            f"mean daily NRMSE against the floor {fmt(f.floor)} % (the lower of TRIV's "
            f"{fmt(f.triv)} % and the best raw reference's {fmt(f.ref)} %, "
            f"{raw_name(res, f.best_ref)}): ratio {fmt(f.ratio, 3)} ({limit}), {where}."
        )
    lo, hi = COVER2_RANGE
    size = (f"RMS σ {fmt(f.rms_std, 3)} {unit} vs RMSE {fmt(f.rmse, 3)} {unit} "
            f"(ratio {fmt(f.rms_std / f.rmse if f.rmse > 0 else np.nan)}; mean σ "
            f"{fmt(f.mean_std, 3)} {unit})")
    if not np.isfinite(f.cover2):
        parts.append("**±2σ coverage: not measurable** (the estimate has no σ).")
    elif f.cover_met:
        parts.append(f"**±2σ coverage: met** — {fmt(f.cover2, 1)} % of the {f.n} scored "
                     f"readings lie inside the estimate's ±2σ band (target {lo:.0f}–{hi:.0f} %; "
                     f"±1σ: {fmt(f.cover1, 1)} %); {size}.")
    else:
        kind = "too narrow" if f.cover2 < lo else "too wide"
        parts.append(f"**±2σ coverage: not met, σ {kind}** — {fmt(f.cover2, 1)} % of the {f.n} "
                     f"scored readings lie inside ±2σ (target {lo:.0f}–{hi:.0f} %; ±1σ: "
                     f"{fmt(f.cover1, 1)} %); {size}.")
    if np.isfinite(f.sigma_cv):
        parts.append(
            f"σ varies within the day (mean within-day std/mean of σ {fmt(100 * f.sigma_cv, 1)} "
            "%)." if f.sigma_varies else "**σ is constant within each day** (a defect).")
    hind = ("also the best trained model on the test days" if f.best_model == f.primary
            else f"in hindsight `{f.best_model}` was the best trained model on the test days "
                 f"({fmt(f.best_nrmse)} %)")
    more.append(f"The estimate is `{f.primary}`'s, chosen on the training days (table above); "
                 f"{hind}.")
    if np.isfinite(f.varma):
        vm = res.ev.artifact.models.get("varma")
        name = getattr(vm, "model_name_", "varma")
        trend = str(getattr(vm, "trend", "?"))
        mode = getattr(vm, "target_mode", None)
        fell = (f", re-levelled each day (target_mode `{mode}`)" if mode == "shifted" else
                f", target_mode `{mode}`" if mode else "")
        fell += (f", here the fallback `{name}`" if name == "var-fallback" else
                 f", here `{name}` ({getattr(vm, 'fit_message_', '')})" if name != "varma"
                 else "")
        live = (f"not published live ({f.varma_withheld})" if f.varma_withheld
                else "published live")
        within = (f"within the {BASELINE_LIMIT:g}× limit" if f.varma_ratio <= BASELINE_LIMIT
                  else f"above the {BASELINE_LIMIT:g}× limit")
        state = "met" if f.varma_met else "not met"
        sent = (f"**VARMA: {state}** — trend `{trend}`{fell}: {fmt(f.varma)} % mean daily "
                f"NRMSE, {fmt(f.varma_ratio)}× TRIV's ({within}); {live}.")
        drift = _varma_drift(res.daily, trend)
        more.append(sent + (" " + drift if drift else ""))
    return "\n\n".join([" ".join(parts), " ".join(more), gp_md(res)])
