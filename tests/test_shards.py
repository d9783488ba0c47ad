"""Fleets (issue 11, item 5): twins split over daemon instances by a stable hash, each
instance subscribing only to its twins' sensors; two instances on one real Mosquitto cover
every twin exactly once and lose nothing when one restarts."""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from daemon_support import (
    DAY,
    HOURS,
    REF,
    TZ,
    day_readings,
    off_grid,
    sml,
    uninterrupted_estimates,
    wait_for,
)
from pseudotwin.config import ServiceConfig, load_config
from pseudotwin.edge import homeassistant as ha
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.fleet import FleetMember, Shard, narrow, shard_of
from pseudotwin.edge.ownership import STILL_THERE, Claim, Heard, Ownership, Run
from pseudotwin.edge.service import Service
from pseudotwin.errors import ConfigError
from test_daemon import Viewer, publisher, reading

IDS = ["office-1", "office-2", "office-3", "office-4", "office-5", "office-6", "lab", "hall"]
# sha256 is the same everywhere: these are what every instance, host and release computes.
OWNER_OF_2 = {"office-1": 0, "office-2": 1, "office-3": 0, "office-4": 1, "office-5": 0,
              "office-6": 0, "lab": 1, "hall": 0}
OWNER_OF_3 = {"office-1": 0, "office-2": 1, "office-3": 2, "office-4": 1, "office-5": 1,
              "office-6": 0, "lab": 2, "hall": 2}
TWINS = IDS[:4]  # shard 0/2: office-1, office-3; shard 1/2: office-2, office-4
PREFIX = "ha-fleet"
NOON = HOURS.at(DAY, 12.0)


# -- the assignment -----------------------------------------------------------------------
def test_shard_assignment_is_fixed_disjoint_and_covering() -> None:
    assert {t: shard_of(t, 2) for t in IDS} == OWNER_OF_2
    assert {t: shard_of(t, 3) for t in IDS} == OWNER_OF_3
    ids = [f"room{i:03d}-{q}" for i in range(300) for q in ("temp", "co2")]
    for n in range(1, 6):
        owners = {t: [i for i in range(n) if Shard(i, n).owns(t)] for t in ids}
        assert all(len(o) == 1 for o in owners.values())  # disjoint and covering
        sizes = [sum(o == [i] for o in owners.values()) for i in range(n)]
        assert min(sizes) > 0.7 * len(ids) / n, sizes  # roughly even, none empty


def test_shard_assignment_is_the_same_in_other_processes() -> None:
    code = ("import json; from pseudotwin.edge.fleet import shard_of; "
            f"print(json.dumps({{t: shard_of(t, 3) for t in {IDS!r}}}))")
    for seed in ("1", "random"):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             check=True, timeout=60, env={**os.environ, "PYTHONHASHSEED": seed})
        assert json.loads(out.stdout) == OWNER_OF_3


