"""PLC bridge: ADS device notifications of configured PLC symbols → MQTT sensor readings.

``pseudotwin bridge --config FILE`` runs it. Per configured symbol the bridge registers an ADS
device notification (transmission mode "on change") and publishes every change as one
reading on the topic of the symbol's sensor, in that sensor's payload format
(:func:`pseudotwin.edge.replay.payload_for`), QoS 1. The reading's time is the FILETIME stamp the
PLC puts on the notification, so a reading delayed by a slow network or a broker outage
still carries the instant the PLC saw the value.

Threads, and why:

- the ADS notification thread (adslib's dispatcher; pyads' test server calls it from its
  connection thread) runs :meth:`Bridge._on_notification`: decode, timestamp, ``put_nowait``
  on a bounded queue and nothing else. It must never block: a blocked dispatcher delays
  every other symbol's notifications, and on a full queue dropping (counted, logged) is
  better than stalling the PLC link;
- one publisher thread turns queue items into MQTT messages (paho keeps QoS 1 messages that
  cannot be sent right now and sends them after the broker reconnect);
- paho's network thread (``loop_start``), which also reconnects to the broker by itself;
- one supervisor thread owns the ADS connection: connect, validate the symbols, register the
  notifications, publish each symbol's current value, then poll ``read_state`` every
  ``poll_seconds``. ADS has no heartbeat: without the poll, a dropped route or a PLC stopped
  by its operator would just look like values that never change. On failure it tears the
  connection down and reconnects with exponential backoff (1 s doubling up to
  ``reconnect_max_seconds``), re-registering every notification.

Configuration (the same TOML file as the daemon, or a file of its own; see
``config/bridge-example.toml``)::

    [broker], [[sensors]]   as for the daemon (``pseudotwin.config``)
    [bridge]                optional: client_id, base_topic, queue_size
    [plc]                   ams_net_id, host, port, local_ams_net_id, poll_seconds,
                            reconnect_max_seconds, timeout_seconds
    [[plc.symbols]]         symbol, sensor, plc_type, cycle_ms, max_delay_ms, scale, offset

A file that also has ``[service]`` or ``[[twins]]`` is the daemon's own file; it is then
validated exactly as the daemon validates it (without looking at artifacts), so one file
cannot be fine for the bridge and broken for the daemon.

Outputs besides the readings (retained, QoS 1):

- ``<base_topic>/bridge/status``: ``online``; the MQTT last will sets ``offline``;
- ``<base_topic>/bridge/plc``: ``up`` while the PLC is connected, in RUN and its
  notifications are registered, ``down`` otherwise.

Configuration problems found on the PLC itself (an unknown symbol, a symbol whose PLC type
differs from ``plc_type``) are fatal at the first successful connection: the bridge stops and
``main`` exits with 78 (EX_CONFIG), so systemd does not restart it in a loop. If they appear
only after a later reconnect (a PLC program changed under a running bridge), the affected
symbols are skipped with an error in the log and the others keep working.
"""

from __future__ import annotations

import argparse
import ctypes
import datetime as dt
import logging
import math
import os
import queue
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pyads
from paho.mqtt.enums import CallbackAPIVersion
from pyads import constants as adsc
from pyads.structs import SAdsSymbolEntry

from pseudotwin.config import (
    BrokerConfig,
    ConfigProblems,
    Found,
    SensorConfig,
    _cross_problems,
    _expect,
    _Loader,
    _nonempty,
    _raise_if,
    _read,
    _suggest,
    _type_name,
    base_topic_problem,
)
from pseudotwin.edge.clock import Clock, SystemClock
from pseudotwin.edge.replay import payload_for
from pseudotwin.edge.sdnotify import notify, watchdog_interval
from pseudotwin.errors import ConfigError

__all__ = [
    "EX_CONFIG",
    "PLC_TYPES",
    "Bridge",
    "BridgeConfig",
    "PlcConfig",
    "PlcType",
    "SymbolConfig",
    "SymbolProblems",
    "filetime_to_utc",
    "load_bridge_config",
    "main",
]

log = logging.getLogger(__name__)

EX_CONFIG = 78  # sysexits; the systemd unit's RestartPreventExitStatus keys on it

#: ADS error "symbol not found" (0x710): what a TwinCAT runtime answers for an unknown name.
ADSERR_SYMBOL_NOT_FOUND = 0x710
#: While tearing down a link that is known to be dead, each notification delete would wait
#: the full request timeout (adslib deletes them one by one, also when closing the port).
TEARDOWN_TIMEOUT_MS = 250
#: paho's reconnect backoff towards the broker [s].
MQTT_RECONNECT_MIN, MQTT_RECONNECT_MAX = 1, 30
#: A PLC clock this far from ours is logged: the daemon rejects readings more than its
#: max_skew in the future and older than its window, so the operator should know why.
CLOCK_SKEW_WARN = dt.timedelta(minutes=5)
_FILETIME_EPOCH = dt.datetime(1601, 1, 1, tzinfo=dt.UTC)
_NET_ID = re.compile(r"\d{1,3}(\.\d{1,3}){5}")
_ADS_STATES = {v: k.removeprefix("ADSSTATE_") for k, v in vars(adsc).items()
               if k.startswith("ADSSTATE_") and isinstance(v, int)}


# -- PLC data types ----------------------------------------------------------------------


@dataclass(frozen=True)
class PlcType:
    """An elementary IEC 61131-3 type: its pyads/ctypes type and the ADS type id the PLC
    reports in its symbol information (used to accept type aliases such as
    ``TYPE T_Celsius : LREAL``)."""

    name: str
    ctype: Any  # a pyads.PLCTYPE_* ctypes type
    ads_type: int

    @property
    def size(self) -> int:
        return ctypes.sizeof(self.ctype)


