"""The one way pseudotwin's long-running processes connect to the broker: paho 2.x with the
VERSION2 callbacks, QoS 1 subscriptions made in on_connect by the caller, a persistent session
under a stable client id, a retained last will on the process's status topic."""

from __future__ import annotations

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from pseudotwin.config import BrokerConfig


def make_client(broker: BrokerConfig, client_id: str, status_topic: str,
                manual_ack: bool = True) -> mqtt.Client:
    """A configured, not yet connected client (connect with ``connect_async`` + loop_start)."""
    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=False,
                    manual_ack=manual_ack)
    c.will_set(status_topic, "offline", qos=1, retain=True)
    if broker.username:
        c.username_pw_set(broker.username, broker.password())
    if broker.tls:
        c.tls_set(ca_certs=str(broker.ca_file) if broker.ca_file else None)
    c.reconnect_delay_set(1, 30)
    return c
