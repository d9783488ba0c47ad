"""Symlinks planted in a state dir (hostile-input audit): a daemon run as root by hand
truncated the target of a `daemon.lock` link, replaced that of an `outputs.json` link with
its JSON, and appended readings to that of a journal file link. None is followed now."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest

from pseudotwin.edge import homeassistant as ha
from pseudotwin.edge.journal import Journal
from pseudotwin.edge.statelock import StateLock
from pseudotwin.errors import ConfigError
from pseudotwin.live.readings import Reading

PRECIOUS = "a file that is not the daemon's\n"


def planted(state: Path, name: str, tmp_path: Path) -> Path:
    """``state/name`` a symlink to a file outside the state dir; that file."""
    target = tmp_path / f"precious-{name}"
    target.write_text(PRECIOUS)
    state.mkdir(exist_ok=True)
    (state / name).symlink_to(target)
    return target


def test_a_lock_file_that_is_a_symlink_is_refused_and_its_target_kept(tmp_path: Path) -> None:
    state = tmp_path / "state"
    target = planted(state, "daemon.lock", tmp_path)
    with pytest.raises(ConfigError, match="lock file cannot be opened"):
        StateLock(state / "daemon.lock", "daemon").acquire()
    assert target.read_text() == PRECIOUS


def test_a_remembered_topics_file_that_is_a_symlink_is_replaced_not_written_through(
    tmp_path: Path,
) -> None:
    state = tmp_path / "state"
    target = planted(state, "outputs.json", tmp_path)
    ha.save_published(state, ["pt/desk/estimate"], "outputs.json")
    assert target.read_text() == PRECIOUS
    assert not (state / "outputs.json").is_symlink()
    assert json.loads((state / "outputs.json").read_text()) == {
        "published": ["pt/desk/estimate"]}


def test_a_journal_file_that_is_a_symlink_is_not_appended_to(tmp_path: Path) -> None:
    state = tmp_path / "journal"
    target = planted(state, "2012-03-20.jsonl", tmp_path)
    journal = Journal(state)
    with pytest.raises(OSError):  # not journaled, so not acknowledged: nothing is lost
        journal.append(Reading("s", dt.datetime(2012, 3, 20, 8, tzinfo=dt.UTC), 1.0))
    journal.close()
    assert target.read_text() == PRECIOUS