#: The numeric types a reading can come from. STRING, TIME, structures and arrays are not
#: readings; they are rejected when the configuration is loaded.
PLC_TYPES: dict[str, PlcType] = {t.name: t for t in (
    PlcType("BOOL", pyads.PLCTYPE_BOOL, adsc.ADST_BIT),
    PlcType("BYTE", pyads.PLCTYPE_BYTE, adsc.ADST_UINT8),
    PlcType("USINT", pyads.PLCTYPE_USINT, adsc.ADST_UINT8),
    PlcType("SINT", pyads.PLCTYPE_SINT, adsc.ADST_INT8),
    PlcType("WORD", pyads.PLCTYPE_WORD, adsc.ADST_UINT16),
    PlcType("UINT", pyads.PLCTYPE_UINT, adsc.ADST_UINT16),
    PlcType("INT", pyads.PLCTYPE_INT, adsc.ADST_INT16),
    PlcType("DWORD", pyads.PLCTYPE_DWORD, adsc.ADST_UINT32),
    PlcType("UDINT", pyads.PLCTYPE_UDINT, adsc.ADST_UINT32),
    PlcType("DINT", pyads.PLCTYPE_DINT, adsc.ADST_INT32),
    PlcType("ULINT", pyads.PLCTYPE_ULINT, adsc.ADST_UINT64),
    PlcType("LINT", pyads.PLCTYPE_LINT, adsc.ADST_INT64),
    PlcType("REAL", pyads.PLCTYPE_REAL, adsc.ADST_REAL32),
    PlcType("LREAL", pyads.PLCTYPE_LREAL, adsc.ADST_REAL64),
)}


#: Elementary IEC types that are not readings, named as such instead of "unknown".
NON_NUMERIC_TYPES = frozenset({"STRING", "WSTRING", "TIME", "LTIME", "TOD", "TIME_OF_DAY",
                               "DATE", "DT", "DATE_AND_TIME", "LWORD"})


def filetime_to_utc(filetime: int) -> dt.datetime:
    """A Windows FILETIME (100 ns ticks since 1601-01-01 UTC) as an aware UTC datetime.

    pyads' own conversion goes through a float of seconds since 1970, which loses the
    sub-microsecond part and can round; integer arithmetic keeps every microsecond.
    """
    return _FILETIME_EPOCH + dt.timedelta(microseconds=filetime // 10)


# -- configuration -----------------------------------------------------------------------


def _net_id_problem(value: str) -> str | None:
    if not _NET_ID.fullmatch(value) or any(int(p) > 255 for p in value.split(".")):
        return f"{value!r} is not an AMS net id (six numbers 0..255, e.g. '5.12.34.56.1.1')"
    return None


def _number_problem(found: Found, name: str, value: object, *, low: float,
                    low_inclusive: bool = True, high: float | None = None) -> None:
    if not _expect(found, name, value, "number"):
        return
    assert isinstance(value, int | float)
    if value < low or (value == low and not low_inclusive):
        found.append((name, f"must be {'at least' if low_inclusive else 'greater than'} "
                            f"{low:g}, got {value:g}"))
    elif high is not None and value > high:
        found.append((name, f"must be at most {high:g}, got {value:g}"))


@dataclass(frozen=True, kw_only=True)
class SymbolConfig:
    """One PLC symbol published as one sensor's readings.

    symbol: the PLC variable, e.g. ``"MAIN.fRoomTemp"`` or ``"GVL_Room.nCo2"``.
    sensor: id of the ``[[sensors]]`` entry whose topic and payload format are used.
    plc_type: its elementary type (a key of :data:`PLC_TYPES`; case is ignored). Checked
        against the PLC's declaration on every connect.
    cycle_ms: how often the PLC checks the value for a change [ms]; 100 ms is ample for room
        climate and keeps the PLC's notification load small.
    max_delay_ms: how long the PLC may collect changes before sending them [ms]; 0 sends
        each change at once.
    scale, offset: reading = raw × scale + offset, for raw integer values (e.g. an INT in
        0.1 °C: scale = 0.1) or unit changes.
    """

    symbol: str
    sensor: str
    plc_type: str
    cycle_ms: float = 100.0
    max_delay_ms: float = 0.0
    scale: float = 1.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.plc_type, str):
            object.__setattr__(self, "plc_type", self.plc_type.strip().upper())
        _raise_if(self._problems())
        for name in ("cycle_ms", "max_delay_ms", "scale", "offset"):
            object.__setattr__(self, name, float(getattr(self, name)))

    def _problems(self) -> Found:
        found: Found = []
        if _nonempty(found, "symbol", self.symbol) and (
            any(c.isspace() or ord(c) < 0x20 for c in self.symbol)
        ):
            found.append(("symbol", f"{self.symbol!r} contains blanks or control characters"))
        _nonempty(found, "sensor", self.sensor)
        if _nonempty(found, "plc_type", self.plc_type) and self.plc_type not in PLC_TYPES:
            if self.plc_type in NON_NUMERIC_TYPES:
                found.append(("plc_type", f"{self.plc_type} is not a numeric type; a reading "
                                          f"is a number ({', '.join(PLC_TYPES)})"))
            else:
                found.append(("plc_type", f"unknown type {self.plc_type!r}"
                                          f"{_suggest(self.plc_type, PLC_TYPES)}; one of "
                                          f"{', '.join(PLC_TYPES)}"))
        # ADS carries both times as 32-bit counts of 100 ns.
        limit = (2**32 - 1) / 1e4
        _number_problem(found, "cycle_ms", self.cycle_ms, low=0.0, high=limit)
        _number_problem(found, "max_delay_ms", self.max_delay_ms, low=0.0, high=limit)
        if _expect(found, "scale", self.scale, "number") and self.scale == 0:
            found.append(("scale", "must not be 0 (every reading would be the offset)"))
        _expect(found, "offset", self.offset, "number")
        return found

    @property
    def type(self) -> PlcType:
        return PLC_TYPES[self.plc_type]

    def convert(self, raw: float | int | bool) -> float:
        """The reading value of a raw PLC value."""
        return float(raw) * self.scale + self.offset


