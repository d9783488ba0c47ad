"""Validation helpers shared by the configuration value types, their loaders and the bridge.

A validator appends ``(field, message)`` pairs to a :data:`Found` list instead of raising at
the first problem, so that one run reports everything to fix; :func:`raise_if` turns the
list into one :class:`ConfigProblems`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from pseudotwin.errors import ConfigError

__all__ = [
    "MAX_TOPIC_BYTES",
    "ConfigProblems",
    "Found",
    "absent_sqlite_file",
    "base_topic_problem",
    "host_problem",
    "expect",
    "field_defaults",
    "is_int",
    "is_number",
    "nonempty",
    "raise_if",
    "suggest",
    "topic_problem",
    "type_name",
]

MAX_TOPIC_BYTES = 65535  # MQTT strings carry a 16-bit length prefix.


class ConfigProblems(ConfigError):
    """A configuration with one or more problems, each ``"<location>: <message>"``."""

    def __init__(self, problems: Iterable[str]) -> None:
        self.problems: list[str] = list(problems)
        super().__init__("\n".join(self.problems))

    def __str__(self) -> str:
        return "\n".join(self.problems)


Found = list[tuple[str, str]]  # (field, message) pairs found by a validator


def raise_if(found: Found) -> None:
    """Raise :class:`ConfigProblems` with every ``"<field>: <message>"`` of ``found``."""
    if found:
        raise ConfigProblems(f"{where}: {msg}" for where, msg in found)


def field_defaults(cls: type) -> dict[str, Any]:
    """The declared defaults of a dataclass's fields (fields without one are left out), so
    that loaders take them from the one place they are declared."""
    return {f.name: f.default for f in dataclasses.fields(cls)
            if f.default is not dataclasses.MISSING}


def suggest(key: str, known: Iterable[str]) -> str:
    """``" (did you mean 'x'?)"`` for the closest of ``known``, or an empty string."""
    close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


# -- small value checks ------------------------------------------------------------------


def type_name(value: object) -> str:
    """How a TOML value's type is named in messages ("an integer", "a table", ...)."""
    names = {bool: "a boolean", int: "an integer", float: "a float", str: "a string",
             list: "an array", tuple: "an array", dict: "a table"}
    return names.get(type(value), f"a {type(value).__name__}")


def is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def expect(found: Found, name: str, value: object, kind: str) -> bool:
    """Append a type problem unless ``value`` is of ``kind``; True when it is.

    kind: ``"string"``, ``"integer"``, ``"number"`` (finite), ``"boolean"`` or ``"path"``.
    """
    ok = {
        "string": isinstance(value, str),
        "integer": is_int(value),
        "number": is_number(value) and math.isfinite(value),  # type: ignore[arg-type]
        "boolean": isinstance(value, bool),
        "path": isinstance(value, Path),
    }[kind]
    if not ok:
        if kind == "number" and is_number(value):
            found.append((name, f"must be a finite number, got {value!r}"))
        else:
            article = "an" if kind[0] in "aeiou" else "a"
            found.append((name, f"expected {article} {kind}, got {type_name(value)}"))
    return ok


def nonempty(found: Found, name: str, value: object) -> bool:
    """Append a problem unless ``value`` is a non-empty string; True when it is."""
    if not expect(found, name, value, "string"):
        return False
    if not value:
        found.append((name, "must not be empty"))
        return False
    return True


def host_problem(host: str) -> str | None:
    """Why ``host`` (a name or an IP address) cannot be connected to, or None: what the
    resolver refuses deep in a network thread (a label over 63 bytes, a name over 253),
    where the error would only stop the thread and leave the process up, never connected."""
    if any(c.isspace() or ord(c) < 0x20 for c in host):
        return f"{host!r} contains a space or a control character"
    name = host.strip("[]")  # an IPv6 address in brackets
    if ":" in name:  # IPv6
        return None
    labels = name.rstrip(".").split(".")
    if len(name.rstrip(".")) > 253 or any(len(label.encode()) > 63 for label in labels):
        return f"{host!r} is not a host name (at most 253 characters, 63 between dots)"
    try:
        name.rstrip(".").encode("idna")
    except UnicodeError:
        return f"{host!r} is not a host name (an empty part between dots?)"
    return None


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


# The store URLs (history/store.py opens them; the loader checks them): a SQLite URL with no
# file path after it (``sqlite:///$DB`` with DB unset: a path forgotten, not a wish for a
# store in memory), and the forms that name a database in memory.
PATHLESS_SQLITE = "sqlite:///"


def is_memory_url(url: str) -> bool:
    """Whether ``url`` names a SQLite store in memory, which keeps nothing once closed."""
    return url.strip() in (":memory:", "sqlite://", "sqlite:///:memory:")


def absent_sqlite_file(url: str) -> str | None:
    """The file a SQLite store URL names when it does not exist yet; None when it exists or
    the store is no SQLite file."""
    file = sqlite_file(url)
    return file if file is not None and not os.path.exists(file) else None


def sqlite_file(url: str) -> str | None:
    """The file a SQLite store URL names: a path, or ``sqlite:///path`` (relative as given);
    None for a database server's URL or a store in memory."""
    text = url.strip()
    if is_memory_url(text) or text == PATHLESS_SQLITE:
        return None
    if text.startswith(PATHLESS_SQLITE):
        return text[len(PATHLESS_SQLITE):]
    return None if "://" in text else text
