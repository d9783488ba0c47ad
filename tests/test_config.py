"""Configuration loading: every validation rule reports the right location, all at once."""

from __future__ import annotations

import copy
import dataclasses
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from pseudotwin.cli.check_config import main as check_config_main
from pseudotwin.config import (
    BrokerConfig,
    ConfigProblems,
    SensorConfig,
    ServiceConfig,
    TwinConfig,
    check_config,
    load_config,
)
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.errors import ArtifactError, ConfigError

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "config" / "example.toml"
SECRET = "hunter2-Sup3r$ecret"


# -- a tiny TOML writer, enough for these tests -------------------------------------------


def _toml_str(s: str) -> str:
    out = []
    for c in s:
        if c in '"\\' or ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04X}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_str(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def dump_toml(doc: dict[str, Any]) -> str:
    lines: list[str] = []
    for key, value in doc.items():  # top-level scalars first, as TOML requires
        if not isinstance(value, dict) and not (
            isinstance(value, list) and value and all(isinstance(x, dict) for x in value)
        ):
            lines.append(f"{_toml_str(key)} = {_toml_value(value)}")
    for key, value in doc.items():
        if isinstance(value, dict):
            lines.append(f"[{_toml_str(key)}]")
            lines += [f"{_toml_str(k)} = {_toml_value(v)}" for k, v in value.items()]
        elif isinstance(value, list) and value and all(isinstance(x, dict) for x in value):
            for item in value:
                lines.append(f"[[{_toml_str(key)}]]")
                lines += [f"{_toml_str(k)} = {_toml_value(v)}" for k, v in item.items()]
    return "\n".join(lines) + "\n"


def base_doc() -> dict[str, Any]:
    return {
        "broker": {"host": "broker.local"},
        "service": {"timezone": "Europe/Berlin", "state_dir": "state"},
        "sensors": [
            {"id": "r/hmi/temp", "topic": "b/r/hmi/temp", "unit": "°C", "min": -10, "max": 50},
            {"id": "r/ceiling/temp", "topic": "b/r/ceiling/temp", "unit": "°C",
             "min": -10.0, "max": 50.0},
            {"id": "r/desk/temp", "topic": "b/r/desk/temp", "unit": "°C", "min": -10, "max": 50},
            {"id": "r/ceiling/co2", "topic": "b/r/ceiling/co2", "format": "number",
             "unit": "ppm", "min": 0, "max": 5000},
        ],
        "twins": [
            {"id": "r-desk-temp", "quantity": "temperature",
             "references": ["r/hmi/temp", "r/ceiling/temp"], "target": "r/desk/temp",
             "artifact": "artifacts/t.json"},
            {"id": "r-desk-co2", "quantity": "co2", "references": ["r/ceiling/co2"],
             "artifact": "artifacts/c.json"},
        ],
    }


def write(tmp_path: Path, doc: dict[str, Any] | str, name: str = "config.toml") -> Path:
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else dump_toml(doc), encoding="utf-8")
    return path


def problems_of(tmp_path: Path, doc: dict[str, Any], check: bool = False) -> list[str]:
    path = write(tmp_path, doc)
    with pytest.raises(ConfigProblems) as info:
        (check_config if check else load_config)(path)
    assert info.value.problems, "ConfigProblems without problems"
    return info.value.problems


def has(problems: list[str], location: str, fragment: str = "") -> bool:
    return any(p.startswith(f"{location}: ") and fragment in p for p in problems)


Mutation = Callable[[dict[str, Any]], None]


def set_(*path: Any) -> Mutation:
    *keys, last, value = path

    def mutate(doc: dict[str, Any]) -> None:
        node = doc
        for k in keys:
            node = node[k]
        node[last] = value

    return mutate


def del_(*path: Any) -> Mutation:
    *keys, last = path

    def mutate(doc: dict[str, Any]) -> None:
        node = doc
        for k in keys:
            node = node[k]
        del node[last]

    return mutate


def both(*mutations: Mutation) -> Mutation:
    def mutate(doc: dict[str, Any]) -> None:
        for m in mutations:
            m(doc)

    return mutate


# -- the valid baseline ---------------------------------------------------------------------


def test_base_doc_is_valid_and_defaults_apply(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, base_doc()))
    assert cfg.broker == BrokerConfig(host="broker.local")
    assert (cfg.broker.port, cfg.broker.tls, cfg.broker.client_id, cfg.broker.keepalive) == (
        1883, False, "pseudotwin", 30)
    assert cfg.base_topic == "pseudotwin"
    assert (cfg.publish_every_minutes, cfg.stale_after_minutes, cfg.max_skew_seconds) == (
        15, 30, 300)
    assert (cfg.queue_size, cfg.log_level) == (10000, "INFO")
    assert cfg.journal_fsync is True  # on disk before the broker lets a reading go
    assert cfg.hours == OperatingHours(8.0, 19.0, 30.0, 15.0, "Europe/Berlin")
    assert list(cfg.sensors) == ["r/hmi/temp", "r/ceiling/temp", "r/desk/temp", "r/ceiling/co2"]
    hmi = cfg.sensors["r/hmi/temp"]
    assert (hmi.format, hmi.ts_key, hmi.value_key, hmi.min, hmi.max) == (
        "json", "ts", "value", -10.0, 50.0)
    assert isinstance(hmi.min, float)
    assert cfg.twins["r-desk-temp"].references == ("r/hmi/temp", "r/ceiling/temp")
    assert cfg.twins["r-desk-temp"].sensors == ("r/hmi/temp", "r/ceiling/temp", "r/desk/temp")
    assert cfg.twins["r-desk-co2"].target is None
    assert cfg.sensor_for_topic("b/r/ceiling/co2") is cfg.sensors["r/ceiling/co2"]
    assert cfg.sensor_for_topic("b/unknown") is None
    triv = cfg.twin_topic("r-desk-temp", "baseline", "triv")
    assert triv == "pseudotwin/r-desk-temp/baseline/triv"
    assert cfg.stale_after.total_seconds() == 1800
    assert cfg.max_skew.total_seconds() == 300
    assert cfg.publish_every.total_seconds() == 900


