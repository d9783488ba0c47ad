"""The configuration's value types: frozen dataclasses that validate themselves.

Each type checks its own fields in ``__post_init__`` and raises :class:`ConfigProblems`
listing every problem (``"<field>: <message>"``); :class:`ServiceConfig` also checks the
sections against each other (:func:`cross_problems`). Field defaults are declared here only;
the TOML loader takes them from these dataclasses.
"""

from __future__ import annotations

import os
import re
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import date, timedelta
from functools import cached_property
from pathlib import Path
from typing import Literal

from pseudotwin.config.validate import (
    ConfigProblems,
    Found,
    base_topic_problem,
    expect,
    host_problem,
    nonempty,
    raise_if,
    suggest,
    topic_problem,
)
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.core.thinning import DEFAULT_MIN_INTERVAL, MIN_INTERVAL_SECONDS, Thinning

__all__ = [
    "LOG_LEVELS",
    "QUANTITIES",
    "SENSOR_FORMATS",
    "BrokerConfig",
    "HomeAssistantConfig",
    "MetricsConfig",
    "SensorConfig",
    "ServiceConfig",
    "TwinConfig",
    "cross_problems",
    "homeassistant_problems",
    "service_scalar_problems",
    "thinning_of",
]

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
# When the baselines are published: on the publishing grid only, also at every reading
# that moves the twin (as the primary estimate always is), or never (not even run).
BASELINE_CADENCES = ("grid", "reading", "none")
SENSOR_FORMATS = ("number", "json")
QUANTITIES = ("temperature", "co2")

# Units a twin of each quantity accepts, with the widest range a sensor of that unit may
# declare. The bounds are physical plausibility limits for a building, not comfort limits:
# they catch a CO2 range typed into a temperature sensor, a °F range labelled °C, etc.
_UNIT_BOUNDS: dict[str, dict[str, tuple[float, float]]] = {
    "temperature": {
        "°C": (-100.0, 200.0),
        "degC": (-100.0, 200.0),
        "C": (-100.0, 200.0),
        "K": (173.15, 473.15),
        "°F": (-148.0, 392.0),
        "degF": (-148.0, 392.0),
        "F": (-148.0, 392.0),
    },
    "co2": {"ppm": (0.0, 100_000.0)},
}
_QUANTITY_OF_UNIT = {u: q for q, units in _UNIT_BOUNDS.items() for u in units}
# The units a twin's references and target may have: its artifact, σ and estimates are in
# the quantity's unit (°C, ppm) and nothing converts, so a °F sensor would be estimated as
# °C and published labelled °C. Other sensors (recorded only, covariates) may be in any.
_TWIN_UNITS = {"temperature": ("°C", "degC", "C"), "co2": ("ppm",)}

_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# Twin ids become one MQTT topic level, a file name stem and a DB key: keep them boring.
_TWIN_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
# Beyond these, durations overflow datetime arithmetic and mean nothing for a building.
MAX_STALE_AFTER_MINUTES = 7 * 24 * 60
MAX_SKEW_SECONDS = 24 * 3600


#: A broker.client_id at most [bytes of UTF-8]: daemons refuse a claim of twins whose client
#: id exceeds edge/ownership.py's MAX_ID_BYTES (1 kB), and the recorder, fleet instances and
#: replays add suffixes of their own to it.
MAX_CLIENT_ID_BYTES = 256


