"""The evaluation's figures are readable (issue 12 item 5): asserted on the matplotlib
objects (Agg backend), no image comparison."""

from __future__ import annotations

import datetime as dt

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

from pseudotwin.analysis.evaluate import Evaluation, evaluate  # noqa: E402
from pseudotwin.analysis.plots import (  # noqa: E402
    DAY_GAP,
    daily_nrmse_figure,
    day_figure,
    plot_daily_nrmse,
    with_gaps,
)
from pseudotwin.core.horizon import OperatingHours  # noqa: E402
from pseudotwin.core.spec import Quantity, TwinSpec  # noqa: E402
from pseudotwin.errors import DataError  # noqa: E402
from pseudotwin.history.convert import load  # noqa: E402

REFS = ("hmi/temp", "ceiling/temp")


def _daily(varma_pct: float) -> pd.DataFrame:
    """Four days, a six-day gap, three days; VARMA at ``varma_pct`` %, the rest ≈ 1–3 %."""
    days = [dt.date(2024, 3, 4) + dt.timedelta(days=i) for i in (0, 1, 2, 3, 10, 11, 12)]
    level = {"triv": 2.0, "corrgp-triv": 1.5, "ref": 3.0, "estimate": 1.5,
             "ref:hmi/temp": 3.0, "ref:ceiling/temp": 2.5, "varma": varma_pct}
    rows = [(str(d), m, v * (1 + 0.1 * np.sin(i)), 0.99) for m, v in level.items()
            for i, d in enumerate(days)]
    return pd.DataFrame(rows, columns=["day", "model", "nrmse_pct", "pearson_r"])


def _lines(ax: plt.Axes) -> dict[str, matplotlib.lines.Line2D]:
    return {str(ln.get_label()): ln for ln in ax.get_lines()}


def test_daily_plot_is_log_when_one_model_dwarfs_the_others_and_breaks_at_gaps() -> None:
    fig = daily_nrmse_figure(_daily(80.0), "desk/temp", REFS, "corrgp-triv")
    try:
        ax = fig.axes[0]
        assert ax.get_yscale() == "log"
        assert ax.get_xlabel() == "day" and ax.get_ylabel() == "daily NRMSE [%]"
        assert any("log scale" in t.get_text() and "varma" in t.get_text() for t in ax.texts)
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        assert "raw reference hmi/temp" in legend and "raw reference ceiling/temp" in legend
        assert "estimate of desk/temp (published: corrgp-triv)" in legend
        assert {"triv", "varma", "corrgp-triv (primary)", "ref (closest reference held)"} <= set(
            legend)
        lines = _lines(ax)
        for label in ("triv", "raw reference hmi/temp",
                      "estimate of desk/temp (published: corrgp-triv)"):
            x = pd.DatetimeIndex(lines[label].get_xdata())
            y = np.asarray(lines[label].get_ydata(), dtype=float)
            assert len(y) == 8 and np.isnan(y).sum() == 1  # seven days, one break
            k = int(np.flatnonzero(np.isnan(y))[0])
            assert x[k - 1] == pd.Timestamp("2024-03-07") and x[k + 1] == pd.Timestamp(
                "2024-03-14")
        # the published estimate is drawn unlike any model
        est = lines["estimate of desk/temp (published: corrgp-triv)"]
        assert est.get_linewidth() > 2 * lines["triv"].get_linewidth()
        assert lines["raw reference hmi/temp"].get_linestyle() != "-"
    finally:
        plt.close(fig)


def test_daily_plot_stays_linear_when_models_are_comparable() -> None:
    fig = daily_nrmse_figure(_daily(4.0), "desk/temp", REFS, "triv")
    try:
        assert fig.axes[0].get_yscale() == "linear"
        assert not fig.axes[0].texts
    finally:
        plt.close(fig)


def test_with_gaps_leaves_consecutive_days_alone() -> None:
    x = pd.date_range("2024-03-04", periods=5, freq="D", tz="Europe/Berlin")
    xs, (y,) = with_gaps(x, DAY_GAP, np.arange(5.0))
    assert xs.equals(x) and not np.isnan(y).any()
    xs, (y,) = with_gaps(x.delete(2), DAY_GAP, np.arange(4.0))
    assert len(xs) == 5 and np.isnan(y[2]) and xs.tz == x.tz
    assert xs[2] == pd.Timestamp("2024-03-06", tz="Europe/Berlin")


@pytest.fixture(scope="module")
def small_evaluation() -> tuple[Evaluation, pd.DataFrame]:
    """A real evaluation: SML2010, five training days, three scored days, REF and TRIV."""
    df = load("sml2010")
    df = df[(df["ts"] >= "2012-03-13T23:00Z") & (df["ts"] < "2012-03-21T23:00Z")]
    spec = TwinSpec(("dining/temp",), "room/temp", Quantity.TEMPERATURE,
                    OperatingHours(timezone="Europe/Madrid"))
    return evaluate(df, spec, dt.date(2012, 3, 14), 5, ["ref", "triv"]), df


def test_typical_day_plot_of_a_real_evaluation(
    small_evaluation: tuple[Evaluation, pd.DataFrame],
) -> None:
    ev, df = small_evaluation
    fig = day_figure(ev, df, dt.date(2012, 3, 20))
    try:
        ax = fig.axes[0]
        assert ax.get_xlabel() == "local time (Europe/Madrid)"
        assert ax.get_ylabel() == "temperature [°C]"
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        assert "reference dining/temp (raw)" in legend
        assert "truth room/temp (desk sensor)" in legend
        assert any(t.startswith("estimate of room/temp") for t in legend)
        assert "estimate ±2σ" in legend
        band = [c for c in ax.collections if isinstance(c, PolyCollection)]
        assert len(band) == 1
        truth = _lines(ax)["truth room/temp (desk sensor)"]
        assert len(truth.get_xdata()) == 45  # every 15 min, 08:00 … 19:00
    finally:
        plt.close(fig)


def test_typical_day_plot_refuses_a_day_without_estimates(
    small_evaluation: tuple[Evaluation, pd.DataFrame],
) -> None:
    ev, df = small_evaluation
    with pytest.raises(DataError, match="no estimates of room/temp on 2012-03-15"):
        day_figure(ev, df, dt.date(2012, 3, 15))  # a training day


def test_daily_plot_of_a_real_evaluation_draws_the_raw_reference(
    small_evaluation: tuple[Evaluation, pd.DataFrame], tmp_path,
) -> None:
    ev, _ = small_evaluation
    a = ev.artifact
    fig = daily_nrmse_figure(ev.daily, a.target, a.references, a.primary)
    try:
        legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert "raw reference dining/temp" in legend
        assert f"estimate of room/temp (published: {a.primary})" in legend
    finally:
        plt.close(fig)
    plot_daily_nrmse(ev.daily, tmp_path / "d.png", a)
    assert (tmp_path / "d.png").stat().st_size > 10_000
