"""The one way pseudotwin's long-running processes connect to the broker: paho 2.x with the
VERSION2 callbacks, QoS 1 subscriptions made in on_connect by the caller, a persistent session
under a stable client id, a retained last will on the process's status topic."""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from pseudotwin.config import BrokerConfig
from pseudotwin.edge.sdnotify import notify

log = logging.getLogger(__name__)

EX_NOPERM = 77  # sysexits: the broker refused our credentials; a restart will not help


def refused_fatally(reason_code: Any) -> tuple[int, str] | None:
    """(exit status, why) when a refused CONNACK will not change by retrying: bad user name
    or password, not authorized. None for refusals worth retrying (server unavailable)."""
    value = getattr(reason_code, "value", reason_code)
    if value in (4, 5, 134, 135):  # MQTT 3.1.1 CONNACK 4/5; MQTT 5 reason codes 0x86/0x87
        return EX_NOPERM, f"the broker refused the credentials ({reason_code})"
    return None


def log_connect_failures(broker: BrokerConfig) -> Any:
    """An ``on_connect_fail`` that logs every failed connection attempt with its reason
    (paho calls it inside its ``except OSError``, so the error is ``sys.exc_info()``'s),
    from the first one on; repeats of the same reason are logged once a minute."""
    last: dict[str, Any] = {"why": None, "at": 0.0, "n": 0}

    def on_connect_fail(client: mqtt.Client, userdata: Any) -> None:
        exc = sys.exc_info()[1]
        why = f"{type(exc).__name__}: {exc}" if exc is not None else "unknown reason"
        last["n"] += 1
        now = time.monotonic()
        if why != last["why"] or now - last["at"] >= 60:
            log.warning("cannot connect to the broker at %s:%d (%s); attempt %d, retrying "
                        "with backoff", broker.host, broker.port, why, last["n"])
            last["why"], last["at"] = why, now

    return on_connect_fail


#: Outgoing QoS 1 messages on their way to the broker at once (paho's default is 20).
MAX_INFLIGHT = 1000


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
    # paho sends at most 20 QoS 1 messages before their PUBACKs return, and queues the
    # rest. A grid tick of 1,000 twins hands it ~6,000 estimates at once: at 20 in flight,
    # the estimate of a reading arriving next waited seconds behind them.
    c.max_inflight_messages_set(MAX_INFLIGHT)
    c.on_connect_fail = log_connect_failures(broker)
    return c


#: The largest packet a broker must take from pseudotwin's clients [bytes] (README: Packet
#: size): subscriptions and claims go in pieces well below it; a monitor grows with its
#: twin's sensors.
BROKER_PACKET_BYTES = 16384

#: Disconnects within this long of the connect that count towards a session taken over [s],
#: and how many of them in TAKEOVER_WINDOW_S make the warning.
TAKEOVER_AFTER_S = 5.0
TAKEOVER_COUNT = 3
TAKEOVER_WINDOW_S = 120.0


def watch_takeover(client: mqtt.Client, client_id: str) -> None:
    """Warn when the broker keeps dropping ``client`` right after it connects: another
    client with the same id (a second daemon, recorder or bridge on one ``client_id``) takes
    the session over each time, and the log said only "disconnected; reconnecting".
    Call once the client's on_connect and on_disconnect are set: it wraps them."""
    on_connect, on_disconnect = client.on_connect, client.on_disconnect
    state: dict[str, Any] = {"up": None, "quick": [], "warned": -math.inf}

    def connected(*args: Any) -> None:
        # (client, userdata, flags, reason_code, properties): a refused CONNACK is followed
        # by on_disconnect at once, and is no session taken over
        refused = len(args) > 3 and getattr(args[3], "is_failure", False)
        state["up"] = None if refused else time.monotonic()
        if on_connect is not None:
            on_connect(*args)

    def disconnected(*args: Any) -> None:
        now, up = time.monotonic(), state["up"]
        state["up"] = None
        if up is not None and now - up < TAKEOVER_AFTER_S:
            state["quick"] = [t for t in state["quick"] if now - t < TAKEOVER_WINDOW_S] + [now]
            if (len(state["quick"]) >= TAKEOVER_COUNT
                    and now - state["warned"] >= TAKEOVER_WINDOW_S):
                state["warned"] = now
                log.warning("the broker dropped client id %r %d times within %g s of "
                            "connecting: another client with the same id probably takes the "
                            "session over each time (two processes on one broker.client_id? "
                            "give each its own), or the broker refuses a packet this client "
                            "sends (its max_packet_size below %d bytes? see its log)",
                            client_id, len(state["quick"]), TAKEOVER_AFTER_S,
                            BROKER_PACKET_BYTES)
        if on_disconnect is not None:
            on_disconnect(*args)

    client.on_connect = connected
    client.on_disconnect = disconnected


