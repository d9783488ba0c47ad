"""Who publishes a twin: every daemon claims its twins and hears the other daemons' claims.

Nothing in a fleet's configuration stops two daemons from owning the same twin (overlapping
``--twins`` lists, a plain ``run`` left enabled beside the fleet, a second host started from
a copied image): both then publish ``<twin>/estimate``, perhaps from different artifacts,
and a controller gets the two streams interleaved. So each daemon sends one claim of all its
twins on ``<base>/claims`` (QoS 1, not retained: a stopped daemon leaves none behind) when it
connects and every ``CLAIM_EVERY``, and subscribes to that topic. A claim of many twins goes
in parts of at most ``CLAIM_BYTES`` (a broker's ``max_packet_size`` drops a client that sends
a larger packet), answers too; what a run claims is gathered from all of them.

Whether the sender of a claim still runs is decided without comparing clocks: a daemon that
hears a claim naming any of its twins answers it with a claim addressed to the sender's run
(``to``) of those of its twins it has not told that run of yet (so the answers end). An
answer addressed to this run proves its sender alive now: it is reported (an error naming
the other daemon and the twins), and answered in turn, so both daemons report, whichever
started first. A claim the broker kept for this daemon while it was away is answered, but
never reported by itself: its sender may have stopped since, and one that still runs
answers. A daemon reported once counts as publishing as long as its periodic claims come,
``STILL_THERE`` at most apart; then it is forgotten whole, so that a later claim of it is
answered and reported anew.
"""

from __future__ import annotations

import datetime as dt
import json
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

CLAIMS_SUFFIX = "claims"  # <base>/claims
#: A claim's size at most [bytes of payload]: a claim of more twins goes in parts. A broker
#: with a ``max_packet_size`` drops a client that sends a larger packet, and the daemon
#: reconnected for good (a claim of 10,000 twins is 230 kB).
CLAIM_BYTES = 8192
CLAIM_EVERY = 3600.0  # [s] between a daemon's claims after the one at connect
STILL_THERE = 2 * CLAIM_EVERY + 600.0  # [s] a reported daemon counts as running this long
KEPT_RUNS = 1000  # other runs remembered at most (answered or reported): a crash-looping
# daemon starts a new run every few seconds
#: A claim's client id and host at most [UTF-8 bytes]. An answer echoes the client id (``to``)
#: and every run heard is kept with it: a claim with an id of 16 kB was answered with a packet
#: above a broker's max_packet_size 16384, which dropped the daemon at every reconnect for
#: good (the claim redelivered), and KEPT_RUNS runs of 1 MB ids held 1 GB.
MAX_ID_BYTES = 1024
#: A claims message larger than this [bytes] is refused unparsed: a part is at most
#: CLAIM_BYTES (more only for one twin of a longer id), and parsing a claim of 40 MB (3
#: million twins) took the network thread half a gigabyte.
MAX_CLAIM_MESSAGE = 256 * 1024


@dataclass(frozen=True)
class Run:
    """One run of a daemon: its MQTT client id (unique per running daemon: two on one id
    knock each other off the broker) and its start [UTC, wall clock]."""

    client_id: str
    since: dt.datetime

    def __post_init__(self) -> None:
        if not self.client_id:
            raise ValueError("a claim needs a client id")
        if self.since.tzinfo is None:
            raise ValueError("a claim's since must be timezone-aware")


@dataclass(frozen=True)
class Claim:
    """A run's claim of ``twins``, sent from ``host`` by process ``pid``; ``to``: the run it
    answers (None: a claim of its own accord); ``part``: which part of the message it is (a
    claim of many twins goes in parts of at most CLAIM_BYTES)."""

    run: Run
    host: str
    pid: int
    twins: frozenset[str]
    to: Run | None = None
    part: int = 0

    def __post_init__(self) -> None:
        if self.part < 0:
            raise ValueError("a claim's part is not negative")

    def payload(self) -> bytes:
        return self._encode(sorted(self.twins))

    def _encode(self, twins: list[str]) -> bytes:
        def run(r: Run) -> dict[str, str]:
            return {"client_id": r.client_id, "since": r.since.isoformat()}

        return json.dumps({**run(self.run), "host": self.host, "pid": self.pid,
                           "twins": twins, "to": run(self.to) if self.to else None,
                           "part": self.part}, separators=(",", ":")).encode()

    def payloads(self, limit: int = CLAIM_BYTES) -> list[bytes]:
        """The claim in parts of at most ``limit`` bytes each (a part of one twin whose id
        alone is longer is larger), the twins in sorted order, numbered from 0; one part
        when it fits."""
        twins = sorted(self.twins)
        whole = self._encode(twins)
        if len(whole) <= limit or len(twins) < 2:
            return [whole]
        # a part's size: the envelope (with a wide part number) plus each id's JSON and comma
        envelope = len(replace(self, part=10**6)._encode([]))
        out: list[bytes] = []
        chunk: list[str] = []
        size = envelope
        for t in twins:
            n = len(json.dumps(t).encode()) + 1
            if chunk and size + n > limit:
                out.append(replace(self, part=len(out))._encode(chunk))
                chunk, size = [], envelope
            chunk.append(t)
            size += n
        out.append(replace(self, part=len(out))._encode(chunk))
        return out

    @classmethod
    def parse(cls, payload: bytes) -> Claim:
        """The claim in ``payload``; ValueError when it is not one (or one larger than
        MAX_CLAIM_MESSAGE, or with a client id or host longer than MAX_ID_BYTES)."""
        if len(payload) > MAX_CLAIM_MESSAGE:
            raise ValueError(f"not a claim (a message of {len(payload)} bytes, more than "
                             f"{MAX_CLAIM_MESSAGE})")
        try:
            d = json.loads(payload)
            pid, twins, to, part = d["pid"], d["twins"], d.get("to"), d.get("part", 0)
            if not isinstance(pid, int) or isinstance(pid, bool):
                raise TypeError("pid")
            if not isinstance(part, int) or isinstance(part, bool):
                raise TypeError("part")
            if not isinstance(twins, list) or not all(isinstance(t, str) for t in twins):
                raise TypeError("twins")

            def bounded(name: str, value: object) -> str:
                text = str(value)
                if len(text.encode("utf-8", "surrogatepass")) > MAX_ID_BYTES:
                    raise ValueError(f"{name} longer than {MAX_ID_BYTES} bytes")
                return text

            def run(x: dict[str, object]) -> Run:
                return Run(bounded("client_id", x["client_id"]),
                           dt.datetime.fromisoformat(str(x["since"])))

            return cls(run(d), bounded("host", d["host"]), pid, frozenset(twins),
                       run(to) if to is not None else None, part)
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            raise ValueError(f"not a claim ({exc!r})") from None

    def who(self) -> str:
        return (f"client id {self.run.client_id!r} on host {self.host!r} (pid {self.pid}, up "
                f"since {self.run.since.isoformat(timespec='seconds')})")


