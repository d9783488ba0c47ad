"""Home Assistant MQTT discovery (DESIGN.md §6, optional integrations): pure payload building.

One Home Assistant *device* per twin (a twin is what a user places, trains and removes; a
room with two twins shows as two devices), holding a ``sensor`` entity for the estimate
(``<base>/<twin>/estimate``) and, with ``baselines = true``, one per published baseline
(``<base>/<twin>/baseline/<kind>``). Every entity reads the daemon's own JSON payloads:
``value_template`` takes ``value``, except that a ``stale`` estimate (a reference silent and
no failover: made from its last value, without σ) and a ``null`` value render ``None``, which
Home Assistant shows as unknown; ``json_attributes_topic`` is the same topic, so ``std`` (σ),
``quality``, ``model``, ``ts`` and ``refs`` become attributes.

Availability comes from ``<base>/status``. The daemon publishes ``online``, ``offline`` (last
will, stop) and ``degraded`` (its journal cannot be written: it still publishes estimates on
its grid, so they stay usable); ``availability_template`` maps everything but ``offline`` to
``online``. ``expire_after`` is the config's ``stale_after`` (never shorter than two steps
of the publish grid, on which the baselines come): an entity that has not been published
for that long turns unavailable in Home Assistant, e.g. outside operating hours.

Discovery messages are retained and published on every connect. Removal: the config topics
this daemon ever published are remembered in ``<state_dir>/homeassistant.json``; on start,
every remembered topic that the current configuration no longer produces (a twin left the
config, a baseline withheld after retraining, ``baselines`` or the whole section turned off,
another prefix) gets an empty retained payload, which deletes the entity in Home Assistant
and the retained message on the broker. Topics stay remembered, so the empty payload is sent
again on each connect (idempotent) until a twin comes back under the same id.

Fleets (fleet.py): each twin is announced by the instance that owns it, with that
instance's status topic ``<base>/status/<instance>`` as its availability, and an instance
never removes the topics of twins the other instances own (``removals``' ``others``).

``object_id`` is deprecated by Home Assistant (2025.10, removed 2026.4): the entity id is
suggested with ``default_entity_id`` (``sensor.<unique_id>``) instead.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pseudotwin import __version__
from pseudotwin.core.files import write_replacing

log = logging.getLogger(__name__)

__all__ = [
    "AVAILABILITY_TEMPLATE",
    "STATE_FILE",
    "VALUE_TEMPLATE",
    "TwinEntities",
    "config_topic",
    "discovery_messages",
    "entity_config",
    "load_published",
    "removals",
    "save_published",
    "slug",
    "unique_id",
]

COMPONENT = "sensor"
MANUFACTURER = "pseudotwin"
STATE_FILE = "homeassistant.json"
ESTIMATE = "estimate"
# A stale estimate is made from a silent reference's last value (for the MPC, with quality
# ``stale`` and no σ); Home Assistant has no quality, so its state becomes unknown (Jinja's
# none renders "None").
VALUE_TEMPLATE = "{{ value_json.value if value_json.quality != 'stale' else none }}"
# ``degraded`` (journal failing, estimates still published) counts as available.
AVAILABILITY_TEMPLATE = "{{ 'offline' if value == 'offline' else 'online' }}"

DEVICE_CLASSES = {"temperature": "temperature", "co2": "carbon_dioxide"}
# Home Assistant's units for those device classes.
_UNITS = {"°C": "°C", "degC": "°C", "C": "°C", "K": "K", "°F": "°F", "degF": "°F", "F": "°F",
          "ppm": "ppm"}
_PRECISION = {"temperature": 2, "co2": 0}
_NOT_ID = re.compile(r"[^A-Za-z0-9_-]")


def slug(text: str) -> str:
    """``text`` with every character a discovery topic level does not allow made ``_``."""
    return _NOT_ID.sub("_", text)


def entity_object_id(text: str) -> str:
    """``text`` as the object part of a Home Assistant entity id, which takes lower-case
    letters, digits and single underscores, not at either end (``room1-desk`` → ``room1_desk``):
    unlike ``object_id`` before it, ``default_entity_id`` is not made valid for us."""
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_") or "pseudotwin"


@dataclass(frozen=True)
class TwinEntities:
    """What discovery needs of one running twin.

    quantity: ``"temperature"`` or ``"co2"``; unit: the unit of its estimates;
    primary: the model behind ``estimate``; baselines: the other published models.
    """

    id: str
    quantity: str
    unit: str
    primary: str
    baselines: tuple[str, ...] = ()


def unique_id(base_topic: str, twin: str, kind: str = ESTIMATE) -> str:
    """Stable across restarts and retraining: the daemon's base topic, the twin, the kind."""
    return f"pseudotwin_{slug(base_topic)}_{slug(twin)}_{slug(kind)}"


def config_topic(prefix: str, base_topic: str, twin: str, kind: str = ESTIMATE) -> str:
    """``<prefix>/sensor/<node_id>/<object_id>/config``: node = the daemon's base topic."""
    return f"{prefix}/{COMPONENT}/{slug(base_topic)}/{slug(twin)}_{slug(kind)}/config"


