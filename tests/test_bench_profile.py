"""scripts/bench_daemon.py --profile: py-spy's raw stacks turned into ms per reading."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

from scripts_support import script_module


@pytest.fixture(scope="module")
def bench_daemon() -> Iterator[ModuleType]:
    with script_module("bench_daemon") as module:
        yield module


def test_profile_table_splits_each_threads_cpu_by_function(bench_daemon: ModuleType,
                                                           tmp_path: Path) -> None:
    raw = tmp_path / "raw.txt"
    loop = "Thread.run (threading.py:982);Service._work (pseudotwin/edge/service.py:500)"
    raw.write_text(
        # worker: 100 samples; Twin.estimate on two lines of the same function (60 + 20)
        f"thread (11): worker;{loop};Twin.estimate (pseudotwin/live/twin.py:373) 60\n"
        f"thread (11): worker;{loop};Twin.estimate (pseudotwin/live/twin.py:380) 20\n"
        f"thread (11): worker;{loop};Twin.observe (pseudotwin/live/twin.py:262) 20\n"
        # network thread: 10 samples
        "thread (12): paho;Client._packet_read (paho/mqtt/client.py:3000) 10\n"
        # a thread whose CPU is negligible is left out
        "thread (13): watchdog;Event.wait (threading.py:600) 5\n")
    table = bench_daemon.profile_table(raw, {11: 2.0, 12: 0.5, 13: 0.0}, readings=1000)

    assert list(table) == ["worker (2.000 ms, 100 samples)", "paho (0.500 ms, 10 samples)"]
    worker = dict(table["worker (2.000 ms, 100 samples)"])
    # 80 of 100 samples of 2 ms per reading; the run loop (in every sample) is not a row
    assert worker == {"Twin.estimate (pseudotwin/live/twin.py)": 1.6,
                      "Twin.observe (pseudotwin/live/twin.py)": 0.4}
    # a single-function thread: that function is its whole loop, so nothing is left
    assert table["paho (0.500 ms, 10 samples)"] == []
