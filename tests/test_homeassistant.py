"""Home Assistant MQTT discovery: the config section, the payloads, and the daemon publishing
and removing them on a real Mosquitto broker (checked against Home Assistant's documented
MQTT sensor schema: https://www.home-assistant.io/integrations/sensor.mqtt/)."""

from __future__ import annotations

import json
import logging
import re
import shutil
import uuid
from pathlib import Path

import jinja2
import pytest

from daemon_support import DAY, HOURS, off_grid, wait_for, write_config
from pseudotwin.config import ConfigProblems, load_config
from pseudotwin.config.model import HomeAssistantConfig
from pseudotwin.edge import homeassistant as ha
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.outputs import estimate_payload
from pseudotwin.edge.service import Service, output_topic
from pseudotwin.live.twin import Quality, TwinEstimate
from test_daemon import reading

# Options of an MQTT sensor in Home Assistant's documentation (full names; the payloads use
# no abbreviations), and of its device and origin blocks.
SENSOR_OPTIONS = {
    "availability", "availability_mode", "availability_template", "availability_topic",
    "default_entity_id", "device", "device_class", "enabled_by_default", "encoding",
    "entity_category", "entity_picture", "expire_after", "force_update", "icon",
    "json_attributes_template", "json_attributes_topic", "last_reset_value_template", "name",
    "object_id", "options", "origin", "payload_available", "payload_not_available", "platform",
    "qos", "state_class", "state_topic", "suggested_display_precision", "unique_id",
    "unit_of_measurement", "value_template",
}
DEVICE_OPTIONS = {"configuration_url", "connections", "hw_version", "identifiers",
                  "manufacturer", "model", "model_id", "name", "serial_number",
                  "suggested_area", "sw_version", "via_device"}
ORIGIN_OPTIONS = {"name", "sw_version", "support_url"}
UNITS_OF = {"temperature": {"°C", "°F", "K"}, "carbon_dioxide": {"ppm"}}
TOPIC_LEVEL = re.compile(r"[A-Za-z0-9_-]+")


def render_value(template: str, payload: bytes) -> str:
    """Home Assistant's rendering of a value template: Jinja2, its template engine, with the
    payload as ``value`` and its JSON as ``value_json`` (Jinja renders None as 'None', which
    the MQTT sensor takes as unknown)."""
    env = jinja2.Environment(undefined=jinja2.StrictUndefined)
    return env.from_string(template).render(value=payload.decode(),
                                            value_json=json.loads(payload))


def render_availability(template: str, value: str) -> str:
    return jinja2.Environment(undefined=jinja2.StrictUndefined).from_string(template).render(
        value=value)


def check_sensor_config(topic: str, body: dict, prefix: str) -> None:
    """Valid per Home Assistant's MQTT sensor schema, as this integration uses it."""
    levels = topic.split("/")
    assert levels[0] == prefix and levels[1] == "sensor" and levels[-1] == "config"
    assert len(levels) == 5 and all(TOPIC_LEVEL.fullmatch(x) for x in levels[2:4]), topic
    assert set(body) <= SENSOR_OPTIONS, set(body) - SENSOR_OPTIONS
    assert isinstance(body["state_topic"], str) and body["state_topic"]  # required
    assert isinstance(body["unique_id"], str) and body["unique_id"].startswith("pseudotwin_pt_")
    # Home Assistant's entity id rule (homeassistant.core.valid_entity_id): lower-case letters,
    # digits, single underscores, none at either end of the object id
    assert re.fullmatch(r"sensor\.(?!_)(?!.*__)[a-z0-9_]+(?<!_)", body["default_entity_id"])
    assert body["default_entity_id"].startswith("sensor.pseudotwin_pt_")
    assert body["state_class"] == "measurement"
    assert body["unit_of_measurement"] in UNITS_OF[body["device_class"]]
    assert isinstance(body["expire_after"], int) and body["expire_after"] > 0
    assert body["json_attributes_topic"] == body["state_topic"]
    assert body["availability_topic"] == "pt/status"
    assert body["qos"] in (0, 1, 2)
    assert isinstance(body["suggested_display_precision"], int)
    device = body["device"]
    assert set(device) <= DEVICE_OPTIONS
    assert isinstance(device["identifiers"], list) and device["identifiers"]
    assert all(isinstance(x, str) for x in device["identifiers"])
    assert device["manufacturer"] == "pseudotwin" and device["name"]
    assert set(body["origin"]) <= ORIGIN_OPTIONS and body["origin"]["name"]
    for status, shown in (("online", "online"), ("degraded", "online"),
                          ("offline", "offline")):
        assert render_availability(body["availability_template"], status) == shown
    assert body["payload_available"] == "online"
    assert body["payload_not_available"] == "offline"