@dataclass(frozen=True, kw_only=True)
class BrokerConfig:
    """Where and how to reach the MQTT broker.

    The password is never stored: ``password_env`` names an environment variable and
    ``password_file`` a file holding it (at most one of them); :meth:`password` reads it.
    """

    host: str
    port: int = 1883
    tls: bool = False
    ca_file: Path | None = None
    username: str | None = None
    password_env: str | None = None
    password_file: Path | None = None
    client_id: str = "pseudotwin"
    keepalive: int = 30

    def __post_init__(self) -> None:
        if isinstance(self.ca_file, str):
            object.__setattr__(self, "ca_file", Path(self.ca_file))
        if isinstance(self.password_file, str):
            object.__setattr__(self, "password_file", Path(self.password_file))
        raise_if(self._problems())

    def _problems(self) -> Found:
        found: Found = []
        if nonempty(found, "host", self.host) and (problem := host_problem(self.host)):
            found.append(("host", problem))
        if expect(found, "port", self.port, "integer") and not 1 <= self.port <= 65535:
            found.append(("port", f"must be in 1..65535, got {self.port}"))
        expect(found, "tls", self.tls, "boolean")
        if self.ca_file is not None and expect(found, "ca_file", self.ca_file, "path"):
            if self.tls is not True:
                found.append(("ca_file", "is only used with tls = true"))
        if self.username is not None and nonempty(found, "username", self.username):
            if "\x00" in self.username or len(self.username.encode()) > 65535:
                found.append(("username", "must not contain NUL, and at most 65535 bytes"))
        if self.password_env is not None and expect(
            found, "password_env", self.password_env, "string"
        ):
            if not _ENV_NAME.fullmatch(self.password_env):
                found.append(("password_env",
                              f"{self.password_env!r} is not an environment variable name"))
        if self.password_file is not None:
            expect(found, "password_file", self.password_file, "path")
        if self.password_env is not None and self.password_file is not None:
            found.append(("password_file", "give either password_env or password_file, not both"))
        if (self.password_env is not None or self.password_file is not None) and (
            self.username is None
        ):
            # MQTT 3.1.1 forbids a password without a user name.
            found.append(("username", "is required when a password source is configured"))
        if nonempty(found, "client_id", self.client_id):
            if any(ord(c) < 0x20 for c in self.client_id):
                found.append(("client_id", "must not contain NUL or control characters"))
            elif len(self.client_id.encode("utf-8")) > MAX_CLIENT_ID_BYTES:
                found.append(("client_id", f"is longer than {MAX_CLIENT_ID_BYTES} bytes (the "
                              "other daemons refuse a claim of twins by a longer id)"))
        if expect(found, "keepalive", self.keepalive, "integer") and not (
            1 <= self.keepalive <= 65535
        ):
            found.append(("keepalive", f"must be in 1..65535 seconds, got {self.keepalive}"))
        return found

    def password_problem(self) -> tuple[str, str] | None:
        """(field, message) if the configured password source cannot be read now, else None.

        Messages never contain the password or any part of the secret file.
        """
        if self.password_env is not None:
            value = os.environ.get(self.password_env)
            if value is None:
                return ("password_env", f"environment variable {self.password_env} is not set")
            if not value:
                return ("password_env", f"environment variable {self.password_env} is empty")
        elif self.password_file is not None:
            try:
                text = self.password_file.read_text(encoding="utf-8")
            except FileNotFoundError:
                return ("password_file", f"{self.password_file} does not exist")
            except OSError as exc:
                return ("password_file", f"{self.password_file}: {exc.strerror or 'unreadable'}")
            except UnicodeDecodeError:
                return ("password_file", f"{self.password_file} is not UTF-8 text")
            if not text.rstrip("\r\n"):
                return ("password_file", f"{self.password_file} is empty")
        return None

    def password(self) -> str | None:
        """The MQTT password, read now from the environment or the secret file.

        None when no password source is configured. Raises :class:`ConfigProblems` (without
        the secret in it) when the source is configured but unavailable. A trailing newline
        in the file is not part of the password (``echo secret > file`` is common).
        """
        problem = self.password_problem()
        if problem is not None:
            raise ConfigProblems([f"broker.{problem[0]}: {problem[1]}"])
        if self.password_env is not None:
            return os.environ[self.password_env]
        if self.password_file is not None:
            return self.password_file.read_text(encoding="utf-8").rstrip("\r\n")
        return None


