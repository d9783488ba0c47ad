"""Command-line plumbing shared by the subcommands that own their parsers."""

from __future__ import annotations

import argparse
from typing import NoReturn


class UsageError(Exception):
    """Bad command-line arguments, reported by the subcommand as one error line."""


class Parser(argparse.ArgumentParser):
    # argparse would print its usage block and exit; the CLI contract is one error line and
    # exit status 2, so its complaints become an exception the subcommand's main() reports.
    def error(self, message: str) -> NoReturn:
        raise UsageError(message)