#: Topic bytes per SUBSCRIBE packet at most: a broker with a ``max_packet_size`` drops a
#: client that sends a larger packet, and one SUBSCRIBE of a fleet's thousands of sensor
#: topics (tens of kB) had the daemon reconnect for good.
SUBSCRIBE_BYTES = 8192


def subscribe_packets(topics: list[tuple[str, int]], limit: int = SUBSCRIBE_BYTES
                      ) -> list[list[tuple[str, int]]]:
    """``topics`` in consecutive groups of at most ``limit`` bytes each as a SUBSCRIBE
    packet's payload counts them (each topic's UTF-8 bytes, its 2-byte length and its QoS
    byte; a single longer topic goes alone)."""
    out: list[list[tuple[str, int]]] = []
    size = 0
    for topic, qos in topics:
        n = len(topic.encode()) + 3
        if not out or (out[-1] and size + n > limit):
            out.append([])
            size = 0
        out[-1].append((topic, qos))
        size += n
    return out


class Subscription:
    """The sensor topics a client subscribes to on every connect (in packets of at most
    SUBSCRIBE_BYTES); once the broker's SUBACKs are all back (at once when there are no
    topics) ``connected`` is set and, the first time, systemd hears READY=1: only then does
    a message published to them reach the client, so "connected" (READY=1, ``start``'s
    wait) means receiving. Topics the broker refused (its ACL) are logged as errors."""

    def __init__(self, topics: list[tuple[str, int]], connected: threading.Event) -> None:
        self.topics = topics
        self.connected = connected
        self._pending: dict[int, list[tuple[str, int]]] = {}  # SUBSCRIBE mid → its topics
        self._notified = False

    def ready(self) -> None:
        if not self._notified:
            self._notified = True
            notify("READY=1")  # once: a reconnect is no new start
        self.connected.set()

    def subscribe(self, client: mqtt.Client) -> None:
        self._pending = {}  # a reconnect: the earlier connection's SUBACKs will not come
        if not self.topics:  # a fleet instance may own no twin (paho refuses an empty list)
            self.ready()
            return
        for packet in subscribe_packets(self.topics):
            rc, mid = client.subscribe(packet)
            if rc != mqtt.MQTT_ERR_SUCCESS or mid is None:  # the connection went meanwhile:
                return  # the next connect subscribes again
            self._pending[mid] = packet

    def on_subscribe(self, client: mqtt.Client, userdata: Any, mid: int,
                     reason_codes: list[Any], properties: Any) -> None:
        topics = self._pending.pop(mid, None)
        if topics is None:
            return
        refused = [t for (t, _), rc in zip(topics, reason_codes, strict=False)
                   if rc.is_failure]
        if refused:
            log.error("the broker refused the subscription to %s (its ACL?): nothing "
                      "arrives on them", ", ".join(refused))
        if not self._pending:
            self.ready()


class StaleTopics:
    """Topics the broker's persistent session still delivers though no configured sensor has
    them any more (removed from the configuration, or its twin moved to another fleet
    instance): the session would deliver and queue their readings for good. Each is
    unsubscribed once, with one log line (tried again at its next message while the client
    is not connected); sensor topics have no wildcards, so unsubscribing one takes nothing
    else away. ``who``: the process, for the log ("daemon", "recorder")."""

    def __init__(self, who: str) -> None:
        self.who = who
        self._done: set[str] = set()

    def drop(self, client: mqtt.Client, topic: str) -> None:
        if topic in self._done:
            return
        rc, _ = client.unsubscribe(topic)
        if rc != mqtt.MQTT_ERR_SUCCESS:  # not connected: nothing was sent
            return
        self._done.add(topic)
        log.warning("%s: message on %s, which no configured sensor has (a sensor removed from "
                    "the configuration, still subscribed in the broker's session): ignored, "
                    "and the topic unsubscribed", self.who, topic)
