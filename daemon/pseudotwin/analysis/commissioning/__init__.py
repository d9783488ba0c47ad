"""The commissioning report of a freshly trained twin (``pseudotwin train --report DIR``).

One self-contained HTML page for the engineer who left a desk sensor in a room for a week:
the data found per sensor and day and whether it is enough (``coverage``), the candidates'
held-out scores and the chosen primary, the raw reference's own score, the primary's typical
and worst held-out days with the ±2σ band (``heldout``: the rows validation already replayed
through the daemon's twin code, so nothing is refit), the criteria of ``uncertain``, the
failovers for silent references, and the TOML for the twin (``snippet``). ``page`` renders
it.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pandas as pd

from pseudotwin.analysis.commissioning.coverage import training_data
from pseudotwin.analysis.commissioning.heldout import figures, held_out
from pseudotwin.analysis.commissioning.page import Page, render
from pseudotwin.analysis.commissioning.snippet import config_snippet, twin_id
from pseudotwin.analysis.validation import Validation
from pseudotwin.core.files import write_replacing
from pseudotwin.live.artifact import Artifact

__all__ = ["config_snippet", "twin_id", "write_report"]


def write_report(out_dir: Path, artifact: Artifact, validation: Validation | None,
                 history: pd.DataFrame, first_day: dt.date, artifact_path: Path,
                 store: str | None = None) -> Path:
    """Write ``<out_dir>/<twin id>.html`` and return its path.

    history: the readings ``train`` was given; first_day: its first candidate training day;
    validation: what ``train_validated`` returned (None: the page says it was not validated);
    store: the history store they came from, for the configuration (None: a file).
    """
    twin = twin_id(artifact_path)
    data = training_data(history, artifact, first_day)
    ho = held_out(artifact, validation) if validation is not None else None
    page = Page(artifact, twin, artifact_path.resolve(), data, ho,
                figures(ho, history) if ho is not None else [],
                config_snippet(artifact, artifact_path, twin, store))
    text = render(page)
    return write_replacing(out_dir / f"{twin}.html",
                           lambda tmp: tmp.write_text(text, encoding="utf-8"))
