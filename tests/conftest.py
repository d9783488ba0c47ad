"""Shared fixtures: a real Mosquitto broker and paho-mqtt clients connected to it.

The broker is a real process (not a mock) because the daemon's hard parts — persistent
sessions, QoS 1 redelivery, reconnects after a broker restart — only show against one.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import queue
import shutil
import signal
import socket
import subprocess
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

MOSQUITTO_CANDIDATES = ("/usr/sbin/mosquitto", "/usr/bin/mosquitto", "/usr/local/sbin/mosquitto")
START_TIMEOUT = 10.0  # s until a freshly started broker must accept TCP connections
STOP_TIMEOUT = 10.0  # s for a graceful stop, which writes the persistence file


def _find_mosquitto() -> str | None:
    for candidate in (*MOSQUITTO_CANDIDATES, shutil.which("mosquitto")):
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    return None


def _mosquitto_binary() -> str:
    """The broker binary; installs the Debian package once if missing, else fails loudly.

    Failing (not skipping) is deliberate: silently skipped broker tests would leave the
    MQTT code untested without anyone noticing.
    """
    binary = _find_mosquitto()
    if binary:
        return binary
    detail = "apt-get not found"
    if shutil.which("apt-get"):
        proc = subprocess.run(
            ["apt-get", "install", "-y", "mosquitto"],
            capture_output=True, text=True, timeout=600, check=False,
            env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"},
        )
        binary = _find_mosquitto()
        if binary:
            return binary
        detail = f"apt-get install -y mosquitto exited {proc.returncode}: {proc.stderr[-500:]}"
    pytest.fail(
        "Mosquitto is required for the MQTT tests but is not installed and could not be "
        f"installed ({detail}). Install it, e.g. `apt-get install mosquitto`.",
        pytrace=False,
    )


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def closed_port() -> int:
    """A port on 127.0.0.1 that nothing listens on: an unreachable broker."""
    return _free_port("127.0.0.1")


def _accepts(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


@contextlib.contextmanager
def own_broker(folder: Path, settings: str, what: str) -> Iterator[int]:
    """A Mosquitto of its own on a free port with ``settings`` (mosquitto.conf lines), for
    the test's duration; its port. ``what`` names it when it does not start."""
    from daemon_support import wait_for

    port = closed_port()
    conf = folder / f"mosquitto-{port}.conf"
    conf.write_text(f"listener {port} 127.0.0.1\n{settings}"
                    f"user {pwd.getpwuid(os.getuid()).pw_name}\n")
    proc = subprocess.Popen([shutil.which("mosquitto") or "/usr/sbin/mosquitto", "-c", str(conf)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: _accepts(port), what=what)
        yield port
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.fixture
def password_broker(tmp_path: Path) -> Iterator[int]:
    """A Mosquitto of its own that takes user ``pt`` with password ``right`` only; its
    port."""
    pw = tmp_path / "passwd"
    subprocess.run(["mosquitto_passwd", "-b", "-c", str(pw), "pt", "right"], check=True,
                   capture_output=True)
    with own_broker(tmp_path, f"allow_anonymous false\npassword_file {pw}\n",
                    "auth broker") as port:
        yield port


class MosquittoBroker:
    """A Mosquitto process on 127.0.0.1 with persistence, restartable on the same port.

    stop() is graceful (SIGTERM) so the broker writes its persistence file: a start()
    afterwards keeps persistent sessions, their subscriptions and queued QoS 1 messages.
    kill() (SIGKILL) loses what was not yet saved, like a crash.
    """

    host = "127.0.0.1"

    def __init__(self, binary: str, workdir: Path) -> None:
        self.binary = binary
        self.workdir = workdir
        self.port = 0
        self.proc: subprocess.Popen[bytes] | None = None
        self.log_path = workdir / "mosquitto.out"
        self.conf_path = workdir / "mosquitto.conf"
        (workdir / "data").mkdir(exist_ok=True)

    def _write_conf(self) -> None:
        # When run as root, mosquitto drops to user "mosquitto", which could not write the
        # persistence dir in our tmp folder; "user" is ignored when not root.
        user = pwd.getpwuid(os.getuid()).pw_name
        self.conf_path.write_text(
            f"listener {self.port} {self.host}\n"
            "allow_anonymous true\n"
            "persistence true\n"
            # Save after every change, so a SIGKILLed broker keeps the daemon's persistent
            # session and queued messages: stricter than deploy/mosquitto.conf, which saves
            # every 10 s (saving on every change slowed the broker into dropping messages).
            "autosave_on_changes true\n"
            "autosave_interval 1\n"
            f"persistence_location {self.workdir / 'data'}/\n"
            f"user {user}\n"
            "log_dest stderr\n"
            "log_type error\nlog_type warning\nlog_type notice\n"
        )

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log_tail(self, chars: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def start(self) -> None:
        """Start (or restart on the same port) and wait until it accepts connections."""
        if self.running:
            return
        if not self.port:
            self.port = _free_port(self.host)
        self._write_conf()
        deadline = time.monotonic() + START_TIMEOUT
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen(
                [self.binary, "-c", str(self.conf_path)],
                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            )
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"mosquitto exited with {self.proc.returncode} on port {self.port}:\n"
                    f"{self.log_tail()}"
                )
            try:
                with socket.create_connection((self.host, self.port), timeout=0.5):
                    return
            except OSError:
                time.sleep(0.02)  # poll interval, not a timing assumption
        self.kill()
        raise RuntimeError(f"mosquitto did not accept connections within {START_TIMEOUT} s:\n"
                           f"{self.log_tail()}")

    def stop(self) -> None:
        """Graceful stop; mosquitto saves its persistence file on SIGTERM."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=STOP_TIMEOUT)
        self.proc = None

    def kill(self) -> None:
        """Crash-like stop (SIGKILL): unsaved persistence is lost."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=STOP_TIMEOUT)
        self.proc = None

    def restart(self) -> None:
        self.stop()
        self.start()


@pytest.fixture(scope="session")
def mosquitto(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MosquittoBroker]:
    """A real Mosquitto broker for the whole session: ``.host``, ``.port``, ``.stop()``,
    ``.start()``, ``.kill()``, ``.restart()``. Tests that stop it should start it again;
    :func:`mqtt_client` also restarts it if a previous test left it stopped."""
    broker = MosquittoBroker(_mosquitto_binary(), tmp_path_factory.mktemp("mosquitto"))
    # A port picked free can be taken before mosquitto binds it: retry with a new one.
    for attempt in range(3):
        try:
            broker.start()
            break
        except RuntimeError:
            if attempt == 2:
                raise
            broker.port = 0
    try:
        yield broker
    finally:
        broker.stop()


@dataclass
class TestClient:
    """A paho-mqtt client (callback API v2) with its network loop running in a thread.

    Messages received are collected in ``messages``; ``connects`` counts CONNACKs and
    ``session_present`` holds the flag of the latest one.
    """

    __test__ = False  # not a test class, despite the name

    client: mqtt.Client
    client_id: str
    messages: queue.Queue[mqtt.MQTTMessage] = field(default_factory=queue.Queue)
    connects: int = 0
    session_present: bool | None = None
    _cond: threading.Condition = field(default_factory=threading.Condition)

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: mqtt.ConnectFlags,
                    reason_code: Any, properties: Any) -> None:
        if reason_code.is_failure:
            return
        with self._cond:
            self.connects += 1
            self.session_present = bool(flags.session_present)
            self._cond.notify_all()

    def _on_message(self, client: mqtt.Client, userdata: Any, msg: mqtt.MQTTMessage) -> None:
        self.messages.put(msg)

    def wait_connects(self, n: int, timeout: float = 10.0) -> None:
        """Block until at least ``n`` successful CONNACKs were received."""
        with self._cond:
            if not self._cond.wait_for(lambda: self.connects >= n, timeout=timeout):
                raise TimeoutError(f"{self.client_id!r}: {self.connects} connects, "
                                   f"expected {n} within {timeout} s")

    def subscribe(self, topic: str, qos: int = 1, timeout: float = 10.0) -> None:
        """Subscribe and wait for the SUBACK."""
        done = threading.Event()
        result: list[Any] = []

        def on_subscribe(client: mqtt.Client, userdata: Any, mid: int,
                         reason_codes: list[Any], properties: Any) -> None:
            result.extend(reason_codes)
            done.set()

        self.client.on_subscribe = on_subscribe
        rc, _ = self.client.subscribe(topic, qos=qos)
        if rc != mqtt.MQTT_ERR_SUCCESS:
            raise RuntimeError(f"subscribe {topic!r}: {mqtt.error_string(rc)}")
        if not done.wait(timeout):
            raise TimeoutError(f"no SUBACK for {topic!r} within {timeout} s")
        if any(code.is_failure for code in result):
            raise RuntimeError(f"subscribe {topic!r} refused: {result}")

    def publish(self, topic: str, payload: bytes | str, qos: int = 1, retain: bool = False,
                timeout: float = 10.0) -> None:
        """Publish and, for QoS > 0, wait until the broker acknowledged it."""
        info = self.client.publish(topic, payload, qos=qos, retain=retain)
        info.wait_for_publish(timeout)
        if not info.is_published():
            raise TimeoutError(f"publish to {topic!r} not acknowledged within {timeout} s")

    def get(self, timeout: float = 10.0) -> mqtt.MQTTMessage:
        """The next received message; raises queue.Empty after ``timeout``."""
        return self.messages.get(timeout=timeout)

    def disconnect(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


MqttClientFactory = Callable[..., TestClient]


@pytest.fixture
def mqtt_client(mosquitto: MosquittoBroker) -> Iterator[MqttClientFactory]:
    """Factory of connected clients: ``mqtt_client(client_id=None, clean_session=True)``.

    Callbacks are installed before connecting, so messages queued in a persistent session
    are not missed. Every client is disconnected at the end of the test.
    """
    if not mosquitto.running:
        mosquitto.start()
    made: list[TestClient] = []

    def make(client_id: str | None = None, *, clean_session: bool = True,
             wait: bool = True) -> TestClient:
        client_id = client_id or f"test-{uuid.uuid4().hex[:12]}"
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=clean_session
        )
        # Quick reconnects keep broker-restart tests short; paho's default waits up to 120 s.
        client.reconnect_delay_set(min_delay=1, max_delay=2)
        tc = TestClient(client, client_id)
        client.on_connect = tc._on_connect
        client.on_message = tc._on_message
        made.append(tc)
        client.connect(mosquitto.host, mosquitto.port, keepalive=10)
        client.loop_start()
        if wait:
            tc.wait_connects(1)
        return tc

    yield make
    for tc in made:
        try:
            tc.disconnect()
        except Exception:  # noqa: BLE001 - teardown must reach every client
            pass