@dataclass(frozen=True, kw_only=True)
class SensorConfig:
    """One measured quantity at one place, arriving on one MQTT topic.

    format: ``"number"`` (the payload is a bare number; its time is the arrival time) or
        ``"json"`` (an object with the value under ``value_key`` and the time under
        ``ts_key``; ``ts_key = ""`` means the payload carries no time and arrival time is used).
    unit: unit of the values, e.g. ``"°C"`` or ``"ppm"``.
    min, max: valid range [unit], inclusive; readings outside are rejected.
    min_interval_seconds: the window keeps at most one point of this sensor per interval
        [s], the mean of its readings in it (core/thinning.py); a chatty sensor then costs
        the models what a reading a minute costs.
    """

    id: str
    topic: str
    unit: str
    min: float
    max: float
    format: Literal["number", "json"] = "json"
    ts_key: str = "ts"
    value_key: str = "value"
    min_interval_seconds: float = DEFAULT_MIN_INTERVAL.total_seconds()

    def __post_init__(self) -> None:
        found = self._problems()
        raise_if(found)
        object.__setattr__(self, "min", float(self.min))
        object.__setattr__(self, "max", float(self.max))

    @property
    def stamped(self) -> bool:
        """Whether a payload carries its reading's time; if not, it is stamped on arrival."""
        return self.format == "json" and bool(self.ts_key)

    def _problems(self) -> Found:
        found: Found = []
        if nonempty(found, "id", self.id):
            if self.id != self.id.strip() or any(ord(c) < 0x20 for c in self.id):
                found.append(("id", f"{self.id!r} has surrounding blanks or control characters"))
            elif "#" in self.id:  # history CSV files take '#' for a comment
                found.append(("id", f"{self.id!r} contains '#', which history files (CSV) "
                                    "read as the start of a comment"))
        if expect(found, "topic", self.topic, "string"):
            problem = topic_problem(self.topic)
            if problem:
                found.append(("topic", problem))
        if expect(found, "format", self.format, "string") and self.format not in SENSOR_FORMATS:
            found.append(("format", f"must be one of {', '.join(map(repr, SENSOR_FORMATS))}, "
                                    f"got {self.format!r}"))
        expect(found, "ts_key", self.ts_key, "string")
        nonempty(found, "value_key", self.value_key)
        if (self.format == "json" and isinstance(self.ts_key, str) and self.ts_key
                and self.ts_key == self.value_key):
            found.append(("ts_key", "must differ from value_key"))
        nonempty(found, "unit", self.unit)
        if expect(found, "min_interval_seconds", self.min_interval_seconds, "number"):
            lo, hi = MIN_INTERVAL_SECONDS
            if not lo <= self.min_interval_seconds <= hi:
                found.append(("min_interval_seconds",
                              f"must be in {lo:g}..{hi:g} seconds, got "
                              f"{self.min_interval_seconds}"))
        lo_ok = expect(found, "min", self.min, "number")
        hi_ok = expect(found, "max", self.max, "number")
        if lo_ok and hi_ok:
            if not self.min < self.max:
                found.append(("max", f"must be greater than min ({self.min} >= {self.max})"))
            elif isinstance(self.unit, str) and self.unit in _QUANTITY_OF_UNIT:
                quantity = _QUANTITY_OF_UNIT[self.unit]
                lo, hi = _UNIT_BOUNDS[quantity][self.unit]
                label = "CO2" if quantity == "co2" else quantity
                for name, value in (("min", self.min), ("max", self.max)):
                    if not lo <= value <= hi:
                        found.append((name, f"{value:g} {self.unit} is not a plausible {label} "
                                            f"(expected within {lo:g}..{hi:g} {self.unit})"))
        return found

    def accepts(self, value: float) -> bool:
        """Whether ``value`` lies in the configured valid range (inclusive)."""
        return self.min <= value <= self.max