@pytest.mark.parametrize("text,message", [
    ("2/2", "index must be in 0..1"), ("-1/2", "expected INDEX/COUNT"),
    ("0/0", "at least 1"), ("1", "expected INDEX/COUNT"), ("a/b", "expected INDEX/COUNT"),
])
def test_a_bad_shard_is_a_clear_error(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        Shard.parse(text)


def test_home_assistant_removals_spare_the_twins_of_other_instances() -> None:
    topic = lambda twin, kind="estimate": ha.config_topic("ha", "pt", twin, kind)  # noqa: E731
    published = [topic("a"), topic("a", "triv"), topic("a.b"), topic("gone"), topic("x")]
    assert ha.removals(published, [topic("x")], others=["a"]) == sorted(
        [topic("a.b"), topic("gone")])  # 'a.b' is not 'a', though its topic starts alike


# -- a site config of four twins, one reference sensor each ---------------------------------
def sensor_of(twin: str) -> str:
    return f"{twin}/wall/temp"


def topic_of(twin: str) -> str:
    return f"house/{sensor_of(twin)}"


def relabel(obj: object, mapping: dict[str, str]) -> object:
    if isinstance(obj, dict):
        return {mapping.get(k, k): relabel(v, mapping) for k, v in obj.items()}
    if isinstance(obj, list):
        return [relabel(v, mapping) for v in obj]
    return mapping.get(obj, obj) if isinstance(obj, str) else obj


def site_config(folder: Path, port: int, artifact: Path) -> Path:
    """Four twins, each on its own reference (the desk twin relabelled), one sensor no twin
    reads, Home Assistant discovery on."""
    base = json.loads(artifact.read_text())
    parts = [f'[broker]\nhost = "127.0.0.1"\nport = {port}\nclient_id = "fleet"\n\n'
             f'[service]\nbase_topic = "pt"\ntimezone = "{TZ}"\nstate_dir = "state"\n\n'
             f'[homeassistant]\nenabled = true\ndiscovery_prefix = "{PREFIX}"\n\n'
             '[[sensors]]\nid = "unused/temp"\ntopic = "house/unused/temp"\nunit = "°C"\n'
             "min = -10\nmax = 50\n"]
    for t in TWINS:
        art = folder / f"{t}.json"
        art.write_text(json.dumps(relabel(base, {REF: sensor_of(t)})))
        parts.append(f'[[sensors]]\nid = "{sensor_of(t)}"\ntopic = "{topic_of(t)}"\n'
                     'unit = "°C"\nmin = -10\nmax = 50\n')
        parts.append(f'[[twins]]\nid = "{t}"\nreferences = ["{sensor_of(t)}"]\n'
                     f'quantity = "temperature"\nartifact = "{art}"\n')
    path = folder / "site.toml"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def test_an_instance_gets_only_its_twins_their_sensors_and_names_of_its_own(
    tmp_path: Path, desk_artifact: Path
) -> None:
    cfg = load_config(site_config(tmp_path, 1883, desk_artifact))
    parts = [narrow(cfg, shard=Shard(i, 2)) for i in range(2)]
    for i, (c, m) in enumerate(parts):
        owned = [t for t in TWINS if OWNER_OF_2[t] == i]
        assert list(c.twins) == list(m.twins) == owned
        assert set(c.sensors) == {sensor_of(t) for t in owned}  # "unused/temp" in neither
        assert m.others == set(TWINS) - set(owned)
        assert m.name == f"shard-{i}-of-2"
        assert c.broker.client_id == f"fleet-shard-{i}-of-2"
        assert c.state_dir == cfg.state_dir / m.name
    assert parts[0][0].broker.client_id != parts[1][0].broker.client_id
    # an explicit list: the file's twins, named after the set whatever its order
    c, m = narrow(cfg, twins=["office-4", "office-2"])
    assert list(c.twins) == ["office-2", "office-4"]
    assert m == narrow(cfg, twins=["office-2", "office-4"])[1]
    assert m.name != narrow(cfg, twins=["office-2"])[1].name
    with pytest.raises(ConfigError, match="unknown twin 'ofice-2' \\(did you mean 'office-2'"):
        narrow(cfg, twins=["ofice-2"])
    with pytest.raises(ConfigError, match="listed more than once: office-2$"):
        narrow(cfg, twins=["office-2", "office-2"])
    assert narrow(cfg, shard=Shard(0, 2), metrics_port=9200)[0].metrics.port == 9200


def test_run_with_an_unknown_twin_exits_78_naming_it(tmp_path: Path, desk_artifact: Path
                                                      ) -> None:
    path = site_config(tmp_path, 1883, desk_artifact)
    p = subprocess.run([sys.executable, "-m", "pseudotwin.cli", "run", "--config", str(path),
                        "--twins", "office-1,office-9"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 78, p.stderr
    assert "unknown twin 'office-9'" in p.stderr and "Traceback" not in p.stderr


def test_a_broken_artifact_stops_its_owner_only(tmp_path: Path, desk_artifact: Path) -> None:
    """Every instance checked every twin's artifact: one bad retrained artifact made the
    whole fleet exit 78, which systemd does not restart."""
    from pseudotwin.cli import _load_service_config, _owned, build_parser

    path = site_config(tmp_path, 1883, desk_artifact)
    (tmp_path / "office-2.json").write_text("{ not json", encoding="utf-8")  # shard 1/2's
    args = [build_parser().parse_args(["run", "--config", str(path), "--shard", f"{i}/2"])
            for i in range(2)]
    assert set(_load_service_config(path, _owned(args[0])).twins) == {"office-1", "office-3",
                                                                      "office-2", "office-4"}
    with pytest.raises(ConfigError, match="office-2.json"):
        _load_service_config(path, _owned(args[1]))
    with pytest.raises(ConfigError, match="office-2.json"):
        _load_service_config(path)  # a single daemon runs them all


# -- two instances on one real broker -------------------------------------------------------
def start(cfg: ServiceConfig, shard: Shard) -> tuple[Service, FleetMember]:
    c, member = narrow(cfg, shard=shard)
    svc = Service(c, clock=ReplayClock(off_grid(12.0), 1.0), member=member)
    svc.start(wait_connected=15)
    return svc, member


def estimates(viewer: Viewer) -> dict[str, list[str]]:
    """Twin → timestamps of its estimates, in arrival order."""
    out: dict[str, list[str]] = {t: [] for t in TWINS}
    with viewer.lock:
        for topic, body in viewer.msgs:
            parts = topic.split("/")
            if len(parts) == 3 and parts[2] == "estimate" and isinstance(body, dict):
                out[parts[1]].append(body["ts"])
    return out


def test_two_sharded_daemons_publish_every_twin_once_and_lose_nothing_on_a_restart(
    tmp_path: Path, mosquitto, mqtt_client, desk_artifact: Path, caplog
) -> None:
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.service")
    cfg = load_config(site_config(tmp_path, mosquitto.port, desk_artifact))
    readings = day_readings(sml())
    readings = readings[readings["ts"] < HOURS.at(DAY, 11.0)]
    split = HOURS.at(DAY, 9.0)
    first, second = readings[readings["ts"] < split], readings[readings["ts"] >= split]
    in_hours = lambda df: [  # noqa: E731 — the estimates a twin publishes for these readings
        t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")
        for t in (x.to_pydatetime() for x in df["ts"]) if t >= HOURS.at(DAY, 8.0)]
    assert in_hours(first) and in_hours(second)
    mine = {i: [t for t in TWINS if OWNER_OF_2[t] == i] for i in (0, 1)}
    viewer = Viewer(mosquitto.port, "pt/#")
    pub = publisher(mosquitto.port, "fleet-bridge")

    def send(df, twins=TWINS) -> None:
        for _, r in df.iterrows():
            for t in twins:
                pub.publish(topic_of(t), reading(r["ts"].to_pydatetime(), float(r["value"])),
                            qos=1).wait_for_publish(10)
        pub.publish("house/unused/temp", reading(NOON, 20.0), qos=1).wait_for_publish(10)

    a, ma = start(cfg, Shard(0, 2))
    b, mb = start(cfg, Shard(1, 2))
    b2 = None
    try:
        assert "fleet: shard 0/2 (instance shard-0-of-2): owns 2 of 4 twin(s): " \
               "office-1, office-3" in caplog.text
        send(first)
        wait_for(lambda: all(len(e) == len(in_hours(first)) for e in estimates(viewer).values()),
                 what=lambda: f"first estimates {estimates(viewer)}")
        for svc in (a, b):  # each received its own twins' readings, nothing else
            wait_for(lambda svc=svc: svc.accepted == 2 * len(first), what="accepted")
            assert svc.health.received == svc.accepted

        b.stop()  # instance 1 restarts; its twins' readings meanwhile wait in its session
        wait_for(lambda: ("pt/status/shard-1-of-2", "offline") in viewer.msgs,
                 what="instance 1 offline")
        send(second)
        wait_for(lambda: a.accepted == 2 * len(readings), what="instance 0 took everything")
        wait_for(lambda: all(len(estimates(viewer)[t]) == len(in_hours(readings))
                             for t in mine[0]), what="instance 0's estimates")
        got = estimates(viewer)
        # nobody publishes instance 1's twins while it is down
        assert all(got[t] == in_hours(first) for t in mine[1])
        # its Home Assistant bookkeeping names instance 0's twins and a twin gone from the
        # config: only the gone one may be removed
        gone = ha.config_topic(PREFIX, "pt", "gone")
        watcher = mqtt_client()
        watcher.publish(gone, b"{}", retain=True)
        state = cfg.state_dir / mb.name
        ha.save_published(state, [*ha.load_published(state), gone,
                                  *(ha.config_topic(PREFIX, "pt", t) for t in mine[0])])
        watcher.subscribe(f"{PREFIX}/#")

        b2, _ = start(cfg, Shard(1, 2))
        wait_for(lambda: all(len(e) == len(in_hours(readings))
                             for e in estimates(viewer).values()),
                 what=lambda: f"all estimates {estimates(viewer)}")
        # (one reading more is a redelivery of one whose ack the stop overtook)
        wait_for(lambda: b2.accepted >= len(mine[1]) * len(second), what="instance 1 caught up")
        # instance 0 got none of them, nor the reading of the sensor no twin reads
        assert a.accepted == a.health.received == 2 * len(readings)
        # exactly once per twin and reading, and what a daemon that never stopped publishes
        expected = uninterrupted_estimates(desk_artifact, readings)
        for t in mine[1]:
            with viewer.lock:
                live = {b["ts"]: b for tp, b in viewer.msgs if tp == f"pt/{t}/estimate"}
            assert estimates(viewer)[t] == in_hours(readings) == list(live)
            for ts, e in live.items():
                assert e["value"] == round(expected[ts].value, 6), (t, ts)
        # instance 1 sends its removals, then its own configs: once those arrived, any
        # removal of instance 0's twins would have too
        seen: list[tuple[str, bytes]] = []
        own = {ha.config_topic(PREFIX, "pt", t) for t in mine[1]}
        while not own <= {tp for tp, _ in seen} or (gone, b"") not in seen:
            m = watcher.get(timeout=20)
            if not m.retain:  # retained: what the broker held before instance 1 came back
                seen.append((m.topic, m.payload))
        assert {tp for tp, _ in seen} == {gone, *own}  # nothing of instance 0's twins
        # what Home Assistant finds now: each twin announced, available by its owner's status
        fresh = mqtt_client()
        fresh.subscribe(f"{PREFIX}/#")
        configs: dict[str, bytes] = {}
        while not {ha.config_topic(PREFIX, "pt", t) for t in TWINS} <= set(configs):
            m = fresh.get(timeout=20)
            configs[m.topic] = m.payload
        for t in TWINS:
            body = json.loads(configs[ha.config_topic(PREFIX, "pt", t)])
            assert body["availability_topic"] == f"pt/status/shard-{OWNER_OF_2[t]}-of-2"
        with viewer.lock:
            statuses = [(tp, s) for tp, s in viewer.msgs if tp.startswith("pt/status")]
        assert ("pt/status", "online") not in statuses  # no shared status topic
        assert statuses[-1] == ("pt/status/shard-1-of-2", "online")
        assert ("pt/status/shard-0-of-2", "offline") not in statuses
        # disjoint shards: each heard its own claims only
        assert "published by another daemon too" not in caplog.text
    finally:
        for svc in (a, b, b2):
            if svc is not None and not svc.stop_event.is_set():
                svc.stop()
        pub.loop_stop()
        viewer.close()


def claims(viewer: Viewer) -> list[dict]:
    with viewer.lock:
        return [b for tp, b in viewer.msgs if tp == "pt/claims" and isinstance(b, dict)]


def publishers(svc: Service, twin: str) -> float | None:
    return svc.metrics.registry.get_sample_value("pseudotwin_twin_other_publishers",
                                                 {"twin": twin})


def test_two_daemons_owning_one_twin_both_say_so_and_a_claim_kept_while_away_is_answered(
    tmp_path: Path, mosquitto, desk_artifact: Path, caplog
) -> None:
    """Overlapping --twins lists: office-2 is published by both instances. The one started
    first answers the second's claim, the second reports it and answers in turn, and the
    first reports that: both say so, naming the other, and nothing more goes back and forth.
    A claim the broker kept for a stopped instance is answered at its return but not
    reported: its sender stopped meanwhile."""
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.service")
    cfg = load_config(site_config(tmp_path, mosquitto.port, desk_artifact))

    def start_twins(twins: list[str]) -> Service:
        c, member = narrow(cfg, twins=twins)
        svc = Service(c, clock=ReplayClock(off_grid(12.0), 1.0), member=member)
        svc.start(wait_connected=15)
        return svc

    def reports() -> list[logging.LogRecord]:
        return [r for r in caplog.records if "published by another daemon too" in r.message]

    viewer = Viewer(mosquitto.port, "pt/claims")
    a = start_twins(["office-1", "office-2"])
    b = start_twins(["office-2", "office-3"])
    later: list[Service] = []
    try:
        wait_for(lambda: publishers(a, "office-2") == 1 == publishers(b, "office-2"),
                 what=lambda: caplog.text)
        assert publishers(a, "office-1") == 0 == publishers(b, "office-3")
        named = {svc.cfg.broker.client_id: [r.message for r in reports()
                                             if repr(svc.cfg.broker.client_id) in r.message]
                 for svc in (a, b)}
        assert all(len(said) == 1 and said[0].endswith("counts them all): office-2")
                   for said in named.values())
        viewer.c.publish("pt/claims", b"not a claim", qos=1)  # ignored, said, acknowledged
        wait_for(lambda: caplog.text.count("1 message(s) on pt/claims that are not claims") == 2,
                 what="the stray message noticed by both")
        # a's claim, b's, a's answer to b, b's answer to a (the answers in either order: a
        # busy a may send its claim after b subscribed)
        wait_for(lambda: len(claims(viewer)) == 4, what="claims and answers")
        got = sorted(((c["client_id"], c["to"] and c["to"]["client_id"], c["twins"])
                      for c in claims(viewer)), key=str)
        assert got == sorted([
            (a.cfg.broker.client_id, None, ["office-1", "office-2"]),
            (b.cfg.broker.client_id, None, ["office-2", "office-3"]),
            (a.cfg.broker.client_id, b.cfg.broker.client_id, ["office-2"]),
            (b.cfg.broker.client_id, a.cfg.broker.client_id, ["office-2"])], key=str)

        a.stop()  # a's session keeps b's next claim
        b.stop()
        b2 = start_twins(["office-2", "office-3"])
        later.append(b2)
        wait_for(lambda: len(claims(viewer)) == 5, what="b's new claim")
        b2.stop()
        caplog.clear()
        a2 = start_twins(["office-1", "office-2"])
        later.append(a2)
        run = a2.ownership.run
        assert run is not None
        # a2's claim, and its answer to b2's kept claim (to b's too, should a's stop have
        # left it unacknowledged): no report, nobody to answer
        wait_for(lambda: any(c["to"] == {"client_id": b2.cfg.broker.client_id,
                                         "since": b2.ownership.run.since.isoformat()}
                             for c in claims(viewer)), what="a2's answer to b2's kept claim")
        assert publishers(a2, "office-2") == 0 and not reports()
    finally:
        for svc in (a, b, *later):
            if not svc.stop_event.is_set():
                svc.stop()
        viewer.close()


@pytest.mark.parametrize("payload", [
    b"", b"not json", b"[]", b'{"client_id": "x"}',
    b'{"client_id": "x", "host": "h", "pid": "1", "since": "2024-01-01T00:00:00+00:00", '
    b'"twins": ["a"]}',
    b'{"client_id": "x", "host": "h", "pid": 1, "since": "2024-01-01T00:00:00+00:00", '
    b'"twins": "a"}',
    b'{"client_id": "x", "host": "h", "pid": 1, "since": "2024-01-01T00:00:00", '
    b'"twins": ["a"]}',
    b'{"client_id": "x", "host": "h", "pid": 1, "since": "2024-01-01T00:00:00+00:00", '
    b'"twins": ["a"], "to": "y"}',
])
def test_a_claim_that_is_not_one_is_refused(payload: bytes) -> None:
    with pytest.raises(ValueError, match="not a claim"):
        Claim.parse(payload)


def test_claims_are_answered_once_reported_when_answered_and_forgotten_when_they_stop() -> None:
    """The rules without a broker: own claims and other fleet instances' are ignored; another
    run's claim is answered once; a report needs an answer addressed to this run; a reported
    run counts while its periodic claims come."""
    now = [0.0]
    own = Ownership("pt-a", "host-a", 1, ["x", "y"], clock=lambda: now[0])
    own.start(NOON)
    ours = Run("pt-a", NOON)
    assert [Claim.parse(p) for p in own.claim()] == [Claim(ours, "host-a", 1,
                                                           frozenset({"x", "y"}))]
    earlier = Claim(Run("pt-a", NOON - dt.timedelta(days=1)), "host-a", 7, frozenset({"x"}))
    elsewhere = Claim(Run("pt-c", NOON), "host-c", 3, frozenset({"z"}))  # disjoint
    for payload in (*own.claim(), earlier.payload(), elsewhere.payload()):
        assert own.heard(payload) == Heard(None, None, frozenset())
    b = Claim(Run("pt-b", NOON), "host-b", 2, frozenset({"y", "z"}))
    heard = own.heard(b.payload())  # kept, or new: answered, not reported
    assert heard == Heard(Claim(ours, "host-a", 1, frozenset({"y"}), b.run), None,
                          frozenset({"y"}))
    assert own.heard(b.payload()).answer is None  # once
    assert own.publishers() == {"x": 0, "y": 0}
    answer = Claim(b.run, "host-b", 2, frozenset({"y"}), ours)
    assert own.heard(answer.payload()) == Heard(None, answer, frozenset({"y"}), frozenset({"y"}))
    assert own.publishers() == {"x": 0, "y": 1}
    assert own.heard(answer.payload()).reported is None  # reported once
    now[0] += STILL_THERE - 1
    own.heard(b.payload())  # its periodic claim
    now[0] += STILL_THERE - 1
    assert own.gone() == [] and own.publishers()["y"] == 1
    now[0] += 2
    assert own.gone() == [b]  # the claim last heard
    assert own.publishers() == {"x": 0, "y": 0} and own.gone() == []
    # back from an outage longer than STILL_THERE (its claims kept meanwhile say nothing of
    # it running): its next claim is answered, and its answer reports it again
    assert own.heard(b.payload()).answer is not None
    assert own.heard(answer.payload()).reported == answer
    assert own.publishers() == {"x": 0, "y": 1} and own.publishers(["y"]) == {"y": 1}


def test_an_instance_owning_no_twin_warns_and_stays_online(
    tmp_path: Path, mosquitto, mqtt_client, desk_artifact: Path, caplog
) -> None:
    caplog.set_level(logging.INFO, logger="pseudotwin.edge.service")
    cfg = load_config(site_config(tmp_path, mosquitto.port, desk_artifact))
    empty = next(i for i in range(8) if not any(Shard(i, 8).owns(t) for t in TWINS))
    watcher = mqtt_client()
    watcher.subscribe(f"pt/status/shard-{empty}-of-8")
    svc, member = start(cfg, Shard(empty, 8))
    try:
        assert member.twins == () and not svc.cfg.sensors
        assert watcher.get(timeout=15).payload == b"online"
        assert f"fleet: shard {empty}/8 owns no twin" in caplog.text
    finally:
        svc.stop()


def test_grid_work_goes_first_to_the_twins_that_heard_from_their_sensors_longest_ago(
    tmp_path: Path, mosquitto, desk_artifact: Path
) -> None:
    """A reading of a twin whose grid estimate is still queued waits for that twin's grid
    work; cyclic sensors report next where they reported longest ago, so those twins' grid
    work goes first, whatever their order in the config."""
    cfg = load_config(site_config(tmp_path, mosquitto.port, desk_artifact))
    heard = ["office-3", "office-1", "office-4", "office-2"]  # oldest reading first
    assert heard != TWINS
    viewer = Viewer(mosquitto.port, "pt/+/estimate")
    pub = publisher(mosquitto.port, "order-bridge")
    svc = Service(cfg, clock=ReplayClock(off_grid(12.0), 1.0))
    svc.start(wait_connected=15)
    try:
        for k, t in enumerate(heard):
            ts = NOON - dt.timedelta(minutes=10 - 2 * k)
            pub.publish(topic_of(t), reading(ts, 20.0 + k), qos=1).wait_for_publish(10)
            wait_for(lambda k=k: svc.accepted == k + 1, what="the reading applied")
        svc.queue.put(("tick", NOON))
        noon = NOON.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")

        def at_noon() -> list[str]:
            with viewer.lock:
                return [t.split("/")[1] for t, b in viewer.msgs
                        if isinstance(b, dict) and b["ts"] == noon]

        wait_for(lambda: len(at_noon()) == len(TWINS), what="every twin's grid estimate")
        assert at_noon() == heard
    finally:
        svc.stop()
        pub.loop_stop()
        viewer.close()