@dataclass(frozen=True, kw_only=True)
class PlcConfig:
    """Where the PLC is and how the bridge watches it.

    ams_net_id: the PLC's AMS net id, e.g. ``"5.12.34.56.1.1"``.
    host: its IP address or host name; default: the first four numbers of ``ams_net_id``
        (pyads' own default, right for most TwinCAT installations).
    port: the AMS port of the PLC runtime: 851 for the first TwinCAT 3 runtime, 801 for
        TwinCAT 2.
    local_ams_net_id: this host's AMS net id, which the PLC needs a route back to. Default:
        derived by pyads' router from this host's IP address plus ``.1.1``.
    poll_seconds: how often the PLC state is read to detect a dropped link [s].
    reconnect_max_seconds: upper bound of the reconnect backoff [s].
    timeout_seconds: timeout of each ADS request [s].
    """

    ams_net_id: str
    symbols: tuple[SymbolConfig, ...]
    host: str | None = None
    port: int = 851
    local_ams_net_id: str | None = None
    poll_seconds: float = 5.0
    reconnect_max_seconds: float = 60.0
    timeout_seconds: float = 5.0

    def __post_init__(self) -> None:
        if isinstance(self.symbols, list):
            object.__setattr__(self, "symbols", tuple(self.symbols))
        _raise_if(self._problems())
        for name in ("poll_seconds", "reconnect_max_seconds", "timeout_seconds"):
            object.__setattr__(self, name, float(getattr(self, name)))

    def _problems(self) -> Found:
        found = _plc_scalar_problems(
            ams_net_id=self.ams_net_id, host=self.host, port=self.port,
            local_ams_net_id=self.local_ams_net_id, poll_seconds=self.poll_seconds,
            reconnect_max_seconds=self.reconnect_max_seconds,
            timeout_seconds=self.timeout_seconds,
        )
        syms = self.symbols
        if not isinstance(syms, tuple) or not all(isinstance(s, SymbolConfig) for s in syms):
            found.append(("symbols", "expected an array of [[plc.symbols]] tables"))
        elif not syms:
            found.append(("symbols", "at least one [[plc.symbols]] table is required"))
        return found

    @property
    def ip_address(self) -> str:
        return self.host or ".".join(self.ams_net_id.split(".")[:4])


def _plc_scalar_problems(*, ams_net_id: object, host: object, port: object,
                         local_ams_net_id: object, poll_seconds: object,
                         reconnect_max_seconds: object, timeout_seconds: object) -> Found:
    found: Found = []
    if ams_net_id is None:
        found.append(("ams_net_id", "missing required key"))
    elif _nonempty(found, "ams_net_id", ams_net_id):
        assert isinstance(ams_net_id, str)
        problem = _net_id_problem(ams_net_id)
        if problem:
            found.append(("ams_net_id", problem))
    if host is not None and _nonempty(found, "host", host):
        assert isinstance(host, str)
        if any(c.isspace() or ord(c) < 0x20 for c in host):
            found.append(("host", f"{host!r} contains blanks or control characters"))
    if _expect(found, "port", port, "integer") and not 1 <= port <= 65535:  # type: ignore[operator]
        found.append(("port", f"must be in 1..65535, got {port}"))
    if local_ams_net_id is not None and _nonempty(found, "local_ams_net_id", local_ams_net_id):
        assert isinstance(local_ams_net_id, str)
        problem = _net_id_problem(local_ams_net_id)
        if problem:
            found.append(("local_ams_net_id", problem))
    _number_problem(found, "poll_seconds", poll_seconds, low=0.0, low_inclusive=False)
    _number_problem(found, "reconnect_max_seconds", reconnect_max_seconds, low=1.0)
    # adslib takes the timeout in whole milliseconds.
    _number_problem(found, "timeout_seconds", timeout_seconds, low=0.001, high=3600.0)
    return found


def _bridge_cross_problems(
    symbols: Sequence[tuple[str, object, object]],
    sensors: Mapping[str, SensorConfig],
    unchecked_ids: set[str] | None,
) -> list[str]:
    """Between symbols and sensors, from (location, symbol name, sensor id) triples whose
    values may still be of any type (a symbol table with other problems is checked too):
    no symbol twice, each names a configured sensor, and no sensor gets two sources (two
    symbols on one topic would interleave two different quantities).

    ``unchecked_ids`` are ids of sensors that exist but failed their own validation; None
    means the sensor list itself is unusable, so no sensor is reported as unknown.
    """
    out: list[str] = []
    first_symbol: dict[str, str] = {}
    first_sensor: dict[str, str] = {}
    for loc, symbol, sensor in symbols:
        if isinstance(symbol, str) and symbol:
            # IEC 61131-3 identifiers are case-insensitive: MAIN.x and main.X are one.
            key = symbol.upper()
            if key in first_symbol:
                out.append(f"{loc}.symbol: duplicate symbol {symbol!r} (first in "
                           f"{first_symbol[key]})")
            else:
                first_symbol[key] = loc
        if not isinstance(sensor, str) or not sensor:
            continue
        if sensor not in sensors:
            if unchecked_ids is not None and sensor not in unchecked_ids:
                out.append(f"{loc}.sensor: unknown sensor {sensor!r}"
                           f"{_suggest(sensor, sensors)}; add it as a [[sensors]] table")
        elif sensor in first_sensor:
            out.append(f"{loc}.sensor: sensor {sensor!r} is already fed by "
                       f"{first_sensor[sensor]}; one PLC symbol per sensor")
        else:
            first_sensor[sensor] = loc
    return out


def _bridge_scalar_problems(*, client_id: object, base_topic: object, queue_size: object,
                            broker_client_id: str | None) -> Found:
    found: Found = []
    # None: no default could be derived because [broker] is invalid (reported there).
    if client_id is not None and _nonempty(found, "client_id", client_id):
        assert isinstance(client_id, str)
        if any(ord(c) < 0x20 for c in client_id):
            found.append(("client_id", "must not contain NUL or control characters"))
        elif client_id == broker_client_id:
            # Both use persistent sessions: one id would make the broker kick the daemon
            # off every time the bridge connects, and vice versa.
            found.append(("client_id", f"{client_id!r} is broker.client_id, which the daemon "
                                       "uses; the bridge needs its own"))
    if _expect(found, "base_topic", base_topic, "string"):
        assert isinstance(base_topic, str)
        problem = base_topic_problem(base_topic)
        if problem:
            found.append(("base_topic", problem))
    if _expect(found, "queue_size", queue_size, "integer"):
        assert isinstance(queue_size, int)
        if queue_size < 1:
            found.append(("queue_size", "must be at least 1"))
    return found