def test_tls_without_port_defaults_to_8883(tmp_path: Path) -> None:
    doc = base_doc()
    doc["broker"]["tls"] = True
    assert load_config(write(tmp_path, doc)).broker.port == 8883
    doc["broker"]["port"] = 1884
    assert load_config(write(tmp_path, doc)).broker.port == 1884


def test_values_that_are_legal_but_unusual_are_accepted(tmp_path: Path) -> None:
    doc = base_doc()
    doc["sensors"][0]["topic"] = "/b//x/"  # empty levels are legal MQTT
    doc["sensors"][1]["ts_key"] = ""  # no timestamp in the payload: arrival time
    doc["sensors"][1]["value_key"] = "temperature"
    doc["service"]["publish_every_minutes"] = 0.5  # 30 s divides a day
    doc["service"]["log_level"] = "debug"
    doc["service"]["day_end"] = "24:00"
    cfg = load_config(write(tmp_path, doc))
    assert cfg.sensors["r/hmi/temp"].topic == "/b//x/"
    assert cfg.sensors["r/ceiling/temp"].ts_key == ""
    assert cfg.log_level == "DEBUG"
    assert cfg.hours.day_end == 24.0


def test_relative_paths_resolve_against_config_folder_not_cwd(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "etc"
    folder.mkdir()
    doc = base_doc()
    doc["broker"].update(username="u", password_file="secret.txt", tls=True, ca_file="ca.pem")
    doc["twins"][1]["artifact"] = "/abs/c.json"
    path = write(folder, doc)
    monkeypatch.chdir(tmp_path)
    cfg = load_config(Path("etc") / "config.toml")
    assert cfg.twins["r-desk-temp"].artifact == folder.absolute() / "artifacts" / "t.json"
    assert cfg.twins["r-desk-co2"].artifact == Path("/abs/c.json")
    assert cfg.state_dir == folder.absolute() / "state"
    assert cfg.broker.password_file == folder.absolute() / "secret.txt"
    assert cfg.broker.ca_file == folder.absolute() / "ca.pem"
    assert path.exists()


# -- one rule, one location ----------------------------------------------------------------

BAD: list[tuple[str, Mutation, str, str]] = [
    # broker
    ("host-label-too-long", set_("broker", "host", "a" * 64 + ".example.com"), "broker.host",
     "63 between dots"),
    ("host-with-space", set_("broker", "host", "my broker"), "broker.host", "a space"),
    ("username-nul", set_("broker", "username", "a\x00b"), "broker.username", "NUL"),
    ("tz-region-folder", set_("service", "timezone", "Europe"), "service.timezone",
     "unknown IANA time zone"),
    ("tz-too-long", set_("service", "timezone", "Europe/" + "x" * 300), "service.timezone",
     "unknown IANA time zone"),
    ("tz-letter-case", set_("service", "timezone", "europe/berlin"), "service.timezone",
     "unknown IANA time zone 'europe/berlin' (did you mean 'Europe/Berlin'?)"),
    ("publish-every-tiny", set_("service", "publish_every_minutes", 1e-300),
     "service.publish_every_minutes", "does not divide a day"),
    ("publish-every-huge", set_("service", "publish_every_minutes", 1e308),
     "service.publish_every_minutes", "at most a day"),
    ("stale-after-huge", set_("service", "stale_after_minutes", 1e308),
     "service.stale_after_minutes", "at most a week"),
    ("max-skew-huge", set_("service", "max_skew_seconds", 9223372036854775807),
     "service.max_skew_seconds", "at most a day"),
    ("sensor-id-hash", set_("sensors", 0, "id", "room#1/temp"), "sensors[0].id", "comment"),
    ("port-string", set_("broker", "port", "1883"), "broker.port", "expected an integer"),
    ("port-float", set_("broker", "port", 1883.0), "broker.port", "expected an integer"),
    ("port-zero", set_("broker", "port", 0), "broker.port", "1..65535"),
    ("port-high", set_("broker", "port", 65536), "broker.port", "1..65535"),
    ("tls-string", set_("broker", "tls", "yes"), "broker.tls", "expected a boolean"),
    ("keepalive-zero", set_("broker", "keepalive", 0), "broker.keepalive", "1..65535"),
    ("client-id-empty", set_("broker", "client_id", ""), "broker.client_id", "empty"),
    ("client-id-long", set_("broker", "client_id", "p" * 257), "broker.client_id",
     "longer than 256 bytes"),
    ("host-empty", set_("broker", "host", ""), "broker.host", "empty"),
    ("host-missing", del_("broker", "host"), "broker.host", "missing required key"),
    ("broker-missing", del_("broker"), "broker", "missing table"),
    ("broker-not-table", set_("broker", "localhost"), "broker", "expected a table"),
    ("env-name", both(set_("broker", "username", "u"), set_("broker", "password_env", "1-X")),
     "broker.password_env", "not an environment variable name"),
    ("two-password-sources",
     both(set_("broker", "username", "u"), set_("broker", "password_env", "PW"),
          set_("broker", "password_file", "pw.txt")),
     "broker.password_file", "not both"),
    ("password-without-user", set_("broker", "password_env", "PW"), "broker.username",
     "required when a password source"),
    ("ca-without-tls", set_("broker", "ca_file", "ca.pem"), "broker.ca_file", "tls = true"),
    # service
    ("tz-unknown", set_("service", "timezone", "Europe/Berln"), "service.timezone",
     "did you mean 'Europe/Berlin'"),
    ("tz-missing", del_("service", "timezone"), "service.timezone", "missing required key"),
    ("state-dir-missing", del_("service", "state_dir"), "service.state_dir", "missing required"),
    ("state-dir-empty", set_("service", "state_dir", ""), "service.state_dir", "empty"),
    ("state-dir-int", set_("service", "state_dir", 5), "service.state_dir", "path string"),
    ("store-in-memory", set_("service", "store", ":memory:"), "service.store", "keeps nothing"),
    ("store-no-path", set_("service", "store", "sqlite:///"), "service.store", "keeps nothing"),
    ("service-missing", del_("service"), "service", "missing table"),
    ("day-start-format", set_("service", "day_start", "8am"), "service.day_start", "HH:MM"),
    ("day-start-25h", set_("service", "day_start", "25:00"), "service.day_start", "HH:MM"),
    ("day-end-number", set_("service", "day_end", 19), "service.day_end", "expected a string"),
    ("day-order", both(set_("service", "day_start", "19:00"), set_("service", "day_end", "08:00")),
     "service.day_start", "before day_end"),
    ("init-too-long", set_("service", "init_minutes", 600), "service.init_minutes", "init"),
    ("init-negative", set_("service", "init_minutes", -30), "service.init_minutes", "≥ 0"),
    ("slot-not-dividing", set_("service", "slot_minutes", 7), "service.slot_minutes", "divide"),
    ("publish-not-dividing", set_("service", "publish_every_minutes", 7),
     "service.publish_every_minutes", "does not divide a day"),
    # anchored at midnight, a day-long step has no instant within 08:00–19:00
    ("publish-off-hours", set_("service", "publish_every_minutes", 1440),
     "service.publish_every_minutes", "no multiple since local midnight"),
    ("publish-zero", set_("service", "publish_every_minutes", 0),
     "service.publish_every_minutes", "positive"),
    ("stale-zero", set_("service", "stale_after_minutes", 0), "service.stale_after_minutes",
     "positive"),
    ("stale-negative", set_("service", "stale_after_minutes", -5.0),
     "service.stale_after_minutes", "positive"),
    ("stale-inf", set_("service", "stale_after_minutes", math.inf),
     "service.stale_after_minutes", "finite"),
    ("skew-negative", set_("service", "max_skew_seconds", -1), "service.max_skew_seconds",
     "negative"),
    ("queue-zero", set_("service", "queue_size", 0), "service.queue_size", "at least 1"),
    ("queue-float", set_("service", "queue_size", 1.5), "service.queue_size", "integer"),
    ("fsync-string", set_("service", "journal_fsync", "no"), "service.journal_fsync",
     "expected a boolean"),
    ("log-level", set_("service", "log_level", "VERBOSE"), "service.log_level", "one of"),
    ("baselines-cadence", set_("service", "baselines", "sometimes"), "service.baselines",
     "one of grid, reading"),
    ("base-wildcard", set_("service", "base_topic", "pt/+/x"), "service.base_topic", "wildcard"),
    ("base-hash", set_("service", "base_topic", "pt/#"), "service.base_topic", "wildcard"),
    ("base-empty", set_("service", "base_topic", ""), "service.base_topic", "empty"),
    ("base-trailing-slash", set_("service", "base_topic", "pt/"), "service.base_topic", "'/'"),
    ("base-dollar", set_("service", "base_topic", "$SYS/pt"), "service.base_topic", "reserved"),
    # sensors
    ("topic-plus", set_("sensors", 1, "topic", "b/+/temp"), "sensors[1].topic", "wildcard"),
    ("topic-hash", set_("sensors", 1, "topic", "b/#"), "sensors[1].topic", "wildcard"),
    ("topic-nul", set_("sensors", 1, "topic", "b/\x00x"), "sensors[1].topic", "NUL"),
    ("topic-control", set_("sensors", 1, "topic", "b/\x07x"), "sensors[1].topic", "control"),
    ("topic-empty", set_("sensors", 1, "topic", ""), "sensors[1].topic", "empty"),
    ("topic-too-long", set_("sensors", 1, "topic", "é" * 32768), "sensors[1].topic", "65535"),
    ("topic-dollar", set_("sensors", 1, "topic", "$SYS/broker/load"), "sensors[1].topic",
     "reserved"),
    ("topic-not-string", set_("sensors", 1, "topic", 42), "sensors[1].topic", "expected a string"),
    ("topic-missing", del_("sensors", 0, "topic"), "sensors[0].topic", "missing required key"),
    ("topic-duplicate", set_("sensors", 1, "topic", "b/r/hmi/temp"), "sensors[1].topic",
     "already the topic of sensors[0]"),
    ("topic-under-base", set_("sensors", 2, "topic", "pseudotwin/r-desk-temp/estimate"),
     "sensors[2].topic", "under base_topic"),
    ("id-duplicate", set_("sensors", 2, "id", "r/hmi/temp"), "sensors[2].id",
     "duplicate id 'r/hmi/temp' (first used by sensors[0])"),
    ("id-empty", set_("sensors", 2, "id", ""), "sensors[2].id", "empty"),
    ("id-blanks", set_("sensors", 2, "id", " r/desk/temp"), "sensors[2].id", "blanks"),
    ("min-above-max", both(set_("sensors", 0, "min", 50), set_("sensors", 0, "max", 10)),
     "sensors[0].max", "greater than min"),
    ("min-equals-max", set_("sensors", 0, "min", 50), "sensors[0].max", "greater than min"),
    ("min-nan", set_("sensors", 0, "min", math.nan), "sensors[0].min", "finite"),
    ("min-string", set_("sensors", 0, "min", "0"), "sensors[0].min", "expected a number"),
    ("max-bool", set_("sensors", 0, "max", True), "sensors[0].max", "expected a number"),
    ("range-implausible-celsius", set_("sensors", 0, "max", 5000), "sensors[0].max",
     "not a plausible temperature"),
    ("range-implausible-co2", set_("sensors", 3, "min", -400), "sensors[3].min",
     "not a plausible CO2"),
    ("format", set_("sensors", 0, "format", "csv"), "sensors[0].format", "one of"),
    ("ts-key-with-number", set_("sensors", 3, "ts_key", "ts"), "sensors[3].ts_key",
     'only applies to format = "json"'),
    ("value-key-empty", set_("sensors", 0, "value_key", ""), "sensors[0].value_key", "empty"),
    ("ts-equals-value-key", set_("sensors", 0, "ts_key", "value"), "sensors[0].ts_key",
     "differ"),
    ("unit-empty", set_("sensors", 0, "unit", ""), "sensors[0].unit", "empty"),
    ("sensors-not-array", set_("sensors", {"id": "x"}), "sensors", "array of tables"),
    ("sensors-empty", set_("sensors", []), "sensors", "at least one"),
    ("sensors-missing", del_("sensors"), "sensors", "missing"),
    # twins
    ("ref-unknown", set_("twins", 0, "references", ["r/hmi/temp", "nope"]),
     "twins[0].references", "unknown sensor 'nope'"),
    ("ref-typo", set_("twins", 0, "references", ["r/hmi/tmp"]), "twins[0].references",
     "unknown sensor 'r/hmi/tmp' (did you mean 'r/hmi/temp'?)"),
    ("ref-empty", set_("twins", 0, "references", []), "twins[0].references", "at least one"),
    ("ref-string", set_("twins", 0, "references", "r/hmi/temp"), "twins[0].references",
     "array"),
    ("ref-twice", set_("twins", 0, "references", ["r/hmi/temp", "r/hmi/temp"]),
     "twins[0].references", "listed twice"),
    ("target-is-reference", set_("twins", 0, "target", "r/hmi/temp"), "twins[0].target",
     "also a reference"),
    ("target-unknown", set_("twins", 0, "target", "ghost"), "twins[0].target",
     "unknown sensor 'ghost'"),
    ("quantity", set_("twins", 0, "quantity", "humidity"), "twins[0].quantity", "one of"),
    ("twin-id-slash", set_("twins", 0, "id", "room/desk"), "twins[0].id", "topic level"),
    ("twin-id-duplicate", set_("twins", 1, "id", "r-desk-temp"), "twins[1].id",
     "duplicate id 'r-desk-temp' (first used by twins[0])"),
    ("artifact-shared", set_("twins", 1, "artifact", "artifacts/t.json"), "twins[1].artifact",
     "already the artifact of twins[0]"),
    ("artifact-empty", set_("twins", 1, "artifact", ""), "twins[1].artifact", "empty"),
    ("artifact-missing", del_("twins", 1, "artifact"), "twins[1].artifact", "missing required"),
    ("unit-vs-quantity", set_("twins", 1, "references", ["r/hmi/temp"]), "twins[1].references",
     "not a co2 unit"),
    ("kelvin-reference",
     both(set_("sensors", 1, "unit", "K"), set_("sensors", 1, "min", 263.15),
          set_("sensors", 1, "max", 323.15)),
     "twins[0].references", "a temperature twin works in °C"),
    ("fahrenheit-reference",
     both(set_("sensors", 1, "unit", "°F"), set_("sensors", 1, "min", 14.0),
          set_("sensors", 1, "max", 122.0)),
     "twins[0].references", "its sensors must report °C"),
    ("twins-empty", set_("twins", []), "twins", "at least one"),
    ("covariate-unknown", set_("twins", 0, "covariates", ["r/ceiling/c02"]),
     "twins[0].covariates", "unknown sensor 'r/ceiling/c02' (did you mean 'r/ceiling/co2'?)"),
    ("covariate-twice", set_("twins", 0, "covariates", ["r/ceiling/co2", "r/ceiling/co2"]),
     "twins[0].covariates", "listed twice"),
    ("covariate-is-reference", set_("twins", 0, "covariates", ["r/hmi/temp"]),
     "twins[0].covariates", "also a reference or the target"),
    ("covariate-is-target", set_("twins", 0, "covariates", ["r/desk/temp"]),
     "twins[0].covariates", "also a reference or the target"),
    ("covariates-string", set_("twins", 0, "covariates", "r/ceiling/co2"),
     "twins[0].covariates", "array"),
    # unknown keys, with suggestions
    ("unknown-top", set_("brokr", {"host": "x"}), "brokr", "unknown key (did you mean 'broker'?)"),
    ("unknown-broker", set_("broker", "hots", "x"), "broker.hots",
     "unknown key (did you mean 'host'?)"),
    ("unknown-service", set_("service", "timzone", "UTC"), "service.timzone",
     "(did you mean 'timezone'?)"),
    ("unknown-sensor", set_("sensors", 2, "valu_key", "v"), "sensors[2].valu_key",
     "(did you mean 'value_key'?)"),
    ("unknown-twin", set_("twins", 1, "refrences", []), "twins[1].refrences",
     "(did you mean 'references'?)"),
    ("unknown-no-suggestion", set_("service", "zzz", 1), "service.zzz", "unknown key"),
]


@pytest.mark.parametrize(("mutate", "location", "fragment"),
                         [pytest.param(m, loc, frag, id=name) for name, m, loc, frag in BAD])
def test_each_rule_reports_its_location(
    tmp_path: Path, mutate: Mutation, location: str, fragment: str
) -> None:
    doc = copy.deepcopy(base_doc())
    mutate(doc)
    problems = problems_of(tmp_path, doc)
    assert has(problems, location, fragment), problems


def test_a_name_too_long_for_the_file_system_is_a_problem_not_a_traceback(
    tmp_path: Path
) -> None:
    doc = copy.deepcopy(base_doc())
    doc["service"]["state_dir"] = "x" * 300
    doc["twins"][0]["artifact"] = "y" * 300 + ".json"
    problems = problems_of(tmp_path, doc, check=True)
    assert has(problems, "service.state_dir", "too long"), problems
    assert has(problems, "twins[0].artifact", "too long"), problems


def test_a_sqlite_store_that_is_a_directory_is_a_problem(tmp_path: Path) -> None:
    doc = copy.deepcopy(base_doc())
    doc["service"]["store"] = "."
    assert has(problems_of(tmp_path, doc, check=True), "service.store",
               "is a directory, not a SQLite file")


def test_unknown_key_without_close_match_has_no_suggestion(tmp_path: Path) -> None:
    doc = base_doc()
    doc["service"]["zzz"] = 1
    [problem] = problems_of(tmp_path, doc)
    assert problem == "service.zzz: unknown key"


def test_all_problems_are_reported_at_once(tmp_path: Path) -> None:
    doc = base_doc()
    doc["broker"]["port"] = 0
    doc["service"]["timezone"] = "Mars/Olympus"
    doc["sensors"][1]["topic"] = "b/+"
    doc["twins"][1]["references"] = ["nope"]
    doc["twins"][0]["colour"] = "red"
    problems = problems_of(tmp_path, doc)
    for loc in ("broker.port", "service.timezone", "sensors[1].topic", "twins[1].references",
                "twins[0].colour"):
        assert has(problems, loc), (loc, problems)
    assert len(problems) == 5, problems


def test_reference_to_an_invalid_sensor_is_not_also_called_unknown(tmp_path: Path) -> None:
    doc = base_doc()
    doc["sensors"][0]["topic"] = "b/#"
    problems = problems_of(tmp_path, doc)
    assert problems == [p for p in problems if p.startswith("sensors[0].topic: ")], problems


@pytest.mark.parametrize("broken", [set_("sensors", []), del_("sensors"),
                                    set_("sensors", {"id": "x"})])
def test_unusable_sensor_list_does_not_flood_twins_with_unknown_references(
    tmp_path: Path, broken: Mutation
) -> None:
    doc = base_doc()
    broken(doc)
    problems = problems_of(tmp_path, doc)
    assert len(problems) == 1 and problems[0].startswith("sensors: "), problems


def test_config_error_carries_problem_list_and_joins_lines(tmp_path: Path) -> None:
    doc = base_doc()
    doc["broker"]["port"] = 0
    doc["service"]["queue_size"] = 0
    path = write(tmp_path, doc)
    with pytest.raises(ConfigError) as info:  # ConfigProblems is a ConfigError
        load_config(path)
    err = info.value
    assert isinstance(err, ConfigProblems)
    assert str(err) == "\n".join(err.problems)
    assert len(err.problems) == 2


def test_unparseable_toml_is_a_plain_config_error_with_position(tmp_path: Path) -> None:
    path = write(tmp_path, "[broker]\nhost = \n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert not isinstance(info.value, ConfigProblems)
    assert "line 2" in str(info.value) and "column" in str(info.value)


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "absent.toml")


# -- the dataclasses validate themselves ---------------------------------------------------


def test_dataclasses_validate_on_direct_construction() -> None:
    with pytest.raises(ConfigProblems) as info:
        SensorConfig(id="s", topic="a/+", unit="°C", min=5, max=1)
    assert has(info.value.problems, "topic", "wildcard")
    assert has(info.value.problems, "max", "greater than min")
    with pytest.raises(ConfigProblems, match="port: must be in 1..65535"):
        BrokerConfig(host="h", port=70000)
    # a bucket that rounds to no time at all would fail only when the twins start
    with pytest.raises(ConfigProblems, match=r"min_interval_seconds: must be in 0.001..3600"):
        SensorConfig(id="s", topic="a/b", unit="°C", min=0, max=40, min_interval_seconds=1e-7)
    per_sensor = ServiceConfig(
        broker=BrokerConfig(host="h"), hours=OperatingHours(), state_dir=Path("/tmp/s"),
        sensors={"s": SensorConfig(id="s", topic="a/b", unit="°C", min=0, max=40,
                                   min_interval_seconds=10)}, twins={}).thinning
    assert per_sensor.interval("s").total_seconds() == 10
    with pytest.raises(ConfigProblems, match="target: sensor 'a' is also a reference"):
        TwinConfig(id="t", references=("a",), target="a", artifact=Path("x"),
                   quantity="temperature")


def test_dataclasses_are_frozen_and_normalize() -> None:
    twin = TwinConfig(id="t", references=["a", "b"], artifact="x.json",  # type: ignore[arg-type]
                      quantity="co2")
    assert twin.references == ("a", "b") and twin.artifact == Path("x.json")
    with pytest.raises(dataclasses.FrozenInstanceError):
        twin.id = "u"  # type: ignore[misc]


def test_service_config_cross_checks_by_id() -> None:
    sensor = SensorConfig(id="a", topic="t/a", unit="°C", min=0, max=40)
    twin = TwinConfig(id="tw", references=("a", "b"), artifact=Path("x"), quantity="temperature")
    with pytest.raises(ConfigProblems) as info:
        ServiceConfig(broker=BrokerConfig(host="h"), hours=OperatingHours(),
                      state_dir=Path("/tmp/s"), sensors={"a": sensor}, twins={"tw": twin})
    assert info.value.problems == ["twins['tw'].references: unknown sensor 'b'"]


# -- passwords: read at call time, never shown ---------------------------------------------


def _with_password_env(doc: dict[str, Any]) -> dict[str, Any]:
    doc["broker"].update(username="pt", password_env="PT_TEST_MQTT_PASSWORD")
    return doc


def test_password_env_is_read_at_call_time(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PT_TEST_MQTT_PASSWORD", raising=False)
    cfg = load_config(write(tmp_path, _with_password_env(base_doc())))  # absent var: loads
    with pytest.raises(ConfigProblems, match="PT_TEST_MQTT_PASSWORD is not set"):
        cfg.broker.password()
    monkeypatch.setenv("PT_TEST_MQTT_PASSWORD", SECRET)
    assert cfg.broker.password() == SECRET
    monkeypatch.setenv("PT_TEST_MQTT_PASSWORD", "rotated")
    assert cfg.broker.password() == "rotated"
    monkeypatch.setenv("PT_TEST_MQTT_PASSWORD", "")
    with pytest.raises(ConfigProblems, match="is empty"):
        cfg.broker.password()


def test_no_password_configured_means_none(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, base_doc())).broker.password() is None


def test_check_config_reports_unset_password_env(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("PT_TEST_MQTT_PASSWORD", raising=False)
    problems = problems_of(tmp_path, _with_password_env(base_doc()), check=True)
    assert has(problems, "broker.password_env", "PT_TEST_MQTT_PASSWORD is not set")


def test_password_written_in_the_file_is_refused_without_echoing_it(tmp_path: Path) -> None:
    doc = base_doc()
    doc["broker"].update(username="pt", password=SECRET)
    problems = problems_of(tmp_path, doc)
    assert has(problems, "broker.password", "use password_env or password_file")
    assert SECRET not in "\n".join(problems)


def test_password_file_strips_trailing_newline_and_reports_absence(tmp_path: Path) -> None:
    doc = base_doc()
    doc["broker"].update(username="pt", password_file="pw.txt")
    path = write(tmp_path, doc)
    cfg = load_config(path)
    with pytest.raises(ConfigProblems, match="pw.txt does not exist"):
        cfg.broker.password()
    (tmp_path / "pw.txt").write_text(SECRET + "\n")
    assert cfg.broker.password() == SECRET
    (tmp_path / "pw.txt").write_text("\n")
    with pytest.raises(ConfigProblems, match="is empty"):
        cfg.broker.password()


def test_password_never_appears_in_repr_str_or_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("PT_TEST_MQTT_PASSWORD", SECRET)
    cfg = load_config(write(tmp_path, _with_password_env(base_doc())))
    assert cfg.broker.password() == SECRET  # it is really configured ...
    for text in (repr(cfg), str(cfg), repr(cfg.broker), str(cfg.broker)):
        assert SECRET not in text  # ... yet never rendered
    assert "PT_TEST_MQTT_PASSWORD" in repr(cfg.broker)  # only its source is

    bad = _with_password_env(base_doc())
    bad["broker"]["port"] = 0
    path = write(tmp_path, bad, "bad.toml")
    with pytest.raises(ConfigProblems) as info:
        check_config(path)
    assert SECRET not in str(info.value)
    assert check_config_main([str(path)]) == 1
    out = capsys.readouterr()
    assert SECRET not in out.out + out.err

    # A secret file that is not UTF-8 is reported without its content.
    doc = base_doc()
    doc["broker"].update(username="pt", password_file="pw.bin")
    (tmp_path / "pw.bin").write_bytes(SECRET.encode() + b"\xff")
    with pytest.raises(ConfigProblems) as info:
        check_config(write(tmp_path, doc, "file.toml"))
    assert has(info.value.problems, "broker.password_file", "not UTF-8")
    assert SECRET not in str(info.value)


# -- start-up checks: artifacts, files ------------------------------------------------------


def test_check_config_requires_artifacts_load_config_does_not(tmp_path: Path) -> None:
    path = write(tmp_path, base_doc())
    load_config(path)  # artifacts not trained yet: still loads
    with pytest.raises(ConfigProblems) as info:
        check_config(path)
    assert has(info.value.problems, "twins[0].artifact", "t.json does not exist")
    assert has(info.value.problems, "twins[1].artifact", "c.json does not exist")
    (tmp_path / "artifacts").mkdir()
    (tmp_path / "artifacts" / "t.json").write_text("{}")
    (tmp_path / "artifacts" / "c.json").write_text("{}")
    assert len(check_config(path).twins) == 2


def test_check_config_reports_missing_ca_file_and_state_dir_that_is_a_file(
    tmp_path: Path,
) -> None:
    doc = base_doc()
    doc["broker"].update(tls=True, ca_file="ca.pem")
    (tmp_path / "state").write_text("not a dir")
    problems = problems_of(tmp_path, doc, check=True)
    assert has(problems, "broker.ca_file", "does not exist")
    assert has(problems, "service.state_dir", "not a directory")


def test_check_config_refuses_a_ca_file_that_holds_no_certificate(tmp_path: Path) -> None:
    """paho's tls_set raised ssl.SSLError at start (a traceback, exit 1: systemd restarted the
    daemon in a loop) while check-config passed the file."""
    doc = base_doc()
    doc["broker"].update(tls=True, ca_file="ca.pem")
    (tmp_path / "ca.pem").write_text("not a certificate\n")
    assert has(problems_of(tmp_path, doc, check=True), "broker.ca_file",
               "holds no usable CA certificate (PEM expected")
    system = Path("/etc/ssl/certs/ca-certificates.crt")  # Debian's bundle: real PEM CAs
    if system.is_file():
        shutil.copy(system, tmp_path / "ca.pem")
        assert not has(problems_of(tmp_path, doc, check=True), "broker.ca_file")


def test_a_sqlite_url_is_a_path_from_the_config_folder_and_its_folder_is_checked(
        tmp_path: Path) -> None:
    """A plain path was resolved against the config's folder, ``sqlite:///rel.db`` against
    the working directory (/ under systemd), and its missing folder went unnoticed."""
    folder = tmp_path / "etc"
    folder.mkdir()
    doc = base_doc()
    for url, want in (("sqlite:///history.db", folder / "history.db"),
                      ("history.db", folder / "history.db"),
                      (f"sqlite:///{tmp_path}/abs.db", tmp_path / "abs.db")):
        doc["service"]["store"] = url
        assert load_config(write(folder, doc)).store == str(want), url
    doc["service"]["store"] = "sqlite:///nodir/history.db"
    assert has(problems_of(folder, doc, check=True), "service.store",
               f"directory {folder / 'nodir'} does not exist")


def test_artifact_check_hook_gets_each_existing_twin(tmp_path: Path) -> None:
    path = write(tmp_path, base_doc())
    (tmp_path / "artifacts").mkdir()
    (tmp_path / "artifacts" / "t.json").write_text("{}")
    seen: list[str] = []

    def artifact_check(twin: TwinConfig, hours: OperatingHours | None,
                       thinning: object) -> list[str]:
        seen.append(twin.id)
        if twin.quantity == "temperature":
            return ["trained for sensors ('x', 'y'), configured ('r/hmi/temp', 'r/ceiling/temp')"]
        return []

    with pytest.raises(ConfigProblems) as info:
        check_config(path, artifact_check=artifact_check)
    assert seen == ["r-desk-temp"]  # the co2 artifact is missing, so not checked
    assert has(info.value.problems, "twins[0].artifact", "trained for sensors ('x', 'y')")
    assert has(info.value.problems, "twins[1].artifact", "does not exist")

    seen.clear()
    with pytest.raises(ConfigProblems) as info:
        load_config(path, artifact_check=artifact_check)
    assert seen == ["r-desk-temp"]
    assert [p.split(":")[0] for p in info.value.problems] == ["twins[0].artifact"]


def test_artifact_check_exceptions_become_problems(tmp_path: Path) -> None:
    path = write(tmp_path, base_doc())
    (tmp_path / "artifacts").mkdir()
    for name in ("t.json", "c.json"):
        (tmp_path / "artifacts" / name).write_text("{}")

    def artifact_check(twin: TwinConfig, hours: OperatingHours | None,
                       thinning: object) -> list[str]:
        raise ArtifactError(f"{twin.artifact.name}: format version 9 is newer than supported")

    with pytest.raises(ConfigProblems) as info:
        check_config(path, artifact_check=artifact_check)
    assert has(info.value.problems, "twins[0].artifact", "format version 9")
    assert has(info.value.problems, "twins[1].artifact", "format version 9")


# -- the example ------------------------------------------------------------------------------


def test_example_config_loads() -> None:
    cfg = load_config(EXAMPLE)
    # SML2010's names: the README's commissioning path trains on that house's data.
    assert set(cfg.sensors) == {"dining/temp", "dining/co2", "room/temp", "room/co2"}
    temp, co2 = cfg.twins["room1-desk-temp"], cfg.twins["room1-desk-co2"]
    assert temp.quantity == "temperature" and co2.quantity == "co2"
    assert (temp.references, temp.target) == (("dining/temp",), "room/temp")
    assert (co2.references, co2.target) == (("dining/co2",), "room/co2")
    assert temp.artifact == EXAMPLE.parent / "artifacts" / "room1-desk-temp.json"
    assert cfg.state_dir == Path("/var/lib/pseudotwin")  # what the systemd unit provides
    assert cfg.sensors["dining/temp"].format == "json"
    assert cfg.sensors["dining/co2"].format == "number"
    assert cfg.hours.timezone == "Europe/Madrid"


def test_example_passes_check_once_artifacts_exist(tmp_path: Path) -> None:
    shutil.copy(EXAMPLE, tmp_path / "example.toml")
    with pytest.raises(ConfigProblems) as info:
        check_config(tmp_path / "example.toml")
    assert sorted(p.split(":")[0] for p in info.value.problems) == [
        "twins[0].artifact", "twins[1].artifact"]
    (tmp_path / "artifacts").mkdir()
    for name in ("room1-desk-temp.json", "room1-desk-co2.json"):
        (tmp_path / "artifacts" / name).write_text("{}")
    assert len(check_config(tmp_path / "example.toml").twins) == 2


# -- the command --------------------------------------------------------------------------------


def test_cli_ok(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, base_doc())
    (tmp_path / "artifacts").mkdir()
    for name in ("t.json", "c.json"):
        (tmp_path / "artifacts" / name).write_text("{}")
    assert check_config_main([str(path)]) == 0
    out = capsys.readouterr()
    assert out.out == f"{path}: OK (4 sensors, 2 twins)\n"
    assert out.err == ""


def test_cli_problems(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = base_doc()
    doc["sensors"][1]["topic"] = "b/#"
    path = write(tmp_path, doc)
    assert check_config_main([str(path)]) == 1
    out = capsys.readouterr()
    lines = out.err.splitlines()
    assert out.out == ""
    assert any(line.startswith(f"{path}: sensors[1].topic: ") for line in lines), lines
    assert all(line.startswith(f"{path}: ") for line in lines)
    assert "Traceback" not in out.err


@pytest.mark.parametrize("content", ["[broker\n", "a = 1\na = 2\n", b"\xff\xfe"])
def test_cli_unparseable(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                         content: str | bytes) -> None:
    path = tmp_path / "broken.toml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    assert check_config_main([str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"{path}: ")
    if isinstance(content, str):
        assert "line" in err and "column" in err
    assert "Traceback" not in err


def test_cli_missing_file_and_help(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert check_config_main([str(tmp_path / "nope.toml")]) == 2
    assert "no such file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        check_config_main(["--help"])
    assert info.value.code == 0
    assert "pseudotwin check-config" in capsys.readouterr().out


def test_a_duplicate_sensor_id_does_not_shadow_the_first(tmp_path: Path) -> None:
    """The CO2 sensor given the temperature sensor's id: its own error, and the temperature
    twin still judged by the first definition (not 'has unit ppm')."""
    doc = base_doc()
    doc["sensors"][3]["id"] = "r/hmi/temp"
    found = problems_of(tmp_path, doc)
    assert has(found, "sensors[3].id", "duplicate id 'r/hmi/temp' (first used by sensors[0])")
    assert not any("ppm" in p for p in found), found


def test_every_store_url_the_store_opens_is_a_valid_configuration(tmp_path: Path) -> None:
    """``crate+http://`` opened in ``import --store`` but was an unknown scheme in the
    configuration."""
    doc = base_doc()
    for url in ("crate://db:4200", "crate+http://db:4200", "crate+https://db:4200",
                "CRATE://db:4200", "postgresql://pt@db/history"):
        doc["service"]["store"] = url
        assert load_config(write(tmp_path, doc)).store == url
    doc["service"]["store"] = "mysql://db/history"
    assert has(problems_of(tmp_path, doc), "service.store", "unknown store URL scheme")
