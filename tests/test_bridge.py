"""The PLC bridge against pyads' own ADS test server and a real Mosquitto broker.

The PLC is ``pyads.testserver.AdsTestServer`` with an ``AdvancedHandler``: real AMS/ADS
frames over TCP on 127.0.0.1:48898 through pyads' own router (adslib), not a mock. What that
server cannot do, and what the tests do about it:

- It never sends ADS DEVICE_NOTIFICATION frames. When a variable is written (here by a
  second pyads client, over TCP), it calls the callbacks the clients registered in pyads'
  ``callback_store`` directly, in the same process. So the bridge runs inside the test
  process, and what is tested is: the add-notification request over TCP, the bridge's
  callback decoding the notification header (value and FILETIME stamp), the queue, MQTT.
  How adslib receives real notification frames is not covered here.
- Each ``PLCVariable`` numbers its notification handles from 10, so two variables would
  both hand out handle 10, and pyads' ``callback_store`` (keyed by address and handle) would
  keep one callback for both. Every variable here gets its own handle range.
- Its notifications cannot be addressed by symbol handle, only by index group/offset. The
  bridge registers by index group/offset (as pyads' ``AdsSymbol`` does).
- It stamps notifications with its wall clock truncated to whole seconds. The tests use
  that: a reading with microsecond 0 carries the PLC's stamp, not the arrival time.
- For an unknown name, ``AdvancedHandler`` raises KeyError in its connection thread, which
  kills that connection without an answer (the client sees a timeout). A TwinCAT runtime
  answers ADS error 0x710 "symbol not found"; :class:`PlcHandler` does the same.
- It always reports RUN. :class:`PlcHandler` makes the state settable, like a PLC's
  Stop/Run buttons.
- pyads' router shares one TCP connection per PLC address among all connections of a
  process (reference-counted). A second client held open across a server restart would
  keep the dead connection alive for the bridge too, so the writer here opens a
  connection per write.

Nothing waits on timing: every wait polls a condition with a deadline.
"""

from __future__ import annotations

import ctypes
import datetime as dt
import json
import logging
import math
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pyads
import pytest
from pyads import constants as adsc
from pyads.filetimes import dt_to_filetime
from pyads.pyads_ex import callback_store
from pyads.testserver import AdsTestServer, AdvancedHandler, PLCVariable
from pyads.testserver.handler import AmsPacket, AmsResponseData

import pseudotwin.edge.bridge.plc as plc_module
from conftest import MosquittoBroker, MqttClientFactory, TestClient, closed_port
from pseudotwin.cli.bridge import EX_CONFIG, main
from pseudotwin.config import ConfigProblems
from pseudotwin.edge.bridge import (
    ADSERR_SYMBOL_NOT_FOUND,
    Bridge,
    BridgeConfig,
    SymbolConfig,
    filetime_to_utc,
    load_bridge_config,
)
from pseudotwin.edge.replay import payload_for

ROOT = Path(__file__).resolve().parent.parent
ADS_HOST = "127.0.0.1"
ADS_NET_ID = "127.0.0.1.1.1"  # pyads' router derives this host's net id the same way
ADS_TCP_PORT = 48898  # fixed in pyads' router: a PLC always listens here
AMS_PORT = 851
DEADLINE = 20.0  # s; generous, only reached when something is broken

# name, PLC type (IEC name, ADS type id, pyads type), initial value
VARIABLES = (
    ("MAIN.fRoomTemp", "LREAL", adsc.ADST_REAL64, pyads.PLCTYPE_LREAL, 21.5),
    ("MAIN.iCeilingTemp", "INT", adsc.ADST_INT16, pyads.PLCTYPE_INT, 215),  # 0.1 °C
    ("MAIN.nCo2", "DINT", adsc.ADST_INT32, pyads.PLCTYPE_DINT, 450),
)
CTYPE = {name: ctype for name, _, _, ctype, _ in VARIABLES}


# -- the PLC -------------------------------------------------------------------------------


class PlcHandler(AdvancedHandler):
    """AdvancedHandler plus two things a TwinCAT runtime does: it answers an unknown symbol
    name with ADS error 0x710 (instead of dropping the connection), and its ADS state can
    be set (``ads_state``), as with the PLC's Stop/Run."""

    def __init__(self) -> None:
        super().__init__()
        self.ads_state = adsc.ADSSTATE_RUN
        self.answers = True  # False: like a PLC without a route back, it never answers
        # Set: like a TwinCAT runtime, the current value is notified at registration,
        # stamped on this PLC clock (a function returning the instant)
        self.notify_at_registration: Callable[[], dt.datetime] | None = None

    @staticmethod
    def _reply(request: AmsPacket, data: bytes) -> AmsResponseData:
        flags = struct.unpack("<H", request.ams_header.state_flags)[0] | 0x0001  # response
        return AmsResponseData(struct.pack("<H", flags), request.ams_header.error_code, data)

    def handle_request(self, request: AmsPacket) -> AmsResponseData:
        command = struct.unpack("<H", request.ams_header.command_id)[0]
        if not self.answers:
            raise KeyError("no route")  # the connection thread ends without an answer
        if command == adsc.ADSCOMMAND_READSTATE:
            return self._reply(request, struct.pack("<IHH", 0, self.ads_state, 0))
        if (command == adsc.ADSCOMMAND_ADDDEVICENOTE
                and self.notify_at_registration is not None):
            response = super().handle_request(request)
            group, offset = struct.unpack("<II", request.ams_header.data[:8])
            var = self.get_variable_by_indices(group, offset)
            handle = var.notifications[-1]
            threading.Thread(target=self._first_notification,
                             args=(var, handle, self.notify_at_registration()),
                             daemon=True).start()
            return response
        try:
            return super().handle_request(request)
        except KeyError:
            if command != adsc.ADSCOMMAND_READWRITE:  # name lookups are READWRITEs
                raise
            # result code + length of the (empty) read data
            return self._reply(request, struct.pack("<II", ADSERR_SYMBOL_NOT_FOUND, 0))


    @staticmethod
    def _first_notification(var: PLCVariable, handle: int, stamp: dt.datetime) -> None:
        """Deliver the registration's notification as the test server delivers a write's
        (module doc), once pyads has stored the client's callback for the handle."""
        deadline = time.monotonic() + DEADLINE
        while time.monotonic() < deadline:
            found = [(k, f) for k, f in list(callback_store.items()) if k[1] == handle]
            if found:
                break
            time.sleep(0.005)  # poll interval, not a timing assumption
        else:
            return
        header = pyads.structs.SAdsNotificationHeader()
        header.hNotification = handle
        header.nTimeStamp = dt_to_filetime(stamp)
        header.cbSampleSize = len(var.value)
        ctypes.memmove(ctypes.addressof(header) + pyads.structs.SAdsNotificationHeader.data.offset,
                       var.value, len(var.value))
        for (addr, _), func in found:
            func(addr.amsAddrStruct(), header, 0)


