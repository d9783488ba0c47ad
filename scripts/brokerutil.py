"""A Mosquitto broker for the demo and the benchmarks: on a free loopback port, in a
temporary folder, ready when returned."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_broker(folder: Path, port: int, extra: str = "") -> subprocess.Popen:
    """Start mosquitto on 127.0.0.1:``port`` and wait until it accepts connections."""
    exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not Path(exe).exists():
        sys.exit("Mosquitto is not installed; run scripts/bootstrap.sh first")
    conf = folder / "mosquitto.conf"
    # As root, mosquitto would drop to its own user, which cannot write our temp folder.
    user = f"user {os.environ.get('USER', 'root')}\n" if os.geteuid() == 0 else ""
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\n{user}{extra}")
    proc = subprocess.Popen([exe, "-c", str(conf)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return proc
        except OSError:
            time.sleep(0.05)
    proc.kill()
    sys.exit("the broker did not start")