def ha_config(folder: Path, port: int, artifact: Path, ha_table: str,
              extra_twin: Path | None = None, **service: object) -> Path:
    path = write_config(folder, port, artifact, **service)
    text = path.read_text(encoding="utf-8") + "\n" + ha_table + "\n"
    if extra_twin is not None:
        text += f"""
[[twins]]
id = "desk.two"
references = ["dining/temp"]
quantity = "temperature"
artifact = "{extra_twin}"
"""
    path.write_text(text, encoding="utf-8")
    return path


def start(path: Path) -> Service:
    svc = Service(load_config(path), clock=ReplayClock(off_grid(9.0), 1.0))
    svc.start(wait_connected=15)
    return svc


def drain(client, topic: str) -> dict[str, bytes]:
    """What ``client``, just subscribed to ``topic`` (a filter ending in ``/#``), got from the
    broker so far, in order (topic → latest payload): a marker published after the
    subscription ends it, as the broker hands a subscriber messages in order (its retained
    ones at the subscription)."""
    marker = f"{topic.removesuffix('#')}end-{uuid.uuid4().hex[:8]}"
    client.publish(marker, b"end")
    out: dict[str, bytes] = {}
    while (m := client.get(timeout=15)).topic != marker:
        out[m.topic] = m.payload
    return out


def retained(mqtt_client, topic: str, svc: Service | None = None) -> dict[str, bytes]:
    """What the broker keeps under ``topic`` (a filter ending in ``/#``): a new subscriber's
    retained messages, once every message the running daemon ``svc`` sent is acknowledged
    (it may publish just after ``start`` returns); an empty payload deletes
    (topic → payload)."""
    if svc is not None:
        wait_for(lambda: svc.unconfirmed() == 0, what="the daemon's messages acknowledged")
    c = mqtt_client()
    c.subscribe(topic)
    out = drain(c, topic)
    c.disconnect()
    return {t: p for t, p in out.items() if p}


# -- the config section -------------------------------------------------------------------
def test_section_defaults_and_absence(tmp_path, desk_artifact) -> None:
    cfg = load_config(write_config(tmp_path, 1883, desk_artifact))
    assert cfg.homeassistant == HomeAssistantConfig()
    assert cfg.homeassistant.enabled is False
    cfg = load_config(ha_config(tmp_path, 1883, desk_artifact, "[homeassistant]\nenabled = true"))
    assert cfg.homeassistant == HomeAssistantConfig(enabled=True)
    assert cfg.homeassistant.discovery_prefix == "homeassistant"


@pytest.mark.parametrize(("table", "problem"), [
    ("enabled = true\nbaseline = true",
     "homeassistant.baseline: unknown key (did you mean 'baselines'?)"),
    ('enabled = "yes"', "homeassistant.enabled: expected a boolean, got a string"),
    ("baselines = 1", "homeassistant.baselines: expected a boolean, got an integer"),
    ('discovery_prefix = "ha/#"', "homeassistant.discovery_prefix: 'ha/#' contains a wildcard"),
    ('discovery_prefix = "ha/"', "homeassistant.discovery_prefix: must not end with '/'"),
    ('discovery_prefix = ""', "homeassistant.discovery_prefix: must not be empty"),
])
def test_section_problems_are_config_errors(tmp_path, desk_artifact, table, problem) -> None:
    path = ha_config(tmp_path, 1883, desk_artifact, "[homeassistant]\n" + table)
    with pytest.raises(ConfigProblems) as err:
        load_config(path)
    assert any(p.startswith(problem) for p in err.value.problems), err.value.problems


def test_baseline_entities_without_baselines_are_a_config_error(tmp_path, desk_artifact
                                                                ) -> None:
    table = "[homeassistant]\nenabled = true\nbaselines = true"
    with pytest.raises(ConfigProblems, match='service.baselines = "none" runs no baselines'):
        load_config(ha_config(tmp_path, 1883, desk_artifact, table, baselines="none"))
    # the estimate's entity alone is fine, and so are baseline entities of run baselines
    load_config(ha_config(tmp_path, 1883, desk_artifact, "[homeassistant]\nenabled = true",
                          baselines="none"))
    load_config(ha_config(tmp_path, 1883, desk_artifact, table, baselines="grid"))