@dataclass(frozen=True, kw_only=True)
class BridgeConfig:
    """Everything the bridge needs.

    client_id: the bridge's MQTT client id (persistent session); default
        ``<broker.client_id>-bridge``, never the daemon's.
    base_topic: status topics go to ``<base_topic>/bridge/...``; default the daemon's
        ``service.base_topic`` when the file has one, else ``"pseudotwin"``.
    queue_size: bound of the queue between the ADS notification thread and the publisher,
        and of paho's queue of messages waiting for the broker (readings).
    """

    broker: BrokerConfig
    sensors: dict[str, SensorConfig]
    plc: PlcConfig
    client_id: str
    base_topic: str = "pseudotwin"
    queue_size: int = 10000

    def __post_init__(self) -> None:
        found = _bridge_scalar_problems(
            client_id=self.client_id, base_topic=self.base_topic, queue_size=self.queue_size,
            broker_client_id=self.broker.client_id if isinstance(self.broker, BrokerConfig)
            else None,
        )
        if not isinstance(self.broker, BrokerConfig):
            found.append(("broker", "expected a BrokerConfig"))
        if not isinstance(self.plc, PlcConfig):
            found.append(("plc", "expected a PlcConfig"))
        if not isinstance(self.sensors, Mapping) or not all(
            isinstance(v, SensorConfig) and k == v.id for k, v in self.sensors.items()
        ):
            found.append(("sensors", "expected a mapping of id to SensorConfig"))
        _raise_if(found)
        cross = _bridge_cross_problems(
            [(f"plc.symbols[{i}]", s.symbol, s.sensor) for i, s in enumerate(self.plc.symbols)],
            self.sensors, set(),
        )
        if cross:
            raise ConfigProblems(cross)

    @property
    def status_topic(self) -> str:
        return f"{self.base_topic}/bridge/status"

    @property
    def plc_topic(self) -> str:
        return f"{self.base_topic}/bridge/plc"

    def sensor_of(self, symbol: SymbolConfig) -> SensorConfig:
        return self.sensors[symbol.sensor]


class _BridgeLoader:
    """Turns one parsed TOML document into a BridgeConfig, collecting every problem.

    Broker and sensors are parsed by the daemon's own loader (:class:`pseudotwin.config.
    _Loader`), so they follow exactly the daemon's rules and messages.
    """

    BRIDGE_TOP_KEYS = ("bridge", "plc")
    TOP_KEYS = (*_Loader.TOP_KEYS, *BRIDGE_TOP_KEYS)
    BRIDGE_KEYS = ("client_id", "base_topic", "queue_size")
    PLC_KEYS = ("ams_net_id", "host", "port", "local_ams_net_id", "poll_seconds",
                "reconnect_max_seconds", "timeout_seconds", "symbols")
    PLC_REQUIRED = ("ams_net_id", "symbols")
    PLC_DEFAULTS: dict[str, Any] = {
        "ams_net_id": None, "host": None, "port": 851, "local_ams_net_id": None,
        "poll_seconds": 5.0, "reconnect_max_seconds": 60.0, "timeout_seconds": 5.0,
    }
    SYMBOL_KEYS = ("symbol", "sensor", "plc_type", "cycle_ms", "max_delay_ms", "scale",
                   "offset")
    SYMBOL_REQUIRED = ("symbol", "sensor", "plc_type")

    def __init__(self, base_dir: Path, runtime: bool) -> None:
        self.base_dir = base_dir
        self.runtime = runtime
        # The daemon's loader in its non-runtime mode: it must not require the twins'
        # artifacts, which are none of the bridge's business.
        self.inner = _Loader(base_dir, runtime=False, artifact_check=None)
        self.problems = self.inner.problems  # one list for the daemon's sections and ours

    def load(self, doc: dict[str, Any]) -> BridgeConfig | None:
        for key in doc:
            if key not in self.TOP_KEYS:
                self.inner.add(key, f"unknown key{_suggest(key, self.TOP_KEYS)}")
        daemon_part = {k: v for k, v in doc.items() if k in _Loader.TOP_KEYS}
        if "service" in doc or "twins" in doc:
            broker, sensors, bad_ids, service_base = self.load_daemon_file(daemon_part)
        else:
            broker = self.inner.load_broker(doc)
            good, _complete, bad_ids = self.inner.load_sensors(doc)
            sensors = {s.id: s for _, s in good}
            service_base = None
            if good or bad_ids is not None:
                base = doc.get("bridge", {}).get("base_topic", "pseudotwin") \
                    if isinstance(doc.get("bridge"), dict) else None
                self.problems.extend(_cross_problems(
                    base if isinstance(base, str) else None, good, [], bad_ids
                ))
        bridge = self.load_bridge(doc, broker, service_base)
        plc = self.load_plc(doc, sensors, bad_ids)
        if self.runtime and broker is not None:
            problem = broker.password_problem()
            if problem is not None:
                self.inner.add(f"broker.{problem[0]}", problem[1])
            if broker.ca_file is not None and not broker.ca_file.is_file():
                self.inner.add("broker.ca_file", f"{broker.ca_file} does not exist")
        if self.problems or broker is None or bridge is None or plc is None:
            return None
        return BridgeConfig(broker=broker, sensors=sensors, plc=plc, **bridge)

    def load_daemon_file(
        self, doc: dict[str, Any]
    ) -> tuple[BrokerConfig | None, dict[str, SensorConfig], set[str] | None, str | None]:
        """Validate the daemon's part exactly as the daemon does; (broker, valid sensors,
        ids of invalid sensors, service.base_topic)."""
        cfg = self.inner.load(doc)
        if cfg is not None:
            return cfg.broker, dict(cfg.sensors), set(), cfg.base_topic
        # The file has problems (already reported); go on with what is valid so that the
        # [plc] part is checked in the same run. A scratch loader keeps them from being
        # reported twice.
        scratch = _Loader(self.base_dir, runtime=False, artifact_check=None)
        broker = scratch.load_broker(doc)
        good, _complete, bad_ids = scratch.load_sensors(doc)
        service = doc.get("service")
        base = service.get("base_topic", "pseudotwin") if isinstance(service, dict) else None
        return broker, {s.id: s for _, s in good}, bad_ids, base if isinstance(base, str) \
            else None

    def load_bridge(self, doc: dict[str, Any], broker: BrokerConfig | None,
                    service_base: str | None) -> dict[str, Any] | None:
        table = doc.get("bridge", {})
        if not isinstance(table, dict):
            self.inner.add("bridge", f"expected a table [bridge], got {_type_name(table)}")
            return None
        self.inner.keys(table, self.BRIDGE_KEYS, (), "bridge")
        broker_id = broker.client_id if broker is not None else None
        values = {
            "client_id": table.get("client_id", f"{broker_id}-bridge" if broker_id else None),
            "base_topic": table.get("base_topic", service_base or "pseudotwin"),
            "queue_size": table.get("queue_size", 10000),
        }
        found = _bridge_scalar_problems(**values, broker_client_id=broker_id)
        for where, msg in found:
            self.inner.add(f"bridge.{where}", msg)
        if found or values["client_id"] is None:
            return None
        return values

    def load_plc(self, doc: dict[str, Any], sensors: Mapping[str, SensorConfig],
                 bad_ids: set[str] | None) -> PlcConfig | None:
        table = self.inner.section(doc, "plc")
        if table is None:
            return None
        complete = self.inner.keys(table, self.PLC_KEYS, self.PLC_REQUIRED, "plc")
        values = {k: v for k, v in table.items() if k in self.PLC_KEYS}
        # Scalars are checked here, not only by PlcConfig, so that a broken symbol table
        # does not hide them.
        scalars = {k: values.get(k, v) for k, v in self.PLC_DEFAULTS.items()}
        found = [(where, msg) for where, msg in _plc_scalar_problems(**scalars)
                 if where in values or where not in self.PLC_REQUIRED]  # else reported above
        for where, msg in found:
            self.inner.add(f"plc.{where}", msg)
        before = len(self.problems)
        symbols = self.load_symbols(table, sensors, bad_ids)
        if not complete or symbols is None or found or len(self.problems) > before:
            return None
        values["symbols"] = tuple(symbols)
        return self.inner.build("plc", PlcConfig, **values)

    def load_symbols(self, table: dict[str, Any], sensors: Mapping[str, SensorConfig],
                     bad_ids: set[str] | None) -> list[SymbolConfig] | None:
        items = table.get("symbols")
        if items is None:
            return None  # reported as a missing required key
        if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
            self.inner.add("plc.symbols", "expected an array of tables [[plc.symbols]], got "
                                          f"{_type_name(items)}")
            return None
        if not items:
            self.inner.add("plc.symbols", "at least one [[plc.symbols]] table is required")
            return None
        good: list[SymbolConfig] = []
        refs: list[tuple[str, object, object]] = []
        for i, item in enumerate(items):
            loc = f"plc.symbols[{i}]"
            refs.append((loc, item.get("symbol"), item.get("sensor")))
            if not self.inner.keys(item, self.SYMBOL_KEYS, self.SYMBOL_REQUIRED, loc):
                continue
            values = {k: v for k, v in item.items() if k in self.SYMBOL_KEYS}
            symbol = self.inner.build(loc, SymbolConfig, **values)
            if symbol is not None:
                good.append(symbol)
        self.problems.extend(_bridge_cross_problems(refs, sensors, bad_ids))
        return good if len(good) == len(items) else None


