"""A Mosquitto broker for the demo and the benchmarks: on a free loopback port, in a
temporary folder, ready when returned.

Nothing a script starts may outlive it (issue 11: a benchmark left its broker running):
children get the kernel's parent-death signal (SIGTERM when the script dies, even by
SIGKILL), :func:`stop_process` ends one for sure, and :func:`exit_on_signals` turns SIGTERM
and SIGHUP into SystemExit so the scripts' ``finally`` blocks run. :func:`proc_stats` and
:func:`thread_cpu` read what a process (and each of its threads) has cost from /proc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType

PR_SET_PDEATHSIG = 1  # linux/prctl.h
_LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def die_with_parent() -> None:
    """``preexec_fn`` for Popen: the child gets SIGTERM when this process dies (Linux)."""
    _LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def stop_process(proc: subprocess.Popen | None, sig: int = signal.SIGTERM,
                 timeout: float = 10.0) -> int | None:
    """Send ``sig`` (SIGKILL after ``timeout`` s) and reap the process; its exit status."""
    if proc is None:
        return None
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)
    return proc.returncode


def exit_on_signals() -> None:
    """SIGTERM and SIGHUP raise SystemExit, so cleanups in ``finally`` run (the default
    action ends Python without them)."""
    def on_signal(signum: int, frame: FrameType | None) -> None:
        raise SystemExit(128 + signum)

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)


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
                            stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return proc
        except OSError:
            time.sleep(0.05)
    stop_process(proc, signal.SIGKILL)
    sys.exit("the broker did not start")


def proc_stats(pid: int) -> tuple[float, int]:
    """CPU seconds (user + system) and peak RSS [kB] of a process."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / ticks
    hwm = 0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                hwm = int(line.split()[1])
    return cpu, hwm


def thread_cpu(pid: int) -> dict[int, float]:
    """CPU seconds (user + system) of each thread of a process."""
    ticks = os.sysconf("SC_CLK_TCK")
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended meanwhile
            continue
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / ticks
    return out
