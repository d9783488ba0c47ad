"""Every warning names its twin (issue 12 item 7): a real `train` whose GP fit warns, a
twin's numerical fallback during a real backfill, and the collapsing of warnings that
repeat once per validation fold."""

from __future__ import annotations

import datetime as dt
import logging
import re
import shutil
from pathlib import Path

import pytest

from daemon_support import sml_csv
from pseudotwin.cli import main
from pseudotwin.config import load_config
from pseudotwin.core.twinlog import collapsed, twin_context
from pseudotwin.errors import NumericalError
from pseudotwin.gp.posterior import IncrementalPosterior
from pseudotwin.history.backfill import backfill
from pseudotwin.history.store import open_store

ROOT = Path(__file__).resolve().parent.parent
TWIN = "room1-desk-temp"  # config/example.toml's temperature twin
Trained = tuple[Path, list[logging.LogRecord]]  # the config file, training's warnings


class Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Trained:
    """config/example.toml in a folder with the temperature twin trained (Corr-GP LCM, whose
    training blocks on SML2010 reach condition numbers that warn) and its store filled;
    the WARNING records of the training."""
    folder = tmp_path_factory.mktemp("twinlog")
    sml = sml_csv(folder, dt.date(2012, 3, 19))
    (folder / "config").mkdir()
    shutil.copy(ROOT / "config" / "example.toml", folder / "config" / "example.toml")
    collect = Collect()
    logging.getLogger().addHandler(collect)
    try:
        rc = main(["train", "--history", str(sml), "--references", "dining/temp",
                   "--target", "room/temp", "--quantity", "temperature",
                   "--train-start", "2012-03-14", "--timezone", "Europe/Madrid",
                   "--models", "triv,corrgp-lcm",
                   "--out", str(folder / "config" / "artifacts" / f"{TWIN}.json")])
    finally:
        logging.getLogger().removeHandler(collect)
    assert rc == 0
    assert main(["import", str(sml), "--store", str(folder / "config" / "history.db")]) == 0
    return folder / "config" / "example.toml", collect.records


def test_train_warnings_name_the_twin(trained: Trained) -> None:
    _, records = trained
    assert any("condition number" in r.getMessage() for r in records)
    for r in records:
        assert r.getMessage().startswith(f"twin {TWIN}: "), r.getMessage()
        assert getattr(r, "twin", None) == TWIN


def test_train_does_not_repeat_a_warning_per_fold(trained: Trained) -> None:
    _, records = trained
    shapes = [re.sub(r"[\d.e+-]+", "#", r.getMessage()) for r in records]
    # at most the final fit's and the validation folds' one, collapsed
    assert max(shapes.count(s) for s in shapes) <= 2, shapes


def test_a_twin_fallback_in_backfill_names_the_twin(
    trained: Trained, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    config, _ = trained

    def broken(self: object, *args: object) -> None:  # fault injection: the GP factor fails
        raise NumericalError("injected")

    monkeypatch.setattr(IncrementalPosterior, "add", broken)
    cfg = load_config(config)
    day = dt.date(2012, 3, 19)
    with caplog.at_level(logging.WARNING), open_store(str(cfg.store)) as store:
        summary = backfill(cfg, TWIN, day, day, store, progress=False)
    assert summary.estimates > 0
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("numerical failure (injected)" in r.getMessage() for r in warnings)
    for r in warnings:
        assert r.getMessage().startswith(f"twin {TWIN}: "), r.getMessage()


def test_collapsed_logs_each_repeated_warning_once_with_its_count(
    caplog: pytest.LogCaptureFixture
) -> None:
    lg = logging.getLogger("pseudotwin.test.fold")
    with caplog.at_level(logging.DEBUG), twin_context("t-1"), collapsed([lg.name], "3 folds"):
        for p, cond in enumerate((1.5e6, 3.2e6, 4.1e6), start=1):
            lg.warning("condition number %.2e of a training block approaches 1e6", cond)
            lg.info("VAR(%d) fitted", p)  # a fit message per fold: collapsed too
            lg.debug("fold done")  # asked for: every line, at once
            lg.error("fold failed")  # an error passes at once
        lg.warning("another warning")
        lg.warning("VAR(%d) fitted", 1)  # the shape of an info, but a warning: its own line
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        *[(logging.DEBUG, "twin t-1: fold done"), (logging.ERROR, "twin t-1: fold failed")] * 3,
        (logging.WARNING, "twin t-1: condition number 1.50e+06 of a training block approaches "
                          "1e6 (and 2 more like it during 3 folds)"),
        (logging.INFO, "twin t-1: VAR(1) fitted (and 2 more like it during 3 folds)"),
        (logging.WARNING, "twin t-1: another warning"),
        (logging.WARNING, "twin t-1: VAR(1) fitted"),
    ]


def test_records_outside_a_twin_are_unchanged(caplog: pytest.LogCaptureFixture) -> None:
    lg = logging.getLogger("pseudotwin.test.plain")
    with caplog.at_level(logging.WARNING):
        lg.warning("broker at %s:%d refused", "localhost", 1883)
        with twin_context("50%-twin"):  # a '%' in the prefix survives %-formatting
            lg.warning("ratio %d%%", 5)
    assert [r.getMessage() for r in caplog.records] == [
        "broker at localhost:1883 refused", "twin 50%-twin: ratio 5%"]
    assert getattr(caplog.records[0], "twin", "unset") is None
