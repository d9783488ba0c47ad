"""The configuration for a freshly trained twin, as TOML the config loader accepts.

A complete minimal file (``[broker]``, ``[service]``, ``[[sensors]]``, ``[[twins]]``) rather
than a fragment, so it can be validated as it stands (``pseudotwin check-config``); its
comments say which parts go into an existing configuration. The operating hours are the
artifact's: the daemon refuses an artifact trained on other hours.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from pseudotwin.analysis.training import PLAUSIBLE
from pseudotwin.live.artifact import Artifact

_NOT_IN_ID = re.compile(r"[^A-Za-z0-9._-]+")
_NOT_IN_TOPIC = re.compile(r"[+#\x00]")


def twin_id(artifact_path: Path) -> str:
    """A twin id the config accepts, from the artifact's file name (README's convention:
    ``artifacts/<twin id>.json``)."""
    return _NOT_IN_ID.sub("-", artifact_path.stem).lstrip("._-") or "twin"


def _s(text: str) -> str:
    # A JSON string is a valid TOML basic string for everything json.dumps emits.
    return json.dumps(text, ensure_ascii=False)


def _hhmm(h: float) -> str:
    m = int(round(h * 60))
    return f"{m // 60:02d}:{m % 60:02d}"


def config_snippet(artifact: Artifact, artifact_path: Path, twin: str,
                   store: str | None = None) -> str:
    """TOML for the twin ``twin`` whose artifact is at ``artifact_path`` (made absolute:
    the file's future folder is unknown); ``store``: the history store training read, which
    ``record``, ``backfill`` and the warm start then use (None: none, training read a file)."""
    hours = artifact.hours
    lo, hi = PLAUSIBLE[artifact.quantity]
    # The window training learnt from: check-config refuses another for a live sensor.
    learnt = artifact.training.get("min_interval_seconds", {})

    def window(sensor: str) -> list[str]:
        seconds = learnt.get(sensor)
        return [] if seconds is None else [f"min_interval_seconds = {seconds:.15g}"]

    lines = [
        f"# pseudotwin configuration for the twin {twin} (written by `pseudotwin train "
        "--report`).",
        "# Valid as it stands: pseudotwin check-config FILE. To add the twin to an existing",
        "# configuration, copy its [[sensors]] (those not there yet) and [[twins]] tables, and",
        "# make [service]'s operating hours equal these: the artifact was trained on them.",
        "",
        "[broker]",
        'host = "localhost"  # your MQTT broker',
        "",
        "[service]",
        f"timezone = {_s(hours.timezone)}",
        'state_dir = "/var/lib/pseudotwin"',
        f"day_start = {_s(_hhmm(hours.day_start))}",
        f"day_end = {_s(_hhmm(hours.day_end))}",
        f"init_minutes = {hours.init_minutes:g}",
        f"slot_minutes = {hours.slot_minutes:g}",
        *(["# the history store training read: record writes into it, backfill and the",
           "# daemon's warm start read it",
           f"store = {_s(store)}"] if store else []),
    ]
    for sensor in artifact.sensors:
        role = "desk sensor (temporary)" if sensor == artifact.target else "reference"
        topic = "building/" + _NOT_IN_TOPIC.sub("_", sensor)
        lines += [
            "",
            f"# {role}; topic: where your bridge publishes it; min/max: its valid range",
            "[[sensors]]",
            f"id = {_s(sensor)}",
            f"topic = {_s(topic)}",
            f"unit = {_s(artifact.unit)}",
            f"min = {lo:.1f}",
            f"max = {hi:.1f}",
            *window(sensor),
        ]
    for sensor in artifact.covariates:
        topic = "building/" + _NOT_IN_TOPIC.sub("_", sensor)
        lines += [
            "",
            "# covariate (any quantity): set its unit and valid range; topic as above",
            "[[sensors]]",
            f"id = {_s(sensor)}",
            f"topic = {_s(topic)}",
            'unit = "unknown"',
            "min = -1e9",
            "max = 1e9",
            *window(sensor),
        ]
    refs = ", ".join(_s(r) for r in artifact.references)
    covs = ", ".join(_s(c) for c in artifact.covariates)
    lines += [
        "",
        "[[twins]]",
        f"id = {_s(twin)}",
        f"quantity = {_s(artifact.quantity.value)}",
        f"references = [{refs}]",
        *([f"covariates = [{covs}]"] if covs else []),
        "# compared with the estimate on <base_topic>/<twin>/monitor while it stands there;",
        "# remove this line (and its [[sensors]] table) when the desk sensor is taken away",
        f"target = {_s(artifact.target)}",
        "# relative paths are resolved against the folder of the configuration file",
        f"artifact = {_s(str(artifact_path.resolve()))}",
    ]
    return "\n".join(lines) + "\n"