class Plc:
    """pyads' AdsTestServer on 127.0.0.1:48898, restartable with the same variables."""

    def __init__(self) -> None:
        self.handler = PlcHandler()
        for k, (name, iec, ads_type, _ctype, value) in enumerate(VARIABLES):
            var = PLCVariable(name, value, ads_type, iec)
            var.notification_count = 1000 * (k + 1)  # own handle range, see module doc
            self.handler.add_variable(var)
        self.server: AdsTestServer | None = None

    def start(self) -> None:
        try:
            self.server = AdsTestServer(handler=self.handler, ip_address=ADS_HOST,
                                        port=ADS_TCP_PORT, logging=False)
        except OSError as exc:
            pytest.fail(f"cannot listen on {ADS_HOST}:{ADS_TCP_PORT} for pyads' ADS test "
                        f"server: {exc}", pytrace=False)
        self.server.start()
        # The server thread starts listening only once it runs.
        deadline = time.monotonic() + DEADLINE
        while True:
            try:
                with socket.create_connection((ADS_HOST, ADS_TCP_PORT), timeout=0.5):
                    return
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.01)  # poll interval, not a timing assumption

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()  # closes every client connection: the route drops
            self.server.join(timeout=5)
            self.server = None

    def variable(self, name: str) -> PLCVariable:
        return self.handler.get_variable_by_name(name)

    def write(self, name: str, value: float) -> dt.datetime:
        """Write like an HMI would, over ADS; returns the instant just before the write."""
        before = dt.datetime.now(dt.UTC)
        with pyads.Connection(ADS_NET_ID, AMS_PORT, ADS_HOST) as c:
            c.write_by_name(name, value, CTYPE[name])
        return before


@pytest.fixture(name="plc")  # a name of its own: tests/test_bridge_spool.py imports it
def plc_fixture() -> Iterator[Plc]:
    p = Plc()
    p.start()
    try:
        yield p
    finally:
        p.stop()


# -- configuration and helpers -----------------------------------------------------------


def _symbols_toml(symbols: list[dict[str, Any]]) -> str:
    out = []
    for s in symbols:
        out.append("[[plc.symbols]]")
        out += [f"{k} = {json.dumps(v)}" for k, v in s.items()]
    return "\n".join(out)


DEFAULT_SYMBOLS = [
    {"symbol": "MAIN.fRoomTemp", "sensor": "hmi/temp", "plc_type": "LREAL"},
    {"symbol": "MAIN.iCeilingTemp", "sensor": "ceiling/temp", "plc_type": "INT", "scale": 0.1},
    {"symbol": "MAIN.nCo2", "sensor": "ceiling/co2", "plc_type": "dint"},
]



class Env:
    """One test's topics, config file and MQTT subscriber."""

    def __init__(self, tmp_path: Path, broker: MosquittoBroker) -> None:
        tag = uuid.uuid4().hex[:8]
        self.tmp_path = tmp_path
        self.broker = broker
        self.base = f"test/bridge-{tag}"
        self.client_id = f"bridge-{tag}"
        sensors = f"test/room-{tag}"  # not under base: the daemon publishes there
        self.topics = {
            "hmi/temp": f"{sensors}/hmi/temp",
            "ceiling/temp": f"{sensors}/ceiling/temp",
            "ceiling/co2": f"{sensors}/ceiling/co2",
        }

    def config_text(self, symbols: list[dict[str, Any]] | None = None, **plc: Any) -> str:
        plc_values = {"ams_net_id": ADS_NET_ID, "host": ADS_HOST, "port": AMS_PORT,
                      # Small poll and backoff so that a dropped link is seen within
                      # about a second; the timeout bounds the first failing request.
                      "poll_seconds": 0.2, "reconnect_max_seconds": 1, "timeout_seconds": 1,
                      **plc}
        return "\n".join([
            "[broker]",
            f'host = "{self.broker.host}"',
            f"port = {self.broker.port}",
            f'client_id = "{self.client_id}-daemon"',
            "[bridge]",
            f'client_id = "{self.client_id}"',
            f'base_topic = "{self.base}"',
            "[[sensors]]",
            'id = "hmi/temp"',
            f'topic = "{self.topics["hmi/temp"]}"',
            'unit = "°C"', "min = -10", "max = 50",
            "[[sensors]]",
            'id = "ceiling/temp"',
            f'topic = "{self.topics["ceiling/temp"]}"',
            'unit = "°C"', "min = -10", "max = 50",
            "[[sensors]]",
            'id = "ceiling/co2"',
            f'topic = "{self.topics["ceiling/co2"]}"',
            'format = "number"',
            'unit = "ppm"', "min = 0", "max = 5000",
            "[plc]",
            *(f"{k} = {json.dumps(v)}" for k, v in plc_values.items()),
            _symbols_toml(DEFAULT_SYMBOLS if symbols is None else symbols),
            "",
        ])

    def write_config(self, symbols: list[dict[str, Any]] | None = None, **plc: Any) -> Path:
        path = self.tmp_path / "bridge.toml"
        path.write_text(self.config_text(symbols, **plc), encoding="utf-8")
        return path

    def config(self, symbols: list[dict[str, Any]] | None = None, **plc: Any) -> BridgeConfig:
        return load_bridge_config(self.write_config(symbols, **plc))


