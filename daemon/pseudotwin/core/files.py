"""Writing a file whole or not at all."""

from __future__ import annotations

import contextlib
import errno
import os
import stat
from collections.abc import Callable
from pathlib import Path

__all__ = ["write_replacing"]


def write_replacing(path: Path, write: Callable[[Path], object],
                    follow_symlinks: bool = True) -> Path:
    """``write`` a temporary file, then rename it over ``path``: an interrupted or failed
    write leaves the earlier file whole, never half a file (a daemon loading an artifact, a
    history that would read as shorter). The temporary file has ``path``'s own name, in a
    folder of its own beside it, so pandas infers the same compression (.csv.gz) and archive
    member name (.csv.zip) from it; a symlinked ``path`` is written through. Only a regular
    file is replaced: a device, pipe or folder at ``path`` (say ``--out /dev/null``, which as
    root would have made /dev/null a plain file) is an OSError, nothing written. An OSError
    names ``path``, not the temporary file (gone by then). Returns ``path``.
    ``follow_symlinks`` False (the daemon's own state files): a symlink at ``path`` is
    replaced, never written through (one planted in a state dir had a daemon run as root
    overwrite the file it pointed to)."""
    path = Path(path)
    if path.is_symlink() and follow_symlinks:
        path = path.resolve()
    try:
        mode = path.stat(follow_symlinks=follow_symlinks).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        raise OSError(errno.EEXIST, "exists and is not a regular file (nothing written)",
                      str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    folder = path.with_name(f".tmp{os.getpid()}.{path.name}")
    tmp = folder / path.name
    try:
        folder.mkdir(exist_ok=True)
        write(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
            folder.rmdir()
    return path
