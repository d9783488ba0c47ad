"""Who publishes a twin: every daemon claims its twins at each connect and hears the others.

Nothing in a fleet's configuration stops two daemons from owning the same twin (overlapping
``--twins`` lists, a plain ``run`` left enabled beside the fleet, a second host started from
a copied image): both then publish ``<twin>/estimate``, perhaps from different artifacts,
and a controller gets the two streams interleaved. Each daemon therefore sends a claim on
``<base>/<twin>/owner`` (QoS 1, not retained: a stopped daemon leaves no claim behind) for
each of its twins when it connects, and subscribes to its twins' claim topics. A claim of
another MQTT client id is a second publisher of that twin. It is answered once (per twin and
other daemon) with this daemon's own claim, so the daemon that started first learns of the
second from its connect's claims, and the second of the first from that answer.

A claim sent while this daemon was away (its persistent session kept it) may come from a
daemon that has stopped since: it is answered but not reported; a publisher still running
answers in turn, and that answer is reported.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from dataclasses import dataclass
from typing import Any

CLAIM_SUFFIX = "owner"  # <base>/<twin>/owner


@dataclass(frozen=True)
class Claim:
    """One daemon's claim of a twin: its MQTT client id (unique per running daemon: two
    on one id knock each other off the broker), host, process id and start [UTC]; ``sent``
    [UTC] is when the claim was published."""

    client_id: str
    host: str
    pid: int
    since: dt.datetime
    sent: dt.datetime

    def __post_init__(self) -> None:
        if not self.client_id:
            raise ValueError("a claim needs a client id")
        for name in ("since", "sent"):
            t = getattr(self, name)
            if t.tzinfo is None:
                raise ValueError(f"a claim's {name} must be timezone-aware")

    def payload(self) -> bytes:
        return json.dumps({"client_id": self.client_id, "host": self.host, "pid": self.pid,
                           "since": self.since.isoformat(), "sent": self.sent.isoformat()},
                          separators=(",", ":")).encode()

    @classmethod
    def parse(cls, payload: bytes) -> Claim:
        """The claim in ``payload``; ValueError when it is not one."""
        try:
            d: Any = json.loads(payload)
            pid = d["pid"]
            if not isinstance(pid, int) or isinstance(pid, bool):
                raise TypeError("pid")
            return cls(str(d["client_id"]), str(d["host"]), pid,
                       dt.datetime.fromisoformat(d["since"]),
                       dt.datetime.fromisoformat(d["sent"]))
        except (ValueError, TypeError, KeyError) as exc:
            raise ValueError(f"not a claim ({exc!r})") from None

    def who(self) -> str:
        return f"client id {self.client_id!r} on {self.host} (pid {self.pid}, up since " \
               f"{self.since.isoformat(timespec='seconds')})"


class Ownership:
    """This daemon's claims and what it heard of others'.

    own: this daemon's claim (``sent`` is replaced at each sending); topics: claim topic →
    twin id; late: how far before this daemon's connect a claim may be stamped and still
    count as sent while connected (clocks of two hosts differ) [s]."""

    def __init__(self, client_id: str, host: str, pid: int, topics: dict[str, str],
                 late: dt.timedelta) -> None:
        if late < dt.timedelta(0) or not math.isfinite(late.total_seconds()):
            raise ValueError("late must be a finite, non-negative duration")
        self.client_id, self.host, self.pid = client_id, host, pid
        self.topics = dict(topics)
        self.late = late
        self.since: dt.datetime | None = None  # set by start()
        # (twin, client id, since) of the claims answered and of those reported
        self._answered: set[tuple[str, str, dt.datetime]] = set()
        self._reported: set[tuple[str, str, dt.datetime]] = set()

    def start(self, now: dt.datetime) -> None:
        self.since = now

    def claim(self, now: dt.datetime) -> bytes:
        """This daemon's claim, sent at ``now``."""
        if self.since is None:
            raise RuntimeError("Ownership.start() first")
        return Claim(self.client_id, self.host, self.pid, self.since, now).payload()

    def heard(self, topic: str, payload: bytes, connected_at: dt.datetime
              ) -> tuple[Claim | None, bool, bool]:
        """A claim heard on ``topic``: (the other's claim or None when it is this daemon's
        own, answer it with this daemon's claim, report it as a second publisher).
        ValueError when the payload is not a claim."""
        claim = Claim.parse(payload)
        if claim.client_id == self.client_id:  # our own, or our previous run's
            return None, False, False
        key = (self.topics.get(topic, topic), claim.client_id, claim.since)
        answer = key not in self._answered
        self._answered.add(key)
        report = claim.sent >= connected_at - self.late and key not in self._reported
        if report:
            self._reported.add(key)
        return claim, answer, report