def entity_config(twin: TwinEntities, kind: str, *, base_topic: str,
                  expire_after: int, availability_topic: str | None = None) -> dict[str, Any]:
    """The discovery payload of one sensor entity (Home Assistant's MQTT sensor schema);
    availability from ``<base>/status`` unless ``availability_topic`` (a fleet instance's own
    status topic: fleet.py) is given."""
    state = f"{base_topic}/{twin.id}/{ESTIMATE}" if kind == ESTIMATE \
        else f"{base_topic}/{twin.id}/baseline/{kind}"
    uid = unique_id(base_topic, twin.id, kind)
    payload: dict[str, Any] = {
        "name": "Estimate" if kind == ESTIMATE else f"Baseline {kind}",
        "unique_id": uid,
        "default_entity_id": f"{COMPONENT}.{entity_object_id(uid)}",
        "state_topic": state,
        "value_template": VALUE_TEMPLATE,
        "json_attributes_topic": state,
        "state_class": "measurement",
        "unit_of_measurement": _UNITS.get(twin.unit, twin.unit),
        "expire_after": expire_after,
        "availability_topic": availability_topic or f"{base_topic}/status",
        "availability_template": AVAILABILITY_TEMPLATE,
        "payload_available": "online",
        "payload_not_available": "offline",
        "qos": 1,
        "device": {
            "identifiers": [f"pseudotwin_{slug(base_topic)}_{slug(twin.id)}"],
            "name": twin.id,
            "manufacturer": MANUFACTURER,
            "model": f"{twin.quantity} twin ({twin.primary})",
            "sw_version": __version__,
        },
        "origin": {"name": MANUFACTURER, "sw_version": __version__},
    }
    if twin.quantity in DEVICE_CLASSES:
        payload["device_class"] = DEVICE_CLASSES[twin.quantity]
        payload["suggested_display_precision"] = _PRECISION[twin.quantity]
    return payload


def discovery_messages(twins: Sequence[TwinEntities], *, prefix: str, base_topic: str,
                       expire_after: int, baselines: bool,
                       availability_topic: str | None = None) -> dict[str, bytes]:
    """Config topic → retained payload (UTF-8 JSON) for every entity of ``twins``."""
    out: dict[str, bytes] = {}
    for twin in twins:
        kinds = (ESTIMATE, *(twin.baselines if baselines else ()))
        for kind in kinds:
            topic = config_topic(prefix, base_topic, twin.id, kind)
            body = entity_config(twin, kind, base_topic=base_topic, expire_after=expire_after,
                                 availability_topic=availability_topic)
            out[topic] = json.dumps(body, ensure_ascii=False, sort_keys=True).encode()
    return out


def removals(published: Iterable[str], current: Mapping[str, bytes] | Iterable[str],
             others: Iterable[str] = ()) -> list[str]:
    """Config topics published before that the current configuration no longer has, except
    those of ``others``: twins still configured but owned by another fleet instance."""
    keep = set(current)
    foreign = {slug(t) for t in others}
    return sorted(t for t in set(published)
                  if t not in keep and _twin_slug(t) not in foreign)


def _twin_slug(topic: str) -> str:
    """The twin part of a config topic's ``<twin>_<kind>`` level (no kind holds a '_')."""
    levels = topic.split("/")
    return levels[-2].rsplit("_", 1)[0] if len(levels) >= 2 else ""


def load_published(state_dir: Path, name: str = STATE_FILE,
                   ours: Callable[[str], bool] = lambda t: t.endswith("/config")) -> set[str]:
    """The topics remembered in ``state_dir`` (empty when none or unreadable); ``name``: the
    file (default the discovery config topics; the daemon keeps its retained outputs in
    another). Only topics one can publish to and that ``ours`` takes for the file's kind
    are kept, the others said: each is cleared (an empty retained message) at the next
    connect, and a wildcard in a damaged or planted file killed the MQTT network thread
    there (paho raises), where another service's topic would have had its retained
    message wiped."""
    try:
        data = json.loads((state_dir / name).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return set()
    topics = data.get("published") if isinstance(data, dict) else None
    if not isinstance(topics, list):
        return set()
    kept = {t for t in topics if isinstance(t, str) and publishable(t) and ours(t)}
    if dropped := [t for t in topics if t not in kept]:
        log.warning("%s: %d entr(y/ies) that are not topics this daemon publishes, ignored "
                    "(the file damaged, or written by something else?): %s", state_dir / name,
                    len(dropped), ", ".join(repr(t)[:80] for t in dropped[:5]))
    return kept


def publishable(topic: str) -> bool:
    """Whether a message can be published to ``topic`` (MQTT: no wildcard, no NUL, not
    empty, at most 65,535 bytes of UTF-8)."""
    return bool(topic) and not {"+", "#", "\0"} & set(topic) \
        and len(topic.encode("utf-8", "surrogatepass")) <= 65535


def save_published(state_dir: Path, topics: Iterable[str], name: str = STATE_FILE) -> None:
    """Remember ``topics`` (never half a file: core/files.py)."""
    text = json.dumps({"published": sorted(set(topics))}, indent=1) + "\n"
    write_replacing(state_dir / name, lambda tmp: tmp.write_text(text, encoding="utf-8"),
                    follow_symlinks=False)