@dataclass(frozen=True, kw_only=True)
class TwinConfig:
    """One pseudo-measurement stream.

    references: the permanent sensors feeding the twin live (ids of configured sensors).
    target: the sensor at the user-relevant spot when it is live (temporarily installed), for
        monitoring against the estimate; None otherwise.
    artifact: the trained model file.
    quantity: what is estimated; selects kernels and the accepted units.
    covariates: other permanent sensors the twin reads live, of any unit (e.g. CO2 or
        illuminance for a temperature twin); only the models made for them use them.
    """

    id: str
    references: tuple[str, ...]
    artifact: Path
    quantity: Literal["temperature", "co2"]
    target: str | None = None
    covariates: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.references, list):
            object.__setattr__(self, "references", tuple(self.references))
        if isinstance(self.covariates, list):
            object.__setattr__(self, "covariates", tuple(self.covariates))
        if isinstance(self.artifact, str):
            object.__setattr__(self, "artifact", Path(self.artifact))
        raise_if(self._problems())

    def spec(self, hours: OperatingHours, target: str) -> TwinSpec:
        """What this twin pseudo-measures under the service's ``hours``; ``target`` stands in
        when the configuration names none (the desk sensor is usually gone live)."""
        return TwinSpec(self.references, self.target or target, Quantity.parse(self.quantity),
                        hours, self.covariates)

    def _problems(self) -> Found:
        found: Found = []
        if nonempty(found, "id", self.id) and not _TWIN_ID.fullmatch(self.id):
            found.append(("id", f"{self.id!r} must be letters, digits, '.', '_' or '-' "
                                "(it becomes an MQTT topic level and a file name)"))
        refs = self.references
        if not isinstance(refs, tuple) or not all(isinstance(r, str) for r in refs):
            found.append(("references", "expected an array of sensor ids (strings)"))
        elif not refs:
            found.append(("references", "needs at least one reference sensor"))
        else:
            seen: set[str] = set()
            for ref in refs:
                if ref in seen:
                    found.append(("references", f"sensor {ref!r} is listed twice"))
                seen.add(ref)
        if self.target is not None and nonempty(found, "target", self.target):
            if isinstance(refs, tuple) and self.target in refs:
                found.append(("target", f"sensor {self.target!r} is also a reference; "
                                        "the target must not feed its own estimate"))
        covs = self.covariates
        if not isinstance(covs, tuple) or not all(isinstance(c, str) for c in covs):
            found.append(("covariates", "expected an array of sensor ids (strings)"))
        else:
            for i, c in enumerate(covs):
                if c in covs[:i]:
                    found.append(("covariates", f"sensor {c!r} is listed twice"))
                elif (isinstance(refs, tuple) and c in refs) or c == self.target:
                    found.append(("covariates", f"sensor {c!r} is also a reference or the "
                                                "target"))
        expect(found, "artifact", self.artifact, "path")
        if expect(found, "quantity", self.quantity, "string") and self.quantity not in QUANTITIES:
            found.append(("quantity", f"must be one of {', '.join(map(repr, QUANTITIES))}, "
                                      f"got {self.quantity!r}"))
        return found

    @property
    def sensors(self) -> tuple[str, ...]:
        """References, then the target if configured."""
        return (*self.references, self.target) if self.target else self.references

    @property
    def inputs(self) -> tuple[str, ...]:
        """References then covariates: what the twin subscribes to."""
        return (*self.references, *self.covariates)


@dataclass(frozen=True, kw_only=True)
class MetricsConfig:
    """``[metrics]``: Prometheus endpoints over HTTP (edge/prometheus.py); off by default.

    host: the address the endpoints listen on ("0.0.0.0" for every interface).
    port: the daemon's (``pseudotwin run``) port; None: no endpoint.
    record_port: the recorder's (``pseudotwin record``) port; None: no endpoint. The two
        commands usually read one file, so each has its own port.
    """

    host: str = "127.0.0.1"
    port: int | None = None
    record_port: int | None = None

    def __post_init__(self) -> None:
        found: Found = []
        if nonempty(found, "host", self.host) and (problem := host_problem(self.host)):
            found.append(("host", problem))
        for name in ("port", "record_port"):
            value = getattr(self, name)
            if value is not None and expect(found, name, value, "integer") \
                    and not 1 <= value <= 65535:
                found.append((name, f"must be a TCP port 1..65535, got {value}"))
        if self.port is not None and self.port == self.record_port:
            found.append(("record_port", "must differ from port (both may run on one host)"))
        raise_if(found)


