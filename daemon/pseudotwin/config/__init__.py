"""Service configuration: a TOML file turned into typed, frozen, self-validating dataclasses.

Every problem is reported with its location (``sensors[2].topic: ...``) and all problems of a
file are collected before raising, so one ``check-config`` run shows everything to fix.

The MQTT password is never part of the configuration values: the file names an environment
variable or a secret file, and :meth:`BrokerConfig.password` reads it at call time. It can
therefore not leak through ``repr``, logs of the config, or error messages.

TOML layout (see ``config/example.toml`` for a commented example)::

    [broker]     host, port, tls, ca_file, username, password_env | password_file,
                 client_id, keepalive
    [service]    timezone, state_dir, base_topic, day_start, day_end, init_minutes,
                 slot_minutes, publish_every_minutes, stale_after_minutes, max_skew_seconds,
                 log_level, queue_size
    [[sensors]]  id, topic, format, ts_key, value_key, unit, min, max
    [[twins]]    id, quantity, references, target, artifact
"""

from __future__ import annotations

import argparse
import difflib
import math
import os
import re
import sys
import tomllib
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any, Literal
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError, available_timezones

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.errors import ConfigError, PseudotwinError

__all__ = [
    "ArtifactCheck",
    "BrokerConfig",
    "ConfigProblems",
    "SensorConfig",
    "ServiceConfig",
    "TwinConfig",
    "check_config",
    "check_config_main",
    "load_config",
    "topic_problem",
]

#: Called per twin by :func:`load_config`/:func:`check_config` when its artifact file exists;
#: returns problem messages (without location), e.g. "artifact was trained for sensors ...".
# (twin, the service's operating hours if they are valid) → problems
ArtifactCheck = Callable[["TwinConfig", "OperatingHours | None"], list[str]]

MAX_TOPIC_BYTES = 65535  # MQTT strings carry a 16-bit length prefix.
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
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

_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# Twin ids become one MQTT topic level, a file name stem and a DB key: keep them boring.
_TWIN_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
_HHMM = re.compile(r"(\d{1,2}):(\d{2})")


class ConfigProblems(ConfigError):
    """A configuration with one or more problems, each ``"<location>: <message>"``."""

    def __init__(self, problems: Iterable[str]) -> None:
        self.problems: list[str] = list(problems)
        super().__init__("\n".join(self.problems))

    def __str__(self) -> str:
        return "\n".join(self.problems)


Found = list[tuple[str, str]]  # (field, message) pairs found by a validator


def _raise_if(found: Found) -> None:
    if found:
        raise ConfigProblems(f"{where}: {msg}" for where, msg in found)


# -- small value checks ------------------------------------------------------------------


def _type_name(value: object) -> str:
    names = {bool: "a boolean", int: "an integer", float: "a float", str: "a string",
             list: "an array", tuple: "an array", dict: "a table"}
    return names.get(type(value), f"a {type(value).__name__}")


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _expect(found: Found, name: str, value: object, kind: str) -> bool:
    """Append a type problem unless ``value`` is of ``kind``; True when it is."""
    ok = {
        "string": isinstance(value, str),
        "integer": _is_int(value),
        "number": _is_number(value) and math.isfinite(value),  # type: ignore[arg-type]
        "boolean": isinstance(value, bool),
        "path": isinstance(value, Path),
    }[kind]
    if not ok:
        if kind == "number" and _is_number(value):
            found.append((name, f"must be a finite number, got {value!r}"))
        else:
            article = "an" if kind[0] in "aeiou" else "a"
            found.append((name, f"expected {article} {kind}, got {_type_name(value)}"))
    return ok


def _nonempty(found: Found, name: str, value: object) -> bool:
    if not _expect(found, name, value, "string"):
        return False
    if not value:
        found.append((name, "must not be empty"))
        return False
    return True


