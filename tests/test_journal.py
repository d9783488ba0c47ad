"""The daemon's journal: crash-cut lines, rotation and pruning."""

from __future__ import annotations

import datetime as dt
import os
import resource
import shutil
import signal
from pathlib import Path

import pytest

from daemon_support import Synced
from pseudotwin.edge.journal import Journal
from pseudotwin.live.readings import Reading


def r(h: int, value: float, day: int = 20) -> Reading:
    return Reading("s", dt.datetime(2012, 3, day, h, tzinfo=dt.UTC), value)


def test_a_line_cut_short_by_a_crash_costs_only_itself(tmp_path: Path) -> None:
    j = Journal(tmp_path)
    j.append(r(8, 1.0))
    j.close()
    path = tmp_path / "2012-03-20.jsonl"
    path.write_text(path.read_text() + '{"sensor": "s", "ts": "2012-03-20T08:3')  # torn
    j = Journal(tmp_path)  # the restarted daemon
    j.append(r(9, 2.0))
    j.close()
    got = [(x.ts.hour, x.value) for x in Journal(tmp_path).replay(r(0, 0).ts)]
    assert got == [(8, 1.0), (9, 2.0)]


def test_days_rotate_and_old_days_are_pruned(tmp_path: Path) -> None:
    j = Journal(tmp_path, keep_days=2)
    for day in (17, 18, 19, 20):
        j.append(r(8, float(day), day))
    j.close()
    assert sorted(p.name for p in tmp_path.glob("*.jsonl")) == ["2012-03-19.jsonl",
                                                               "2012-03-20.jsonl"]
    assert [x.value for x in Journal(tmp_path).replay(r(0, 0, 19).ts)] == [19.0, 20.0]


def test_readings_straddling_midnight_go_to_their_days_without_rotating_back(
    tmp_path: Path, monkeypatch
) -> None:
    """Two sensors stamping either side of UTC midnight alternated the journal between the
    two days' files, re-reading the whole of each at every switch, a cost growing with the
    day's file. The earlier day's stragglers are appended to its file; the current one
    stays open, and is read in only when the journal rotates forward."""
    j = Journal(tmp_path)
    j.append(r(23, 0.0, 19))
    j.append(r(0, 0.5, 20))  # the new day: the one rotation forward
    reads: list[Path] = []
    real = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda p: reads.append(p) or real(p))
    for k in range(1, 50):
        late = Reading("a", dt.datetime(2012, 3, 19, 23, 59, 59, tzinfo=dt.UTC), float(k))
        j.append_many([late, r(0, float(k), 20)])
    j.close()
    assert reads == []
    got = list(Journal(tmp_path).replay(r(0, 0, 19).ts))
    assert [x.value for x in got if x.ts.day == 19] == [0.0, *range(1, 50)]
    assert [x.value for x in got if x.ts.day == 20] == [0.5, *range(1, 50)]


def test_a_straggler_after_the_state_dir_was_deleted_rebuilds_the_journal(
    tmp_path: Path
) -> None:
    """A reading of the day before, the first after the folder went: it must not fail for
    good (the daemon holds it and retries, oldest first, so it held everything after)."""
    folder = tmp_path / "journal"
    j = Journal(folder)
    j.append(r(23, 1.0, 19))
    j.append(r(0, 2.0, 20))
    shutil.rmtree(folder)
    late = Reading("a", dt.datetime(2012, 3, 19, 23, 59, 30, tzinfo=dt.UTC), 3.0)
    j.append(late)
    j.append(r(1, 4.0, 20))
    j.close()
    assert [x.value for x in Journal(folder).replay(r(0, 0, 19).ts)] == [1.0, 3.0, 2.0, 4.0]


