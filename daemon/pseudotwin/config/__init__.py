"""Service configuration: a TOML file turned into typed, frozen, self-validating dataclasses.

- :mod:`~pseudotwin.config.model`: the value types (BrokerConfig, SensorConfig, TwinConfig,
  ServiceConfig), which validate themselves and declare every default;
- :mod:`~pseudotwin.config.validate`: the validation helpers they share with the bridge;
- :mod:`~pseudotwin.config.loader`: the TOML loader (:func:`load_config`);
- :mod:`~pseudotwin.config.checks`: what must hold at start-up (:func:`check_config`).

The MQTT password is never part of the configuration values: the file names an environment
variable or a secret file, and :meth:`BrokerConfig.password` reads it at call time. It can
therefore not leak through ``repr``, logs of the config, or error messages.

TOML layout (see ``config/example.toml`` for a commented example)::

    [broker]     host, port, tls, ca_file, username, password_env | password_file,
                 client_id, keepalive
    [service]    timezone, state_dir, base_topic, day_start, day_end, init_minutes,
                 slot_minutes, publish_every_minutes, stale_after_minutes, max_skew_seconds,
                 log_level, queue_size, baselines, monitor_every_minutes, journal_fsync,
                 store
    [[sensors]]  id, topic, format, ts_key, value_key, unit, min, max
    [[twins]]    id, quantity, references, target, artifact
    [metrics]    host, port, record_port (optional: Prometheus endpoints)
    [homeassistant]  enabled, discovery_prefix, baselines (optional: HA MQTT discovery)
"""

from __future__ import annotations

from pseudotwin.config.checks import check_config
from pseudotwin.config.loader import ArtifactCheck, load_config
from pseudotwin.config.model import BrokerConfig, SensorConfig, ServiceConfig, TwinConfig
from pseudotwin.config.validate import ConfigProblems, base_topic_problem, topic_problem

__all__ = [
    "ArtifactCheck",
    "BrokerConfig",
    "ConfigProblems",
    "SensorConfig",
    "ServiceConfig",
    "TwinConfig",
    "base_topic_problem",
    "check_config",
    "load_config",
    "topic_problem",
]
