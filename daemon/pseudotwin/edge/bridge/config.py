"""The bridge's configuration: PLC, symbols and its own MQTT settings, validated like the
daemon's (:mod:`pseudotwin.config`) and usually in the same file.

Layout (the same TOML file as the daemon, or a file of its own; see
``config/bridge-example.toml``)::

    [broker], [[sensors]]   as for the daemon (``pseudotwin.config``)
    [bridge]                optional: client_id, base_topic, queue_size, spool_dir,
                            spool_fsync
    [plc]                   ams_net_id, host, port, local_ams_net_id, poll_seconds,
                            reconnect_max_seconds, timeout_seconds
    [[plc.symbols]]         symbol, sensor, plc_type, cycle_ms, max_delay_ms, scale, offset

A file that also has ``[service]`` or ``[[twins]]`` is the daemon's own file; it is then
validated exactly as the daemon validates it (without looking at artifacts), so one file
cannot be fine for the bridge and broken for the daemon.
"""

from __future__ import annotations

import ctypes
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any

import numpy as np
import pyads
from pyads import constants as adsc

from pseudotwin.config import BrokerConfig, ConfigProblems, SensorConfig
from pseudotwin.config.checks import broker_problems
from pseudotwin.config.loader import SERVICE_DEFAULTS, Loader, read_toml
from pseudotwin.config.model import cross_problems
from pseudotwin.config.validate import (
    Found,
    base_topic_problem,
    expect,
    field_defaults,
    nonempty,
    raise_if,
    suggest,
    type_name,
)

__all__ = [
    "NON_NUMERIC_TYPES",
    "PLC_TYPES",
    "BridgeConfig",
    "PlcConfig",
    "PlcType",
    "SymbolConfig",
    "load_bridge_config",
]

_NET_ID = re.compile(r"\d{1,3}(\.\d{1,3}){5}")


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


# -- configuration -----------------------------------------------------------------------

#: Smallest plc.poll_seconds [s].
MIN_POLL_SECONDS = 0.1
#: The TCP port of ADS (AMS/TCP): every PLC's router listens on it.
ADS_TCP_PORT = 48898


def _net_id_problem(value: str) -> str | None:
    if not _NET_ID.fullmatch(value) or any(int(p) > 255 for p in value.split(".")):
        return f"{value!r} is not an AMS net id (six numbers 0..255, e.g. '5.12.34.56.1.1')"
    return None


