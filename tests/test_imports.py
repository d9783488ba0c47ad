"""Every package imports first, in a fresh interpreter: a circular import between packages
shows only in the order that closes the cycle (scripts/results.py imports the report package
before anything else, the test suite happened not to)."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import pytest

import pseudotwin

PACKAGES = sorted(m.name for m in pkgutil.walk_packages(pseudotwin.__path__, "pseudotwin.")
                  if m.ispkg)


def test_the_packages_are_found() -> None:
    assert {"pseudotwin.analysis.report", "pseudotwin.analysis.commissioning",
            "pseudotwin.edge", "pseudotwin.models"} <= set(PACKAGES)


@pytest.mark.parametrize("package", PACKAGES)
def test_a_package_imports_first(package: str) -> None:
    run = subprocess.run([sys.executable, "-c", f"import {package}"], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
