"""What must hold before the service can start, beyond the file's own consistency.

:func:`check_config` is what ``pseudotwin check-config``, ``run`` and ``record`` use: every
twin's artifact exists (and passes the artifact check), the CA file exists, the MQTT password
source is readable, and the state dir is not a file and could be created.
:func:`prepare_state_dir` is what ``run`` and ``record`` do with it before they start.
"""

from __future__ import annotations

import os
import ssl
from pathlib import Path
from typing import Any

from pseudotwin.config.loader import ArtifactCheck, Loader, load_file
from pseudotwin.config.model import BrokerConfig, ServiceConfig, TwinConfig
from pseudotwin.config.validate import Found
from pseudotwin.errors import ConfigError

__all__ = ["StartupLoader", "broker_problems", "check_config", "prepare_state_dir",
           "state_dir_problem"]


def broker_problems(broker: BrokerConfig) -> Found:
    """(field, message) pairs for what keeps the broker connection from starting now: an
    unreadable password source, a missing CA file (shared with the bridge)."""
    found: Found = []
    problem = broker.password_problem()
    if problem is not None:
        found.append(problem)
    if broker.ca_file is not None:
        if not broker.ca_file.is_file():
            found.append(("ca_file", f"{broker.ca_file} does not exist"))
        else:
            try:  # as paho's tls_set will load it: a bad file must not crash the start
                ssl.create_default_context(cafile=str(broker.ca_file))
            except (ssl.SSLError, OSError, ValueError) as exc:
                found.append(("ca_file", f"{broker.ca_file} holds no usable CA certificate "
                                         f"(PEM expected; {getattr(exc, 'reason', None) or exc})"))
    return found


def state_dir_problem(state_dir: Path) -> str | None:
    """Why ``state_dir`` can certainly not serve, judged without creating anything: it is a
    file, or a part of its path is, or it would be on a read-only file system. Whether the
    service's user may write there is left to :func:`prepare_state_dir` (systemd creates a
    StateDirectory for its own, often dynamic, user: the checking user's rights say nothing)."""
    try:
        return _state_dir_problem(state_dir)
    except OSError as exc:  # a name too long, a loop of links: the OS's reason
        return f"{state_dir}: {exc.strerror or exc}"


def _state_dir_problem(state_dir: Path) -> str | None:
    if state_dir.exists():
        if not state_dir.is_dir():
            return f"{state_dir} exists and is not a directory"
        existing = state_dir
    else:
        existing = next(p for p in state_dir.parents if p.exists())
        if not existing.is_dir():
            return f"{state_dir} cannot be created: {existing} is not a directory"
    if os.statvfs(existing).f_flag & os.ST_RDONLY:
        return f"{state_dir}: {existing} is on a read-only file system"
    return None


def prepare_state_dir(state_dir: Path) -> None:
    """Create ``state_dir`` (and its parents) if need be and check it is writable; raises
    ConfigError naming it and the OS's reason (``run`` and ``record`` exit 78 on it)."""
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"service.state_dir: {state_dir} cannot be created: "
                          f"{exc.strerror or exc}") from None
    if not os.access(state_dir, os.W_OK | os.X_OK):
        raise ConfigError(f"service.state_dir: {state_dir} is not writable by this user")


class StartupLoader(Loader):
    """The loader plus the checks of what the service needs to start."""

    def check_sections(self, broker: BrokerConfig | None, service: dict[str, Any] | None,
                       twins: list[tuple[str, TwinConfig]]) -> None:
        if broker is not None:
            for where, msg in broker_problems(broker):
                self.add(f"broker.{where}", msg)
        if service is not None:
            state_dir: Path = service["state_dir"]
            if (problem := state_dir_problem(state_dir)) is not None:
                self.add("service.state_dir", problem)
            store = service.get("store")
            # A SQLite file's folder is never created (a mistyped path must not become a new
            # empty database): missing, the recorder would only ever spool.
            if store is not None and "://" not in store and not Path(store).parent.is_dir():
                self.add("service.store", f"directory {Path(store).parent} does not exist")
            elif store is not None and "://" not in store and Path(store).is_dir():
                # (the recorder would spool for good, taking it for a store away)
                self.add("service.store", f"{store} is a directory, not a SQLite file")
        for loc, twin in self.checked(twins):
            try:
                twin.artifact.stat()
            except FileNotFoundError:
                pass  # said below
            except OSError as exc:  # a name too long, a loop of links
                self.add(f"{loc}.artifact", f"{twin.artifact}: {exc.strerror or exc}")
                continue
            if twin.artifact.is_dir():
                self.add(f"{loc}.artifact", f"{twin.artifact} is a directory, not an "
                                            "artifact file")
            elif not twin.artifact.is_file():
                self.add(f"{loc}.artifact", f"{twin.artifact} does not exist (train the twin "
                                            "first)")
            elif self.artifact_check is not None:
                self.run_artifact_check(loc, twin)


def check_config(path: str | os.PathLike[str], *,
                 artifact_check: ArtifactCheck | None = None,
                 only_twins: frozenset[str] | None = None) -> ServiceConfig:
    """Everything :func:`~pseudotwin.config.loader.load_config` checks, plus what the service
    needs to start: each artifact exists (and passes ``artifact_check``), the CA file exists,
    the password source is readable, and the state dir is not a file and could be created.
    only_twins: check the artifacts of these twins only (a fleet instance's own)."""
    return load_file(path, StartupLoader, artifact_check, only_twins)
