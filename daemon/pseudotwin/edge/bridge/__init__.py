"""PLC bridge: ADS device notifications of configured PLC symbols → MQTT sensor readings.

- :mod:`~pseudotwin.edge.bridge.config`: its configuration ([plc], [[plc.symbols]],
  [bridge]) and loader, which reuse the daemon's broker and sensor sections;
- :mod:`~pseudotwin.edge.bridge.plc`: the runtime (:class:`Bridge`): ADS connection,
  notifications, the MQTT publisher and the reconnect supervisor;
- :mod:`~pseudotwin.edge.bridge.outbox`: the spool every reading is on until the broker
  acknowledged it.

``pseudotwin bridge --config FILE`` (:mod:`pseudotwin.cli.bridge`) runs it.
"""

from __future__ import annotations

from pseudotwin.edge.bridge.config import (
    PLC_TYPES,
    BridgeConfig,
    PlcConfig,
    PlcType,
    SymbolConfig,
    load_bridge_config,
)
from pseudotwin.edge.bridge.plc import (
    ADSERR_SYMBOL_NOT_FOUND,
    Bridge,
    SymbolProblems,
    filetime_to_utc,
)

__all__ = [
    "ADSERR_SYMBOL_NOT_FOUND",
    "PLC_TYPES",
    "Bridge",
    "BridgeConfig",
    "PlcConfig",
    "PlcType",
    "SymbolConfig",
    "SymbolProblems",
    "filetime_to_utc",
    "load_bridge_config",
]
