"""The README's promise, checked where a user test broke it: errors in input, configuration
or artifacts end in one clear message and a non-zero status, never a traceback (issue of the
user test after ab178f3). Real files, real subprocesses or the CLI's main function."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from daemon_support import write_config
from pseudotwin.cli.check_config import main as check_config_main

EXE = [sys.executable, "-m", "pseudotwin.cli"]


def _with_state_dir(cfg: Path, state_dir: str) -> Path:
    cfg.write_text(cfg.read_text().replace('state_dir = "state"', f'state_dir = "{state_dir}"'))
    return cfg


def _one_line(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


# ------------------------------------------------------------------ 1. state_dir


@pytest.mark.parametrize("command", ["run", "record"])
def test_a_state_dir_that_cannot_be_created_exits_78(
    desk_artifact: Path, tmp_path: Path, command: str
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder\n")
    cfg = _with_state_dir(write_config(tmp_path, 1, desk_artifact, store="h.db"),
                          f"{blocker}/state")
    p = subprocess.run([*EXE, command, "--config", str(cfg)], capture_output=True, text=True,
                       timeout=60, check=False)
    assert p.returncode == 78, p.stderr
    line = _one_line(p.stderr)
    assert f"pseudotwin {command}: configuration error in {cfg}" in line
    assert f"service.state_dir: {blocker}/state cannot be created" in line


def test_a_state_dir_the_os_refuses_exits_78(desk_artifact: Path, tmp_path: Path) -> None:
    """/proc/nope: nothing on the path is a file, only mkdir can tell (check-config cannot
    without creating it); run names state_dir and the OS's reason."""
    cfg = _with_state_dir(write_config(tmp_path, 1, desk_artifact), "/proc/nope")
    p = subprocess.run([*EXE, "run", "--config", str(cfg)], capture_output=True, text=True,
                       timeout=60, check=False)
    assert p.returncode == 78, p.stderr
    line = _one_line(p.stderr)
    assert "service.state_dir: /proc/nope cannot be created: " in line
    assert not Path("/proc/nope").exists()


def test_check_config_reports_a_state_dir_under_a_file(
    desk_artifact: Path, tmp_path: Path, capsys
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder\n")
    cfg = _with_state_dir(write_config(tmp_path, 1, desk_artifact), f"{blocker}/x/state")
    assert check_config_main([str(cfg)]) == 1
    err = capsys.readouterr().err
    assert f"service.state_dir: {blocker}/x/state cannot be created: {blocker} is not a " \
           "directory" in err
    assert not (tmp_path / "state").exists()  # check-config creates nothing