@dataclass(frozen=True, kw_only=True)
class HomeAssistantConfig:
    """``[homeassistant]``: Home Assistant MQTT discovery (edge/homeassistant.py); off by
    default.

    enabled: publish the retained discovery messages (false, or no section: the ones published
        before are removed).
    discovery_prefix: Home Assistant's discovery prefix (its MQTT integration's setting).
    baselines: also one entity per published baseline model, besides the estimate.
    """

    enabled: bool = False
    discovery_prefix: str = "homeassistant"
    baselines: bool = False

    def __post_init__(self) -> None:
        found: Found = []
        expect(found, "enabled", self.enabled, "boolean")
        expect(found, "baselines", self.baselines, "boolean")
        if nonempty(found, "discovery_prefix", self.discovery_prefix):
            problem = base_topic_problem(self.discovery_prefix)
            if problem:
                found.append(("discovery_prefix", problem))
        raise_if(found)


def homeassistant_problems(ha: HomeAssistantConfig, twin_ids: Collection[str]) -> list[str]:
    """Twin ids that would share a discovery topic ('.' is not allowed there, it becomes '_')."""
    if not ha.enabled:
        return []
    first: dict[str, str] = {}
    out = []
    for tid in twin_ids:
        key = tid.replace(".", "_")
        if key in first:
            out.append(f"homeassistant: twins {first[key]!r} and {tid!r} would share one Home "
                       "Assistant discovery topic ('.' becomes '_'); rename one")
        else:
            first[key] = tid
    return out


def service_scalar_problems(
    *,
    base_topic: object,
    publish_every_minutes: object,
    stale_after_minutes: object,
    max_skew_seconds: object,
    queue_size: object,
    log_level: object,
    baselines: object = "grid",
    monitor_every_minutes: object = 60,
    journal_fsync: object = True,
) -> Found:
    found: Found = []
    if expect(found, "base_topic", base_topic, "string"):
        assert isinstance(base_topic, str)
        problem = base_topic_problem(base_topic)
        if problem:
            found.append(("base_topic", problem))
    if expect(found, "publish_every_minutes", publish_every_minutes, "number"):
        assert isinstance(publish_every_minutes, int | float)
        seconds = publish_every_minutes * 60.0
        if not 0 < publish_every_minutes <= 24 * 60:
            found.append(("publish_every_minutes", "must be positive and at most a day (1440)"))
        elif abs(seconds - round(seconds)) > 1e-6 or round(seconds) < 1 \
                or 86400 % round(seconds):
            # The grid is anchored at local midnight, so it must tile the day exactly.
            found.append(("publish_every_minutes",
                          f"{publish_every_minutes:g} min does not divide a day into whole "
                          "seconds (e.g. 1, 5, 10, 15, 30, 60)"))
    if expect(found, "stale_after_minutes", stale_after_minutes, "number"):
        assert isinstance(stale_after_minutes, int | float)
        if not 0 < stale_after_minutes <= MAX_STALE_AFTER_MINUTES:
            found.append(("stale_after_minutes", "must be positive and at most a week "
                                                 f"({MAX_STALE_AFTER_MINUTES})"))
    if expect(found, "max_skew_seconds", max_skew_seconds, "number"):
        assert isinstance(max_skew_seconds, int | float)
        if not 0 <= max_skew_seconds <= MAX_SKEW_SECONDS:
            found.append(("max_skew_seconds", "must not be negative, and at most a day "
                                              f"({MAX_SKEW_SECONDS})"))
    if expect(found, "queue_size", queue_size, "integer"):
        assert isinstance(queue_size, int)
        if queue_size < 1:
            found.append(("queue_size", "must be at least 1"))
    if expect(found, "log_level", log_level, "string"):
        assert isinstance(log_level, str)
        if log_level.upper() not in LOG_LEVELS:
            found.append(("log_level",
                          f"must be one of {', '.join(LOG_LEVELS)}, got {log_level!r}"))
    if baselines not in BASELINE_CADENCES:
        found.append(("baselines", f"must be one of {', '.join(BASELINE_CADENCES)}, "
                                   f"got {baselines!r}"))
    if expect(found, "monitor_every_minutes", monitor_every_minutes, "number"):
        assert isinstance(monitor_every_minutes, int | float)
        if monitor_every_minutes <= 0:
            found.append(("monitor_every_minutes", "must be positive"))
    expect(found, "journal_fsync", journal_fsync, "boolean")
    return found


