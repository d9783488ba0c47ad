"""VARMA's order is chosen from the training days (issue Trust I, item 5): each order is scored
leave-one-day-out like a candidate, and the smallest one within noise of the best wins.

The rule on tables of held-out errors whose verdict is known, then real training on synthetic
days (real statsmodels, real replays): the artifact records every order's score and fits the
form validation scored; an order the user sets is never searched.
"""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pandas as pd
import pytest

from pseudotwin.analysis.training import train_twin
from pseudotwin.analysis.validation import (
    MIN_DAYS,
    TIE_RELATIVE,
    pick_setting,
    smallest_within_noise,
    validation_table,
)
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.live.artifact import Artifact
from pseudotwin.models.varma import VarmaModel

HOURS = OperatingHours(timezone="UTC")
SPEC = TwinSpec(("ref",), "desk", Quantity.TEMPERATURE, HOURS)
DAY0 = dt.date(2024, 3, 4)


def test_a_smaller_order_within_the_tie_margin_wins() -> None:
    best = np.array([1.0, 1.2, 0.8, 1.1, 0.9])
    table = np.array([best * (1 + TIE_RELATIVE / 2), best * 1.5, best])
    chosen, lowest, why = smallest_within_noise(table)
    assert (chosen, lowest) == (0, 2) and "within 3%" in why


def test_a_smaller_order_worse_by_less_than_the_days_noise_wins() -> None:
    # 10 % worse on average, but better on two of five days: five days cannot tell
    best = np.array([1.0, 1.0, 1.0, 1.0, 1.0])
    table = np.array([best + np.array([0.45, -0.2, 0.3, -0.1, 0.05]), best])
    assert table[0].mean() > (1 + TIE_RELATIVE) * table[1].mean()
    chosen, lowest, why = smallest_within_noise(table)
    assert (chosen, lowest) == (0, 1) and "standard error" in why


def test_a_smaller_order_worse_on_every_day_loses() -> None:
    best = np.array([1.0, 1.2, 0.8, 1.1, 0.9])
    table = np.array([best * 1.10 + 0.01 * np.arange(5), best])
    chosen, lowest, why = smallest_within_noise(table)
    assert (chosen, lowest, why) == (1, 1, "")


def _days(n: int) -> list[dt.date]:
    return [DAY0 + dt.timedelta(days=i) for i in range(n)]


def test_orders_are_compared_on_the_days_all_of_them_scored() -> None:
    d = _days(5)
    # order 1 is 5 % worse on four days and left day 0 unscored (NaN); order 4 lost day 1
    four = {x: 1.0 for x in d} | {d[1]: float("nan")}
    one = {x: 1.05 + 0.002 * i for i, x in enumerate(d)} | {d[0]: float("nan")}
    c = pick_setting("varma", "p", (1, 2, 4), {1: one, 4: four})
    assert c.chosen == 4 and np.isnan(c.scores[2])
    assert c.scores[1] == np.mean([one[x] for x in d[2:]]) and c.scores[4] == 1.0
    assert np.isfinite(c.nested)


def test_with_too_few_common_days_the_default_stays_and_says_why() -> None:
    d = _days(5)
    c = pick_setting("varma", "p", (1, 2, 4),
                     {1: {x: 1.0 for x in d[:2]}, 4: {x: 2.0 for x in d[2:]}})
    assert c.chosen == 4 and "default" in c.reason and np.isnan(c.nested)
    assert "0 day(s)" in c.reason and MIN_DAYS == 3
    assert pick_setting("varma", "p", (1, 2, 4), {}).chosen == 4


def test_the_nested_score_is_that_of_the_choice_not_the_lowest() -> None:
    d = _days(5)
    # each order is best on some days: the lowest mean is optimistic for whichever is chosen
    a = {x: v for x, v in zip(d, [1.0, 2.0, 1.0, 2.0, 1.0], strict=True)}
    b = {x: v for x, v in zip(d, [2.0, 1.0, 2.0, 1.0, 1.2], strict=True)}
    c = pick_setting("m", "p", (1, 2), {1: a, 2: b})
    assert c.nested >= min(c.scores.values())


def _frame(days: int, seed: int) -> pd.DataFrame:
    """A smooth reference and a desk that follows it with a constant offset, 15-min grid."""
    rng = np.random.default_rng(seed)
    h = 7.0 + np.arange(52) * 0.25
    rows = []
    for d in range(days):
        ref = 21.0 + np.cumsum(rng.normal(0.0, 0.08, size=len(h)))
        desk = ref + 0.5 + rng.normal(0.0, 0.05, size=len(h))
        ts = (pd.Timestamp(DAY0 + dt.timedelta(days=d), tz="UTC")
              + pd.to_timedelta(h, unit="h"))
        rows.append(pd.DataFrame({"sensor": "ref", "ts": ts, "value": ref}))
        rows.append(pd.DataFrame({"sensor": "desk", "ts": ts, "value": desk}))
    return pd.concat(rows, ignore_index=True).sort_values("ts", kind="stable")


def test_training_chooses_the_order_records_every_score_and_fits_what_was_scored(
    tmp_path,
) -> None:
    art = train_twin(_frame(6, 11), SPEC, DAY0, 5, models=["triv", "varma"])
    tuned = art.validation["tuned"]["varma"]
    assert tuned["setting"] == "p" and set(tuned["nrmse_pct"]) == {"1", "2", "4"}
    scores = {int(k): v for k, v in tuned["nrmse_pct"].items()}
    assert all(np.isfinite(v) for v in scores.values())
    model = art.models["varma"]
    assert isinstance(model, VarmaModel)
    assert model.p == tuned["chosen"] and model.force_fallback
    # never a larger order than the best's, and a smaller one only when within noise
    assert tuned["chosen"] <= min(scores, key=lambda p: scores[p])
    # the primary validation scored the chosen order: the same held-out error
    assert art.validation["scores"]["varma"]["nrmse_pct"] == scores[tuned["chosen"]]
    assert f"varma p = {tuned['chosen']}:" in validation_table(art.validation, art.unit)
    assert np.isfinite(tuned["nested_nrmse_pct"])
    back = Artifact.load(art.save(tmp_path / "a.json"))
    assert back.validation["tuned"] == json.loads(json.dumps(art.validation["tuned"]))
    reloaded = back.models["varma"]
    assert isinstance(reloaded, VarmaModel) and reloaded.p == model.p


@pytest.mark.parametrize("options", [{"p": 2, "force_fallback": True},
                                     {"maxiter": 1}])
def test_an_order_or_a_varmax_setting_the_user_sets_is_not_searched(
    options: dict[str, object],
) -> None:
    art = train_twin(_frame(6, 12), SPEC, DAY0, 5, models=["triv", "varma"],
                     options={"varma": options})
    assert "tuned" not in art.validation
    model = art.models["varma"]
    assert isinstance(model, VarmaModel) and model.p == options.get("p", 4)
    assert model.model_name_ in (("var",) if options.get("force_fallback")
                                 else ("varma", "var-fallback"))
