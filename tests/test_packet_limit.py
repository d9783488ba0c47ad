"""A broker with a ``max_packet_size`` drops a client that sends a larger packet. A daemon of
hundreds of twins sent one SUBSCRIBE of all its sensor topics and one claim of all its twins,
both tens of kB: it reconnected for good and never came online. Subscriptions and claims now
go in pieces small enough for a broker that allows packets of 16 kB (README: Packet size)."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from conftest import own_broker
from daemon_support import REF, TZ, off_grid, wait_for
from pseudotwin.config import load_config
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.fleet import narrow
from pseudotwin.edge.mqttconn import SUBSCRIBE_BYTES, subscribe_packets
from pseudotwin.edge.ownership import CLAIM_BYTES, Claim, Ownership
from pseudotwin.edge.service import Service
from test_daemon import publisher, reading

LIMIT = 16384  # the broker's max_packet_size [bytes]
TWINS = [f"building-a.floor-3.room-{i:03d}.desk-by-the-window" for i in range(400)]
SENSORS = [f"room-{i:03d}/wall/temp" for i in range(400)]


@pytest.fixture
def small_packet_broker(tmp_path: Path) -> Iterator[int]:
    """A Mosquitto of its own that drops a client sending a packet above LIMIT; its port."""
    with own_broker(tmp_path, f"allow_anonymous true\nmax_packet_size {LIMIT}\n",
                    "the broker with a packet limit") as port:
        yield port


def site(folder: Path, port: int, artifact: Path) -> Path:
    """400 twins on the desk reference and 400 more sensors on long topics: one SUBSCRIBE of
    them all is ~25 kB, one claim of all twins ~20 kB."""
    sensors = [f'[[sensors]]\nid = "{REF}"\ntopic = "house/dining/temp"\nunit = "°C"\n'
               f"min = -10\nmax = 50\n"]
    sensors += [f'[[sensors]]\nid = "{s}"\ntopic = "site/building-a/floor-3/{s}/panel/value"\n'
                f'unit = "°C"\nmin = -10\nmax = 50\n' for s in SENSORS]
    (folder / "artifacts").mkdir()
    for i in range(len(TWINS)):  # a file of its own per twin: links of the desk twin's
        os.link(artifact, folder / "artifacts" / f"{i}.json")
    twins = [f'[[twins]]\nid = "{t}"\nreferences = ["{REF}"]\nquantity = "temperature"\n'
             f'artifact = "artifacts/{i}.json"\n' for i, t in enumerate(TWINS)]
    p = folder / "config.toml"
    p.write_text(f'[broker]\nhost = "127.0.0.1"\nport = {port}\nclient_id = "pt-big"\n\n'
                 f'[service]\nbase_topic = "pt"\ntimezone = "{TZ}"\nstate_dir = "state"\n'
                 f'baselines = "none"\n\n' + "\n".join(sensors + twins), encoding="utf-8")
    return p


def test_pieces_stay_within_their_bounds_and_lose_nothing() -> None:
    topics = [(f"site/building-a/floor-3/{s}/panel/value", 1) for s in SENSORS]
    packets = subscribe_packets(topics)
    assert len(packets) > 1 and [t for p in packets for t in p] == topics
    assert all(sum(len(t.encode()) + 3 for t, _ in p) <= SUBSCRIBE_BYTES for p in packets)
    assert subscribe_packets([("a" * 2 * SUBSCRIBE_BYTES, 1), ("b", 1)]) == [
        [("a" * 2 * SUBSCRIBE_BYTES, 1)], [("b", 1)]]  # a longer topic goes alone

    own = Ownership("pt-a", "host-a", 1, TWINS)
    own.start(off_grid(12.0))
    parts = [Claim.parse(p) for p in own.claim()]
    assert len(parts) > 1 and all(len(p) <= CLAIM_BYTES for p in own.claim())
    assert [c.part for c in parts] == list(range(len(parts)))
    assert frozenset().union(*(c.twins for c in parts)) == frozenset(TWINS)
    assert sum(len(c.twins) for c in parts) == len(TWINS)


def test_claims_and_answers_in_parts_end_and_tell_every_shared_twin() -> None:
    """The second half's owner starts later: it hears none of the first's claims (not
    retained), the answers themselves go in parts, and still each daemon counts all shared
    twins once the messages stop, which they do."""
    first = Ownership("pt-big", "host", 1, TWINS)
    first.start(off_grid(12.0))
    second = Ownership("pt-big-2", "host", 2, TWINS[200:])
    second.start(off_grid(12.5))
    inbox = [(first, p) for p in second.claim()]
    sent = 0
    while inbox:
        to, payload = inbox.pop(0)
        sent += 1
        assert sent < 100, "the answers do not end"
        answer = to.heard(payload).answer
        if answer is not None:
            other = second if to is first else first
            inbox += [(other, p) for p in answer.payloads()]
    assert first.publishers() == {t: int(t in TWINS[200:]) for t in TWINS}
    assert set(second.publishers().values()) == {1}


def test_a_daemon_of_many_twins_comes_online_under_a_packet_limit_and_hears_a_second_owner(
    tmp_path: Path, small_packet_broker: int, desk_artifact: Path, caplog
) -> None:
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.service")
    cfg = load_config(site(tmp_path, small_packet_broker, desk_artifact))
    a = Service(cfg, clock=ReplayClock(off_grid(12.0), 1.0))
    b = None
    try:
        a.start(wait_connected=20)
        assert a.connected.is_set(), "not subscribed: " + caplog.text[-2000:]
        # the last sensor topic of the last SUBSCRIBE is served
        pub = publisher(small_packet_broker, "pt-big-bridge")
        try:
            pub.publish(f"site/building-a/floor-3/{SENSORS[-1]}/panel/value",
                        reading(off_grid(12.0), 21.5), qos=1).wait_for_publish(10)
            wait_for(lambda: a.metrics.registry.get_sample_value(
                "pseudotwin_readings_accepted_total", {"sensor": SENSORS[-1]}) == 1,
                what=lambda: "the reading of the last sensor: " + caplog.text[-2000:])
        finally:
            pub.disconnect()
            pub.loop_stop()
        # A second daemon owning the second half (its own client id): its claim and each
        # answer go in parts, and every shared twin is counted by both, whichever part
        # named it.
        shared = TWINS[200:]
        c, member = narrow(cfg, twins=shared)
        b = Service(c, clock=ReplayClock(off_grid(12.0), 1.0), member=member)
        b.start(wait_connected=20)

        def counted(svc: Service) -> dict[str, float]:
            """The other-publishers gauge per twin (one collection of the registry: a
            sample looked up per twin collects every series each time)."""
            return {s.labels["twin"]: s.value for fam in svc.metrics.registry.collect()
                    if fam.name == "pseudotwin_twin_other_publishers" for s in fam.samples}

        wait_for(lambda: set(counted(b).values()) == {1}
                 and all(counted(a)[t] == 1 for t in shared),
                 what=lambda: f"both to count all {len(shared)} shared twins: "
                 + caplog.text[-2000:])
        assert all(counted(a)[t] == 0 for t in TWINS[:200])
        assert "disconnected from the broker" not in caplog.text
    finally:
        for svc in (a, b):
            if svc is not None and not svc.stop_event.is_set():
                svc.stop()
