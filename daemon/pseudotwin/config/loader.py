"""The TOML loader: a configuration file turned into a :class:`ServiceConfig`.

Every problem is reported with its location (``sensors[2].topic: ...``) and all problems of a
file are collected before raising, so one ``check-config`` run shows everything to fix.
Defaults are not repeated here: a key that is missing keeps its dataclass's default.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from pseudotwin.config.model import (
    BrokerConfig,
    HomeAssistantConfig,
    MetricsConfig,
    SensorConfig,
    ServiceConfig,
    TwinConfig,
    cross_problems,
    homeassistant_problems,
    service_scalar_problems,
    thinning_of,
)
from pseudotwin.config.validate import (
    PATHLESS_SQLITE,
    ConfigProblems,
    Found,
    expect,
    field_defaults,
    is_memory_url,
    nonempty,
    sqlite_file,
    suggest,
    type_name,
)
from pseudotwin.core.horizon import OperatingHours, parse_hhmm, zone_hint
from pseudotwin.core.thinning import Thinning
from pseudotwin.errors import ConfigError, PseudotwinError

__all__ = ["SERVICE_DEFAULTS", "ArtifactCheck", "Loader", "load_config", "load_file", "read_toml"]

#: Called per twin by :func:`load_config`/:func:`check_config` when its artifact file exists;
#: returns problem messages (without location), e.g. "artifact was trained for sensors ...".
# (twin, the service's operating hours if they are valid, the sensors' thinning) → problems
ArtifactCheck = Callable[[TwinConfig, OperatingHours | None, Thinning | None], list[str]]

MQTT_TLS_PORT = 8883  # the registered MQTT-over-TLS port: the default with tls = true
SERVICE_DEFAULTS = field_defaults(ServiceConfig)


class Loader:
    """Turns one parsed TOML document into a ServiceConfig, collecting every problem.

    Each section is validated on its own, so a broken [service] table does not hide a
    twin's unknown reference: the user sees everything in one run.
    """

    # [bridge] and [plc] belong to `pseudotwin bridge` (edge/bridge); one file may serve both.
    TOP_KEYS = ("broker", "service", "sensors", "twins", "bridge", "plc", "metrics",
                "homeassistant")
    BROKER_KEYS = ("host", "port", "tls", "ca_file", "username", "password_env",
                   "password_file", "client_id", "keepalive")
    SERVICE_KEYS = ("timezone", "state_dir", "base_topic", "day_start", "day_end",
                    "init_minutes", "slot_minutes", "publish_every_minutes",
                    "stale_after_minutes", "max_skew_seconds", "log_level", "queue_size",
                    "store", "baselines", "monitor_every_minutes", "journal_fsync")
    SENSOR_KEYS = ("id", "topic", "format", "ts_key", "value_key", "unit", "min", "max",
                   "min_interval_seconds")
    SENSOR_REQUIRED = ("id", "topic", "unit", "min", "max")
    TWIN_KEYS = ("id", "quantity", "references", "target", "artifact", "covariates")
    TWIN_REQUIRED = ("id", "quantity", "references", "artifact")
    METRICS_KEYS = ("host", "port", "record_port")
    HOMEASSISTANT_KEYS = ("enabled", "discovery_prefix", "baselines")

    SERVICE_SCALARS = ("base_topic", "publish_every_minutes", "stale_after_minutes",
                       "max_skew_seconds", "queue_size", "log_level", "baselines",
                       "monitor_every_minutes", "journal_fsync")
    HOURS_KEYS = ("day_start", "day_end", "init_minutes", "slot_minutes", "timezone")

    def __init__(self, base_dir: Path, *, artifact_check: ArtifactCheck | None = None,
                 only_twins: frozenset[str] | None = None) -> None:
        """only_twins: the twins whose artifacts are checked (a fleet instance's own: another
        instance's broken artifact is that instance's problem); None: all."""
        self.base_dir = base_dir
        self.artifact_check = artifact_check
        self.only_twins = only_twins
        self.problems: list[str] = []
        self.hours: OperatingHours | None = None
        self.thinning: Thinning | None = None

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
                self.add(f"{prefix}{key}", f"unknown key{suggest(key, known)}")
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
            self.add(name, f"expected a table [{name}], got {type_name(table)}")
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
        metrics = self.load_metrics(doc)
        if service is not None and metrics is not None:
            service["metrics"] = metrics
        homeassistant = self.load_homeassistant(doc)
        if service is not None and homeassistant is not None:
            service["homeassistant"] = homeassistant
        sensors, sensors_complete, bad_ids = self.load_sensors(doc)
        twins, twins_complete = self.load_twins(doc)
        raw_base = doc["service"].get("base_topic", SERVICE_DEFAULTS["base_topic"]) \
            if isinstance(doc.get("service"), dict) else None
        self.problems.extend(cross_problems(
            raw_base if isinstance(raw_base, str) else None, sensors, twins, bad_ids
        ))
        if homeassistant is not None:
            self.problems.extend(homeassistant_problems(homeassistant, [t.id for _, t in twins]))
        self.hours = service["hours"] if service is not None else None
        self.thinning = thinning_of(s for _, s in sensors) if sensors_complete else None
        self.check_sections(broker, service, twins)
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
            values["port"] = MQTT_TLS_PORT
        return self.build("broker", BrokerConfig, **values)

    def load_metrics(self, doc: dict[str, Any]) -> MetricsConfig | None:
        """The optional [metrics] table (absent: no Prometheus endpoint); None on problems."""
        table = doc.get("metrics")
        if table is None:
            return MetricsConfig()
        if not isinstance(table, dict):
            self.add("metrics", f"expected a table [metrics], got {type_name(table)}")
            return None
        self.keys(table, self.METRICS_KEYS, (), "metrics")
        values = {k: v for k, v in table.items() if k in self.METRICS_KEYS}
        return self.build("metrics", MetricsConfig, **values)

    def load_homeassistant(self, doc: dict[str, Any]) -> HomeAssistantConfig | None:
        """The optional [homeassistant] table (absent: no discovery); None on problems."""
        table = doc.get("homeassistant")
        if table is None:
            return HomeAssistantConfig()
        if not isinstance(table, dict):
            self.add("homeassistant", f"expected a table [homeassistant], got {type_name(table)}")
            return None
        self.keys(table, self.HOMEASSISTANT_KEYS, (), "homeassistant")
        values = {k: v for k, v in table.items() if k in self.HOMEASSISTANT_KEYS}
        return self.build("homeassistant", HomeAssistantConfig, **values)

    def load_service(self, doc: dict[str, Any]) -> dict[str, Any] | None:
        """The [service] table as ServiceConfig keyword arguments (without sensors/twins)."""
        table = self.section(doc, "service")
        if table is None:
            return None
        complete = self.keys(table, self.SERVICE_KEYS, ("timezone", "state_dir"), "service")
        scalars = {k: table.get(k, SERVICE_DEFAULTS[k]) for k in self.SERVICE_SCALARS}
        found = service_scalar_problems(**scalars)
        state_dir = self.path(table, "state_dir", "service")
        if state_dir is not None and not isinstance(state_dir, Path):
            found.append(("state_dir", f"expected a path string, got {type_name(state_dir)}"))
        for where, msg in found:
            self.add(f"service.{where}", msg)
        store = self.store_url(table.get("store"))
        hours = self.load_hours(table)
        if found or hours is None or not complete or not isinstance(state_dir, Path):
            return None
        scalars["log_level"] = str(scalars["log_level"]).upper()
        return {"hours": hours, "state_dir": state_dir, "store": store, **scalars}

    def store_url(self, value: object) -> str | None:
        """The history store: a SQLite file (relative to this file), postgresql://host/db or
        crate://host:4200."""
        if value is None:
            return None
        if not isinstance(value, str) or not value.strip():
            self.add("service.store", f"expected a SQLite path or crate:// URL, got {value!r}")
            return None
        if is_memory_url(value) or value.strip() == PATHLESS_SQLITE:
            self.add("service.store", f"{value!r} keeps nothing: the recorder's readings and "
                                      "the backfilled estimates would be gone when it stops "
                                      "(give a SQLite file path or a database URL)")
            return None
        if "://" in value:
            scheme = value.split("://", 1)[0].lower()  # as history/store.py reads it
            if scheme in ("postgresql", "postgres"):
                # A user name may be given, a password never (PGPASSWORD or ~/.pgpass).
                if ":" in value.split("://", 1)[1].split("/", 1)[0].rpartition("@")[0]:
                    self.add("service.store", "a password does not belong in the store URL; "
                                              "set PGPASSWORD or use ~/.pgpass")
                    return None
                return value
            if scheme not in ("crate", "crate+http", "crate+https", "sqlite"):
                self.add("service.store", f"unknown store URL scheme in {value!r} (a SQLite "
                                          "file path, sqlite:///path, postgresql://host/db, "
                                          "crate://host:4200, crate+http:// or "
                                          "crate+https://host:4200)")
                return None
            if "@" in value.split("://", 1)[1].split("/", 1)[0]:
                self.add("service.store", "credentials do not belong in the store URL; set "
                                          "PSEUDOTWIN_CRATE_USER / PSEUDOTWIN_CRATE_PASSWORD")
                return None
        # A SQLite file's path, as a path is taken: a relative one from this file's folder
        # (not the working directory, / under systemd), its folder checked.
        file = sqlite_file(value)
        return str(self.base_dir / file) if file is not None else value

    def load_hours(self, table: dict[str, Any]) -> OperatingHours | None:
        """OperatingHours from the keys given; the others keep OperatingHours' defaults."""
        found: Found = []
        given = {k: table[k] for k in self.HOURS_KEYS if k in table}
        for key in ("day_start", "day_end"):
            text = given.get(key)
            if text is not None and expect(found, key, text, "string"):
                try:
                    parse_hhmm(text, key)
                except ConfigError:
                    found.append((key, "expected a time of day HH:MM (00:00..24:00), got "
                                       f"{text!r}"))
        for key in ("init_minutes", "slot_minutes"):
            if key in given:
                expect(found, key, given[key], "number")
        tz = given.get("timezone")
        if tz is not None and nonempty(found, "timezone", tz):
            try:
                ZoneInfo(tz)
            except (ZoneInfoNotFoundError, ValueError, OSError):  # OSError: "Europe", a folder
                found.append(("timezone", f"unknown IANA time zone {tz!r}{zone_hint(tz)}"))
        for where, msg in found:
            self.add(f"service.{where}", msg)
        if found or tz is None:
            return None
        try:
            return OperatingHours.from_strings(**given)
        except ConfigError as exc:
            self.add(f"service.{_hours_field(str(exc))}", str(exc))
            return None

    def tables(self, doc: dict[str, Any], name: str) -> list[dict[str, Any]] | None:
        items = doc.get(name)
        if items is None:
            self.add(name, f"missing; add at least one [[{name}]] table")
            return None
        if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
            self.add(name, f"expected an array of tables [[{name}]], got {type_name(items)}")
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
        for key in ("references", "covariates"):
            if isinstance(values.get(key), list):
                values[key] = tuple(values[key])
        if not complete or values["artifact"] is None:
            return None
        return self.build(loc, TwinConfig, **values)

    # -- checks after parsing --------------------------------------------------------------
    def check_sections(self, broker: BrokerConfig | None, service: dict[str, Any] | None,
                       twins: list[tuple[str, TwinConfig]]) -> None:
        """Called once the sections are parsed: each twin whose artifact file exists is
        checked by ``artifact_check``. :class:`pseudotwin.config.checks.StartupLoader`
        checks what must hold at start-up instead."""
        if self.artifact_check is not None:
            for loc, twin in self.checked(twins):
                if twin.artifact.is_file():
                    self.run_artifact_check(loc, twin)

    def checked(self, twins: list[tuple[str, TwinConfig]]) -> list[tuple[str, TwinConfig]]:
        """The twins whose artifacts are checked (``only_twins``)."""
        only = self.only_twins
        return twins if only is None else [(loc, t) for loc, t in twins if t.id in only]

    def run_artifact_check(self, loc: str, twin: TwinConfig) -> None:
        assert self.artifact_check is not None
        try:
            messages = list(self.artifact_check(twin, self.hours, self.thinning))
        except (PseudotwinError, OSError, ValueError) as exc:
            messages = [str(exc)]
        for msg in messages:
            self.add(f"{loc}.artifact", msg)


def _hours_field(message: str) -> str:
    """Best location for an OperatingHours error, by the first field its message names."""
    candidates = {"day_start": "day_start", "day_end": "day_end", "init phase": "init_minutes",
                  "init_minutes": "init_minutes", "slot_minutes": "slot_minutes",
                  "time zone": "timezone"}
    hits = [(message.find(k), v) for k, v in candidates.items() if k in message]
    return min(hits)[1] if hits else "day_start"


def read_toml(path: Path) -> dict[str, Any]:
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


def load_file(path: str | os.PathLike[str], make_loader: Callable[..., Loader],
              artifact_check: ArtifactCheck | None = None,
              only_twins: frozenset[str] | None = None) -> ServiceConfig:
    """Read ``path`` and load it with ``make_loader(base_dir, artifact_check=...,
    only_twins=...)``."""
    path = Path(path)
    doc = read_toml(path)
    loader = make_loader(path.absolute().parent, artifact_check=artifact_check,
                         only_twins=only_twins)
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
    return load_file(path, Loader, artifact_check)
