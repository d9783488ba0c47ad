"""Publish stored readings to their MQTT topics on an accelerated clock (``pseudotwin replay``).

Each reading goes out when the replay clock reaches its timestamp, as JSON ``{"ts", "value"}``
(or the sensor's configured format), QoS 1 — what a PLC bridge would have sent live.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import secrets
import threading

import paho.mqtt.client as mqtt
import pandas as pd
from paho.mqtt.enums import CallbackAPIVersion

from pseudotwin.config import ServiceConfig
from pseudotwin.edge.clock import Clock, ReplayClock
from pseudotwin.errors import BrokerError, DataError

log = logging.getLogger(__name__)

PUBLISH_TIMEOUT_S = 30.0  # a reading the broker has not acknowledged by then is lost to it


def payload_for(fmt: str, ts_key: str, value_key: str, ts: dt.datetime, value: float) -> bytes:
    if fmt == "number":
        return repr(float(value)).encode()
    body: dict[str, float | str] = {value_key: value}
    if ts_key:
        body[ts_key] = ts.isoformat()
    return json.dumps(body).encode()


def replay(
    cfg: ServiceConfig,
    history: pd.DataFrame,
    start: dt.datetime,
    end: dt.datetime,
    speed: float,
    stop: threading.Event | None = None,
    client_id: str | None = None,
    clock: Clock | None = None,
    hold: bool = False,
) -> int:
    """Publish readings with start ≤ ts < end; returns how many were published.

    hold: return only when the clock reaches ``end``, not at the last reading, so that a
    daemon on the same time line has done the span's grid work by then (the CLI's way).

    client_id: default the configuration's with ``-replay-<pid>-<random>``: a second
    replay, or the daemon itself, must not take over this one's session.

    clock: what publishes each reading at its time (default: a ReplayClock from ``start``
    at ``speed``). An in-process daemon's own clock puts both on one time line: with two
    clocks, the daemon's runs ahead by however long the replay took to start (at 3000×,
    0.1 s is 5 minutes), and its grid ticks see readings that late.
    """
    stop = stop or threading.Event()
    known = {s.id: s for s in cfg.sensors.values()}
    sub = history[history["sensor"].isin(list(known)) & (history["ts"] >= start)
                  & (history["ts"] < end)].sort_values("ts", kind="stable")
    if sub.empty:
        raise DataError(f"no readings of the configured sensors between {start} and {end}")
    # A bare number carries no instant: a daemon in replay mode stamps it on its own replay
    # clock, but a recorder stamps it on the real one, so the store took replayed
    # commissioning days of such a sensor at today's time, and train --config missed them.
    if unstamped := sorted(s for s in set(sub["sensor"]) if not known[s].stamped):
        log.warning("replay: sensor(s) %s have no timestamp of their own (format = "
                    "\"number\" or no ts_key): a daemon in replay mode stamps their readings "
                    "on its replay clock, but `record` stamps them on arrival, at today's "
                    "time, not the replayed one (to store them, import the history instead)",
                    ", ".join(unstamped))
    # PID and a random part: in containers every replay may be PID 1
    client_id = client_id or f"{cfg.broker.client_id}-replay-{os.getpid()}-{secrets.token_hex(2)}"
    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=True)
    if cfg.broker.username:
        c.username_pw_set(cfg.broker.username, cfg.broker.password())
    if cfg.broker.tls:
        c.tls_set(ca_certs=str(cfg.broker.ca_file) if cfg.broker.ca_file else None)
    try:
        c.connect(cfg.broker.host, cfg.broker.port, keepalive=30)
    except OSError as exc:  # refused, unknown host, unreachable network, timeout
        raise BrokerError(f"MQTT broker {cfg.broker.host}:{cfg.broker.port} unreachable: "
                          f"{exc.strerror or exc}") from None
    c.loop_start()
    clock = clock or ReplayClock(start, speed)
    n = 0
    try:
        for sensor, ts, value in zip(sub["sensor"], sub["ts"], sub["value"], strict=True):
            t = ts.to_pydatetime()
            if not clock.wait_until(t, stop):
                break
            s = known[sensor]
            info = c.publish(s.topic, payload_for(s.format, s.ts_key, s.value_key, t, value),
                             qos=1)
            try:
                info.wait_for_publish(timeout=PUBLISH_TIMEOUT_S)
                why = "" if info.is_published() else f"not acknowledged in {PUBLISH_TIMEOUT_S:g} s"
            except (RuntimeError, ValueError) as exc:  # paho: not connected, or queue full
                why = str(exc)
            if why:
                raise BrokerError(
                    f"lost the broker {cfg.broker.host}:{cfg.broker.port} after {n} readings "
                    f"({why}); the rest, from {t.isoformat()} on, were not published: rerun "
                    f"with --start {t.isoformat()} (readings at that instant may go twice; "
                    "the daemon drops repeats)")
            n += 1
        if hold:  # returns at once when stopped
            clock.wait_until(end, stop)
    finally:
        c.disconnect()
        c.loop_stop()
    log.info("replayed %d readings from %s to %s at %g×", n, start, end, speed)
    return n
