"""The bridge's spool (``[bridge] spool_dir``): no reading lost to a long broker outage or a
restart of the bridge, against pyads' ADS test server and a real Mosquitto (the PLC and
helpers of tests/test_bridge.py), and the outbox's bookkeeping on real files."""

from __future__ import annotations

import datetime as dt
import json
import logging
from pathlib import Path
from typing import Any

import pytest

import pseudotwin.edge.bridge.outbox as outbox_module
from conftest import MosquittoBroker, MqttClientFactory
from daemon_support import Synced
from pseudotwin.cli.bridge import EX_CONFIG, main
from pseudotwin.config import ConfigProblems
from pseudotwin.edge.bridge import Bridge, load_bridge_config
from pseudotwin.edge.bridge.outbox import COMPACT_BYTES, Outbox
from pseudotwin.edge.clock import EX_TEMPFAIL
from pseudotwin.edge.spool import Spool
from pseudotwin.errors import ConfigError, StateInUseError
from pseudotwin.live.readings import Reading
from test_bridge import (  # noqa: F401 - the fixtures plc and env
    DEFAULT_SYMBOLS,
    Env,
    Plc,
    _eleven_readings_in_an_outage,
    _is,
    _shared_file,
    _subscribe,
    _ts,
    _wait_for,
    _wait_initial,
    env_fixture,
    plc_fixture,
    running,
)

T0 = dt.datetime(2026, 11, 28, 8, 0, tzinfo=dt.UTC)


def _spooled_config(env: Env, **bridge: Any) -> Path:
    """The test's bridge file with ``spool_dir`` (and any other [bridge] keys) set."""
    path = env.write_config()
    keys = {"spool_dir": str(env.tmp_path / "spool"), **bridge}
    lines = "".join(f"{k} = {json.dumps(v)}\n" for k, v in keys.items())
    path.write_text(path.read_text().replace("[bridge]\n", f"[bridge]\n{lines}"),
                    encoding="utf-8")
    return path


def _hmi_values(inbox: Any, env: Env) -> list[float]:
    return [json.loads(m.payload)["value"] for m in inbox.seen
            if m.topic == env.topics["hmi/temp"]]


# -- through the PLC and the broker -------------------------------------------------------


def test_a_broker_outage_longer_than_the_queue_loses_nothing_with_a_spool(
    plc: Plc, env: Env, mosquitto: MosquittoBroker, mqtt_client: MqttClientFactory
) -> None:
    """Without a spool, readings beyond queue_size during an outage are dropped (only each
    sensor's newest kept: test_bridge.py); with one, every reading arrives, in order."""
    inbox = _subscribe(mqtt_client, env, client_id=f"sub-{env.client_id}", clean_session=False)
    with running(Bridge(load_bridge_config(_spooled_config(env, queue_size=5)))) as bridge:
        _eleven_readings_in_an_outage(plc, bridge, mosquitto, inbox, env, bridge.queue.empty,
                                      "the publisher has every reading")
        inbox.wait(env.topics["hmi/temp"], _is(39.0))
        inbox.wait(env.topics["ceiling/co2"], _is(800))
        _wait_for(lambda: bridge.unacknowledged() == 0, "everything acknowledged")
        assert bridge.dropped == 0
        outbox = bridge.outbox
        assert outbox is not None
        _wait_for(lambda: outbox.mark == outbox.end, "the spool marked acknowledged")
    assert _hmi_values(inbox, env) == [21.5, *(30.0 + i for i in range(10))]