def topic_problem(topic: str, *, sensor: bool = True) -> str | None:
    """Why ``topic`` is not a valid MQTT topic *name* (no wildcards), or None.

    Empty levels (``a//b``, a leading or trailing ``/``) are legal MQTT and stay allowed.
    """
    if not topic:
        return "must not be empty"
    if "\x00" in topic:
        return "must not contain NUL"
    if "+" in topic or "#" in topic:
        hint = "; give one exact topic per sensor" if sensor else ""
        return f"{topic!r} contains a wildcard ('+' or '#'){hint}"
    if any(ord(c) < 0x20 or 0x7F <= ord(c) <= 0x9F for c in topic):
        # MQTT says SHOULD NOT and brokers may drop the connection over them.
        return f"{topic!r} contains a control character"
    if topic.startswith("$"):
        return f"{topic!r} starts with '$', which is reserved for the broker"
    if len(topic.encode("utf-8", "surrogatepass")) > MAX_TOPIC_BYTES:
        return f"is longer than {MAX_TOPIC_BYTES} bytes in UTF-8"
    return None


def base_topic_problem(topic: str) -> str | None:
    """Why ``topic`` cannot prefix output topics, or None (shared with the bridge)."""
    problem = topic_problem(topic, sensor=False)
    if problem:
        return problem
    if topic.endswith("/"):
        return "must not end with '/' (outputs go to '<base_topic>/<twin>/...')"
    return None


def _parse_hhmm(text: str) -> float | None:
    m = _HHMM.fullmatch(text)
    if not m:
        return None
    h, mi = int(m[1]), int(m[2])
    if h > 24 or mi >= 60 or (h == 24 and mi):
        return None
    return h + mi / 60.0


# -- the dataclasses -----------------------------------------------------------------------


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
        _raise_if(self._problems())

    def _problems(self) -> Found:
        found: Found = []
        _nonempty(found, "host", self.host)
        if _expect(found, "port", self.port, "integer") and not 1 <= self.port <= 65535:
            found.append(("port", f"must be in 1..65535, got {self.port}"))
        _expect(found, "tls", self.tls, "boolean")
        if self.ca_file is not None and _expect(found, "ca_file", self.ca_file, "path"):
            if self.tls is not True:
                found.append(("ca_file", "is only used with tls = true"))
        if self.username is not None:
            _nonempty(found, "username", self.username)
        if self.password_env is not None and _expect(
            found, "password_env", self.password_env, "string"
        ):
            if not _ENV_NAME.fullmatch(self.password_env):
                found.append(("password_env",
                              f"{self.password_env!r} is not an environment variable name"))
        if self.password_file is not None:
            _expect(found, "password_file", self.password_file, "path")
        if self.password_env is not None and self.password_file is not None:
            found.append(("password_file", "give either password_env or password_file, not both"))
        if (self.password_env is not None or self.password_file is not None) and (
            self.username is None
        ):
            # MQTT 3.1.1 forbids a password without a user name.
            found.append(("username", "is required when a password source is configured"))
        if _nonempty(found, "client_id", self.client_id):
            if any(ord(c) < 0x20 for c in self.client_id):
                found.append(("client_id", "must not contain NUL or control characters"))
            elif len(self.client_id.encode("utf-8")) > MAX_TOPIC_BYTES:
                found.append(("client_id", f"is longer than {MAX_TOPIC_BYTES} bytes"))
        if _expect(found, "keepalive", self.keepalive, "integer") and not (
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
    """

    id: str
    topic: str
    unit: str
    min: float
    max: float
    format: Literal["number", "json"] = "json"
    ts_key: str = "ts"
    value_key: str = "value"

    def __post_init__(self) -> None:
        found = self._problems()
        _raise_if(found)
        object.__setattr__(self, "min", float(self.min))
        object.__setattr__(self, "max", float(self.max))

    def _problems(self) -> Found:
        found: Found = []
        if _nonempty(found, "id", self.id):
            if self.id != self.id.strip() or any(ord(c) < 0x20 for c in self.id):
                found.append(("id", f"{self.id!r} has surrounding blanks or control characters"))
        if _expect(found, "topic", self.topic, "string"):
            problem = topic_problem(self.topic)
            if problem:
                found.append(("topic", problem))
        if _expect(found, "format", self.format, "string") and self.format not in SENSOR_FORMATS:
            found.append(("format", f"must be one of {', '.join(map(repr, SENSOR_FORMATS))}, "
                                    f"got {self.format!r}"))
        _expect(found, "ts_key", self.ts_key, "string")
        _nonempty(found, "value_key", self.value_key)
        if (self.format == "json" and isinstance(self.ts_key, str) and self.ts_key
                and self.ts_key == self.value_key):
            found.append(("ts_key", "must differ from value_key"))
        _nonempty(found, "unit", self.unit)
        lo_ok = _expect(found, "min", self.min, "number")
        hi_ok = _expect(found, "max", self.max, "number")
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
    """

    id: str
    references: tuple[str, ...]
    artifact: Path
    quantity: Literal["temperature", "co2"]
    target: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.references, list):
            object.__setattr__(self, "references", tuple(self.references))
        if isinstance(self.artifact, str):
            object.__setattr__(self, "artifact", Path(self.artifact))
        _raise_if(self._problems())

    def _problems(self) -> Found:
        found: Found = []
        if _nonempty(found, "id", self.id) and not _TWIN_ID.fullmatch(self.id):
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
        if self.target is not None and _nonempty(found, "target", self.target):
            if isinstance(refs, tuple) and self.target in refs:
                found.append(("target", f"sensor {self.target!r} is also a reference; "
                                        "the target must not feed its own estimate"))
        _expect(found, "artifact", self.artifact, "path")
        if _expect(found, "quantity", self.quantity, "string") and self.quantity not in QUANTITIES:
            found.append(("quantity", f"must be one of {', '.join(map(repr, QUANTITIES))}, "
                                      f"got {self.quantity!r}"))
        return found

    @property
    def sensors(self) -> tuple[str, ...]:
        """References, then the target if configured."""
        return (*self.references, self.target) if self.target else self.references