def cross_problems(
    base_topic: str | None,
    sensors: Sequence[tuple[str, SensorConfig]],
    twins: Sequence[tuple[str, TwinConfig]],
    unchecked_ids: Collection[str] | None = (),
) -> list[str]:
    """Problems between sections: duplicate ids, topics and artifacts; twins vs sensors.

    Items come as (location, config). ``unchecked_ids`` are ids of sensors that exist but
    failed their own validation: references to them are not reported as unknown. None
    means the sensor list itself is unusable, so no reference is reported as unknown.
    """
    out: list[str] = []
    first_id: dict[str, str] = {}
    first_topic: dict[str, str] = {}
    for loc, s in sensors:
        if s.id in first_id:
            out.append(f"{loc}.id: duplicate id {s.id!r} (first used by {first_id[s.id]})")
        else:
            first_id[s.id] = loc
        if s.topic in first_topic:
            out.append(f"{loc}.topic: {s.topic!r} is already the topic of "
                       f"{first_topic[s.topic]}; one topic per sensor")
        else:
            first_topic[s.topic] = loc
        if base_topic is not None and (
            s.topic == base_topic or s.topic.startswith(base_topic + "/")
        ):
            out.append(f"{loc}.topic: {s.topic!r} lies under base_topic {base_topic!r}, "
                       "where the daemon publishes its own outputs")
    by_id: dict[str, SensorConfig] = {}
    for _, s in sensors:  # a duplicate id is its own error: the first definition stands
        by_id.setdefault(s.id, s)
    first_twin: dict[str, str] = {}
    first_artifact: dict[Path, str] = {}
    for loc, t in twins:
        if t.id in first_twin:
            out.append(f"{loc}.id: duplicate id {t.id!r} (first used by {first_twin[t.id]})")
        else:
            first_twin[t.id] = loc
        if t.artifact in first_artifact:
            out.append(f"{loc}.artifact: {t.artifact} is already the artifact of "
                       f"{first_artifact[t.artifact]}")
        else:
            first_artifact[t.artifact] = loc
        roles = [("references", r) for r in t.references]
        if t.target is not None:
            roles.append(("target", t.target))
        accepted = _TWIN_UNITS[t.quantity]
        for field, sid in roles:
            sensor = by_id.get(sid)
            if sensor is None:
                if unchecked_ids is not None and sid not in unchecked_ids:
                    out.append(f"{loc}.{field}: unknown sensor {sid!r}{suggest(sid, by_id)}")
            elif sensor.unit in _UNIT_BOUNDS[t.quantity] and sensor.unit not in accepted:
                out.append(f"{loc}.{field}: sensor {sid!r} has unit {sensor.unit!r}: a "
                           f"{t.quantity} twin works in {accepted[0]} (its models, σ and "
                           f"estimates; nothing is converted), so its sensors must report "
                           f"{accepted[0]}")
            elif sensor.unit not in accepted:
                out.append(f"{loc}.{field}: sensor {sid!r} has unit {sensor.unit!r}, not a "
                           f"{t.quantity} unit ({', '.join(accepted)})")
        for sid in t.covariates:  # any unit: a covariate is not the estimated quantity
            if sid not in by_id and unchecked_ids is not None and sid not in unchecked_ids:
                out.append(f"{loc}.covariates: unknown sensor {sid!r}{suggest(sid, by_id)}")
    return out