def load_bridge_config(path: str | os.PathLike[str], *, runtime: bool = False) -> BridgeConfig:
    """Parse and validate a bridge configuration file (see the module docstring).

    With ``runtime``, also check what the bridge needs to start: the MQTT password source is
    readable and the CA file exists.

    Raises :class:`ConfigProblems` listing every problem (``.problems``, each
    ``"<location>: <message>"``), or plain :class:`ConfigError` when the file cannot be read
    or is not valid TOML.
    """
    path = Path(path)
    doc = _read(path)
    loader = _BridgeLoader(path.absolute().parent, runtime)
    cfg = loader.load(doc)
    if loader.problems or cfg is None:
        raise ConfigProblems(loader.problems or ["config: invalid"])
    return cfg


# -- runtime -----------------------------------------------------------------------------


class SymbolProblems(ConfigProblems):
    """The PLC does not have a configured symbol, or declares it with another type."""


class _PlcNotRunning(Exception):
    """The PLC answers, but its runtime is not in RUN: values are frozen, and a restart may
    invalidate notification handles, so the link counts as down."""


#: Failures of the PLC link itself (anything else is logged with a traceback).
_EXPECTED = (pyads.ADSError, _PlcNotRunning, OSError, RuntimeError)


@dataclass
class _Resolved:
    """A configured symbol as found on the PLC."""

    cfg: SymbolConfig
    sensor: SensorConfig
    index_group: int
    index_offset: int


@dataclass
class _Link:
    """One ADS connection and what was registered on it."""

    conn: pyads.Connection
    gen: int
    symbols: list[_Resolved] = field(default_factory=list)
    handles: list[tuple[int, int | None]] = field(default_factory=list)


@dataclass(frozen=True)
class _Item:
    """One reading on its way from the ADS thread to the publisher."""

    symbol: SymbolConfig
    sensor: SensorConfig
    ts: dt.datetime
    value: float
    arrival: dt.datetime
    source: str  # "notification" or "read"


_STOP = object()


