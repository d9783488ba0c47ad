"""Artifact round trip, versioning and corrupt files."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest

from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.errors import ArtifactError
from pseudotwin.history.convert import load
from pseudotwin.live.artifact import VERSION, Artifact
from pseudotwin.live.twin import Twin
from pseudotwin.models.registry import ALL_MODELS


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Artifact, Path]:
    df = load("sml2010")
    df = df[df["ts"] < "2012-03-22T00:00Z"]
    hours = OperatingHours(timezone="Europe/Madrid")
    # a covariate of another unit, so that every registered model is trained
    spec = TwinSpec(("dining/co2",), "room/co2", Quantity.CO2, hours, ("dining/temp",))
    art = train_twin(df, spec, dt.date(2012, 3, 14), 5)
    path = art.save(tmp_path_factory.mktemp("art") / "co2.json")
    return art, path


def test_artifact_holds_everything_and_round_trips(trained, tmp_path: Path) -> None:
    art, path = trained
    d = json.loads(path.read_text(encoding="utf-8"))
    assert d["version"] == VERSION and d["twin"]["unit"] == "ppm"
    assert d["twin"]["covariates"] == ["dining/temp"]
    # every registered model that serves a one-reference twin with a covariate, trained
    assert set(d["models"]) == set(ALL_MODELS) - {"corrgp-multi"}
    gp = d["models"]["corrgp-triv"]
    assert gp["kernel"] == "matern52"  # the CO2 default
    assert {"offset", "scale"} <= set(gp["scaling"])
    assert "B" in gp["hyperparameters"]["terms"][0]
    assert {"jitter_max", "condition_max", "nlml"} <= set(gp["diagnostics"])
    assert len(d["training"]["days"]) == 5
    loaded = Artifact.load(path)
    # the same readings through a twin of each give bit-identical estimates
    df = load("sml2010")
    day = df[(df["ts"] >= "2012-03-20T06:00Z") & (df["ts"] < "2012-03-20T18:00Z")]
    day = day[day["sensor"] == "dining/co2"]
    a, b = Twin(art), Twin(loaded)
    for _, r in day.iterrows():
        t = r["ts"].to_pydatetime()
        a.observe(r["sensor"], t, r["value"])
        b.observe(r["sensor"], t, r["value"])
        ea, eb = a.estimate(t), b.estimate(t)
        assert ea == eb
    assert set(ea) == set(art.published)


def test_newer_format_is_refused_clearly(trained, tmp_path: Path) -> None:
    _, path = trained
    d = json.loads(path.read_text(encoding="utf-8"))
    d["version"] = VERSION + 1
    p = tmp_path / "new.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ArtifactError, match=r"newer than this pseudotwin"):
        Artifact.load(p)


def test_a_model_s_own_error_names_the_artifact_file(trained, tmp_path: Path) -> None:
    _, path = trained
    d = json.loads(path.read_text(encoding="utf-8"))
    d["models"]["varma"]["state_space"]["obs_cov"] = [[1.0]]
    p = tmp_path / "broken.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ArtifactError, match=rf"^{p}: VARMA state_space obs_cov has shape"):
        Artifact.load(p)


@pytest.mark.parametrize("mutate", [
    lambda d: d.__setitem__("models", []),
    lambda d: d.__setitem__("training", 5),
    lambda d: d.__setitem__("validation", 0),
    lambda d: d["hours"].__setitem__("day_start", 1e308),
    lambda d: next(iter(d["calibration"].values())).__setitem__("bins", None),
    lambda d: d["models"]["triv"]["std"].pop(),
    lambda d: next(iter(d["models"]["triv"]["profiles"].values())).pop(),
], ids=["models-list", "training-number", "validation-number", "day-start-huge", "bins-null",
        "triv-std-short", "triv-profile-short"])
def test_a_value_of_the_wrong_type_is_a_corrupt_artifact_not_a_traceback(
    trained, tmp_path: Path, mutate
) -> None:
    """Fuzzed artifacts (a helper's): wrong JSON types raised AttributeError or
    OverflowError out of check-config and run."""
    _, path = trained
    d = json.loads(path.read_text(encoding="utf-8"))
    mutate(d)
    p = tmp_path / "broken.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ArtifactError, match=rf"^{p}: "):
        Artifact.load(p)


@pytest.mark.parametrize(
    "content,message",
    [
        ("{not json", "cannot read artifact"),
        ('{"format": "something-else"}', "not a pseudotwin model artifact"),
        ('{"format": "pseudotwin-artifact", "version": 1}', "incomplete or corrupt"),
    ],
)
def test_corrupt_artifacts(tmp_path: Path, content: str, message: str) -> None:
    p = tmp_path / "a.json"
    p.write_text(content)
    with pytest.raises(ArtifactError, match=message):
        Artifact.load(p)
    with pytest.raises(ArtifactError, match="no such artifact"):
        Artifact.load(tmp_path / "missing.json")