def test_twins_sharing_a_discovery_topic_are_a_config_error(tmp_path, desk_artifact) -> None:
    other = tmp_path / "two.json"
    shutil.copy(desk_artifact, other)
    path = ha_config(tmp_path, 1883, desk_artifact, "[homeassistant]\nenabled = true", other)
    text = path.read_text(encoding="utf-8").replace('id = "desk"', 'id = "desk_two"')
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigProblems, match="share one Home Assistant discovery topic"):
        load_config(path)
    # without discovery the same twins are fine
    path.write_text(text.replace("enabled = true", "enabled = false"), encoding="utf-8")
    assert set(load_config(path).twins) == {"desk_two", "desk.two"}


# -- payloads -----------------------------------------------------------------------------
def test_payloads_per_quantity() -> None:
    twins = [ha.TwinEntities("t.1", "temperature", "°C", "triv", ("ref", "corrgp-triv")),
             ha.TwinEntities("c", "co2", "ppm", "corrgp-triv", ("triv",))]
    msgs = ha.discovery_messages(twins, prefix="homeassistant", base_topic="pt",
                                 expire_after=1800, baselines=True)
    assert sorted(msgs) == [
        "homeassistant/sensor/pt/c_estimate/config",
        "homeassistant/sensor/pt/c_triv/config",
        "homeassistant/sensor/pt/t_1_corrgp-triv/config",
        "homeassistant/sensor/pt/t_1_estimate/config",
        "homeassistant/sensor/pt/t_1_ref/config",
    ]
    for topic, raw in msgs.items():
        check_sensor_config(topic, json.loads(raw), "homeassistant")
    co2 = json.loads(msgs["homeassistant/sensor/pt/c_estimate/config"])
    assert (co2["device_class"], co2["unit_of_measurement"]) == ("carbon_dioxide", "ppm")
    assert co2["state_topic"] == "pt/c/estimate"
    t = json.loads(msgs["homeassistant/sensor/pt/t_1_ref/config"])
    assert (t["device_class"], t["unit_of_measurement"]) == ("temperature", "°C")
    assert t["state_topic"] == "pt/t.1/baseline/ref"
    assert t["device"] == json.loads(msgs["homeassistant/sensor/pt/t_1_estimate/config"])[
        "device"]  # one device per twin
    no_baselines = ha.discovery_messages(twins, prefix="homeassistant", base_topic="pt",
                                         expire_after=1800, baselines=False)
    assert sorted(no_baselines) == ["homeassistant/sensor/pt/c_estimate/config",
                                    "homeassistant/sensor/pt/t_1_estimate/config"]
    assert ha.removals(msgs, no_baselines) == [
        "homeassistant/sensor/pt/c_triv/config", "homeassistant/sensor/pt/t_1_corrgp-triv/config",
        "homeassistant/sensor/pt/t_1_ref/config"]


def test_published_topics_are_remembered(tmp_path) -> None:
    assert ha.load_published(tmp_path) == set()
    ha.save_published(tmp_path / "state", ["ha/sensor/a/config", "ha/sensor/b/config",
                                           "ha/sensor/a/config"])
    assert ha.load_published(tmp_path / "state") == {"ha/sensor/a/config",
                                                     "ha/sensor/b/config"}
    (tmp_path / "state" / ha.STATE_FILE).write_text("{not json", encoding="utf-8")
    assert ha.load_published(tmp_path / "state") == set()