@dataclass(frozen=True)
class Heard:
    """What to do with a claim heard: ``answer`` (a claim addressed to its run, or None),
    ``reported``: the other run, newly known to publish ``twins`` of ours (None: nothing new
    to tell; ``twins`` are then those this claim names); ``counted``: the twins of ours whose
    count of other publishers this claim may have changed (a claim in parts tells them part
    by part)."""

    answer: Claim | None
    reported: Claim | None
    twins: frozenset[str]
    counted: frozenset[str] = frozenset()


class Ownership:
    """This daemon's claims and what it heard of others' (thread-safe: claims are heard on
    the MQTT network thread, the periodic claim is made on the worker).

    client_id, host, pid: this daemon's; twins: the twins it publishes; clock: monotonic
    seconds (replaceable in tests)."""

    def __init__(self, client_id: str, host: str, pid: int, twins: Iterable[str],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.client_id, self.host, self.pid = client_id, host, pid
        self.twins = frozenset(twins)
        self._clock = clock
        self._lock = threading.Lock()
        self.run: Run | None = None  # set by start()
        # run → our twins it claims (from every part and answer heard), and those of them
        # this run has told it of: answers carry only what was not told yet, so they end
        self._seen: dict[Run, set[str]] = {}
        self._told: dict[Run, set[str]] = {}
        # run reported → (its claim, our twins it publishes, when last heard)
        self._reported: dict[Run, tuple[Claim, set[str], float]] = {}

    def start(self, now: dt.datetime) -> None:
        """This run begins at ``now`` (wall clock, UTC: a run's identity)."""
        self.run = Run(self.client_id, now)

    def claim(self) -> list[bytes]:
        """This run's claim of all its twins, in parts of at most CLAIM_BYTES (answers are
        made by ``heard``)."""
        if self.run is None:
            raise RuntimeError("Ownership.start() first")
        return Claim(self.run, self.host, self.pid, self.twins).payloads()

    def heard(self, payload: bytes) -> Heard:
        """A message on the claims topic; ValueError when it is not a claim."""
        claim = Claim.parse(payload)
        ours = claim.twins & self.twins
        if claim.run.client_id == self.client_id or not ours:  # our own (an echo, an earlier
            return Heard(None, None, frozenset())  # run), or another fleet instance's
        now = self._clock()
        with self._lock:
            other = claim.run
            # (sets grown in place: a claim of 100,000 twins comes in some 300 parts)
            seen = self._seen.setdefault(other, set())
            seen |= ours
            reported = None
            if other in self._reported:  # still there: its periodic claim, or an answer
                self._reported[other] = (claim, seen, now)
                counted = ours
            elif claim.to == self.run:  # an answer to this run: its sender runs now
                self._reported[other] = (claim, seen, now)
                reported, counted = claim, frozenset(seen)
            else:
                counted = frozenset()
            answer = None
            told = self._told.setdefault(other, set())
            if self.run is not None and not ours <= told:  # tell it what it does not know
                answer = Claim(self.run, self.host, self.pid, ours - told, other)
                told |= ours
            self._prune()
        return Heard(answer, reported, counted if reported else ours, counted)

    def publishers(self, twins: Iterable[str] | None = None) -> dict[str, int]:
        """Twin → how many other daemons publish it (reported, and heard within
        STILL_THERE), for ``twins`` (None: every twin of ours; a part of a claim asks for
        its own only: all of 100,000 per part held the network thread for seconds)."""
        now = self._clock()
        count = dict.fromkeys(self.twins if twins is None else twins, 0)
        with self._lock:
            for _, theirs, heard in self._reported.values():
                if now - heard <= STILL_THERE:
                    for t in count.keys() & theirs if twins is not None else theirs:
                        count[t] += 1
        return count

    def gone(self) -> list[Claim]:
        """Runs reported whose claims stopped coming (longer than STILL_THERE), each once."""
        now = self._clock()
        with self._lock:
            out = [c for r, (c, _, heard) in self._reported.items()
                   if now - heard > STILL_THERE]
            for c in out:  # forgotten whole: should it claim again (back from an outage
                del self._reported[c.run]  # longer than STILL_THERE), it is answered
                self._told.pop(c.run, None)  # and so reported again
                self._seen.pop(c.run, None)
        return out

    def _prune(self) -> None:
        kept: dict[Run, Any]
        for kept in (self._seen, self._told, self._reported):
            while len(kept) > KEPT_RUNS:  # oldest first (insertion order)
                del kept[next(iter(kept))]