@pytest.fixture(name="env")
def env_fixture(tmp_path: Path, mosquitto: MosquittoBroker) -> Env:
    if not mosquitto.running:
        mosquitto.start()
    return Env(tmp_path, mosquitto)


class Inbox:
    """Every message a subscriber received, searchable by topic without losing others."""

    def __init__(self, client: TestClient) -> None:
        self.client = client
        self.seen: list[mqtt.MQTTMessage] = []
        self.used: set[int] = set()

    def wait(self, topic: str, match: Callable[[bytes], bool] = lambda p: True,
             timeout: float = DEADLINE) -> bytes:
        """The first unused payload on ``topic`` that matches; waits up to ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            for i, msg in enumerate(self.seen):
                if i not in self.used and msg.topic == topic and match(msg.payload):
                    self.used.add(i)
                    return msg.payload
            left = deadline - time.monotonic()
            if left <= 0:
                got = [(m.topic, m.payload) for m in self.seen]
                raise AssertionError(f"no matching message on {topic!r} within {timeout} s; "
                                     f"received: {got}")
            try:
                self.seen.append(self.client.get(timeout=min(left, 0.5)))
            except Exception:  # noqa: BLE001 - queue.Empty: look again until the deadline
                pass


def _value(payload: bytes) -> float:
    return float(json.loads(payload)["value"])


def _ts(payload: bytes) -> dt.datetime:
    return dt.datetime.fromisoformat(json.loads(payload)["ts"])


def _is(value: float) -> Callable[[bytes], bool]:
    def match(payload: bytes) -> bool:
        body = json.loads(payload)
        number = body["value"] if isinstance(body, dict) else body
        return abs(float(number) - value) < 1e-9
    return match


def _wait_for(condition: Callable[[], bool], what: str, timeout: float = DEADLINE) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        time.sleep(0.02)  # poll interval, not a timing assumption


@contextmanager
def running(bridge: Bridge) -> Iterator[Bridge]:
    bridge.start()
    try:
        yield bridge
    finally:
        bridge.stop()


class FixedClock:
    """The bridge's clock frozen at one instant: the initial values carry exactly it."""

    def __init__(self, instant: dt.datetime) -> None:
        self.instant = instant

    def now(self) -> dt.datetime:
        return self.instant

    def wait_until(self, instant: dt.datetime, stop: threading.Event) -> bool:
        return not stop.is_set()


def _subscribe(mqtt_client: MqttClientFactory, env: Env, **kwargs: Any) -> Inbox:
    sub = mqtt_client(**kwargs)
    for topic in (*env.topics.values(), f"{env.base}/bridge/#"):
        sub.subscribe(topic, qos=1)
    return Inbox(sub)


def _wait_initial(inbox: Inbox, env: Env) -> None:
    inbox.wait(env.topics["hmi/temp"], _is(21.5))
    inbox.wait(env.topics["ceiling/temp"], _is(21.5))
    inbox.wait(env.topics["ceiling/co2"], _is(450))


# -- tests: readings ---------------------------------------------------------------------


def test_initial_values_then_changes_are_published_with_the_plc_timestamp(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory
) -> None:
    inbox = _subscribe(mqtt_client, env)
    start = dt.datetime.now(dt.UTC).replace(microsecond=123456)
    with running(Bridge(env.config(), clock=FixedClock(start))) as bridge:
        # After connect: every symbol's current value, stamped with the bridge's clock.
        first = inbox.wait(env.topics["hmi/temp"])
        assert json.loads(first) == {"value": 21.5, "ts": start.isoformat()}
        scaled = inbox.wait(env.topics["ceiling/temp"])
        assert _value(scaled) == pytest.approx(21.5)  # INT 215 × scale 0.1
        assert _ts(scaled) == start
        assert inbox.wait(env.topics["ceiling/co2"]) == b"450.0"  # format "number"
        assert inbox.wait(f"{env.base}/bridge/status") == b"online"
        assert inbox.wait(f"{env.base}/bridge/plc", lambda p: p == b"up")
        assert bridge.plc_up.is_set()

        # A change on the PLC: one reading, stamped by the PLC (ADS FILETIME).
        before = plc.write("MAIN.fRoomTemp", 22.25)
        payload = inbox.wait(env.topics["hmi/temp"])
        assert _value(payload) == 22.25
        ts = _ts(payload)
        assert ts.utcoffset() == dt.timedelta(0)
        # The test server stamps whole seconds of its wall clock; the bridge's own clock is
        # frozen at ``start``, so this can only be the PLC's stamp.
        assert ts.microsecond == 0 and ts != start
        assert before - dt.timedelta(seconds=1) <= ts <= dt.datetime.now(dt.UTC)

        plc.write("MAIN.iCeilingTemp", 231)
        assert _value(inbox.wait(env.topics["ceiling/temp"])) == pytest.approx(23.1)
        plc.write("MAIN.nCo2", 612)
        assert inbox.wait(env.topics["ceiling/co2"]) == b"612.0"
        assert bridge.dropped == 0 and bridge.decode_errors == 0


def test_stop_deletes_notifications_and_publishes_offline(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory
) -> None:
    inbox = _subscribe(mqtt_client, env)
    bridge = Bridge(env.config())
    with running(bridge):
        _wait_initial(inbox, env)
        assert all(plc.variable(name).notifications for name, *_ in VARIABLES)
    # stop() deleted every notification on the PLC (ADS requests), then went offline.
    assert not any(plc.variable(name).notifications for name, *_ in VARIABLES)
    assert inbox.wait(f"{env.base}/bridge/status", lambda p: p == b"offline")
    assert bridge.finished.is_set() and bridge.fatal is None
    # what a later subscriber finds retained: not the PLC "up" of a bridge that stopped
    late = _subscribe(mqtt_client, env)
    assert late.wait(f"{env.base}/bridge/plc") == b"down"