def _service_scalar_problems(
    *,
    base_topic: object,
    publish_every_minutes: object,
    stale_after_minutes: object,
    max_skew_seconds: object,
    queue_size: object,
    log_level: object,
) -> Found:
    found: Found = []
    if _expect(found, "base_topic", base_topic, "string"):
        assert isinstance(base_topic, str)
        problem = base_topic_problem(base_topic)
        if problem:
            found.append(("base_topic", problem))
    if _expect(found, "publish_every_minutes", publish_every_minutes, "number"):
        assert isinstance(publish_every_minutes, int | float)
        seconds = publish_every_minutes * 60.0
        if publish_every_minutes <= 0:
            found.append(("publish_every_minutes", "must be positive"))
        elif abs(seconds - round(seconds)) > 1e-6 or 86400 % round(seconds):
            # The grid is anchored at local midnight, so it must tile the day exactly.
            found.append(("publish_every_minutes",
                          f"{publish_every_minutes:g} min does not divide a day into whole "
                          "seconds (e.g. 1, 5, 10, 15, 30, 60)"))
    if _expect(found, "stale_after_minutes", stale_after_minutes, "number"):
        assert isinstance(stale_after_minutes, int | float)
        if stale_after_minutes <= 0:
            found.append(("stale_after_minutes", "must be positive"))
    if _expect(found, "max_skew_seconds", max_skew_seconds, "number"):
        assert isinstance(max_skew_seconds, int | float)
        if max_skew_seconds < 0:
            found.append(("max_skew_seconds", "must not be negative"))
    if _expect(found, "queue_size", queue_size, "integer"):
        assert isinstance(queue_size, int)
        if queue_size < 1:
            found.append(("queue_size", "must be at least 1"))
    if _expect(found, "log_level", log_level, "string"):
        assert isinstance(log_level, str)
        if log_level.upper() not in LOG_LEVELS:
            found.append(("log_level",
                          f"must be one of {', '.join(LOG_LEVELS)}, got {log_level!r}"))
    return found