@pytest.fixture(scope="session")
def desk_artifact(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A twin trained on SML2010 (dining → bedroom temperature), all four models."""
    import datetime as dt

    from daemon_support import HOURS, REF, TARGET, sml
    from pseudotwin.analysis.training import train_twin
    from pseudotwin.core.spec import Quantity, TwinSpec

    spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, HOURS)
    # Pinned: the daemon tests exercise the GP on <twin>/estimate (validation would pick TRIV).
    art = train_twin(sml(), spec, dt.date(2012, 3, 14), 5, primary="corrgp-triv")
    return art.save(tmp_path_factory.mktemp("artifact") / "desk.json")


@pytest.fixture(scope="session")
def postgres() -> Iterator[Any]:
    """A real PostgreSQL server (tests/postgres_server.py) for the session, stopped and
    deleted at the end. Missing binaries fail (not skip), as for Mosquitto."""
    from postgres_server import PostgresServer, find_bindir

    bindir = find_bindir()
    if bindir is None:
        pytest.fail("PostgreSQL (initdb, pg_ctl) is required for the PostgreSQL store tests "
                    "but is not installed; run scripts/bootstrap.sh or `apt-get install "
                    "postgresql`", pytrace=False)
    server = PostgresServer(bindir)
    try:
        for attempt in range(3):  # a port picked free can be taken before the server binds
            try:
                server.start()
                break
            except RuntimeError:
                if attempt == 2:
                    raise
                server.port = 0
        yield server
    finally:
        server.destroy()


@pytest.fixture
def service_factory(
    mosquitto: MosquittoBroker, desk_artifact: Path, tmp_path: Path
) -> Iterator[Callable[..., Any]]:
    """Start in-process daemons (or recorders: ``kind``) on the test broker with the desk
    twin, on a replay clock from ``start`` (default a minute past noon: off_grid) at ``speed``;
    all are stopped at the end."""
    import datetime as dt

    from daemon_support import config, off_grid
    from pseudotwin.edge.clock import ReplayClock
    from pseudotwin.edge.service import Service

    made: list[Any] = []

    def make(start: dt.datetime | None = None, speed: float = 1.0, *, kind: type = Service,
             **kw: object) -> Any:
        cfg = config(tmp_path, mosquitto.port, desk_artifact, **kw)
        s = kind(cfg, clock=ReplayClock(start or off_grid(12.0), speed))
        s.start(wait_connected=15)
        made.append(s)
        return s

    yield make
    for s in made:
        if not s.stop_event.is_set():
            s.stop()