def test_filetime_conversion_keeps_microseconds() -> None:
    stamp = dt.datetime(2024, 5, 13, 6, 15, 0, 123456, tzinfo=dt.UTC)
    ticks = int((stamp - dt.datetime(1601, 1, 1, tzinfo=dt.UTC)).total_seconds()) * 10**7 \
        + stamp.microsecond * 10 + 7  # 700 ns below a microsecond are dropped
    assert filetime_to_utc(ticks) == stamp


# -- tests: configuration problems -------------------------------------------------------


@pytest.mark.parametrize(("plc_type", "raw", "scale", "offset", "text"), [
    ("INT", 219, 0.1, 0.0, b"21.9"),  # not 21.900000000000002
    ("REAL", struct.unpack("<f", struct.pack("<f", 21.3))[0], 1.0, 0.0, b"21.3"),
    ("REAL", struct.unpack("<f", struct.pack("<f", 2953.1))[0], 0.1, -273.15, b"22.16"),
    ("LREAL", 21.123456789012344, 1.0, 0.0, b"21.123456789012344"),  # every digit kept
    ("DINT", 450, 1.0, 0.0, b"450.0"),
])
def test_readings_carry_the_plcs_digits_not_binary_noise(
        plc_type: str, raw: float, scale: float, offset: float, text: bytes) -> None:
    """A scaled INT 219 went out as 21.900000000000002 and a REAL 21.3 as
    21.299999237060547: a subscriber logging or comparing values saw noise."""
    sym = SymbolConfig(symbol="MAIN.x", sensor="s", plc_type=plc_type, scale=scale,
                       offset=offset)
    ts = dt.datetime(2026, 1, 5, 8, tzinfo=dt.UTC)
    assert payload_for("number", "", "", ts, sym.convert(raw)) == text
    assert b'"value": ' + text in payload_for("json", "ts", "value", ts, sym.convert(raw))


def test_a_flickering_nan_is_counted_and_logged_sparingly(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """A wire break flickering between NaN and a value logged one warning per NaN, without
    end, and the stop's summary did not count them."""
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.bridge")
    inbox = _subscribe(mqtt_client, env)
    with running(Bridge(env.config())) as bridge:
        _wait_initial(inbox, env)
        for i in range(6):
            plc.write("MAIN.fRoomTemp", math.nan)
            plc.write("MAIN.fRoomTemp", 22.0 + i)
            inbox.wait(env.topics["hmi/temp"], _is(22.0 + i))  # the values in between go out
        assert bridge.not_finite == 6
    warned = [r.getMessage() for r in caplog.records if "is nan; not published" in r.message]
    assert [w.split("not published ")[1] for w in warned] == [
        f"({n} such value(s) of it so far)" for n in (1, 2, 4)]
    assert "6 not a number (not published)" in caplog.text


def test_unknown_symbol_and_wrong_type_are_configuration_errors(
    plc: Plc, env: Env, capsys: pytest.CaptureFixture[str]
) -> None:
    path = env.write_config([
        {"symbol": "MAIN.fRoomTemp", "sensor": "hmi/temp", "plc_type": "LREAL"},
        {"symbol": "MAIN.fNoSuchTemp", "sensor": "ceiling/temp", "plc_type": "LREAL"},
        {"symbol": "MAIN.nCo2", "sensor": "ceiling/co2", "plc_type": "REAL"},
    ])
    assert main(["--config", str(path)]) == EX_CONFIG
    err = capsys.readouterr().err
    assert (f"{path}: plc.symbols[1].symbol: 'MAIN.fNoSuchTemp' is not a symbol of the PLC "
            f"at {ADS_NET_ID}:{AMS_PORT}") in err
    assert (f"{path}: plc.symbols[2].plc_type: configured REAL, but the PLC declares "
            "'MAIN.nCo2' as DINT (4 bytes)") in err
    assert "plc.symbols[0]" not in err
    # It gave up before registering anything.
    assert not any(plc.variable(name).notifications for name, *_ in VARIABLES)


def test_bridge_reports_symbol_problems_as_fatal(plc: Plc, env: Env) -> None:
    cfg = env.config([{"symbol": "MAIN.iCeilingTemp", "sensor": "ceiling/temp",
                       "plc_type": "UINT"}])
    bridge = Bridge(cfg)
    with running(bridge):
        assert bridge.finished.wait(DEADLINE)
    assert bridge.fatal is not None
    assert bridge.fatal.problems == [
        "plc.symbols[0].plc_type: configured UINT, but the PLC declares 'MAIN.iCeilingTemp' "
        'as INT (2 bytes); set plc_type = "INT" if that is right'
    ]


def test_a_time_symbol_is_not_taken_for_a_number(plc: Plc, env: Env) -> None:
    """A TIME is a UDINT on the wire: the alias rule passed it, and its milliseconds went out
    as readings."""
    delay = PLCVariable("MAIN.tDelay", 5000, adsc.ADST_UINT32, "TIME")
    delay.notification_count = 9000  # a handle range of its own, as the others'
    plc.handler.add_variable(delay)
    bridge = Bridge(env.config([{"symbol": "MAIN.tDelay", "sensor": "ceiling/co2",
                                 "plc_type": "UDINT"}]))
    with running(bridge):
        assert bridge.finished.wait(DEADLINE)
    assert bridge.fatal is not None
    assert bridge.fatal.problems == [
        "plc.symbols[0].plc_type: configured UDINT, but the PLC declares 'MAIN.tDelay' as "
        "TIME, which is not a reading (a duration, date or bit string)"]


def test_configuration_file_problems_are_located_with_suggestions(
    env: Env, capsys: pytest.CaptureFixture[str]
) -> None:
    text = env.config_text([
        {"symbol": "MAIN.a", "sensor": "hmi/tmep", "plc_type": "LRAEL"},
        {"symbol": "main.A", "sensor": "ceiling/co2", "plc_type": "STRING", "cycle": 5},
        {"symbol": "MAIN.b", "sensor": "ceiling/co2", "plc_type": "INT", "scale": 0},
    ], ams_net_id="127.0.0.1.1", poll_seconds=0.01, host="10.0.0.7:851")
    path = env.tmp_path / "bad.toml"
    path.write_text(text.replace("[bridge]", "[bridge]\nqueue_sise = 5"), encoding="utf-8")
    with pytest.raises(ConfigProblems) as caught:
        load_bridge_config(path)
    problems = caught.value.problems
    for expected in (
        "bridge.queue_sise: unknown key (did you mean 'queue_size'?)",
        "plc.ams_net_id: '127.0.0.1.1' is not an AMS net id (six numbers 0..255, e.g. "
        "'5.12.34.56.1.1')",
        "plc.poll_seconds: must be at least 0.1, got 0.01",
        "plc.host: '10.0.0.7:851': give the IPv4 address or host name alone; the AMS port goes "
        "in plc.port (the ADS TCP port is always 48898)",
        "plc.symbols[0].plc_type: unknown type 'LRAEL' (did you mean 'LREAL'?); one of BOOL, "
        "BYTE, USINT, SINT, WORD, UINT, INT, DWORD, UDINT, DINT, ULINT, LINT, REAL, LREAL",
        "plc.symbols[0].sensor: unknown sensor 'hmi/tmep' (did you mean 'hmi/temp'?); add it "
        "as a [[sensors]] table",
        "plc.symbols[1].cycle: unknown key (did you mean 'cycle_ms'?)",
        "plc.symbols[1].plc_type: STRING is not a numeric type; a reading is a number (BOOL, "
        "BYTE, USINT, SINT, WORD, UINT, INT, DWORD, UDINT, DINT, ULINT, LINT, REAL, LREAL)",
        "plc.symbols[1].symbol: duplicate symbol 'main.A' (first in plc.symbols[0])",
        "plc.symbols[2].scale: must not be 0 (every reading would be the offset)",
        "plc.symbols[2].sensor: sensor 'ceiling/co2' is already fed by plc.symbols[1]; one PLC "
        "symbol per sensor",
    ):
        assert expected in problems
    assert len(problems) == 11, problems

    assert main(["--config", str(path)]) == EX_CONFIG
    err = capsys.readouterr().err
    assert f"{path}: plc.poll_seconds: must be at least 0.1, got 0.01" in err
    assert main(["--config", str(env.tmp_path / "missing.toml")]) == EX_CONFIG
    assert "missing.toml: no such file" in capsys.readouterr().err


def test_bridge_client_id_must_not_take_the_daemons_session(env: Env) -> None:
    path = env.write_config()
    text = path.read_text(encoding="utf-8").replace(
        f'client_id = "{env.client_id}"', f'client_id = "{env.client_id}-daemon"'
    )
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigProblems) as caught:
        load_bridge_config(path)
    assert caught.value.problems == [
        f"bridge.client_id: '{env.client_id}-daemon' is broker.client_id, which the daemon "
        "uses; the bridge needs its own"
    ]