# -- the daemon on a real broker ----------------------------------------------------------
def test_discovery_messages_are_retained_valid_and_describe_real_payloads(
    tmp_path, mosquitto, mqtt_client, desk_artifact
) -> None:
    prefix = "ha-valid"
    path = ha_config(tmp_path, mosquitto.port, desk_artifact,
                     f'[homeassistant]\nenabled = true\ndiscovery_prefix = "{prefix}"\n'
                     "baselines = true", stale_after_minutes=20,
                     baselines="reading")  # a reading then shows every entity's payload
    svc = start(path)
    try:
        art = svc.twins["desk"].twin.artifact
        configs = {t: json.loads(p) for t, p in retained(mqtt_client, f"{prefix}/#", svc).items()}
        kinds = [k for k in art.published if k != art.primary]
        assert len(configs) == 1 + len(kinds) and kinds
        for topic, body in configs.items():
            check_sensor_config(topic, body, prefix)
            assert body["expire_after"] == 2 * 15 * 60  # two grid steps > stale_after
            assert body["device"]["name"] == "desk"
        by_state = {b["state_topic"]: b for b in configs.values()}
        assert set(by_state) == {"pt/desk/estimate", *(f"pt/desk/baseline/{k}" for k in kinds)}
        est = by_state["pt/desk/estimate"]
        assert (est["device_class"], est["unit_of_measurement"]) == ("temperature", "°C")
        # the topics really carry the daemon's payloads: a reading makes estimates, and the
        # value template gives a number, the attributes σ, quality and model
        viewer = mqtt_client()
        viewer.subscribe("pt/desk/#")
        pub = mqtt_client()
        # 17.5 °C: like the training mornings (else the quality is `uncertain`)
        pub.publish("house/dining/temp", reading(HOURS.at(DAY, 8.5), 17.5))
        seen: dict[str, bytes] = {}
        while not set(by_state) <= set(seen):
            m = viewer.get(timeout=20)
            if not m.retain and m.topic in by_state:
                seen[m.topic] = m.payload
        for state, body in by_state.items():
            value = float(render_value(body["value_template"], seen[state]))
            attrs = json.loads(seen[state])
            assert attrs["value"] == pytest.approx(value)
            assert attrs["std"] > 0 and attrs["quality"] == "ok" and attrs["unit"] == "°C"
        assert json.loads(seen["pt/desk/estimate"])["model"] == art.primary
        assert render_availability(est["availability_template"], "online") == "online"
    finally:
        svc.stop()


def test_a_twin_leaving_the_config_is_removed_from_home_assistant(
    tmp_path, mosquitto, mqtt_client, desk_artifact
) -> None:
    prefix = "ha-remove"
    other = tmp_path / "two.json"
    shutil.copy(desk_artifact, other)
    table = f'[homeassistant]\nenabled = true\ndiscovery_prefix = "{prefix}"'
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, table, other))
    svc.stop()
    before = retained(mqtt_client, f"{prefix}/#")
    gone = f"{prefix}/sensor/pt/desk_two_estimate/config"
    kept = f"{prefix}/sensor/pt/desk_estimate/config"
    assert set(before) == {kept, gone}
    assert json.loads(before[gone])["state_topic"] == "pt/desk.two/estimate"

    watcher = mqtt_client()
    watcher.subscribe(f"{prefix}/#")
    drain(watcher, f"{prefix}/#")  # drop the retained copies
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, table))  # desk.two gone
    try:
        live: dict[str, bytes] = {}
        while gone not in live or kept not in live:
            m = watcher.get(timeout=15)
            live[m.topic] = m.payload
        assert live[gone] == b""  # the empty retained payload deletes the entity
        check_sensor_config(kept, json.loads(live[kept]), prefix)
        assert set(retained(mqtt_client, f"{prefix}/#", svc)) == {kept}
    finally:
        svc.stop()

    # the section switched off: every entity this daemon published goes
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact,
                          "[homeassistant]\nenabled = false"))
    try:
        assert retained(mqtt_client, f"{prefix}/#", svc) == {}
    finally:
        svc.stop()


@pytest.mark.parametrize(("quality", "shown"), [
    (Quality.OK, "21.5"), (Quality.FALLBACK, "21.5"), (Quality.UNCERTAIN, "21.5"),
    (Quality.STALE, "None"),
])
def test_a_stale_estimate_is_unknown_in_home_assistant(quality: Quality, shown: str) -> None:
    """A stale estimate keeps its last value in the payload (with quality ``stale``), and the
    entity showed it as a current reading."""
    twin = ha.TwinEntities("desk", "temperature", "°C", "triv")
    body = ha.entity_config(twin, ha.ESTIMATE, base_topic="pt", expire_after=1800)
    e = TwinEstimate(HOURS.at(DAY, 9.0), 21.5, 0.3, "triv", quality)
    assert render_value(body["value_template"], estimate_payload(e, "°C")) == shown