def test_a_durable_journal_rebuilt_after_its_state_dir_went_syncs_every_entry_up_to_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The whole state dir deleted and made again: the rebuilt files survive a power cut
    only with the journal folder's entry and the state dir's own (in its parent) on disk."""
    synced = Synced(monkeypatch)
    state = tmp_path / "state"
    j = Journal(state / "journal", durable=True)
    j.append(r(8, 1.0))
    shutil.rmtree(state)
    del synced.folders[:]
    j.append(r(9, 2.0))
    j.close()
    assert {state / "journal", state, tmp_path} <= set(synced.folders)
    assert [x.value for x in Journal(state / "journal").replay(r(0, 0, 19).ts)] == [1.0, 2.0]


def test_a_rebuild_cut_short_by_a_full_disk_leaves_no_half_file(tmp_path: Path) -> None:
    """The rebuild copied straight to the journal's path: cut short by a full disk, the
    half file stood there, the retry took it for the rebuilt one and let the whole go (63
    of 1,001 readings left). Here the disk is a file size limit of this process."""
    folder = tmp_path / "journal"
    j = Journal(folder)
    t0 = dt.datetime(2012, 3, 20, 8, tzinfo=dt.UTC)
    day = [Reading("s", t0 + dt.timedelta(seconds=k), float(k)) for k in range(1000)]
    j.append_many(day)
    shutil.rmtree(folder)  # the state dir deleted under the daemon
    late = Reading("s", t0 + dt.timedelta(hours=1), -1.0)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))
    try:
        with pytest.raises(OSError):
            j.append(late)  # not written: the daemon holds it and retries
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)
    assert not (folder / "2012-03-20.jsonl").exists()  # no half file at the path
    j.append(late)  # the retry, with room again
    j.close()
    assert list(Journal(folder).replay(t0)) == [*day, late]


def test_after_a_restart_yesterdays_file_is_rebuilt_too(tmp_path: Path) -> None:
    """Only a journal that had rotated during the run kept yesterday's file (today's
    carry-over) for a rebuild; after a restart it was lost with the state dir."""
    folder = tmp_path / "journal"
    j = Journal(folder)
    j.append(r(23, 1.0, 19))
    j.append(r(0, 2.0, 20))
    j.close()
    j = Journal(folder)  # the restarted daemon
    j.append(r(1, 3.0, 20))
    shutil.rmtree(folder)
    j.append(r(2, 4.0, 20))
    j.close()
    assert [x.value for x in Journal(folder).replay(r(0, 0, 19).ts)] == [1.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize("durable", [True, False])
def test_a_durable_journal_puts_lines_and_new_files_on_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, durable: bool
) -> None:
    """durable: sync() fsyncs what was appended since the last sync, once, an earlier day's
    straggler's file too; a new day's file has its folder (and the folder's parent) synced.
    Not durable: nothing is ever synced by append or sync (os.fsync watched, doing its real
    work)."""
    synced: list[tuple[int, int]] = []  # (inode, size) at each fsync
    real = os.fsync

    def fsync(fd: int) -> None:
        real(fd)
        st = os.fstat(fd)
        synced.append((st.st_ino, st.st_size))

    monkeypatch.setattr(os, "fsync", fsync)
    folder = tmp_path / "state" / "journal"
    j = Journal(folder, durable=durable)
    j.append_many([r(8, 1.0), r(9, 2.0)])
    today = folder / "2012-03-20.jsonl"
    inode = {p: p.stat().st_ino for p in (today, folder, folder.parent)}
    if not durable:
        assert not j.sync() and synced == []
        j.append(r(0, 3.0, 19))  # a straggler of the day before
        assert synced == []
        return
    # the new file's directory entries first, then the lines at sync()
    assert {inode[folder], inode[folder.parent]} <= {ino for ino, _ in synced}
    assert (inode[today], today.stat().st_size) not in synced
    assert j.sync() and synced[-1] == (inode[today], today.stat().st_size)
    assert not j.sync()  # nothing new: no second fsync
    n = len(synced)
    j.append(r(0, 3.0, 19))  # a straggler of the day before: its own file, made new
    before = folder / "2012-03-19.jsonl"
    assert len(synced) == n  # not yet: at the batch's sync
    assert j.sync()  # its lines, then its entry in the folder; today's file unchanged
    assert synced[n:] == [(before.stat().st_ino, before.stat().st_size),
                          (inode[folder], folder.stat().st_size)]
    assert not j.sync()
    j.close()
