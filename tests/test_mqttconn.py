"""The shared MQTT client set-up (edge/mqttconn.py), on real paho clients."""

from __future__ import annotations

import logging

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.reasoncodes import ReasonCode

from pseudotwin.edge.mqttconn import TAKEOVER_COUNT, watch_takeover


def _cycle(client: mqtt.Client, connack: str, times: int) -> None:
    """What paho calls for ``times`` connects answered ``connack``, each dropped at once."""
    for _ in range(times):
        client.on_connect(client, None, None, ReasonCode(PacketTypes.CONNACK, connack), None)
        client.on_disconnect(client, None, None,
                             ReasonCode(PacketTypes.DISCONNECT, "Unspecified error"), None)


def test_a_session_taken_over_is_named_and_a_refused_connect_is_not(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """paho calls on_disconnect right after a refused CONNACK: three refusals ("server
    unavailable") read as "another client with the same id" before."""
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.mqttconn")
    seen: list[str] = []
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="pt-x")
    client.on_connect = lambda *a: seen.append("connect")
    client.on_disconnect = lambda *a: seen.append("disconnect")
    watch_takeover(client, "pt-x")
    _cycle(client, "Server unavailable", TAKEOVER_COUNT + 1)
    assert "same id" not in caplog.text
    assert seen == ["connect", "disconnect"] * (TAKEOVER_COUNT + 1)  # still called
    _cycle(client, "Success", TAKEOVER_COUNT)
    assert caplog.text.count("another client with the same id") == 1
    assert "'pt-x'" in caplog.text