def test_a_twin_leaving_the_config_takes_its_retained_estimates_with_it(
    tmp_path, mosquitto, mqtt_client, desk_artifact
) -> None:
    """A twin renamed or removed left its last estimate and baselines retained, quality `ok`,
    with `<base>/status` online: a controller still on the old id took them as current."""
    other = tmp_path / "two.json"
    shutil.copy(desk_artifact, other)
    off = "[homeassistant]\nenabled = false"
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, off, other))
    try:
        viewer = mqtt_client()
        viewer.subscribe("pt/+/estimate")
        mqtt_client().publish("house/dining/temp", reading(HOURS.at(DAY, 8.5), 17.5))
        seen: set[str] = set()
        # (other tests' twins may have estimates retained under pt/ too)
        while not {"pt/desk/estimate", "pt/desk.two/estimate"} <= seen:
            m = viewer.get(timeout=20)
            if m.payload:
                seen.add(m.topic)
    finally:
        svc.stop()
    kinds = [k for k in svc.twins["desk.two"].twin.kinds
             if k != svc.twins["desk.two"].twin.artifact.primary]
    assert kinds and "pt/desk.two/estimate" in retained(mqtt_client, "pt/desk.two/#")

    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, off))  # desk.two gone
    try:
        # its baselines too (they go out on the grid, which this test does not wait for)
        assert set(svc.unretain) == {"pt/desk.two/estimate",
                                     *(f"pt/desk.two/baseline/{k}" for k in kinds)}
        assert retained(mqtt_client, "pt/desk.two/#", svc) == {}
        assert "pt/desk/estimate" in retained(mqtt_client, "pt/desk/#", svc)
    finally:
        svc.stop()
    # cleared once, then forgotten: another daemon may publish under that id later
    assert ha.load_published(tmp_path / "state", "outputs.json", output_topic) \
        == set(svc.outputs)
    mqtt_client().publish("pt/desk.two/estimate", b'{"value": 1}', retain=True)
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, off))
    try:
        assert svc.unretain == []
        assert "pt/desk.two/estimate" in retained(mqtt_client, "pt/desk.two/#", svc)
    finally:
        svc.stop()



def test_remembered_topics_that_are_not_the_daemons_are_neither_cleared_nor_fatal(
    tmp_path, mosquitto, mqtt_client, desk_artifact, caplog
) -> None:
    """A damaged or planted outputs.json / homeassistant.json: a wildcard in it made paho
    raise in on_connect, which killed the network thread (the daemon stayed up, offline, and
    said nothing), and another service's retained topic would have been wiped."""
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.homeassistant")
    state = tmp_path / "state"
    state.mkdir()
    (state / "outputs.json").write_text(json.dumps({"published": [
        "pt/gone/estimate", "pt/+/estimate", "other/service/state", 7]}))
    (state / "homeassistant.json").write_text(json.dumps({"published": ["#"]}))
    mqtt_client().publish("other/service/state", b"keep me", retain=True)
    mqtt_client().publish("pt/gone/estimate", b'{"value": 1}', retain=True)
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact,
                          "[homeassistant]\nenabled = false"))
    try:
        assert svc.connected.is_set() and svc.unretain == ["pt/gone/estimate"]
        assert retained(mqtt_client, "pt/gone/#", svc) == {}
        assert retained(mqtt_client, "other/service/#", svc) == {"other/service/state": b"keep me"}
    finally:
        svc.stop()
    said = [r.getMessage() for r in caplog.records if "not topics this daemon" in r.getMessage()]
    assert len(said) == 2 and "'pt/+/estimate'" in said[0] + said[1] and "'#'" in said[0] + said[1]
    mqtt_client().publish("other/service/state", b"", retain=True)


def test_a_state_dir_of_a_release_without_outputs_json_says_what_it_cannot_clear(
    tmp_path, mosquitto, mqtt_client, desk_artifact, caplog
) -> None:
    """An upgrade from a release before outputs.json: a twin removed in the same change kept
    its retained estimate, `ok`, for good, and nothing said so."""
    off = "[homeassistant]\nenabled = false"
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.service")
    said = lambda: [r for r in caplog.records if "outputs.json is missing" in r.getMessage()]  # noqa: E731
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "daemon.lock").touch()  # a first start that failed early
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, off))
    try:  # a reading journaled: the state dir of a daemon that ran
        mqtt_client().publish("house/dining/temp", reading(HOURS.at(DAY, 8.5), 17.5))
        wait_for(lambda: svc.accepted == 1, what="a reading taken")
    finally:
        svc.stop()
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, off))  # remembered now
    svc.stop()
    assert not said()
    (tmp_path / "state" / "outputs.json").unlink()  # as an older release leaves the state
    svc = start(ha_config(tmp_path, mosquitto.port, desk_artifact, off))
    svc.stop()
    assert len(said()) == 1 and "mosquitto_pub -r -n -t pt/<twin>/estimate" in said()[0].message
    assert (tmp_path / "state" / "outputs.json").exists()  # and the next start knows