def test_example_configuration_is_valid() -> None:
    cfg = load_bridge_config(ROOT / "config" / "bridge-example.toml")
    assert cfg.client_id == "pseudotwin-room1-bridge"
    assert [s.plc_type for s in cfg.plc.symbols] == ["LREAL", "INT", "UINT"]
    assert cfg.spool_dir == Path("/var/lib/pseudotwin") and cfg.spool_fsync is True
    assert main(["--config", str(ROOT / "config" / "bridge-example.toml"), "--check"]) == 0


def _shared_file(folder: Path, net_id_line: str, sensor: str) -> Path:
    """config/example.toml with a [plc] part of one symbol for ``sensor``, as room1.toml."""
    text = (ROOT / "config" / "example.toml").read_text(encoding="utf-8") + "\n".join([
        "", "[plc]", net_id_line,
        _symbols_toml([{"symbol": "MAIN.fRoomTemp", "sensor": sensor, "plc_type": "LREAL"}]),
        "",
    ])
    path = folder / "room1.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_daemon_configuration_file_with_a_plc_section(tmp_path: Path) -> None:
    # One file for daemon and bridge: the daemon's part is validated as the daemon does
    # (artifacts aside), the bridge's defaults come from it.
    path = _shared_file(tmp_path, 'ams_net_id = "192.168.10.20.1.1"', "dining/temp")
    text = path.read_text(encoding="utf-8")
    cfg = load_bridge_config(path)
    assert cfg.client_id == "pseudotwin-room1-bridge"
    assert cfg.base_topic == "pseudotwin"
    assert cfg.plc.ip_address == "192.168.10.20" and cfg.plc.port == 851
    assert cfg.sensor_of(cfg.plc.symbols[0]).topic == "house/dining/temp"

    broken = text.replace('timezone = "Europe/Madrid"', 'timezone = "Europe/Berln"')
    path.write_text(broken.replace('sensor = "dining/temp"', 'sensor = "room1/hmi/tmp"'),
                    encoding="utf-8")
    with pytest.raises(ConfigProblems) as caught:
        load_bridge_config(path)
    assert any(p.startswith("service.timezone: unknown IANA time zone 'Europe/Berln'")
               for p in caught.value.problems)
    assert any(p.startswith("plc.symbols[0].sensor: unknown sensor 'room1/hmi/tmp'")
               for p in caught.value.problems)


def test_check_config_checks_the_plc_part_of_a_shared_file(tmp_path: Path, capsys) -> None:
    """check-config let a [plc] table be (the daemon does not read it): a misspelt key and
    an unknown sensor passed as OK and failed only when the bridge started."""
    from pseudotwin.cli.check_config import main as check_config_main

    path = _shared_file(tmp_path, 'ams_netid = "192.168.10.20.1.1"', "room1/hmi/tmp")
    assert check_config_main([str(path)]) == 1
    err = capsys.readouterr().err
    assert "plc.ams_netid: unknown key (did you mean 'ams_net_id'?)" in err
    assert "plc.symbols[0].sensor: unknown sensor 'room1/hmi/tmp'" in err


