"""The commissioning report (`train --report DIR`, issue 12 item 4): trained on real SML2010
days through the CLI, rendered in a real headless Chromium, its config snippet loaded by the
real config loader."""

from __future__ import annotations

import dataclasses
import datetime as dt
import html
import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from daemon_support import HOURS, REF, TARGET, reference_days, sml, sml_csv
from pseudotwin.analysis.commissioning.coverage import Level, data_found
from pseudotwin.analysis.commissioning.page import FAILOVER_WITHIN, failover_section
from pseudotwin.analysis.training import train_twin
from pseudotwin.cli import _artifact_check, main
from pseudotwin.config import check_config
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.live.artifact import Artifact

TRAINING_DAYS = [dt.date(2012, 3, 14) + dt.timedelta(days=i) for i in range(5)]
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync")
# Written into the DOM once every image has loaded; --dump-dom then shows it.
IMAGE_PROBE = ("<script>window.addEventListener('load', () => {const o = "
               "document.createElement('pre'); o.id = 'image-probe'; o.textContent = "
               "JSON.stringify([...document.images].map(i => [i.complete, i.naturalWidth, "
               "i.naturalHeight])); document.body.appendChild(o);});</script>")


def chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        if path := shutil.which(name):
            return path
    if Path("/usr/bin/chromium").exists():
        return "/usr/bin/chromium"
    pytest.fail("Chromium not found: the commissioning report is checked in a real headless "
                "browser; run scripts/bootstrap.sh (installs Debian's chromium package) or "
                "apt-get install chromium")


