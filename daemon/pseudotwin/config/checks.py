"""What must hold before the service can start, beyond the file's own consistency.

:func:`check_config` is what ``pseudotwin check-config``, ``run`` and ``record`` use: every
twin's artifact exists (and passes the artifact check), the CA file exists, the MQTT password
source is readable, and the state dir is not a file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from pseudotwin.config.loader import ArtifactCheck, Loader, load_file
from pseudotwin.config.model import BrokerConfig, ServiceConfig, TwinConfig
from pseudotwin.config.validate import Found

__all__ = ["StartupLoader", "broker_problems", "check_config"]


def broker_problems(broker: BrokerConfig) -> Found:
    """(field, message) pairs for what keeps the broker connection from starting now: an
    unreadable password source, a missing CA file (shared with the bridge)."""
    found: Found = []
    problem = broker.password_problem()
    if problem is not None:
        found.append(problem)
    if broker.ca_file is not None and not broker.ca_file.is_file():
        found.append(("ca_file", f"{broker.ca_file} does not exist"))
    return found


class StartupLoader(Loader):
    """The loader plus the checks of what the service needs to start."""

    def check_sections(self, broker: BrokerConfig | None, service: dict[str, Any] | None,
                       twins: list[tuple[str, TwinConfig]]) -> None:
        if broker is not None:
            for where, msg in broker_problems(broker):
                self.add(f"broker.{where}", msg)
        if service is not None:
            state_dir: Path = service["state_dir"]
            if state_dir.exists() and not state_dir.is_dir():
                self.add("service.state_dir", f"{state_dir} exists and is not a directory")
        for loc, twin in twins:
            if not twin.artifact.is_file():
                self.add(f"{loc}.artifact", f"{twin.artifact} does not exist (train the twin "
                                            "first)")
            elif self.artifact_check is not None:
                self.run_artifact_check(loc, twin)


def check_config(path: str | os.PathLike[str], *,
                 artifact_check: ArtifactCheck | None = None) -> ServiceConfig:
    """Everything :func:`~pseudotwin.config.loader.load_config` checks, plus what the service
    needs to start: each artifact exists (and passes ``artifact_check``), the CA file exists,
    the password source is readable, and the state dir is not a file."""
    return load_file(path, StartupLoader, artifact_check)
