"""Fleets: one site's twins split over several daemon instances (``run --shard i/N`` or
``run --twins a,b``).

Twins are the unit of work (DESIGN.md §8, scale-out). An instance owns a disjoint set of
the configuration's twins and is given a configuration narrowed to them: only their twins,
only the sensors they read (so only those topics are subscribed), and everything an
instance keeps or announces made its own, so N instances of one config file can share a
broker, a store and even a host:

- the MQTT client id gets the instance name appended (each a persistent session of its own);
- ``state_dir`` gets a subfolder per instance (journal, Home Assistant bookkeeping);
- the status topic is ``<base>/status/<instance>``: one instance's last will must not mark
  the twins of the others unavailable.

Ownership by shard is ``sha256(twin id) mod N == i``: stable across processes, hosts and
Python versions (``hash()`` is salted per process), and independent of the order of the
twins in the file. Changing N moves most twins; a fleet is re-sharded by stopping it and
starting the new one (the instance names, hence sessions and state folders, change with N).
"""

from __future__ import annotations

import dataclasses
import hashlib
import re
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass

from pseudotwin.config import ServiceConfig
from pseudotwin.config.validate import suggest
from pseudotwin.errors import ConfigError

__all__ = ["FleetMember", "Shard", "narrow", "shard_of"]

_SHARD = re.compile(r"\s*(\d+)\s*/\s*(\d+)\s*")
LOGGED_IDS = 50  # twins named in the start-up log line; the rest are counted


def shard_of(twin_id: str, count: int) -> int:
    """The shard (0..count-1) that owns ``twin_id`` among ``count`` shards."""
    digest = hashlib.sha256(twin_id.encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "big") % count


@dataclass(frozen=True)
class Shard:
    """Shard ``index`` of ``count`` (0-based)."""

    index: int
    count: int

    def __post_init__(self) -> None:
        if self.count < 1:
            raise ConfigError(f"shard {self.index}/{self.count}: the number of shards must be "
                              "at least 1")
        if not 0 <= self.index < self.count:
            raise ConfigError(f"shard {self.index}/{self.count}: the index must be in "
                              f"0..{self.count - 1} (shards are numbered from 0)")

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``"i/N"`` → Shard(i, N); ConfigError with the expected form otherwise."""
        m = _SHARD.fullmatch(text)
        if not m:
            raise ConfigError(f"shard {text!r}: expected INDEX/COUNT, e.g. 0/2 (the first of "
                              "two instances)")
        return cls(int(m.group(1)), int(m.group(2)))

    def owns(self, twin_id: str) -> bool:
        return shard_of(twin_id, self.count) == self.index

    @property
    def name(self) -> str:
        return f"shard-{self.index}-of-{self.count}"

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


@dataclass(frozen=True)
class FleetMember:
    """One instance of a fleet: its name (client id suffix, state subfolder, status topic
    level), how it was chosen, its twins, and the configured twins the other instances own."""

    name: str
    label: str
    twins: tuple[str, ...]
    others: frozenset[str]

    def describe(self) -> str:
        shown = ", ".join(self.twins[:LOGGED_IDS])
        more = f" (+{len(self.twins) - LOGGED_IDS} more)" if len(self.twins) > LOGGED_IDS else ""
        total = len(self.twins) + len(self.others)
        return (f"{self.label} (instance {self.name}): owns {len(self.twins)} of {total} "
                f"twin(s): {shown or '-'}{more}")


def _explicit(twins: Sequence[str], configured: Collection[str]) -> tuple[str, ...]:
    unknown = [t for t in twins if t not in configured]
    if unknown:
        raise ConfigError("; ".join(f"--twins: unknown twin {t!r}{suggest(t, configured)}"
                                    for t in unknown))
    twice = sorted({t for t in twins if twins.count(t) > 1})
    if twice:
        raise ConfigError(f"--twins: listed more than once: {', '.join(twice)}")
    return tuple(t for t in configured if t in set(twins))  # the file's order


def _sensors_of(cfg: ServiceConfig, twins: Iterable[str]) -> set[str]:
    return {s for t in twins for s in (*cfg.twins[t].sensors, *cfg.twins[t].covariates)}


def narrow(cfg: ServiceConfig, *, shard: Shard | None = None,
           twins: Sequence[str] | None = None,
           metrics_port: int | None = None) -> tuple[ServiceConfig, FleetMember]:
    """The configuration of one instance owning ``shard``'s twins or the ``twins`` named,
    and its :class:`FleetMember`. Raises ConfigError for an unknown or repeated twin."""
    if (shard is None) == (twins is None):
        raise ConfigError("give either a shard or a list of twins")
    if shard is not None:
        owned = tuple(t for t in cfg.twins if shard.owns(t))
        name, label = shard.name, f"shard {shard}"
    else:
        assert twins is not None
        owned = _explicit(twins, cfg.twins)
        # Stable for the same set whatever its order: the session and state survive a
        # restart with the list written differently.
        key = hashlib.sha256(",".join(sorted(owned)).encode("utf-8")).hexdigest()[:8]
        name, label = f"twins-{key}", "explicit twin list"
    sensors = _sensors_of(cfg, owned)
    broker = dataclasses.replace(cfg.broker, client_id=f"{cfg.broker.client_id}-{name}")
    metrics = cfg.metrics if metrics_port is None else \
        dataclasses.replace(cfg.metrics, port=metrics_port)
    narrowed = dataclasses.replace(
        cfg,
        broker=broker,
        metrics=metrics,
        state_dir=cfg.state_dir / name,
        twins={t: cfg.twins[t] for t in owned},
        sensors={k: s for k, s in cfg.sensors.items() if k in sensors},
    )
    member = FleetMember(name, label, owned, frozenset(cfg.twins) - set(owned))
    return narrowed, member