def test_sigterm_stops_the_bridge_process_cleanly(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory
) -> None:
    # In its own process the bridge still connects, checks the symbols, reads the initial
    # values and deletes its notifications over ADS/TCP; only the test server's in-process
    # notification delivery needs the test process, so changes are not checked here.
    inbox = _subscribe(mqtt_client, env)
    path = env.write_config()
    proc = subprocess.Popen(
        [sys.executable, "-m", "pseudotwin.cli", "bridge", "--config", str(path)],
        stderr=subprocess.PIPE, text=True,
    )
    try:
        _wait_initial(inbox, env)
        inbox.wait(f"{env.base}/bridge/plc", lambda p: p == b"up")
        assert all(plc.variable(name).notifications for name, *_ in VARIABLES)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=DEADLINE)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert inbox.wait(f"{env.base}/bridge/status", lambda p: p == b"offline")
    assert not any(plc.variable(name).notifications for name, *_ in VARIABLES)


def test_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "--config FILE" in out and "78" in out


# -- tests: the links drop -------------------------------------------------------------


def test_reconnects_by_itself_when_the_plc_drops_and_comes_back(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory
) -> None:
    inbox = _subscribe(mqtt_client, env)
    with running(Bridge(env.config())) as bridge:
        _wait_initial(inbox, env)
        assert bridge.ads_connects == 1

        plc.stop()  # the TCP connection and the route are gone; nothing tells the bridge
        _wait_for(lambda: not bridge.plc_up.is_set(), "the state poll notices the drop")
        inbox.wait(f"{env.base}/bridge/plc", lambda p: p == b"down")

        plc.variable("MAIN.fRoomTemp").value = struct.pack("<d", 19.75)  # changed meanwhile
        plc.start()
        _wait_for(lambda: bridge.plc_up.is_set(), "reconnected after the PLC came back")
        assert bridge.ads_connects == 2
        inbox.wait(f"{env.base}/bridge/plc", lambda p: p == b"up")
        # A fresh value after the reconnect, then notifications work again.
        inbox.wait(env.topics["hmi/temp"], _is(19.75))
        plc.write("MAIN.fRoomTemp", 20.5)
        inbox.wait(env.topics["hmi/temp"], _is(20.5))
        plc.write("MAIN.nCo2", 700)
        inbox.wait(env.topics["ceiling/co2"], _is(700))


def test_a_symbol_gone_at_a_reconnect_is_picked_up_again_when_it_is_back(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory, caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch
) -> None:
    """A symbol missing after a PLC restart was skipped until the next reconnect, which a
    PLC that keeps running never brings: its sensor went stale for good, `plc` said up."""
    monkeypatch.setattr(plc_module, "SYMBOL_RETRY_SECONDS", 0.0,  # every poll (0.2 s)
                        raising=False)
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.bridge")
    inbox = _subscribe(mqtt_client, env)
    with running(Bridge(env.config())) as bridge:
        _wait_initial(inbox, env)
        plc.stop()
        _wait_for(lambda: not bridge.plc_up.is_set(), "the poll notices the drop")
        co2 = plc.variable("MAIN.nCo2")
        plc.handler._data = {k: v for k, v in plc.handler._data.items() if v is not co2}
        plc.start()  # a new PLC program without MAIN.nCo2
        _wait_for(lambda: bridge.plc_up.is_set(), "up again with two symbols")
        assert "skipping a symbol" in caplog.text and "'MAIN.nCo2'" in caplog.text
        assert any(r.levelno == logging.WARNING and "2 of 3 symbols registered" in r.message
                   for r in caplog.records)
        registered = len(co2.notifications)  # the test server keeps the dead link's
        plc.handler.add_variable(co2)  # back, while the PLC keeps running
        _wait_for(lambda: "'MAIN.nCo2' found on the PLC again" in caplog.text,
                  "the symbol looked up again")
        assert len(co2.notifications) > registered  # registered again
        assert bridge.ads_connects == 2  # without a reconnect
        inbox.wait(env.topics["ceiling/co2"], _is(450))  # its value read at once
        plc.write("MAIN.nCo2", 777)
        inbox.wait(env.topics["ceiling/co2"], _is(777))  # and its changes notified


def test_plc_stopped_counts_as_down_until_it_runs_again(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory
) -> None:
    inbox = _subscribe(mqtt_client, env)
    with running(Bridge(env.config())) as bridge:
        _wait_initial(inbox, env)
        plc.handler.ads_state = adsc.ADSSTATE_STOP
        _wait_for(lambda: not bridge.plc_up.is_set(), "the poll sees the PLC in STOP")
        inbox.wait(f"{env.base}/bridge/plc", lambda p: p == b"down")
        # The link itself was fine, so the notifications were deleted on the PLC.
        assert not any(plc.variable(name).notifications for name, *_ in VARIABLES)

        plc.handler.ads_state = adsc.ADSSTATE_RUN
        _wait_for(lambda: bridge.plc_up.is_set(), "up again once the PLC runs")
        assert bridge.ads_connects == 2
        plc.write("MAIN.iCeilingTemp", 199)
        inbox.wait(env.topics["ceiling/temp"], _is(19.9))


def test_readings_arrive_after_a_broker_restart(
    plc: Plc, env: Env, mosquitto: MosquittoBroker, mqtt_client: MqttClientFactory
) -> None:
    # A persistent subscriber: the broker keeps its subscription across the restart.
    inbox = _subscribe(mqtt_client, env, client_id=f"sub-{env.client_id}", clean_session=False)
    with running(Bridge(env.config())) as bridge:
        _wait_initial(inbox, env)
        _wait_for(bridge.mqtt_connected.is_set, "the bridge is connected to the broker")
        try:
            mosquitto.stop()
            _wait_for(lambda: not bridge.mqtt_connected.is_set(), "the bridge sees the outage")
            plc.write("MAIN.fRoomTemp", 23.5)  # while the broker is away: kept by paho
        finally:
            mosquitto.start()
        _wait_for(bridge.mqtt_connected.is_set, "the bridge reconnects to the broker")
        plc.write("MAIN.fRoomTemp", 24.0)  # after the broker is back
        during = inbox.wait(env.topics["hmi/temp"], _is(23.5))
        after = inbox.wait(env.topics["hmi/temp"], _is(24.0))
        assert _ts(during) <= _ts(after)
        assert bridge.dropped == 0