class Bridge:
    """Runs the PLC → MQTT bridge of one configuration until stopped.

    ``start()`` returns at once; the bridge then keeps both links up by itself.
    ``stop()`` deletes the notifications, closes ADS, publishes ``offline`` and disconnects.
    ``finished`` is set when the supervisor has ended: after ``stop()``, or by itself when
    the PLC showed configuration problems at the first connection (``fatal``).
    """

    def __init__(self, cfg: BridgeConfig, clock: Clock | None = None) -> None:
        self.cfg = cfg
        self.clock: Clock = clock or SystemClock()
        self.queue: queue.Queue[Any] = queue.Queue(maxsize=cfg.queue_size)
        self.stop_event = threading.Event()
        self.finished = threading.Event()
        self.plc_up = threading.Event()
        self.mqtt_connected = threading.Event()
        self.fatal: SymbolProblems | None = None
        # Counters (read by tests and worth a look in a debugger; only ever incremented).
        self.ads_connects = 0
        self.published = 0
        self.dropped = 0
        self.decode_errors = 0
        self._gen = 0  # generation of the current ADS link; older callbacks are ignored
        self._validated = False
        self._down_logged = False
        self._down_since: float | None = None
        self._skew_warned_gen = -1
        self._heartbeat = time.monotonic()
        self._count_lock = threading.Lock()  # counters are bumped from several threads
        # Setting plc_up and publishing it happen under one lock, in the supervisor and in
        # paho's on_connect alike: otherwise a connect racing a PLC state change could leave
        # the opposite state retained on the broker.
        self._state_lock = threading.Lock()
        self._publisher_thread: threading.Thread | None = None
        self._supervisor_thread: threading.Thread | None = None
        self._started = False
        self.client = self._make_client()

    # -- MQTT --------------------------------------------------------------------------
    def _make_client(self) -> mqtt.Client:
        b = self.cfg.broker
        c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=self.cfg.client_id,
                        clean_session=False)
        c.will_set(self.cfg.status_topic, "offline", qos=1, retain=True)
        if b.username:
            c.username_pw_set(b.username, b.password())
        if b.tls:
            c.tls_set(ca_certs=str(b.ca_file) if b.ca_file else None)
        c.reconnect_delay_set(MQTT_RECONNECT_MIN, MQTT_RECONNECT_MAX)
        # Readings published while the broker is away wait in paho's queue (QoS 1, sent
        # after the reconnect); the bound keeps a long outage from eating the memory.
        c.max_queued_messages_set(self.cfg.queue_size)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        return c

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason_code: Any,
                    properties: Any) -> None:
        if reason_code.is_failure:
            log.error("broker refused the connection: %s", reason_code)
            return
        client.publish(self.cfg.status_topic, "online", qos=1, retain=True)
        with self._state_lock:
            self._publish_state(self.plc_up.is_set())
        log.info("connected to the broker %s:%d as %r (session present: %s)",
                 self.cfg.broker.host, self.cfg.broker.port, self.cfg.client_id,
                 flags.session_present)
        self.mqtt_connected.set()

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason_code: Any,
                       properties: Any) -> None:
        self.mqtt_connected.clear()
        if not self.stop_event.is_set():
            log.warning("disconnected from the broker (%s); reconnecting, readings are kept "
                        "until it is back (up to %d)", reason_code, self.cfg.queue_size)

    def _publisher(self) -> None:
        while True:
            item = self.queue.get()
            if item is _STOP:
                return
            try:
                self._publish_reading(item)
            except Exception:  # the bridge must outlive one bad reading
                log.exception("unexpected error while publishing a reading of %s",
                              item.symbol.symbol)

    def _publish_reading(self, item: _Item) -> None:
        if item.source == "notification" and self._skew_warned_gen != self._gen:
            skew = item.ts - item.arrival
            if abs(skew) > CLOCK_SKEW_WARN:
                self._skew_warned_gen = self._gen
                log.warning("the PLC's clock differs from this host's by %.0f s (reading of "
                            "%s); readings carry the PLC's time, and the daemon rejects "
                            "readings too far in the future or the past",
                            skew.total_seconds(), item.symbol.symbol)
        s = item.sensor
        payload = payload_for(s.format, s.ts_key, s.value_key, item.ts, item.value)
        info = self.client.publish(s.topic, payload, qos=1)
        if info.rc == mqtt.MQTT_ERR_QUEUE_SIZE:
            self._count_drop(f"the MQTT queue is full ({self.cfg.queue_size} readings waiting "
                             "for the broker)")
        else:
            # MQTT_ERR_NO_CONN means queued by paho for after the reconnect: not lost.
            with self._count_lock:
                self.published += 1

    def _count_drop(self, why: str) -> None:
        with self._count_lock:
            self.dropped += 1
            n = self.dropped
        if n & (n - 1) == 0:  # 1, 2, 4, 8, ...: visible, but not one line per reading
            log.warning("reading dropped: %s (%d dropped so far)", why, n)

    def _publish_state(self, up: bool) -> None:
        self.client.publish(self.cfg.plc_topic, "up" if up else "down", qos=1, retain=True)

    # -- ADS notification thread: decode, stamp, enqueue; nothing that can block -------
    def _enqueue(self, item: _Item) -> None:
        try:
            self.queue.put_nowait(item)
        except queue.Full:
            self._count_drop(f"the reading queue is full ({self.cfg.queue_size}); the "
                             "publisher is behind")

    def _callback(self, link: _Link, r: _Resolved) -> Callable[[Any, Any], None]:
        gen = link.gen
        decode = link.conn.notification(r.cfg.type.ctype, timestamp_as_filetime=True)

        @decode
        def on_change(handle: int, name: Any, filetime: int, raw: Any) -> None:
            if gen != self._gen:
                return  # a late notification of a link already torn down
            arrival = self.clock.now()
            # A zero stamp means the server did not set one; arrival time is then the best.
            ts = filetime_to_utc(filetime) if filetime > 0 else arrival
            self._accept(r, raw, ts, arrival, "notification")

        def guarded(notification: Any, data: Any) -> None:
            # An exception must not escape into the ctypes callback (it would be printed
            # and lost); a sample of an unexpected size makes struct.unpack raise.
            try:
                on_change(notification, data)
            except Exception as exc:  # noqa: BLE001 - counted and logged, never fatal
                with self._count_lock:
                    self.decode_errors += 1
                    n = self.decode_errors
                if n & (n - 1) == 0:
                    log.warning("cannot decode a notification of %s as %s: %s (%d so far)",
                                r.cfg.symbol, r.cfg.plc_type, exc, n)

        return guarded

    def _accept(self, r: _Resolved, raw: Any, ts: dt.datetime, arrival: dt.datetime,
                source: str) -> None:
        value = r.cfg.convert(raw)
        if not math.isfinite(value):
            # JSON has no NaN/Infinity; the daemon would reject it anyway.
            log.warning("%s is %r; not published", r.cfg.symbol, value)
            return
        self._enqueue(_Item(r.cfg, r.sensor, ts, value, arrival, source))

    # -- the supervisor: connect, validate, register, poll, reconnect ------------------
    def _sleep(self, seconds: float) -> bool:
        """Wait ``seconds`` (keeping the watchdog heartbeat fresh); True if asked to stop."""
        deadline = time.monotonic() + seconds
        while True:
            self._heartbeat = time.monotonic()
            left = deadline - self._heartbeat
            if left <= 0:
                return self.stop_event.is_set()
            if self.stop_event.wait(min(left, 1.0)):
                return True

    def _supervise(self) -> None:
        plc = self.cfg.plc
        delay = 1.0
        try:
            while not self.stop_event.is_set():
                self._heartbeat = time.monotonic()
                try:
                    link = self._connect()
                except SymbolProblems as exc:
                    self.fatal = exc
                    log.error("the PLC does not match the configuration:\n%s", exc)
                    return
                except Exception as exc:  # noqa: BLE001 - any failure: back off and retry
                    if not isinstance(exc, _EXPECTED):
                        # A bug rather than the network; retrying beats a supervisor thread
                        # that died silently while the process looks alive.
                        log.exception("unexpected error while connecting to the PLC")
                    self._mark_down(f"cannot connect: {_describe(exc)}")
                    if self._sleep(delay):
                        return
                    delay = min(delay * 2, plc.reconnect_max_seconds)
                    continue
                delay = 1.0
                self._mark_up(link)
                lost = self._poll(link)
                self._gen += 1  # from here on, callbacks of this link are ignored
                self._teardown(link, alive=lost is None or isinstance(lost, _PlcNotRunning))
                if lost is None:
                    return
                self._mark_down(_describe(lost))
        finally:
            self.plc_up.clear()
            self.finished.set()

    def _connect(self) -> _Link:
        plc = self.cfg.plc
        conn = pyads.Connection(plc.ams_net_id, plc.port, plc.ip_address)
        conn.open()  # adds the route; raises ADSError when the PLC cannot be reached
        self._gen += 1
        link = _Link(conn, self._gen)
        try:
            conn.set_timeout(max(1, round(plc.timeout_seconds * 1000)))
            self._check_running(conn)
            link.symbols = self._resolve(conn)
            for r in link.symbols:
                attr = pyads.NotificationAttrib(r.cfg.type.size, adsc.ADSTRANS_SERVERONCHA,
                                                r.cfg.max_delay_ms, r.cfg.cycle_ms)
                # By index group/offset rather than by name: one lookup per connect, and
                # it also works with servers that cannot notify by handle (pyads' own
                # test server). Limitation: a PLC program download or online change that
                # moves a variable without a state change seen by the poll leaves the
                # notification on the old offset until the next reconnect (watching the
                # PLC's symbol version, index group 0xF008, would catch it).
                handles = conn.add_device_notification(
                    (r.index_group, r.index_offset), attr, self._callback(link, r)
                )
                if handles is not None:
                    link.handles.append(handles)
            # A fresh value right away: the symbols may not change for hours.
            now = self.clock.now()
            for r in link.symbols:
                raw = conn.read_by_name(r.cfg.symbol, r.cfg.type.ctype)
                self._accept(r, raw, now, now, "read")
        except BaseException:
            self._gen += 1
            self._teardown(link, alive=False)
            raise
        return link

    def _check_running(self, conn: pyads.Connection) -> None:
        state = conn.read_state()
        if state is None:
            raise RuntimeError("ADS port is not open")
        if state[0] != adsc.ADSSTATE_RUN:
            raise _PlcNotRunning(f"PLC state is {_ADS_STATES.get(state[0], state[0])}, not RUN")

    def _resolve(self, conn: pyads.Connection) -> list[_Resolved]:
        """Look every symbol up on the PLC; SymbolProblems at the first validation, else
        the bad ones are logged and skipped."""
        plc = self.cfg.plc
        where = f"{plc.ams_net_id}:{plc.port} ({plc.ip_address})"
        good: list[_Resolved] = []
        problems: list[str] = []
        for i, sym in enumerate(plc.symbols):
            loc = f"plc.symbols[{i}]"
            try:
                info = conn.read_write(adsc.ADSIGRP_SYM_INFOBYNAMEEX, 0, SAdsSymbolEntry,
                                       sym.symbol, pyads.PLCTYPE_STRING)
            except pyads.ADSError as exc:
                if getattr(exc, "err_code", None) != ADSERR_SYMBOL_NOT_FOUND:
                    raise
                problems.append(f"{loc}.symbol: {sym.symbol!r} is not a symbol of the PLC at "
                                f"{where} (check the spelling and the POU/GVL prefix, e.g. "
                                "'MAIN.' or 'GVL.')")
                continue
            problem = _type_problem(sym, info)
            if problem:
                problems.append(f"{loc}.plc_type: {problem}")
                continue
            good.append(_Resolved(sym, self.cfg.sensor_of(sym), info.iGroup, info.iOffs))
        if problems:
            if not self._validated:
                raise SymbolProblems(problems)
            for p in problems:
                log.error("skipping a symbol until the next reconnect: %s", p)
        self._validated = True
        return good

    def _poll(self, link: _Link) -> BaseException | None:
        """Read the PLC state every poll_seconds; the reason the link is lost, or None when
        asked to stop."""
        while not self._sleep(self.cfg.plc.poll_seconds):
            try:
                self._check_running(link.conn)
            except Exception as exc:  # noqa: BLE001 - whatever it is, the link is not usable
                if not isinstance(exc, _EXPECTED):
                    log.exception("unexpected error while polling the PLC state")
                return exc
        return None

    def _teardown(self, link: _Link, *, alive: bool) -> None:
        """Delete the notifications and close the connection; never raises.

        Deleting also drops pyads' reference to our callback. On a dead link the deletes
        cannot reach the PLC (which forgets a closed connection's notifications anyway), so
        they get a short timeout instead of the full one each.
        """
        conn = link.conn
        try:
            if not alive:
                conn.set_timeout(TEARDOWN_TIMEOUT_MS)
        except pyads.ADSError:
            pass
        for notification, user in link.handles:
            try:
                conn.del_device_notification(notification, user)
            except pyads.ADSError as exc:
                log.debug("deleting notification %d: %s", notification, _describe(exc))
        link.handles.clear()
        try:
            conn.close()
        except (pyads.ADSError, OSError) as exc:
            log.debug("closing the ADS connection: %s", _describe(exc))

    def _mark_up(self, link: _Link) -> None:
        self.ads_connects += 1
        plc = self.cfg.plc
        since = ""
        if self._down_since is not None:
            since = f" after {time.monotonic() - self._down_since:.0f} s"
        log.info("PLC %s:%d (%s) connected%s; %d of %d symbols registered for notifications",
                 plc.ams_net_id, plc.port, plc.ip_address, since, len(link.symbols),
                 len(plc.symbols))
        self._down_logged = False
        self._down_since = None
        with self._state_lock:
            self.plc_up.set()
            self._publish_state(True)

    def _mark_down(self, reason: str) -> None:
        with self._state_lock:
            was_up = self.plc_up.is_set()
            self.plc_up.clear()
            if was_up or not self._down_logged:
                # Also at the start of an outage that began before we were ever up: a
                # retained "up" may be left over from a bridge that was killed.
                self._publish_state(False)
        if self._down_since is None:
            self._down_since = time.monotonic()
        plc = self.cfg.plc
        if not self._down_logged:
            # Once per outage: a PLC away for a weekend must not fill the journal.
            self._down_logged = True
            log.warning("PLC %s:%d (%s) %s: %s; reconnecting (backoff 1..%g s)",
                        plc.ams_net_id, plc.port, plc.ip_address,
                        "lost" if was_up else "unavailable", reason, plc.reconnect_max_seconds)
        else:
            log.debug("PLC still unavailable: %s", reason)

    # -- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        if self._started:
            raise RuntimeError("a Bridge can only be started once")
        self._started = True
        if self.cfg.plc.local_ams_net_id:
            # Process-wide in pyads' router: the net id the PLC's route points back to.
            pyads.set_local_address(self.cfg.plc.local_ams_net_id)
        b = self.cfg.broker
        # connect_async: the bridge starts (and watches the PLC) even if the broker is down.
        self.client.connect_async(b.host, b.port, keepalive=b.keepalive)
        self.client.loop_start()
        self._publisher_thread = threading.Thread(target=self._publisher,
                                                  name="bridge-publisher", daemon=True)
        self._supervisor_thread = threading.Thread(target=self._supervise,
                                                   name="bridge-supervisor", daemon=True)
        self._publisher_thread.start()
        self._supervisor_thread.start()
        interval = watchdog_interval()
        if interval is not None:
            threading.Thread(target=self._watchdog, args=(interval,), name="bridge-watchdog",
                             daemon=True).start()
        notify("READY=1")

    def _watchdog(self, interval: float) -> None:
        while not self.stop_event.wait(interval):
            # Only while the supervisor is alive: a hung ADS call must get us restarted.
            if time.monotonic() - self._heartbeat < 2 * interval + self.cfg.plc.timeout_seconds:
                notify("WATCHDOG=1")

    def request_stop(self) -> None:
        """Ask the bridge to stop (safe from a signal handler); ``stop()`` finishes it."""
        self.stop_event.set()

    def stop(self, timeout: float = 10.0) -> None:
        notify("STOPPING=1")
        self.stop_event.set()
        if self._supervisor_thread is not None:
            self._supervisor_thread.join(timeout)  # deletes the notifications, closes ADS
            if self._supervisor_thread.is_alive():
                log.warning("the ADS connection did not close within %g s", timeout)
        if self._publisher_thread is not None:
            # The publisher empties the queue before it sees _STOP: nothing already read
            # from the PLC is left behind.
            try:
                self.queue.put(_STOP, timeout=timeout)
            except queue.Full:
                log.warning("reading queue still full at stop; %d readings not published",
                            self.queue.qsize())
            self._publisher_thread.join(timeout)
        if self.mqtt_connected.is_set():
            info = self.client.publish(self.cfg.status_topic, "offline", qos=1, retain=True)
            try:
                info.wait_for_publish(timeout)
            except (RuntimeError, ValueError) as exc:
                log.warning("could not publish the offline status: %s", exc)
        self.client.disconnect()
        self.client.loop_stop()
        log.info("bridge stopped: %d readings published, %d dropped", self.published,
                 self.dropped)

    def run(self) -> None:
        """Start, wait until ``request_stop()`` or a fatal problem, then stop."""
        self.start()
        try:
            while not self.finished.wait(1.0):
                pass
        finally:
            self.stop()