def rendered_dom(page: Path, profile: Path) -> str:
    """The page's DOM after Chromium loaded it and the image probe ran."""
    probe = page.with_name(page.stem + "-probe.html")
    probe.write_text(page.read_text(encoding="utf-8").replace("</body>", IMAGE_PROBE + "</body>"),
                     encoding="utf-8")
    done = subprocess.run(
        [chromium(), *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--dump-dom",
         probe.as_uri()],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert done.returncode == 0 and "</html>" in done.stdout, done.stderr[-2000:]
    return done.stdout


class Tables(HTMLParser):
    """Cell texts of every table with an id: id → rows (header row first)."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self.current: list[list[str]] | None = None
        self.cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag == "table" and (tid := dict(attrs).get("id")):
            self.current = self.tables.setdefault(tid, [])
        elif tag == "tr" and self.current is not None:
            self.current.append([])
        elif tag in ("td", "th") and self.current is not None:
            self.cell = []

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self.current = None
        elif tag in ("td", "th") and self.current is not None and self.cell is not None:
            self.current[-1].append("".join(self.cell).strip())
            self.cell = None

    def handle_data(self, data: str) -> None:
        if self.cell is not None:
            self.cell.append(data)


def tables_of(dom: str) -> dict[str, list[list[str]]]:
    p = Tables()
    p.feed(dom)
    return p.tables


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(artifact, report page) of `train --report` on SML2010's five training days, for a
    window of 300 s (SML2010 reports every 15 min: the points are the same as with 60 s)."""
    folder = tmp_path_factory.mktemp("commissioning")
    history = sml_csv(folder, TRAINING_DAYS[-1])
    artifact = folder / "artifacts" / "room1-desk-temp.json"
    rc = main(["--log-level", "WARNING", "train", "--history", str(history),
               "--references", REF, "--target", TARGET, "--quantity", "temperature",
               "--train-start", str(TRAINING_DAYS[0]), "--timezone", "Europe/Madrid",
               "--models", "ref,triv", "--min-interval", "300", "--out", str(artifact),
               "--report", str(folder / "r")])
    assert rc == 0
    return artifact, folder / "r" / "room1-desk-temp.html"


def test_the_page_renders_in_chromium_with_its_tables_and_images(
        trained: tuple[Path, Path], tmp_path: Path) -> None:
    artifact, page = trained
    art = Artifact.load(artifact)
    dom = rendered_dom(page, tmp_path / "profile")
    tables = tables_of(dom)

    validation = tables["validation"]
    assert validation[0][:2] == ["model", "held-out daily NRMSE %"]
    assert [row[0] for row in validation[1:]] == list(art.validation["scores"])
    for row in validation[1:]:
        assert float(row[1]) == pytest.approx(art.validation["scores"][row[0]]["nrmse_pct"],
                                              abs=0.006)
    primary_row = next(r for r in validation[1:] if r[0] == art.primary)
    assert primary_row[-1].startswith("primary")

    data = tables["data"]
    assert data[0][:4] == ["day", "day status", "sensor", "readings"]
    cells = {(r[0], r[2]): r for r in data[1:]}
    assert set(cells) == {(str(d), s) for d in TRAINING_DAYS for s in (REF, TARGET)}
    for row in cells.values():
        assert row[1] == "training day" and int(row[3]) > 0 and row[6] == "enough"

    refs = tables["references"]
    assert [r[0] for r in refs[1:]] == [f"ref:{REF}"]
    assert np.isfinite(float(refs[1][1])) and -1.0 <= float(refs[1][2]) <= 1.0
    assert len(tables["days"]) == 1 + len(TRAINING_DAYS)

    # the self-aware criteria validation judged, each with its verdict as the artifact has it
    env = art.envelope
    assert env is not None and env.kept is not None and env.judged
    criteria = tables["criteria"]
    assert criteria[0][0] == "criterion"
    assert {r[0]: (int(r[1]), r[5]) for r in criteria[1:]} == {
        k: (j["n"], "kept" if k in env.kept else "dropped") for k, j in env.judged.items()}

    found = re.search(r'<pre id="image-probe">([^<]*)</pre>', dom)
    assert found, "the image probe did not run"
    images = json.loads(html.unescape(found.group(1)))
    assert len(images) >= 3  # the held-out NRMSE per day, the typical and the worst day
    assert all(done and w > 300 and h > 200 for done, w, h in images), images
    assert "Enough:" in dom and "Primary:" in dom
    # one reference: no failover, and the page says what a silent reference does
    assert "failover" not in tables and "One reference:" in dom


def test_the_page_is_self_contained(trained: tuple[Path, Path]) -> None:
    text = trained[1].read_text(encoding="utf-8")
    sources = re.findall(r'<img[^>]*\ssrc="([^"]*)"', text)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    assert not re.search(r'(?:src|href)\s*=\s*"?(?:https?:)?//', text)
    assert "<script" not in text and "<link" not in text


def test_the_held_out_days_are_the_ones_validation_scored(trained: tuple[Path, Path]) -> None:
    """No refit: the page's per-day scores of the primary average to validation's score."""
    artifact, page = trained
    art = Artifact.load(artifact)
    days = tables_of(page.read_text(encoding="utf-8"))["days"]
    assert days[0][1] == f"{art.primary} NRMSE %"
    per_day = [float(r[1]) for r in days[1:]]
    assert sorted(r[0] for r in days[1:]) == [str(d) for d in TRAINING_DAYS]
    assert per_day == sorted(per_day)  # best day first
    assert np.mean(per_day) == pytest.approx(
        art.validation["scores"][art.primary]["nrmse_pct"], abs=0.01)


def test_the_config_snippet_loads_with_the_real_loader_and_fits_the_artifact(
        trained: tuple[Path, Path], tmp_path: Path) -> None:
    artifact, page = trained
    found = re.search(r'<pre id="config"><code>(.*?)</code></pre>',
                      page.read_text(encoding="utf-8"), re.S)
    assert found
    path = tmp_path / "twin.toml"
    path.write_text(html.unescape(found.group(1)), encoding="utf-8")
    # the window training learnt from, which check-config holds the sensors to
    assert path.read_text(encoding="utf-8").count("min_interval_seconds = 300") == 1  # REF
    cfg = check_config(path, artifact_check=_artifact_check)  # raises on any problem
    twin = cfg.twins["room1-desk-temp"]
    assert twin.artifact == artifact.resolve()
    assert twin.references == (REF,) and twin.target == TARGET
    assert cfg.hours == Artifact.load(artifact).hours


def test_thin_and_missing_days_are_called_out() -> None:
    df = sml()
    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    day, hrs = HOURS.day_and_hours(df["ts"])
    thin = (df["sensor"] == TARGET) & (day == np.datetime64("2012-03-15")) & (hrs > 10)
    gone = (df["sensor"] == REF) & (day == np.datetime64("2012-03-16"))
    found = data_found(df[~(thin | gone)], spec, dt.date(2012, 3, 14),
                       [dt.date(2012, 3, 14), dt.date(2012, 3, 15), dt.date(2012, 3, 17)])
    rows = {(r.day, r.sensor): r for r in found.rows}
    assert rows[dt.date(2012, 3, 15), TARGET].level is Level.THIN
    assert rows[dt.date(2012, 3, 15), TARGET].coverage < 0.3
    assert rows[dt.date(2012, 3, 16), REF].level is Level.MISSING
    assert found.day_status(dt.date(2012, 3, 16)) == f"skipped: no data of {REF}"
    assert found.level is Level.THIN
    assert f"{TARGET} on 2012-03-15" in found.verdict()
    assert data_found(df, spec, dt.date(2012, 3, 14), TRAINING_DAYS).level is Level.GOOD
    too_few = data_found(df, spec, dt.date(2012, 3, 14), TRAINING_DAYS[:2])
    assert too_few.level is Level.MISSING and too_few.verdict().startswith("Not enough")


def test_training_days_close_together_are_called_one_stretch_of_weather() -> None:
    df = sml()
    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    together = data_found(df, spec, TRAINING_DAYS[0], TRAINING_DAYS)
    assert together.span_days == 5 and together.level is Level.GOOD
    assert together.verdict().startswith("Enough")
    assert "within 5 calendar days" in together.verdict() and "further apart" in together.verdict()
    # the same number of days, a week apart: nothing to add
    apart = [dt.date(2012, 3, 14) + dt.timedelta(days=7 * i) for i in range(5)]
    spread = data_found(df, spec, apart[0], apart)
    assert spread.span_days == 29 and spread.span_advice() == ""
    assert "calendar days" not in spread.verdict()
    # the edge: 14 calendar days are still one stretch, 15 are not
    for last, advised in ((13, True), (14, False)):
        days = [*TRAINING_DAYS[:4], TRAINING_DAYS[0] + dt.timedelta(days=last)]
        found = data_found(df, spec, days[0], days)
        assert found.span_days == last + 1
        assert (found.span_advice() != "") is advised


def test_train_help_explains_the_report(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--report DIR" in out and "self-contained HTML" in out


def test_too_few_days_to_validate_say_so(tmp_path: Path) -> None:
    history = sml_csv(tmp_path, TRAINING_DAYS[1])
    rc = main(["--log-level", "WARNING", "train", "--history", str(history),
               "--references", REF, "--target", TARGET, "--quantity", "temperature",
               "--train-start", str(TRAINING_DAYS[0]), "--train-days", "2",
               "--allow-unvalidated", "--timezone", "Europe/Madrid", "--models", "triv",
               "--out", str(tmp_path / "desk.json"), "--report", str(tmp_path / "r")])
    assert rc == 0
    text = (tmp_path / "r" / "desk.html").read_text(encoding="utf-8")
    assert "Not enough: 2 training day(s)" in text and "Not validated." in text
    assert "none acts, and the estimate is never uncertain" in text  # nothing judged them
    assert "<img" not in text and 'id="config"' in text


def test_the_pages_sigma_on_a_held_out_day_was_calibrated_without_it() -> None:
    """The σ the daemon publishes is calibrated on every training day, the shown one
    included: on that day it would cover by construction. The page shows, and plots, the σ
    validation scored each held-out day with (calibrated on the other days), so its days'
    coverage pools to the validation table's."""
    from pseudotwin.analysis.commissioning.heldout import held_out
    from pseudotwin.analysis.training import train_validated
    from pseudotwin.analysis.validation import NESTED_STD
    from pseudotwin.live import metrics

    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    art, validation = train_validated(sml(), spec, TRAINING_DAYS[0], 5, ("ref", "triv"))
    assert validation is not None
    shown = held_out(art, validation).evaluation.estimates
    rows = validation.held_out
    for kind in ("ref", "triv"):
        mine = (rows["model"] == kind).to_numpy()
        nested = rows.loc[mine, NESTED_STD].to_numpy(float)
        page = shown.loc[mine, "std"].to_numpy(float)
        assert np.isfinite(nested).all() and np.allclose(page, nested)
        published = [art.calibration[kind].sigma(HOURS.hours_of(t), s)
                     for t, s in zip(rows.loc[mine, "ts"], rows.loc[mine, "slope"], strict=True)]
        assert not np.allclose(page, published)  # not the in-sample σ
        cover = metrics.coverage_pct(rows.loc[mine, "truth"], rows.loc[mine, "value"], page, 2.0)
        assert cover == pytest.approx(art.validation["scores"][kind]["cover2_pct"])


def test_a_twin_trained_from_the_store_gets_that_store_in_its_configuration(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Trained with --store, the suggested TOML had no store: backfill then said "no store
    configured" and record refused to start."""
    monkeypatch.chdir(tmp_path)
    assert main(["import", str(sml_csv(tmp_path, dt.date(2012, 3, 20))), "--store",
                 "history.db"]) == 0
    rc = main(["--log-level", "WARNING", "train", "--store", "history.db", "--references", REF,
               "--target", TARGET, "--quantity", "temperature", "--timezone", "Europe/Madrid",
               "--models", "ref,triv", "--out", "art/room1-desk-temp.json",
               "--report", "report"])
    assert rc == 0
    found = re.search(r'<pre id="config"><code>(.*?)</code></pre>',
                      (tmp_path / "report" / "room1-desk-temp.html").read_text(), re.S)
    assert found
    (tmp_path / "etc").mkdir()  # elsewhere than the working directory training ran in
    path = tmp_path / "etc" / "twin.toml"
    path.write_text(html.unescape(found.group(1)), encoding="utf-8")
    cfg = check_config(path, artifact_check=_artifact_check)
    assert cfg.store == str(tmp_path / "history.db")


def _failover_rows(a: Artifact) -> tuple[str, dict[str, list[str]]]:
    section = failover_section(a)
    return section, {r[0]: r for r in tables_of(section).get("failover", [])[1:]}


def test_the_page_names_the_reference_the_twin_can_least_afford_to_lose() -> None:
    """Two references, one precise and one noisy: without the precise one the failover's
    held-out error is several times the primary's, and the page says to keep it reporting;
    each failover's row is the artifact's."""
    first = dt.date(2024, 3, 4)
    good, noisy, desk = "room/wall/temp", "room/ceiling/temp", "room/desk/temp"
    days = reference_days(HOURS, first, (good, noisy, desk), offsets=(0.6, -0.9, 0.2),
                          noise=(0.03, 0.4, 0.03), level_sd=0.3, seed=5)
    spec = TwinSpec((good, noisy), desk, Quantity.TEMPERATURE, HOURS)
    art = train_twin(days, spec, first, 5, ("ref", "triv"), primary="triv")
    own = art.validation["scores"]["triv"]["nrmse_pct"]
    section, rows = _failover_rows(art)
    assert set(rows) == {good, noisy}
    for lost, f in art.failover.items():
        assert rows[lost][1] == f"{f.kind} on {', '.join(f.model.references_)}"
        assert float(rows[lost][2]) == pytest.approx(f.nrmse_pct, abs=0.006)
        assert float(rows[lost][3]) == pytest.approx(f.nrmse_pct / own, abs=0.006)
    worst = art.failover[good].nrmse_pct / own
    assert worst > FAILOVER_WITHIN and worst > art.failover[noisy].nrmse_pct / own
    assert f"losing {good} costs the most" in html.unescape(section)
    assert 'class="verdict thin"' in section


def test_the_page_lists_the_failovers_on_one_reference_alone_and_none_when_untrained() -> None:
    first = dt.date(2024, 3, 4)
    refs = ("room/wall/temp", "room/ceiling/temp", "room/door/temp")
    days = reference_days(HOURS, first, (*refs, "room/desk/temp"), offsets=(0.6, -0.9, 0.3, 0.2),
                          noise=(0.2, 0.2, 0.2, 0.03), level_sd=0.3, seed=7)
    spec = TwinSpec(refs, "room/desk/temp", Quantity.TEMPERATURE, HOURS)
    art = train_twin(days, spec, first, 5, ("ref", "triv"), primary="triv")
    section, rows = _failover_rows(art)
    assert set(rows) == {", ".join(f.lost) for f in art.failovers}
    for kept, f in art.failover_alone.items():
        assert rows[", ".join(f.lost)][1] == f"{f.kind} on {kept}"
    assert "on each reference alone" in section
    # without the failover that does without the wall sensor, one on another reference alone
    # still answers when the wall sensor is silent: the page does not call it stale
    partial = dataclasses.replace(art, failover={r: f for r, f in art.failover.items()
                                                 if r != refs[0]})
    section, rows = _failover_rows(partial)
    assert refs[0] not in rows and "no failover could be validated" not in section
    # an artifact trained without validation has none: the page says the estimate goes stale
    bare = dataclasses.replace(art, failover={}, failover_alone={})
    section, rows = _failover_rows(bare)
    assert rows == {} and "No failover:" in section and 'class="verdict missing"' in section