def _eleven_readings_in_an_outage(plc: Plc, bridge: Bridge, mosquitto: MosquittoBroker,
                                  inbox: Inbox, env: Env, settled: Callable[[], bool],
                                  what: str) -> None:
    """With the initial values acknowledged, the broker away while the PLC changes
    fRoomTemp to 30..39 and nCo2 to 800; the broker back once ``settled``."""
    _wait_initial(inbox, env)
    _wait_for(lambda: bridge.unacknowledged() == 0, "the initial values acknowledged")
    try:
        mosquitto.stop()
        _wait_for(lambda: not bridge.mqtt_connected.is_set(), "the bridge sees the outage")
        for i in range(10):
            plc.write("MAIN.fRoomTemp", 30.0 + i)
        plc.write("MAIN.nCo2", 800)
        _wait_for(settled, what)
    finally:
        mosquitto.start()


def test_a_broker_outage_longer_than_the_queue_keeps_each_sensors_newest_reading(
    plc: Plc, env: Env, mosquitto: MosquittoBroker, mqtt_client: MqttClientFactory
) -> None:
    """With more readings than queue_size during an outage, the newest were dropped: after
    the broker came back the daemon got the outage's first readings and then nothing, and
    the reconnect's retained `online` was refused by the full queue (`offline` stayed)."""
    inbox = _subscribe(mqtt_client, env, client_id=f"sub-{env.client_id}", clean_session=False)
    path = env.write_config()
    path.write_text(path.read_text().replace("[bridge]\n", "[bridge]\nqueue_size = 5\n"),
                    encoding="utf-8")
    with running(Bridge(load_bridge_config(path))) as bridge:
        _eleven_readings_in_an_outage(
            plc, bridge, mosquitto, inbox, env,
            lambda: bridge.dropped == 4 and bridge.queue.empty(),
            "readings 35..38 dropped, 39 and the CO2 held back")
        for value in (30.0, 31.0, 32.0, 33.0, 34.0, 39.0):  # in this order, 35..38 dropped
            inbox.wait(env.topics["hmi/temp"], _is(value))
        inbox.wait(env.topics["ceiling/co2"], _is(800))
        _wait_for(lambda: bridge.unacknowledged() == 0, "everything acknowledged")
        assert bridge.dropped == 4
        check = _subscribe(mqtt_client, env)  # what a later subscriber is told, retained
        assert check.wait(f"{env.base}/bridge/status") == b"online"
    assert not any(_is(v)(m.payload) for m in inbox.seen if m.topic == env.topics["hmi/temp"]
                   for v in (35.0, 36.0, 37.0, 38.0))


