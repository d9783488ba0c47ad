"""The broker fixture itself: a real round trip, and restarts that keep persistent sessions."""

from __future__ import annotations

import socket
import uuid

import pytest

from conftest import MosquittoBroker, MqttClientFactory


def _topic(name: str) -> str:
    return f"test/{name}/{uuid.uuid4().hex[:8]}"


def test_publish_subscribe_round_trip(mqtt_client: MqttClientFactory) -> None:
    topic = _topic("roundtrip")
    sub = mqtt_client()
    sub.subscribe(topic, qos=1)
    pub = mqtt_client()
    pub.publish(topic, b'{"ts": 1700000000, "value": 21.5}', qos=1)

    msg = sub.get(timeout=10)
    assert msg.topic == topic
    assert msg.payload == b'{"ts": 1700000000, "value": 21.5}'
    assert msg.qos == 1
    # exactly one delivery: the next message is a later one (the broker keeps a publisher's
    # order), not a copy of the first
    pub.publish(topic, b"after", qos=1)
    assert sub.get(timeout=10).payload == b"after"


def test_broker_listens_on_loopback_only_port(mosquitto: MosquittoBroker) -> None:
    assert mosquitto.host == "127.0.0.1"
    assert 0 < mosquitto.port < 65536
    with socket.create_connection((mosquitto.host, mosquitto.port), timeout=2):
        pass


def test_restart_keeps_port_and_queued_qos1_message_of_persistent_session(
    mosquitto: MosquittoBroker, mqtt_client: MqttClientFactory
) -> None:
    topic = _topic("persist")
    client_id = f"persist-{uuid.uuid4().hex[:8]}"
    offline = mqtt_client(client_id, clean_session=False)
    assert offline.session_present is False
    offline.subscribe(topic, qos=1)
    offline.disconnect()

    # Published while the subscriber is away: the broker must queue it for the session.
    mqtt_client().publish(topic, b"queued-while-offline", qos=1)

    port, pid = mosquitto.port, mosquitto.proc.pid if mosquitto.proc else None
    try:
        mosquitto.stop()
        assert not mosquitto.running
        with pytest.raises(OSError):
            socket.create_connection((mosquitto.host, port), timeout=1).close()
    finally:
        mosquitto.start()
    assert mosquitto.port == port
    assert mosquitto.proc is not None and mosquitto.proc.pid != pid

    back = mqtt_client(client_id, clean_session=False)
    assert back.session_present is True
    msg = back.get(timeout=10)
    assert (msg.topic, msg.payload, msg.qos) == (topic, b"queued-while-offline", 1)


def test_client_reconnects_after_broker_restart(
    mosquitto: MosquittoBroker, mqtt_client: MqttClientFactory
) -> None:
    topic = _topic("reconnect")
    client_id = f"reconnect-{uuid.uuid4().hex[:8]}"
    sub = mqtt_client(client_id, clean_session=False)
    sub.subscribe(topic, qos=1)
    assert sub.connects == 1

    mosquitto.restart()

    sub.wait_connects(2, timeout=15)  # paho's own reconnect, no new client
    assert sub.session_present is True  # the subscription survived; no re-subscribe needed
    pub = mqtt_client()
    pub.publish(topic, b"after-restart", qos=1)
    msg = sub.get(timeout=10)
    assert msg.payload == b"after-restart"