def test_readings_unacknowledged_at_a_stop_are_sent_by_the_next_start(
    plc: Plc, env: Env, mosquitto: MosquittoBroker, mqtt_client: MqttClientFactory,
    caplog: pytest.LogCaptureFixture
) -> None:
    """paho holds unacknowledged readings in memory only: a bridge stopped during a broker
    outage lost them (test_bridge.py says so at stop). With a spool the next start sends
    them, with the instant the PLC stamped them."""
    inbox = _subscribe(mqtt_client, env, client_id=f"sub-{env.client_id}", clean_session=False)
    cfg = load_bridge_config(_spooled_config(env))
    first = Bridge(cfg)
    first.start()
    try:
        _wait_initial(inbox, env)
        _wait_for(lambda: first.unacknowledged() == 0, "the initial values acknowledged")
        mosquitto.stop()
        _wait_for(lambda: not first.mqtt_connected.is_set(), "the bridge sees the outage")
        written = [plc.write("MAIN.fRoomTemp", 25.0 + i) for i in range(3)]
        _wait_for(lambda: first.unacknowledged() == 3, "the readings handed to paho")
    finally:
        with caplog.at_level(logging.WARNING):
            first.stop()
        mosquitto.start()
    assert first.published == 3  # the initial values only
    assert "3 reading(s) not acknowledged by the broker" in caplog.text
    assert "stay in the spool" in caplog.text
    assert "are lost with this stop" not in caplog.text
    assert not any(_is(25.0 + i)(m.payload) for m in inbox.seen for i in range(3)
                   if m.topic == env.topics["hmi/temp"])

    with caplog.at_level(logging.INFO), running(Bridge(cfg)) as second:
        got = [inbox.wait(env.topics["hmi/temp"], _is(25.0 + i)) for i in range(3)]
        _wait_for(lambda: second.outbox is not None and not second.outbox.busy,
                  "the spool settled")
    assert "3 reading(s) of an earlier run wait in the spool" in caplog.text
    for payload, before in zip(got, written, strict=True):  # the PLC's stamps, in order
        assert before - dt.timedelta(seconds=1) <= _ts(payload) <= dt.datetime.now(dt.UTC)
    assert [_ts(p) for p in got] == sorted(_ts(p) for p in got)
    assert second.dropped == 0