def _cross_problems(
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
    by_id = {s.id: s for _, s in sensors}
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
        accepted = _UNIT_BOUNDS[t.quantity]
        units: dict[str, str] = {}
        for field, sid in roles:
            sensor = by_id.get(sid)
            if sensor is None:
                if unchecked_ids is not None and sid not in unchecked_ids:
                    out.append(f"{loc}.{field}: unknown sensor {sid!r}{_suggest(sid, by_id)}")
                continue
            if sensor.unit not in accepted:
                out.append(f"{loc}.{field}: sensor {sid!r} has unit {sensor.unit!r}, not a "
                           f"{t.quantity} unit ({', '.join(accepted)})")
            units[sid] = sensor.unit
        if len(set(units.values())) > 1:
            listing = ", ".join(f"{sid!r}: {u!r}" for sid, u in units.items())
            out.append(f"{loc}.references: all sensors of a twin must share one unit ({listing})")
    return out


@dataclass(frozen=True, kw_only=True)
class ServiceConfig:
    """Everything the daemon needs: broker, operating hours, sensors and twins.

    publish_every_minutes: the fixed publishing grid [min]; must divide a day.
    stale_after_minutes: a reference silent for longer makes dependent estimates stale [min].
    max_skew_seconds: how far a reading's timestamp may lie in the future [s].
    state_dir: where the daemon keeps its state (window snapshots, counters).
    queue_size: bound of the queue between the MQTT thread and the twins (readings).
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
    store: str | None = None  # history DB: SQLite file path or crate://host:4200

    def __post_init__(self) -> None:
        if isinstance(self.state_dir, str):
            object.__setattr__(self, "state_dir", Path(self.state_dir))
        found = _service_scalar_problems(
            base_topic=self.base_topic,
            publish_every_minutes=self.publish_every_minutes,
            stale_after_minutes=self.stale_after_minutes,
            max_skew_seconds=self.max_skew_seconds,
            queue_size=self.queue_size,
            log_level=self.log_level,
        )
        if not isinstance(self.broker, BrokerConfig):
            found.append(("broker", "expected a BrokerConfig"))
        if not isinstance(self.hours, OperatingHours):
            found.append(("hours", "expected OperatingHours"))
        _expect(found, "state_dir", self.state_dir, "path")
        for name, mapping, cls in (("sensors", self.sensors, SensorConfig),
                                   ("twins", self.twins, TwinConfig)):
            if not isinstance(mapping, Mapping) or not all(
                isinstance(v, cls) and k == v.id for k, v in mapping.items()
            ):
                found.append((name, f"expected a mapping of id to {cls.__name__}"))
        _raise_if(found)
        cross = _cross_problems(
            self.base_topic,
            [(f"sensors[{k!r}]", s) for k, s in self.sensors.items()],
            [(f"twins[{k!r}]", t) for k, t in self.twins.items()],
        )
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

    def sensor_for_topic(self, topic: str) -> SensorConfig | None:
        """The sensor subscribed on ``topic``, if any."""
        for sensor in self.sensors.values():
            if sensor.topic == topic:
                return sensor
        return None

    def twin_topic(self, twin: str, *suffix: str) -> str:
        """``<base_topic>/<twin>/<suffix...>``."""
        return "/".join((self.base_topic, twin, *suffix))


# -- loading ---------------------------------------------------------------------------


def _suggest(key: str, known: Iterable[str]) -> str:
    close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


class _Loader:
    """Turns one parsed TOML document into a ServiceConfig, collecting every problem.

    Each section is validated on its own, so a broken [service] table does not hide a
    twin's unknown reference: the user sees everything in one run.
    """

    # [bridge] and [plc] belong to `pseudotwin bridge` (bridge.py); one file may serve both.
    TOP_KEYS = ("broker", "service", "sensors", "twins", "bridge", "plc")
    BROKER_KEYS = ("host", "port", "tls", "ca_file", "username", "password_env",
                   "password_file", "client_id", "keepalive")
    SERVICE_KEYS = ("timezone", "state_dir", "base_topic", "day_start", "day_end",
                    "init_minutes", "slot_minutes", "publish_every_minutes",
                    "stale_after_minutes", "max_skew_seconds", "log_level", "queue_size",
                    "store")
    SENSOR_KEYS = ("id", "topic", "format", "ts_key", "value_key", "unit", "min", "max")
    SENSOR_REQUIRED = ("id", "topic", "unit", "min", "max")
    TWIN_KEYS = ("id", "quantity", "references", "target", "artifact")
    TWIN_REQUIRED = ("id", "quantity", "references", "artifact")

    def __init__(self, base_dir: Path, *, runtime: bool,
                 artifact_check: ArtifactCheck | None) -> None:
        self.base_dir = base_dir
        self.runtime = runtime
        self.artifact_check = artifact_check
        self.problems: list[str] = []
        self.hours: OperatingHours | None = None

    def add(self, location: str, message: str) -> None:
        self.problems.append(f"{location}: {message}")

    def keys(self, table: Mapping[str, Any], known: tuple[str, ...],
             required: tuple[str, ...], loc: str) -> bool:
        """Report unknown and missing keys; True when all required keys are present."""
        prefix = f"{loc}." if loc else ""
        for key in table:
            if loc == "broker" and key == "password":
                # Never echo the value: it is a secret written where it must not be.
                self.add("broker.password", "the password is never written in the config; "
                                            "use password_env or password_file")
            elif key not in known:
                self.add(f"{prefix}{key}", f"unknown key{_suggest(key, known)}")
        missing = [k for k in required if k not in table]
        for key in missing:
            self.add(f"{prefix}{key}", "missing required key")
        return not missing

    def section(self, doc: Mapping[str, Any], name: str) -> dict[str, Any] | None:
        table = doc.get(name)
        if table is None:
            self.add(name, f"missing table [{name}]")
            return None
        if not isinstance(table, dict):
            self.add(name, f"expected a table [{name}], got {_type_name(table)}")
            return None
        return table

    def path(self, table: Mapping[str, Any], key: str, loc: str) -> Any:
        """A path value resolved against the config's folder. Non-strings are passed through
        for the dataclass to report; an empty string is reported here (it would mean '.')."""
        value = table.get(key)
        if isinstance(value, str):
            if not value:
                self.add(f"{loc}.{key}", "must not be empty")
                return None
            return self.base_dir / value
        return value

    def build(self, loc: str, factory: Callable[..., Any], **kwargs: Any) -> Any:
        try:
            return factory(**kwargs)
        except ConfigProblems as exc:
            self.problems.extend(f"{loc}.{p}" for p in exc.problems)
        except ConfigError as exc:
            self.add(loc, str(exc))
        return None

    # -- sections --------------------------------------------------------------------------
    def load(self, doc: dict[str, Any]) -> ServiceConfig | None:
        self.keys(doc, self.TOP_KEYS, (), "")
        broker = self.load_broker(doc)
        service = self.load_service(doc)
        sensors, sensors_complete, bad_ids = self.load_sensors(doc)
        twins, twins_complete = self.load_twins(doc)
        raw_base = doc.get("service", {}).get("base_topic", "pseudotwin") \
            if isinstance(doc.get("service"), dict) else None
        self.problems.extend(_cross_problems(
            raw_base if isinstance(raw_base, str) else None, sensors, twins, bad_ids
        ))
        self.hours = service["hours"] if service is not None else None
        if self.runtime:
            self.runtime_checks(broker, service, twins)
        elif self.artifact_check is not None:
            for loc, twin in twins:
                if twin.artifact.is_file():
                    self.run_artifact_check(loc, twin)
        if (self.problems or broker is None or service is None
                or not sensors_complete or not twins_complete):
            return None
        return ServiceConfig(broker=broker, sensors={s.id: s for _, s in sensors},
                             twins={t.id: t for _, t in twins}, **service)

    def load_broker(self, doc: dict[str, Any]) -> BrokerConfig | None:
        table = self.section(doc, "broker")
        if table is None:
            return None
        if not self.keys(table, self.BROKER_KEYS, ("host",), "broker"):
            return None
        values = {k: v for k, v in table.items() if k in self.BROKER_KEYS}
        for key in ("ca_file", "password_file"):
            if key in values:
                values[key] = self.path(table, key, "broker")
                if values[key] is None:
                    return None
        if "port" not in values and values.get("tls") is True:
            values["port"] = 8883  # the registered MQTT-over-TLS port
        return self.build("broker", BrokerConfig, **values)

    def load_service(self, doc: dict[str, Any]) -> dict[str, Any] | None:
        """The [service] table as ServiceConfig keyword arguments (without sensors/twins)."""
        table = self.section(doc, "service")
        if table is None:
            return None
        complete = self.keys(table, self.SERVICE_KEYS, ("timezone", "state_dir"), "service")
        scalars = {
            "base_topic": table.get("base_topic", "pseudotwin"),
            "publish_every_minutes": table.get("publish_every_minutes", 15),
            "stale_after_minutes": table.get("stale_after_minutes", 30),
            "max_skew_seconds": table.get("max_skew_seconds", 300),
            "queue_size": table.get("queue_size", 10000),
            "log_level": table.get("log_level", "INFO"),
        }
        found = _service_scalar_problems(**scalars)
        state_dir = self.path(table, "state_dir", "service")
        if state_dir is not None and not isinstance(state_dir, Path):
            found.append(("state_dir", f"expected a path string, got {_type_name(state_dir)}"))
        for where, msg in found:
            self.add(f"service.{where}", msg)
        store = self.store_url(table.get("store"))
        hours = self.load_hours(table)
        if found or hours is None or not complete or not isinstance(state_dir, Path):
            return None
        scalars["log_level"] = str(scalars["log_level"]).upper()
        return {"hours": hours, "state_dir": state_dir, "store": store, **scalars}

    def store_url(self, value: object) -> str | None:
        """The history store: a SQLite file (relative to this file) or crate://host:4200."""
        if value is None:
            return None
        if not isinstance(value, str) or not value.strip():
            self.add("service.store", f"expected a SQLite path or crate:// URL, got {value!r}")
            return None
        if "://" in value:
            if not value.startswith(("crate://", "crate+https://", "sqlite://")):
                self.add("service.store", f"unknown store URL scheme in {value!r} "
                                          "(a SQLite file path, sqlite:///path or crate://host:4200)")
                return None
            if "@" in value.split("://", 1)[1].split("/", 1)[0]:
                self.add("service.store", "credentials do not belong in the store URL; set "
                                          "PSEUDOTWIN_CRATE_USER / PSEUDOTWIN_CRATE_PASSWORD")
                return None
            return value
        return str(self.base_dir / value)

    def load_hours(self, table: dict[str, Any]) -> OperatingHours | None:
        found: Found = []
        texts = {k: table.get(k, d) for k, d in (("day_start", "08:00"), ("day_end", "19:00"))}
        for key, text in texts.items():
            if _expect(found, key, text, "string") and _parse_hhmm(text) is None:
                found.append((key, f"expected a time of day HH:MM (00:00..24:00), got {text!r}"))
        init = table.get("init_minutes", 30)
        slot = table.get("slot_minutes", 15)
        _expect(found, "init_minutes", init, "number")
        _expect(found, "slot_minutes", slot, "number")
        tz = table.get("timezone")
        if tz is not None and _nonempty(found, "timezone", tz):
            try:
                ZoneInfo(tz)
            except (ZoneInfoNotFoundError, ValueError):
                found.append(("timezone", f"unknown IANA time zone {tz!r}{_suggest_tz(tz)}"))
        for where, msg in found:
            self.add(f"service.{where}", msg)
        if found or tz is None:
            return None
        try:
            return OperatingHours.from_strings(texts["day_start"], texts["day_end"],
                                               init, slot, tz)
        except ConfigError as exc:
            self.add(f"service.{_hours_field(str(exc))}", str(exc))
            return None

    def tables(self, doc: dict[str, Any], name: str) -> list[dict[str, Any]] | None:
        items = doc.get(name)
        if items is None:
            self.add(name, f"missing; add at least one [[{name}]] table")
            return None
        if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
            self.add(name, f"expected an array of tables [[{name}]], got {_type_name(items)}")
            return None
        if not items:
            self.add(name, f"at least one [[{name}]] table is required")
            return None
        return items

    def load_sensors(
        self, doc: dict[str, Any]
    ) -> tuple[list[tuple[str, SensorConfig]], bool, set[str] | None]:
        """(valid sensors with their locations, whether all were valid, ids of invalid ones;
        None when the [[sensors]] array itself is unusable)."""
        items = self.tables(doc, "sensors")
        if items is None:
            return [], False, None
        good: list[tuple[str, SensorConfig]] = []
        bad_ids: set[str] = set()
        for i, table in enumerate(items):
            loc = f"sensors[{i}]"
            sensor = self.load_sensor(table, loc)
            if sensor is None:
                if isinstance(table.get("id"), str):
                    bad_ids.add(table["id"])
            else:
                good.append((loc, sensor))
        return good, len(good) == len(items), bad_ids

    def load_sensor(self, table: dict[str, Any], loc: str) -> SensorConfig | None:
        complete = self.keys(table, self.SENSOR_KEYS, self.SENSOR_REQUIRED, loc)
        values = {k: v for k, v in table.items() if k in self.SENSOR_KEYS}
        misplaced = False
        if values.get("format") == "number":
            for key in ("ts_key", "value_key"):
                if key in values:
                    self.add(f"{loc}.{key}", 'only applies to format = "json"')
                    misplaced = True
        if not complete:
            return None
        sensor = self.build(loc, SensorConfig, **values)
        return None if misplaced else sensor

    def load_twins(self, doc: dict[str, Any]) -> tuple[list[tuple[str, TwinConfig]], bool]:
        items = self.tables(doc, "twins")
        if items is None:
            return [], False
        good = []
        for j, table in enumerate(items):
            loc = f"twins[{j}]"
            twin = self.load_twin(table, loc)
            if twin is not None:
                good.append((loc, twin))
        return good, len(good) == len(items)

    def load_twin(self, table: dict[str, Any], loc: str) -> TwinConfig | None:
        complete = self.keys(table, self.TWIN_KEYS, self.TWIN_REQUIRED, loc)
        values = {k: v for k, v in table.items() if k in self.TWIN_KEYS}
        if "artifact" in values:
            values["artifact"] = self.path(table, "artifact", loc)
        if isinstance(values.get("references"), list):
            values["references"] = tuple(values["references"])
        if not complete or values["artifact"] is None:
            return None
        return self.build(loc, TwinConfig, **values)

    # -- what must hold at start-up ------------------------------------------------------
    def run_artifact_check(self, loc: str, twin: TwinConfig) -> None:
        assert self.artifact_check is not None
        try:
            messages = list(self.artifact_check(twin, self.hours))
        except (PseudotwinError, OSError, ValueError) as exc:
            messages = [str(exc)]
        for msg in messages:
            self.add(f"{loc}.artifact", msg)

    def runtime_checks(self, broker: BrokerConfig | None, service: dict[str, Any] | None,
                       twins: list[tuple[str, TwinConfig]]) -> None:
        if broker is not None:
            problem = broker.password_problem()
            if problem is not None:
                self.add(f"broker.{problem[0]}", problem[1])
            if broker.ca_file is not None and not broker.ca_file.is_file():
                self.add("broker.ca_file", f"{broker.ca_file} does not exist")
        if service is not None:
            state_dir: Path = service["state_dir"]
            if state_dir.exists() and not state_dir.is_dir():
                self.add("service.state_dir", f"{state_dir} exists and is not a directory")
        for loc, twin in twins:
            if not twin.artifact.is_file():
                self.add(f"{loc}.artifact", f"{twin.artifact} does not exist (train the twin "
                                            "first)")
            elif self.artifact_check is not None:
                self.run_artifact_check(loc, twin)


def _suggest_tz(name: str) -> str:
    # Empty without tzdata; then there is simply no hint.
    return _suggest(name, available_timezones())


def _hours_field(message: str) -> str:
    """Best location for an OperatingHours error, by the first field its message names."""
    candidates = {"day_start": "day_start", "day_end": "day_end", "init phase": "init_minutes",
                  "slot_minutes": "slot_minutes", "time zone": "timezone"}
    hits = [(message.find(k), v) for k, v in candidates.items() if k in message]
    return min(hits)[1] if hits else "day_start"


def _read(path: Path) -> dict[str, Any]:
    """Parse the TOML file; unreadable or malformed files raise ConfigError (not Problems)."""
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None


def _load(path: str | os.PathLike[str], runtime: bool,
          artifact_check: ArtifactCheck | None) -> ServiceConfig:
    path = Path(path)
    doc = _read(path)
    loader = _Loader(path.absolute().parent, runtime=runtime, artifact_check=artifact_check)
    config = loader.load(doc)
    if loader.problems or config is None:
        raise ConfigProblems(loader.problems or ["config: invalid"])
    return config


def load_config(path: str | os.PathLike[str], *,
                artifact_check: ArtifactCheck | None = None) -> ServiceConfig:
    """Parse and validate a TOML configuration file.

    Checks the file's own consistency only; the files it points to (artifacts, CA file, the
    password source) need not exist yet. With ``artifact_check``, each twin whose artifact
    file exists is also checked by it.

    Raises :class:`ConfigProblems` listing every problem (``.problems``), or plain
    :class:`ConfigError` when the file cannot be read or is not valid TOML.
    """
    return _load(path, False, artifact_check)


def check_config(path: str | os.PathLike[str], *,
                 artifact_check: ArtifactCheck | None = None) -> ServiceConfig:
    """Everything :func:`load_config` checks, plus what the service needs to start: each
    artifact exists (and passes ``artifact_check``), the CA file exists, the password source
    is readable, and the state dir is not a file."""
    return _load(path, True, artifact_check)


def check_config_main(argv: list[str] | None = None, *,
                      artifact_check: ArtifactCheck | None = None) -> int:
    """``pseudotwin check-config FILE``: 0 valid, 1 problems found, 2 unreadable/not TOML."""
    parser = argparse.ArgumentParser(
        prog="pseudotwin check-config",
        description=(
            "Validate a pseudotwin configuration file: unknown or missing keys, types, MQTT "
            "topics, sensor ranges and units, twins' references, operating hours and time "
            "zone, and that every twin's model artifact and the MQTT password source "
            "(password_env / password_file) are available. Prints every problem with its "
            "location, e.g. 'sensors[2].topic: ...'."
        ),
        epilog="Exit status: 0 valid, 1 problems found, 2 file unreadable or not valid TOML.",
    )
    parser.add_argument("file", metavar="FILE", help="the TOML configuration file")
    args = parser.parse_args(argv)
    try:
        config = check_config(args.file, artifact_check=artifact_check)
    except ConfigProblems as exc:
        for problem in exc.problems:
            print(f"{args.file}: {problem}", file=sys.stderr)
        return 1
    except ConfigError as exc:
        # _read already prefixes the path.
        print(str(exc), file=sys.stderr)
        return 2
    print(f"{args.file}: OK ({len(config.sensors)} sensors, {len(config.twins)} twins)")
    return 0
