"""Claims from a hostile or broken peer on ``<base>/claims``: an answer echoes the claim's
client id (``to``) and every run heard is kept with it. A claim with a client id of 16 kB
was answered with a packet above a broker's max_packet_size 16384 (the README's minimum),
which dropped the daemon; the broker redelivered the unacknowledged claim at each
reconnect, and the daemon never stayed connected again, across restarts too."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from conftest import own_broker
from daemon_support import config, off_grid, wait_for
from pseudotwin.edge import ownership
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.ownership import Ownership
from pseudotwin.edge.service import Service
from test_daemon import Viewer, publisher

LIMIT = 16384  # the broker's max_packet_size [bytes]


@pytest.fixture
def small_packet_broker(tmp_path: Path) -> Iterator[int]:
    with own_broker(tmp_path, f"allow_anonymous true\nmax_packet_size {LIMIT}\n",
                    "the broker with a packet limit") as port:
        yield port


def claim(client_id: str, twins: list[str], host: str = "") -> bytes:
    return json.dumps({"client_id": client_id, "since": "2026-01-01T00:00Z", "host": host,
                       "pid": 1, "twins": twins, "to": None, "part": 0},
                      separators=(",", ":")).encode()


def test_a_claim_with_an_oversized_field_or_size_is_refused_not_kept() -> None:
    MAX_ID_BYTES, MAX_CLAIM_MESSAGE = ownership.MAX_ID_BYTES, ownership.MAX_CLAIM_MESSAGE
    own = Ownership("pt-a", "host-a", 1, ["desk"])
    own.start(off_grid(12.0))
    with pytest.raises(ValueError, match="client_id longer"):
        own.heard(claim("x" * (MAX_ID_BYTES + 1), ["desk"]))
    with pytest.raises(ValueError, match="host longer"):
        own.heard(claim("x", ["desk"], host="h" * (MAX_ID_BYTES + 1)))
    with pytest.raises(ValueError, match="bytes, more than"):
        own.heard(claim("x", ["desk"] + [f"t{i:09d}" for i in range(MAX_CLAIM_MESSAGE // 12)]))
    assert own.heard(claim("x" * MAX_ID_BYTES, ["desk"])).answer is not None  # at the bound


def test_a_claim_with_a_long_client_id_does_not_knock_the_daemon_off_the_broker(
    tmp_path: Path, small_packet_broker: int, desk_artifact: Path, caplog
) -> None:
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.service")
    svc = Service(config(tmp_path, small_packet_broker, desk_artifact),
                  clock=ReplayClock(off_grid(12.0), 1.0))
    try:
        svc.start(wait_connected=20)
        assert svc.connected.is_set()
        viewer = Viewer(small_packet_broker, "pt/claims")
        pub = publisher(small_packet_broker, "pt-hostile")
        try:
            body = claim("", ["desk"])
            payload = claim("A" * (16300 - len(body)), ["desk"])  # within the broker's limit
            pub.publish("pt/claims", payload, qos=1).wait_for_publish(10)
            # A well-formed claim after it, on the same connection: the daemon hears the two
            # in order (network thread) and sends their answers in order on one connection.
            # The broker forwarding the witness's answer has read whatever the daemon sent
            # for the long claim before it: an answer over max_packet_size would have cut
            # the daemon off there.
            pub.publish("pt/claims", claim("pt-witness", ["desk"]), qos=1).wait_for_publish(10)
            wait_for(lambda: any((b["to"] or {}).get("client_id") == "pt-witness"
                                 for b in viewer.on("/claims"))
                     or "disconnected from the broker" in caplog.text,
                     what="the witness claim to be answered")
        finally:
            pub.disconnect()
            pub.loop_stop()
            viewer.close()
        assert "disconnected from the broker" not in caplog.text
        assert svc._claims_refused == 1 and svc.connected.is_set()
    finally:
        svc.stop()