def test_every_reading_is_on_disk_before_paho_has_it(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """spool_fsync (the default): a reading handed to MQTT is synced in the spool first, so
    a power cut cannot lose one the broker never acknowledged; switched off, no fsync."""
    synced = [0]
    syncs = [0]
    real_sync = Spool.sync

    def watched_sync(self: Spool) -> None:
        real_sync(self)
        syncs[0] += 1
        synced[0] = self.size()

    monkeypatch.setattr(Spool, "sync", watched_sync)
    inbox = _subscribe(mqtt_client, env)
    bridge = Bridge(load_bridge_config(_spooled_config(env)))
    handed: list[tuple[str, bytes, int]] = []
    real_publish = bridge.client.publish

    def watched_publish(topic: str, payload: Any = None, *args: Any, **kwargs: Any) -> Any:
        handed.append((topic, payload if isinstance(payload, bytes) else str(payload).encode(),
                       synced[0]))
        return real_publish(topic, payload, *args, **kwargs)

    monkeypatch.setattr(bridge.client, "publish", watched_publish)
    with running(bridge):
        _wait_initial(inbox, env)
        for i in range(5):
            plc.write("MAIN.fRoomTemp", 26.0 + i)
        inbox.wait(env.topics["hmi/temp"], _is(30.0))
        outbox = bridge.outbox
        assert outbox is not None
        lines = outbox.path.read_bytes().splitlines(keepends=True)
    ends: dict[tuple[str, float], int] = {}
    offset = 0
    for line in lines:
        offset += len(line)
        o = json.loads(line)
        ends[(o["sensor"], o["value"])] = offset
    topic_sensor = {t: s for s, t in env.topics.items()}
    readings = [(topic_sensor[t], p, at) for t, p, at in handed if t in topic_sensor]
    assert len(readings) == 8  # 3 initial values, 5 changes
    for sensor, payload, synced_then in readings:
        body = json.loads(payload)
        value = float(body["value"] if isinstance(body, dict) else body)
        assert ends[(sensor, value)] <= synced_then, f"{sensor} {value} handed unsynced"
    assert syncs[0] >= 1

    syncs[0] = 0
    off = _spooled_config(env, spool_fsync=False)
    inbox = _subscribe(mqtt_client, env)
    with running(Bridge(load_bridge_config(off))):
        inbox.wait(env.topics["hmi/temp"], _is(30.0))  # the current value, at the connect
        plc.write("MAIN.fRoomTemp", 31.0)
        inbox.wait(env.topics["hmi/temp"], _is(31.0))
    assert syncs[0] == 0


@pytest.mark.parametrize("fault", [OSError(28, "No space left on device"),
                                   RuntimeError("a fault of the spool's own")],
                         ids=["disk-full", "spool-fault"])
def test_readings_the_spool_cannot_take_go_to_the_broker_without_it_until_it_can(
    plc: Plc, env: Env, mqtt_client: MqttClientFactory, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture, fault: Exception
) -> None:
    """A spool that refuses a batch (a full disk, or a fault of its own) loses none of its
    readings: they are published as without a spool, said once (with the traceback of an
    unexpected fault); once it takes readings again, they go through it again."""
    real_add = Spool.add
    failing = [False]

    def refusing_add(self: Spool, readings: list[Reading]) -> Any:
        if failing[0]:
            raise fault
        return real_add(self, readings)

    monkeypatch.setattr(Spool, "add", refusing_add)
    inbox = _subscribe(mqtt_client, env)
    with caplog.at_level(logging.INFO), running(
            Bridge(load_bridge_config(_spooled_config(env)))) as bridge:
        _wait_initial(inbox, env)
        outbox = bridge.outbox
        assert outbox is not None
        failing[0] = True
        for i in range(3):
            plc.write("MAIN.fRoomTemp", 26.0 + i)
            inbox.wait(env.topics["hmi/temp"], _is(26.0 + i))
        written = outbox.end
        failing[0] = False
        plc.write("MAIN.fRoomTemp", 30.0)
        inbox.wait(env.topics["hmi/temp"], _is(30.0))
        assert outbox.end > written  # through the spool again
        assert bridge.dropped == 0
    refused = [r for r in caplog.records if "cannot write the spool" in r.getMessage()]
    assert len(refused) == 1
    assert bool(refused[0].exc_info) == (not isinstance(fault, OSError))
    assert "can be written again" in caplog.text
    assert "unexpected error while publishing readings from the spool" not in caplog.text
    assert _hmi_values(inbox, env) == [21.5, 26.0, 27.0, 28.0, 30.0]


def test_a_second_bridge_on_the_same_spool_is_refused_and_retried_by_systemd(
    env: Env, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _spooled_config(env)
    cfg = load_bridge_config(path)
    assert cfg.spool_path is not None
    holder = Outbox(cfg.spool_path)
    try:
        # Bridge.start first: should it not refuse, main() would run the bridge for good
        with pytest.raises(StateInUseError):
            Bridge(cfg).start()
        assert main(["--config", str(path)]) == EX_TEMPFAIL
    finally:
        holder.close()
    err = capsys.readouterr().err
    assert "in use by another pseudotwin bridge" in err and "one spool of readings" in err


def test_a_spool_dir_that_cannot_be_made_is_a_configuration_error(
    env: Env, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = env.tmp_path / "a-file"
    blocker.write_text("not a folder")
    path = _spooled_config(env, spool_dir=str(blocker / "spool"))
    with pytest.raises(ConfigError):  # first: else main() would run the bridge for good
        Bridge(load_bridge_config(path)).start()
    assert main(["--config", str(path)]) == EX_CONFIG
    assert str(blocker / "spool") in capsys.readouterr().err


# -- configuration ------------------------------------------------------------------------


def test_the_spool_defaults_to_the_daemons_state_dir_and_is_off_in_a_bridge_file(
    env: Env, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    own = env.write_config()
    assert load_bridge_config(own).spool_dir is None
    assert load_bridge_config(own).spool_path is None
    assert main(["--config", str(own), "--check"]) == 0
    assert "no spool: readings wait in memory only" in capsys.readouterr().out
    spooled = _spooled_config(env)
    assert main(["--config", str(spooled), "--check"]) == 0
    assert f"spool {env.tmp_path / 'spool' / f'bridge-{env.client_id}.jsonl'}" in \
        capsys.readouterr().out

    shared = _shared_file(tmp_path, 'ams_net_id = "192.168.10.20.1.1"', "dining/temp")
    cfg = load_bridge_config(shared)  # config/example.toml's state_dir, the units' one
    assert cfg.spool_dir == Path("/var/lib/pseudotwin")
    assert cfg.spool_path == Path("/var/lib/pseudotwin/bridge-pseudotwin-room1-bridge.jsonl")
    assert cfg.spool_fsync is True
    text = shared.read_text(encoding="utf-8")
    shared.write_text(text.replace("[plc]\n", '[bridge]\nspool_dir = "elsewhere"\n'
                                              'spool_fsync = false\n[plc]\n'),
                      encoding="utf-8")
    cfg = load_bridge_config(shared)
    assert cfg.spool_dir == tmp_path / "elsewhere" and cfg.spool_fsync is False


def test_bridged_sensors_without_a_time_stamp_are_named_at_check_and_at_start(
    env: Env, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """A bare number the bridge sends late (a broker outage, the spool after a restart) is
    stamped on arrival, and one sent twice counts twice: said before it happens."""
    caplog.set_level(logging.WARNING, logger="pseudotwin.edge.bridge")
    note = "sensor(s) ceiling/co2 carry no time stamp in their payload"
    path = env.write_config()  # ceiling/co2 is format = "number"
    assert main(["--config", str(path), "--check"]) == 0
    assert f"{path}: note: {note}" in capsys.readouterr().out
    blocker = env.tmp_path / "a-file"
    blocker.write_text("not a folder")
    with pytest.raises(ConfigError):  # start warns first, then fails: spool_dir is a file
        Bridge(load_bridge_config(_spooled_config(env, spool_dir=str(blocker)))).start()
    assert note in caplog.text
    stamped = env.write_config([s for s in DEFAULT_SYMBOLS if s["sensor"] != "ceiling/co2"])
    assert main(["--config", str(stamped), "--check"]) == 0
    assert "note:" not in capsys.readouterr().out


def test_bad_spool_settings_are_located(env: Env) -> None:
    path = _spooled_config(env, spool_dir="", spool_fsync="yes")
    with pytest.raises(ConfigProblems) as exc:
        load_bridge_config(path)
    text = "\n".join(exc.value.problems)
    assert "bridge.spool_dir: must not be empty" in text
    assert "bridge.spool_fsync" in text and "boolean" in text
    path = env.write_config()  # a file of the bridge's own: no spool for it to act on
    path.write_text(path.read_text().replace("[bridge]\n", "[bridge]\nspool_fsync = false\n"),
                    encoding="utf-8")
    with pytest.raises(ConfigProblems, match="spool_fsync: has no effect without a spool"):
        load_bridge_config(path)


def test_a_client_id_makes_a_safe_file_name(env: Env) -> None:
    path = _spooled_config(env)
    path.write_text(path.read_text().replace(f'client_id = "{env.client_id}"',
                                             'client_id = "../up/and away"'), encoding="utf-8")
    cfg = load_bridge_config(path)
    assert cfg.spool_path is not None and cfg.spool_dir is not None
    assert cfg.spool_path.parent == cfg.spool_dir
    assert cfg.spool_path.name == "bridge-.._up_and_away.jsonl"


# -- the outbox on its own: offsets, marks, restarts --------------------------------------


def _readings(n: int, start: int = 0) -> list[Reading]:
    return [Reading("hmi/temp", T0 + dt.timedelta(minutes=start + i), 20.0 + start + i)
            for i in range(n)]


def test_the_mark_moves_only_past_acknowledged_readings_in_order(tmp_path: Path) -> None:
    path = tmp_path / "spool" / "bridge-x.jsonl"
    outbox = Outbox(path, fsync=False)
    spans = outbox.add(_readings(4))
    pending = {11, 12, 13, 14}
    for mid, (_, end) in zip(range(11, 15), spans, strict=True):
        outbox.sent(mid, end)
    pending -= {12, 13}  # acknowledged out of order: the first still pending
    outbox.settle(pending.__contains__, force=True)
    assert outbox.acked_to == 0 and outbox.mark == 0
    pending.discard(11)
    outbox.settle(pending.__contains__, force=True)
    assert outbox.acked_to == outbox.mark == spans[2][1]
    assert Spool(path).consumed() == spans[2][1]
    assert outbox.waiting(pending.__contains__) == 1
    outbox.close()

    again = Outbox(path, fsync=False)  # a restart: the unacknowledged one is unsent again
    assert again.cursor == spans[2][1] and again.busy
    assert [r for r, _ in again.unsent()] == _readings(4)[3:]
    again.close()


def test_a_fully_acknowledged_spool_is_emptied_when_long_or_at_stop(tmp_path: Path) -> None:
    path = tmp_path / "bridge-x.jsonl"
    outbox = Outbox(path, fsync=False)
    for _, end in outbox.add(_readings(3)):
        outbox.sent(None, end)
    outbox.settle(lambda mid: False)
    assert path.stat().st_size == outbox.end > 0  # short: kept (no file churn per batch)
    assert outbox.end < COMPACT_BYTES
    outbox.settle(lambda mid: False, force=True)  # a clean stop
    assert outbox.end == outbox.cursor == outbox.mark == 0
    assert not Spool(path).offset_path.exists() and Spool(path).size() == 0
    spans = outbox.add(_readings(2, start=10))  # and it goes on from the start
    assert spans[0][0] == 0
    outbox.close()


def test_a_spool_deleted_under_the_bridge_goes_on_with_new_readings(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    folder = tmp_path / "state"
    outbox = Outbox(folder / "bridge-x.jsonl", fsync=True)
    outbox.add(_readings(3))  # not sent: the broker away
    for child in folder.iterdir():
        child.unlink()
    folder.rmdir()
    with caplog.at_level(logging.ERROR):
        spans = outbox.add(_readings(1, start=5))
    assert "was deleted or cut short while the bridge ran" in caplog.text
    assert outbox.cursor == spans[0][0]
    assert [r for r, _ in outbox.unsent()] == _readings(1, start=5)
    with pytest.raises(StateInUseError):  # the lock was made again with the folder
        Outbox(folder / "bridge-x.jsonl")
    outbox.close()


def test_an_unwritable_spool_is_a_configuration_error(tmp_path: Path) -> None:
    (tmp_path / "bridge-x.jsonl").mkdir()  # a folder where the file should be
    with pytest.raises(ConfigError, match="the bridge's spool cannot be written"):
        Outbox(tmp_path / "bridge-x.jsonl")
    (tmp_path / "bridge-x.jsonl").rmdir()
    Outbox(tmp_path / "bridge-x.jsonl").close()  # the failed open let its lock go


def test_the_mark_is_written_at_most_every_mark_seconds_and_a_failing_one_is_said_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "bridge-x.jsonl"
    outbox = Outbox(path, fsync=False)
    for _, end in outbox.add(_readings(2)):
        outbox.sent(None, end)
    monkeypatch.setattr(outbox_module, "MARK_SECONDS", 3600.0)
    outbox.settle(lambda mid: False)
    assert outbox.acked_to == outbox.end and outbox.mark == 0  # not yet: one write a while
    assert outbox.busy  # the publisher comes back for it
    monkeypatch.setattr(outbox_module, "MARK_SECONDS", 0.0)
    Spool(path).offset_path.mkdir()  # the mark cannot be written
    with caplog.at_level(logging.INFO):
        outbox.settle(lambda mid: False)
        outbox.settle(lambda mid: False)
        assert caplog.text.count("cannot mark the spool") == 1 and outbox.mark == 0
        Spool(path).offset_path.rmdir()
        outbox.settle(lambda mid: False)
    assert "can be marked again" in caplog.text
    assert outbox.mark == outbox.end == Spool(path).consumed() and not outbox.busy
    outbox.close()


def test_a_busy_sensor_never_all_acknowledged_still_has_its_spool_cut(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reading every 100 ms and acks a round trip behind: no moment had every reading
    acknowledged, so the spool was never emptied and grew ~70 MB a day per 10 readings/s.
    Its acknowledged part is cut off with the readings in flight kept."""
    monkeypatch.setattr(outbox_module, "COMPACT_BYTES", 500)
    path = tmp_path / "bridge-x.jsonl"
    outbox = Outbox(path, fsync=True)
    readings = _readings(200)
    pending: set[int] = set()
    biggest = 0
    for mid, reading in enumerate(readings, start=1):  # as the publisher's loop does
        outbox.settle(pending.__contains__)
        ((_, end),) = outbox.add([reading])
        outbox.sent(mid, end)
        pending.add(mid)
        outbox.settle(pending.__contains__)
        pending.discard(mid - 1)  # the one before is acknowledged while this is in flight
        biggest = max(biggest, path.stat().st_size)
    line = len(path.read_bytes().splitlines(keepends=True)[-1])
    assert biggest < 500 + 3 * line  # 200 lines would be ~30 times that
    assert [r for r, _ in Spool(path).lines(0)][-1] == readings[-1]
    outbox.close()
    again = Outbox(path, fsync=False)  # a restart sends what was not marked: the one in flight
    resent = [r for r, _ in again.unsent()]
    assert resent and resent == readings[-len(resent):] and len(resent) <= 500 // line + 2
    again.close()


def test_a_status_message_acknowledged_leaves_no_stray_early_ack(env: Env) -> None:
    """The status messages' acks were kept among the early acks (a reading's ack that comes
    before publish() returns its mid) for good: once paho's mids wrapped, a reading with
    one of their mids counted as acknowledged at once, and its spool offset could be marked
    before the broker had it."""
    bridge = Bridge(load_bridge_config(_spooled_config(env)))  # not started: paho queues
    info = bridge._publish_other(f"{env.base}/bridge/status", "online")
    bridge._on_publish(bridge.client, None, info.mid, None, None)  # the broker's PUBACK
    assert info.mid not in bridge._early_acks and not bridge._other_mids
    sensor = bridge.cfg.sensors["hmi/temp"]
    mid = bridge._send_value(sensor, T0, 21.0)
    assert mid is not None and bridge._pending(mid) and bridge.published == 0
    bridge._on_publish(bridge.client, None, mid, None, None)
    assert not bridge._pending(mid) and bridge.published == 1


def test_a_synced_spool_has_its_new_files_directory_entry_synced_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The spool file made at the start had its readings fsynced but never its directory
    entry: a power cut could take the new file, readings and all."""
    synced = Synced(monkeypatch).folders
    outbox = Outbox(tmp_path / "state" / "bridge-x.jsonl", fsync=True)
    assert synced == [tmp_path / "state", tmp_path]  # the file's entry, and its folder's
    outbox.add(_readings(2))
    outbox.add(_readings(2, start=5))
    assert synced == [tmp_path / "state", tmp_path]  # the entries are on disk already
    outbox.close()
    synced.clear()
    Outbox(tmp_path / "other" / "bridge-x.jsonl", fsync=False).close()
    assert synced == []