def test_plc_flaps_during_a_broker_outage_do_not_crowd_out_the_status(
    plc: Plc, env: Env, mosquitto: MosquittoBroker, mqtt_client: MqttClientFactory,
    monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each PLC up/down during a broker outage queued a retained state message for the
    broker: past the status messages' room in paho's queue, the reconnect's `online` and
    state were refused without a word, and `offline` stayed retained."""
    monkeypatch.setattr(plc_module, "STATUS_HEADROOM", 3)  # 16: the same in 8 flaps
    path = env.write_config()
    path.write_text(path.read_text().replace("[bridge]\n", "[bridge]\nqueue_size = 5\n"),
                    encoding="utf-8")
    with running(Bridge(load_bridge_config(path))) as bridge:
        _wait_for(lambda: bridge.plc_up.is_set() and bridge.mqtt_connected.is_set(), "up")
        try:
            mosquitto.stop()
            _wait_for(lambda: not bridge.mqtt_connected.is_set(), "the bridge sees the outage")
            for _ in range(2):  # 4 state changes: more than the status messages' room
                plc.handler.ads_state = adsc.ADSSTATE_STOP
                _wait_for(lambda: not bridge.plc_up.is_set(), "down")
                plc.handler.ads_state = adsc.ADSSTATE_RUN
                _wait_for(lambda: bridge.plc_up.is_set(), "up again")
        finally:
            mosquitto.start()
        _wait_for(bridge.mqtt_connected.is_set, "the bridge reconnects")
        later = _subscribe(mqtt_client, env)  # what a new subscriber is told, retained
        assert later.wait(f"{env.base}/bridge/status") == b"online"
        assert later.wait(f"{env.base}/bridge/plc") == b"up"


# -- tests: the broker away or refusing ---------------------------------------------------


def test_an_unreachable_broker_is_logged_and_unsent_readings_are_lost_not_published(
    plc: Plc, env: Env, caplog: pytest.LogCaptureFixture
) -> None:
    """A mistyped broker port looked like a healthy bridge (nothing logged), and the
    readings paho still held at stop were counted as published."""
    port = closed_port()
    path = env.write_config()
    path.write_text(path.read_text().replace(f"port = {env.broker.port}", f"port = {port}"),
                    encoding="utf-8")
    bridge = Bridge(load_bridge_config(path))
    with caplog.at_level("WARNING"), running(bridge):
        _wait_for(lambda: f"cannot connect to the broker at 127.0.0.1:{port}" in caplog.text,
                  "the failed connection logged")
        _wait_for(lambda: bridge.unacknowledged() == len(DEFAULT_SYMBOLS),
                  "the initial values handed to paho")
    assert bridge.published == 0
    assert (f"{len(DEFAULT_SYMBOLS)} readings were never acknowledged by the broker "
            f"127.0.0.1:{port} and are lost with this stop") in caplog.text


def test_refused_credentials_exit_77(plc: Plc, env: Env, password_broker: int,
                                     monkeypatch: pytest.MonkeyPatch,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    """It retried forever, two log lines per attempt; run and record exit 77 here."""
    from pseudotwin.edge.mqttconn import EX_NOPERM

    monkeypatch.setenv("PT_BRIDGE_PASSWORD", "wrong")
    path = env.write_config()
    path.write_text(path.read_text().replace(
        f"port = {env.broker.port}",
        f'port = {password_broker}\nusername = "pt"\npassword_env = "PT_BRIDGE_PASSWORD"'),
        encoding="utf-8")
    assert main(["--config", str(path)]) == EX_NOPERM
    assert "the broker refused the credentials" in capsys.readouterr().err


def test_a_plc_that_drops_packets_is_said_unreachable_and_a_stop_is_not_held_up(
    env: Env, caplog: pytest.LogCaptureFixture
) -> None:
    """A router dropping the packets to the PLC: pyads' connect blocked in the kernel for
    about two minutes, the watchdog heartbeat went stale (systemd killed the bridge before it
    said why) and SIGTERM waited. Stand-in: a listener on the ADS port whose accept queue is
    full, so the kernel drops further connection attempts, as such a router does."""
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.bridge")
    host = "127.0.0.3"  # all of 127/8 is this host
    listener = socket.socket()
    listener.bind((host, plc_module.ADS_TCP_PORT))
    listener.listen(0)
    fillers = []
    for _ in range(3):  # fill the queue; never accepted
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex((host, plc_module.ADS_TCP_PORT))
        fillers.append(s)
    bridge = Bridge(env.config(host=host, timeout_seconds=1, reconnect_max_seconds=1))
    try:
        bridge.start()
        # the timeout is a liveness bound: the kernel's connect blocks for two minutes
        _wait_for(lambda: "unreachable within 1 s" in caplog.text,
                  "the unreachable PLC in the log", timeout=20)
        # the watchdog's own criterion is the heartbeat's age; the supervisor refreshes it
        # at least every second here (probe timeout and back-off 1 s): 5 s catches a stall
        assert time.monotonic() - bridge._heartbeat < 5  # the watchdog is still fed
    finally:
        bridge.stop()
        for s in fillers:
            s.close()
        listener.close()
    # not held up: the supervisor ended within stop()'s join, not left in a connect
    assert bridge.finished.is_set()


# How the test server's connection thread ends without an answer: by an exception.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_plc_that_never_answers_is_said_to_need_a_route_to_this_host(
    plc: Plc, env: Env, caplog: pytest.LogCaptureFixture
) -> None:
    """A PLC without a static route to this host takes the TCP connection and drops the
    requests: the log said only "timeout elapsed (1861).", and nowhere which AMS net id
    the route has to name."""
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.bridge")
    plc.handler.answers = False
    with running(Bridge(env.config())):
        _wait_for(lambda: "cannot connect" in caplog.text, "the failed connect logged")
    assert f"this host's AMS net id is {ADS_NET_ID}" in caplog.text
    assert ("timeout elapsed (1861) (the PLC took the connection but did not answer: check "
            f"that it has a static route to this host's AMS net id {ADS_NET_ID}") in caplog.text


def test_the_value_a_plc_notifies_at_registration_is_the_initial_reading(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory
) -> None:
    """A TwinCAT runtime notifies a symbol's value when the notification is registered;
    the bridge read it as well, stamped on this host's clock before it knew the PLC's: two
    initial readings per symbol, and with the PLC behind, its next changes stamped before
    the read (the daemon, readings in time order, held the read's value)."""
    plc_clock = dt.datetime(2026, 3, 2, 9, 0, 0, tzinfo=dt.UTC)  # pyads stamps whole s
    plc.handler.notify_at_registration = lambda: plc_clock
    host = plc_clock + dt.timedelta(minutes=2)  # this host runs 2 min ahead of the PLC
    inbox = _subscribe(mqtt_client, env)
    with running(Bridge(env.config(), clock=FixedClock(host))) as bridge:
        _wait_for(lambda: bridge.plc_up.is_set(), "connected and registered")
        for sensor in ("hmi/temp", "ceiling/temp"):
            assert _ts(inbox.wait(env.topics[sensor], _is(21.5))) == plc_clock
        inbox.wait(env.topics["ceiling/co2"], _is(450))  # a bare number: no time stamp
        plc.write("MAIN.nCo2", 520)
        inbox.wait(env.topics["ceiling/co2"], _is(520))
    readings = [m for m in inbox.seen if m.topic in env.topics.values()]
    assert len(readings) == 4  # each initial value once, then the change: nothing read


def test_reads_after_a_reconnect_are_stamped_on_the_plcs_clock(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory
) -> None:
    """Reads were stamped on this host's clock, notifications on the PLC's: with the PLC two
    minutes behind, its next change came stamped before the read, and the daemon (readings
    in time order) held the read's value for two minutes after every reconnect."""
    inbox = _subscribe(mqtt_client, env)
    host = dt.datetime.now(dt.UTC) + dt.timedelta(minutes=2)  # the PLC runs 2 min behind
    with running(Bridge(env.config(), clock=FixedClock(host))):
        assert _ts(inbox.wait(env.topics["hmi/temp"])) == host  # nothing known of the PLC
        plc.write("MAIN.fRoomTemp", 22.25)
        change = _ts(inbox.wait(env.topics["hmi/temp"], _is(22.25)))
        assert change < host - dt.timedelta(minutes=1)  # the PLC's stamp
        plc.stop()
        inbox.wait(f"{env.base}/bridge/plc", lambda p: p == b"down")
        plc.variable("MAIN.fRoomTemp").value = struct.pack("<d", 19.75)
        plc.start()
        read = _ts(inbox.wait(env.topics["hmi/temp"], _is(19.75)))
        assert read - change < dt.timedelta(minutes=1)  # on the PLC's clock, not 2 min on
        plc.write("MAIN.fRoomTemp", 20.5)
        assert _ts(inbox.wait(env.topics["hmi/temp"], _is(20.5))) >= read  # in order