def _number_problem(found: Found, name: str, value: object, *, low: float,
                    low_inclusive: bool = True, high: float | None = None) -> None:
    if not expect(found, name, value, "number"):
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
        raise_if(self._problems())
        for name in ("cycle_ms", "max_delay_ms", "scale", "offset"):
            object.__setattr__(self, name, float(getattr(self, name)))

    def _problems(self) -> Found:
        found: Found = []
        if nonempty(found, "symbol", self.symbol) and (
            any(c.isspace() or ord(c) < 0x20 for c in self.symbol)
        ):
            found.append(("symbol", f"{self.symbol!r} contains blanks or control characters"))
        nonempty(found, "sensor", self.sensor)
        if nonempty(found, "plc_type", self.plc_type) and self.plc_type not in PLC_TYPES:
            if self.plc_type in NON_NUMERIC_TYPES:
                found.append(("plc_type", f"{self.plc_type} is not a numeric type; a reading "
                                          f"is a number ({', '.join(PLC_TYPES)})"))
            else:
                found.append(("plc_type", f"unknown type {self.plc_type!r}"
                                          f"{suggest(self.plc_type, PLC_TYPES)}; one of "
                                          f"{', '.join(PLC_TYPES)}"))
        # ADS carries both times as 32-bit counts of 100 ns.
        limit = (2**32 - 1) / 1e4
        _number_problem(found, "cycle_ms", self.cycle_ms, low=0.0, high=limit)
        _number_problem(found, "max_delay_ms", self.max_delay_ms, low=0.0, high=limit)
        if expect(found, "scale", self.scale, "number") and self.scale == 0:
            found.append(("scale", "must not be 0 (every reading would be the offset)"))
        expect(found, "offset", self.offset, "number")
        return found

    @property
    def type(self) -> PlcType:
        return PLC_TYPES[self.plc_type]

    def convert(self, raw: float | int | bool) -> float:
        """The reading value of a raw PLC value, computed on the decimal digits the PLC
        value and the settings show: an INT 219 with scale 0.1 is 21.9, not
        21.900000000000002, and a REAL 21.3 is 21.3, not its float32's 21.299999237060547."""
        if self.plc_type == "REAL":  # shortest digits that give back the PLC's float32
            digits = str(np.float32(raw))
        elif isinstance(raw, float):
            digits = repr(raw)
        else:
            digits = str(int(raw))
        if self.scale == 1 and self.offset == 0:
            return float(digits)
        # (a NaN or infinity stays one: the bridge then says it is not published)
        return float(Decimal(digits) * Decimal(repr(float(self.scale)))
                     + Decimal(repr(float(self.offset))))


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
        raise_if(self._problems())
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
    elif nonempty(found, "ams_net_id", ams_net_id):
        assert isinstance(ams_net_id, str)
        problem = _net_id_problem(ams_net_id)
        if problem:
            found.append(("ams_net_id", problem))
    if host is not None and nonempty(found, "host", host):
        assert isinstance(host, str)
        if any(c.isspace() or ord(c) < 0x20 for c in host):
            found.append(("host", f"{host!r} contains blanks or control characters"))
        elif ":" in host:  # also an IPv6 address: pyads' router speaks IPv4 only
            found.append(("host", f"{host!r}: give the IPv4 address or host name alone; the "
                                  "AMS port goes in plc.port (the ADS TCP port is always "
                                  f"{ADS_TCP_PORT})"))
    if expect(found, "port", port, "integer") and not 1 <= port <= 65535:  # type: ignore[operator]
        found.append(("port", f"must be in 1..65535, got {port}"))
    if local_ams_net_id is not None and nonempty(found, "local_ams_net_id", local_ams_net_id):
        assert isinstance(local_ams_net_id, str)
        problem = _net_id_problem(local_ams_net_id)
        if problem:
            found.append(("local_ams_net_id", problem))
    # Each poll is one ADS request to the PLC: below this it would load its router for
    # nothing (a dropped link is seen within a poll anyway).
    _number_problem(found, "poll_seconds", poll_seconds, low=MIN_POLL_SECONDS)
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
                           f"{suggest(sensor, sensors)}; add it as a [[sensors]] table")
        elif sensor in first_sensor:
            out.append(f"{loc}.sensor: sensor {sensor!r} is already fed by "
                       f"{first_sensor[sensor]}; one PLC symbol per sensor")
        else:
            first_sensor[sensor] = loc
    return out


def _bridge_scalar_problems(*, client_id: object, base_topic: object, queue_size: object,
                            spool_dir: object, spool_fsync: object,
                            broker_client_id: str | None) -> Found:
    found: Found = []
    # None: no default could be derived because [broker] is invalid (reported there).
    if client_id is not None and nonempty(found, "client_id", client_id):
        assert isinstance(client_id, str)
        if any(ord(c) < 0x20 for c in client_id):
            found.append(("client_id", "must not contain NUL or control characters"))
        elif client_id == broker_client_id:
            # Both use persistent sessions: one id would make the broker kick the daemon
            # off every time the bridge connects, and vice versa.
            found.append(("client_id", f"{client_id!r} is broker.client_id, which the daemon "
                                       "uses; the bridge needs its own"))
    if expect(found, "base_topic", base_topic, "string"):
        assert isinstance(base_topic, str)
        problem = base_topic_problem(base_topic)
        if problem:
            found.append(("base_topic", problem))
    if expect(found, "queue_size", queue_size, "integer"):
        assert isinstance(queue_size, int)
        if queue_size < 1:
            found.append(("queue_size", "must be at least 1"))
    if spool_dir is not None:
        expect(found, "spool_dir", spool_dir, "path")
    expect(found, "spool_fsync", spool_fsync, "boolean")
    return found