def _type_problem(sym: SymbolConfig, info: SAdsSymbolEntry) -> str | None:
    """Why the PLC's declaration of ``sym`` does not fit its configured plc_type, or None."""
    want = sym.type
    declared = info.symbol_type.strip()
    name = declared.upper()
    size = int(info.size)
    if name == want.name and size == want.size:
        return None
    # An alias (TYPE T_Celsius : LREAL) reports its own name but the base type's ADS type
    # id and size; a different elementary type name is a mismatch even when the encoding
    # happens to agree (WORD vs UINT), because it usually means the wrong variable.
    if name not in PLC_TYPES and info.dataType == want.ads_type and size == want.size:
        return None
    return (f"configured {want.name}, but the PLC declares {sym.symbol!r} as {declared} "
            f"({size} bytes); set plc_type = \"{declared}\" if that is right"
            if name in PLC_TYPES else
            f"configured {want.name}, but the PLC declares {sym.symbol!r} as {declared} "
            f"({size} bytes), which is not an elementary numeric type")


def _describe(exc: BaseException) -> str:
    return str(exc).removeprefix("ADSError: ").strip() or type(exc).__name__


# -- command line ------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pseudotwin bridge",
        description=(
            "Publish PLC variables as sensor readings: ADS device notifications (on change) "
            "of the symbols in [[plc.symbols]] go to their sensors' MQTT topics, QoS 1, "
            "time-stamped by the PLC. Reconnects by itself when the PLC, the route or the "
            "broker drops; the PLC state is polled every plc.poll_seconds because ADS has no "
            "heartbeat. Runs until SIGTERM/SIGINT."
        ),
        epilog=(
            "Exit status: 0 stopped by a signal; 78 configuration error (the file, or a "
            "symbol the PLC does not have or declares with another type); every problem is "
            "printed with its location, e.g. 'plc.symbols[1].plc_type: ...'."
        ),
    )
    p.add_argument("--config", required=True, type=Path, metavar="FILE",
                   help="TOML configuration: [broker], [[sensors]], [plc], [[plc.symbols]] "
                        "(the daemon's file or one of its own)")
    p.add_argument("--check", action="store_true",
                   help="only validate the configuration file, without connecting to anything")
    p.add_argument("--log-level", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="default INFO")
    return p


def _print_problems(path: Path, problems: Sequence[str]) -> None:
    for problem in problems:
        print(f"{path}: {problem}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """``pseudotwin bridge --config FILE``: 0 after a signal, 78 on configuration errors."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help and usage errors; callers want an int back
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    if args.log_level:
        logging.getLogger().setLevel(args.log_level)
    try:
        cfg = load_bridge_config(args.config, runtime=True)
    except ConfigProblems as exc:
        _print_problems(args.config, exc.problems)
        return EX_CONFIG
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)  # already names the file
        return EX_CONFIG
    if args.check:
        print(f"{args.config}: OK ({len(cfg.plc.symbols)} PLC symbols)")
        return 0
    bridge = Bridge(cfg)

    def on_signal(signum: int, frame: object) -> None:
        log.info("received %s; stopping", signal.Signals(signum).name)
        bridge.request_stop()

    in_main = threading.current_thread() is threading.main_thread()
    previous = {}
    if in_main:
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, on_signal)
    try:
        bridge.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if bridge.fatal is not None:
        print(f"pseudotwin bridge: the PLC does not match {args.config}:", file=sys.stderr)
        _print_problems(args.config, bridge.fatal.problems)
        return EX_CONFIG
    return 0

