"""How often a repeating event is logged: at its 1st, 2nd, 4th, 8th, ... occurrence, so a
fault that lasts days (a flickering wire, a full disk, a store away) is visible without a
line per event, and the count in the line says how long it has gone on."""

from __future__ import annotations

__all__ = ["doubled"]


def doubled(before: int, after: int) -> bool:
    """Whether a count that went from ``before`` to ``after`` passed 1, 2, 4, 8, ...: the
    moments to log it (with an increment of one: ``after`` is a power of two)."""
    return after.bit_length() > before.bit_length()