def thinning_of(sensors: Iterable[SensorConfig]) -> Thinning:
    """The window's thinning policy from the sensors' ``min_interval_seconds`` (of a
    duplicate id, the first definition's, as everywhere)."""
    widths: dict[str, timedelta] = {}
    for s in sensors:
        widths.setdefault(s.id, timedelta(seconds=s.min_interval_seconds))
    return Thinning(per_sensor={sid: w for sid, w in widths.items() if w != DEFAULT_MIN_INTERVAL})


@dataclass(frozen=True, kw_only=True)
class ServiceConfig:
    """Everything the daemon needs: broker, operating hours, sensors and twins.

    publish_every_minutes: the fixed publishing grid [min]; must divide a day.
    stale_after_minutes: a reference silent for longer makes dependent estimates stale [min].
    max_skew_seconds: how far a reading's timestamp may lie in the future [s].
    state_dir: where the daemon keeps its state (window snapshots, counters).
    queue_size: bound of the queue between the MQTT thread and the twins (readings).
    baselines: when the baseline models are published: "grid" (on the publishing grid
        only: they are for monitoring, and at every reading they would quintuple the
        messages), "reading" (also at every reading that moves the twin) or "none" (the
        twins run their primary model only, and what it needs: no baselines, live or
        backfilled; with a TRIV-type primary two fifths less CPU at 1,000 twins and
        half the memory by the evening, scripts/bench_daemon.py --baselines none: a
        fleet's setting).
    monitor_every_minutes: ``<twin>/monitor`` goes out at the day's first and last grid
        instants and at the first grid instant at or after each multiple of this since
        local midnight [min] (every grid instant when it is not longer than
        publish_every_minutes), and at the next one when the estimate's uncertain or
        failover state changes.
    journal_fsync: readings are acknowledged only once their journal lines are on disk
        (fsync, once per batch of readings), so a power cut loses none the broker let go;
        false acknowledges once the lines are in the kernel (a killed daemon still loses
        nothing; a power cut may lose the last seconds), for slow flash storage. The
        recorder likewise: its spool synced, a SQLite store's commits synced (FULL).
    """

    broker: BrokerConfig
    hours: OperatingHours
    state_dir: Path
    sensors: dict[str, SensorConfig]
    twins: dict[str, TwinConfig]
    base_topic: str = "pseudotwin"
    publish_every_minutes: float = 15
    stale_after_minutes: float = 30
    max_skew_seconds: float = 300
    queue_size: int = 10000
    log_level: str = "INFO"
    baselines: str = "grid"
    # Hourly: the monitor's day figures move slowly, and at 1,000 twins one monitor per
    # twin and grid step was a sixth of the daemon's messages (scripts/bench_daemon.py).
    monitor_every_minutes: float = 60
    journal_fsync: bool = True
    store: str | None = None  # history DB: SQLite path, postgresql:// or crate:// URL
    metrics: MetricsConfig = MetricsConfig()  # [metrics]: Prometheus endpoints
    homeassistant: HomeAssistantConfig = HomeAssistantConfig()  # [homeassistant]

    def __post_init__(self) -> None:
        if isinstance(self.state_dir, str):
            object.__setattr__(self, "state_dir", Path(self.state_dir))
        found = service_scalar_problems(
            base_topic=self.base_topic,
            publish_every_minutes=self.publish_every_minutes,
            stale_after_minutes=self.stale_after_minutes,
            max_skew_seconds=self.max_skew_seconds,
            queue_size=self.queue_size,
            log_level=self.log_level,
            baselines=self.baselines,
            monitor_every_minutes=self.monitor_every_minutes,
            journal_fsync=self.journal_fsync,
        )
        if not isinstance(self.broker, BrokerConfig):
            found.append(("broker", "expected a BrokerConfig"))
        if not isinstance(self.hours, OperatingHours):
            found.append(("hours", "expected OperatingHours"))
        expect(found, "state_dir", self.state_dir, "path")
        if not isinstance(self.metrics, MetricsConfig):
            found.append(("metrics", "expected a MetricsConfig"))
        if not isinstance(self.homeassistant, HomeAssistantConfig):
            found.append(("homeassistant", "expected a HomeAssistantConfig"))
        for name, mapping, cls in (("sensors", self.sensors, SensorConfig),
                                   ("twins", self.twins, TwinConfig)):
            if not isinstance(mapping, Mapping) or not all(
                isinstance(v, cls) and k == v.id for k, v in mapping.items()
            ):
                found.append((name, f"expected a mapping of id to {cls.__name__}"))
        raise_if(found)
        cross = cross_problems(
            self.base_topic,
            [(f"sensors[{k!r}]", s) for k, s in self.sensors.items()],
            [(f"twins[{k!r}]", t) for k, t in self.twins.items()],
        )
        cross += homeassistant_problems(self.homeassistant, list(self.twins))
        if not self.hours.grid(date(2024, 1, 1), self.publish_every_minutes / 60.0):
            # Anchored at midnight, a step longer than the operating hours may miss them.
            cross.append(f"service.publish_every_minutes: {self.publish_every_minutes:g} min has "
                         "no multiple since local midnight between day_start and day_end: "
                         "nothing would ever be published on the grid; choose a step that "
                         "divides the day and falls within the operating hours")
        if self.baselines == "none" and self.homeassistant.enabled \
                and self.homeassistant.baselines:
            cross.append('homeassistant.baselines: true announces baseline entities, but '
                         'service.baselines = "none" runs no baselines; set one of them '
                         'otherwise')
        if cross:
            raise ConfigProblems(cross)
        object.__setattr__(self, "log_level", self.log_level.upper())

    @property
    def publish_every(self) -> timedelta:
        return timedelta(minutes=self.publish_every_minutes)

    @property
    def stale_after(self) -> timedelta:
        return timedelta(minutes=self.stale_after_minutes)

    @property
    def max_skew(self) -> timedelta:
        return timedelta(seconds=self.max_skew_seconds)

    def running_kinds(self, primary: str) -> list[str] | None:
        """The models a twin whose primary is ``primary`` runs, live (daemon) and in backfill:
        every published one (None), or the primary alone with ``baselines = "none"``."""
        return [primary] if self.baselines == "none" else None

    def per_reading_kinds(self, primary: str) -> tuple[str, ...] | None:
        """The models published (daemon) or stored (backfill) at a reading that moves a twin
        whose primary is ``primary``: the primary only, unless ``baselines = "reading"``
        (None: all of them). The baselines always go out on the grid."""
        return None if self.baselines == "reading" else (primary,)

    @cached_property
    def thinning(self) -> Thinning:
        """The window's thinning policy from the sensors' ``min_interval_seconds`` (one
        object shared by every twin: a per-twin copy of a thousand sensors' table would cost
        a thousand twins ~100 MB)."""
        return thinning_of(self.sensors.values())

    @cached_property
    def _sensor_by_topic(self) -> dict[str, SensorConfig]:
        return {s.topic: s for s in self.sensors.values()}  # topics are unique (checked)

    def sensor_for_topic(self, topic: str) -> SensorConfig | None:
        """The sensor subscribed on ``topic``, if any (a dict lookup: asked per message)."""
        return self._sensor_by_topic.get(topic)

    def twin_topic(self, twin: str, *suffix: str) -> str:
        """``<base_topic>/<twin>/<suffix...>``."""
        return "/".join((self.base_topic, twin, *suffix))