@dataclass(frozen=True, kw_only=True)
class BridgeConfig:
    """Everything the bridge needs.

    client_id: the bridge's MQTT client id (persistent session); default
        ``<broker.client_id>-bridge``, never the daemon's.
    base_topic: status topics go to ``<base_topic>/bridge/...``; default the daemon's
        ``service.base_topic`` when the file has one, else ``"pseudotwin"``.
    queue_size: bound of the queue between the ADS notification thread and the publisher,
        and of the readings waiting for the broker in paho's queue; beyond it, without a
        spool, each sensor's newest reading is held back until there is room.
    spool_dir: folder of the on-disk spool (``bridge-<client_id>.jsonl``): every reading is
        written there before it is handed to MQTT and stays until the broker acknowledged
        it, so neither a long broker outage nor a restart of the bridge loses one. Default
        the daemon's ``service.state_dir`` when this is the daemon's file; None (readings
        wait in memory only) in a file of the bridge's own without it.
    spool_fsync: fsync the spool before its readings are handed to MQTT (a power cut then
        loses none either); false for SD cards and other slow or wear-sensitive flash.
    """

    broker: BrokerConfig
    sensors: dict[str, SensorConfig]
    plc: PlcConfig
    client_id: str
    base_topic: str = SERVICE_DEFAULTS["base_topic"]  # the daemon's default
    queue_size: int = 10000
    spool_dir: Path | None = None
    spool_fsync: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.spool_dir, str):
            object.__setattr__(self, "spool_dir", Path(self.spool_dir))
        found = _bridge_scalar_problems(
            client_id=self.client_id, base_topic=self.base_topic, queue_size=self.queue_size,
            spool_dir=self.spool_dir, spool_fsync=self.spool_fsync,
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
        raise_if(found)
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
    def unstamped_note(self) -> str | None:
        """What to tell about bridged sensors whose payload carries no time (None: none)."""
        unstamped = sorted({s.sensor for s in self.plc.symbols
                            if not self.sensors[s.sensor].stamped})
        if not unstamped:
            return None
        return (f"sensor(s) {', '.join(unstamped)} carry no time stamp in their payload "
                "(format = \"number\", or no ts_key): a reading the bridge sends late (after "
                "a broker outage; with a spool, after a restart too) is stamped on arrival, "
                "and one sent twice counts twice; give them format = \"json\" with a ts_key "
                "and the PLC's time goes with each reading")

    @property
    def plc_topic(self) -> str:
        return f"{self.base_topic}/bridge/plc"

    def sensor_of(self, symbol: SymbolConfig) -> SensorConfig:
        return self.sensors[symbol.sensor]

    @property
    def spool_path(self) -> Path | None:
        """The spool file, named after the client id (two bridges on one state dir, one per
        PLC, each have their own); None without a spool_dir."""
        if self.spool_dir is None:
            return None
        return self.spool_dir / f"bridge-{re.sub(r'[^A-Za-z0-9._-]', '_', self.client_id)}.jsonl"


_DEFAULTS = field_defaults(BridgeConfig)


class _BridgeLoader:
    """Turns one parsed TOML document into a BridgeConfig, collecting every problem.

    Broker and sensors are parsed by the daemon's own loader
    (:class:`pseudotwin.config.loader.Loader`), so they follow exactly the daemon's rules and
    messages.
    """

    BRIDGE_TOP_KEYS = ("bridge", "plc")
    TOP_KEYS = (*Loader.TOP_KEYS, *BRIDGE_TOP_KEYS)
    BRIDGE_KEYS = ("client_id", "base_topic", "queue_size", "spool_dir", "spool_fsync")
    PLC_KEYS = ("ams_net_id", "host", "port", "local_ams_net_id", "poll_seconds",
                "reconnect_max_seconds", "timeout_seconds", "symbols")
    PLC_REQUIRED = ("ams_net_id", "symbols")
    # The scalars checked on their own; a missing one keeps PlcConfig's default.
    PLC_DEFAULTS: dict[str, Any] = {"ams_net_id": None, **field_defaults(PlcConfig)}
    SYMBOL_KEYS = ("symbol", "sensor", "plc_type", "cycle_ms", "max_delay_ms", "scale",
                   "offset")
    SYMBOL_REQUIRED = ("symbol", "sensor", "plc_type")

    def __init__(self, base_dir: Path, runtime: bool) -> None:
        self.base_dir = base_dir
        self.runtime = runtime
        # The daemon's plain loader, not its start-up checks: it must not require the twins'
        # artifacts, which are none of the bridge's business.
        self.inner = Loader(base_dir)
        self.problems = self.inner.problems  # one list for the daemon's sections and ours

    def load(self, doc: dict[str, Any]) -> BridgeConfig | None:
        for key in doc:
            if key not in self.TOP_KEYS:
                self.inner.add(key, f"unknown key{suggest(key, self.TOP_KEYS)}")
        daemon_part = {k: v for k, v in doc.items() if k in Loader.TOP_KEYS}
        state_dir: Path | None = None
        if "service" in doc or "twins" in doc:
            broker, sensors, bad_ids, service_base, state_dir = \
                self.load_daemon_file(daemon_part)
        else:
            broker = self.inner.load_broker(doc)
            good, _complete, bad_ids = self.inner.load_sensors(doc)
            sensors = {s.id: s for _, s in good}
            service_base = None
            if good or bad_ids is not None:
                base = doc["bridge"].get("base_topic", _DEFAULTS["base_topic"]) \
                    if isinstance(doc.get("bridge"), dict) else None
                self.problems.extend(cross_problems(
                    base if isinstance(base, str) else None, good, [], bad_ids
                ))
        bridge = self.load_bridge(doc, broker, service_base, state_dir)
        plc = self.load_plc(doc, sensors, bad_ids)
        if self.runtime and broker is not None:
            for where, msg in broker_problems(broker):
                self.inner.add(f"broker.{where}", msg)
        if self.problems or broker is None or bridge is None or plc is None:
            return None
        return BridgeConfig(broker=broker, sensors=sensors, plc=plc, **bridge)

    def load_daemon_file(
        self, doc: dict[str, Any]
    ) -> tuple[BrokerConfig | None, dict[str, SensorConfig], set[str] | None, str | None,
               Path | None]:
        """Validate the daemon's part exactly as the daemon does; (broker, valid sensors,
        ids of invalid sensors, service.base_topic, service.state_dir)."""
        cfg = self.inner.load(doc)
        if cfg is not None:
            return cfg.broker, dict(cfg.sensors), set(), cfg.base_topic, cfg.state_dir
        # The file has problems (already reported); go on with what is valid so that the
        # [plc] part is checked in the same run. A scratch loader keeps them from being
        # reported twice.
        scratch = Loader(self.base_dir)
        broker = scratch.load_broker(doc)
        good, _complete, bad_ids = scratch.load_sensors(doc)
        service = doc.get("service")
        base = service.get("base_topic", SERVICE_DEFAULTS["base_topic"]) \
            if isinstance(service, dict) else None
        state_dir = scratch.path(service, "state_dir", "service") \
            if isinstance(service, dict) else None
        return (broker, {s.id: s for _, s in good}, bad_ids,
                base if isinstance(base, str) else None,
                state_dir if isinstance(state_dir, Path) else None)

    def load_bridge(self, doc: dict[str, Any], broker: BrokerConfig | None,
                    service_base: str | None, state_dir: Path | None) -> dict[str, Any] | None:
        table = doc.get("bridge", {})
        if not isinstance(table, dict):
            self.inner.add("bridge", f"expected a table [bridge], got {type_name(table)}")
            return None
        self.inner.keys(table, self.BRIDGE_KEYS, (), "bridge")
        broker_id = broker.client_id if broker is not None else None
        values = {
            "client_id": table.get("client_id", f"{broker_id}-bridge" if broker_id else None),
            "base_topic": table.get("base_topic", service_base or _DEFAULTS["base_topic"]),
            "queue_size": table.get("queue_size", _DEFAULTS["queue_size"]),
            # the daemon's state dir (the units share it) unless set; none in a file of
            # the bridge's own
            "spool_dir": self.inner.path(table, "spool_dir", "bridge")
            if "spool_dir" in table else state_dir,
            "spool_fsync": table.get("spool_fsync", _DEFAULTS["spool_fsync"]),
        }
        found = _bridge_scalar_problems(**values, broker_client_id=broker_id)
        if "spool_fsync" in table and "spool_dir" not in table and state_dir is None:
            found.append(("spool_fsync", "has no effect without a spool: set spool_dir too "
                                         "(a file of the bridge's own has none by default)"))
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
                                          f"{type_name(items)}")
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
    doc = read_toml(path)
    loader = _BridgeLoader(path.absolute().parent, runtime)
    cfg = loader.load(doc)
    if loader.problems or cfg is None:
        raise ConfigProblems(loader.problems or ["config: invalid"])
    return cfg
