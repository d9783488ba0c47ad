"""Log records that name the twin they concern.

Whoever drives a twin (``train``/``evaluate``, ``backfill``, the daemon's worker) wraps that
work in :func:`twin_context`; every record created meanwhile, in any module or library
(GP fitting, validation folds, the twin's numerical fallbacks), gets ``record.twin`` and the
prefix ``twin <id>: `` in its message. A context variable rather than a logger adapter, so
the modules doing the work need not know which twin they serve, and a record factory rather
than a logger filter, so records of child loggers and pytest's ``caplog`` see it too.

:func:`collapsed` folds info lines and warnings that repeat once per validation fold into
one record with a count.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

_TWIN: ContextVar[str | None] = ContextVar("pseudotwin_twin", default=None)
_base_factory = logging.getLogRecordFactory()
_installed = False


def _record(*args: Any, **kwargs: Any) -> logging.LogRecord:
    record = _base_factory(*args, **kwargs)
    twin = _TWIN.get()
    record.twin = twin
    if twin is not None:
        # With args the message is %-formatted later: a '%' in the prefix must be escaped.
        prefix = f"twin {twin.replace('%', '%%') if record.args else twin}: "
        record.msg = prefix + str(record.msg)
    return record


def install() -> None:
    """Make every log record carry the current twin (idempotent)."""
    global _installed
    if not _installed:
        logging.setLogRecordFactory(_record)
        _installed = True


install()


@contextmanager
def twin_context(twin_id: str) -> Iterator[None]:
    """Records created inside (in this thread or task) name ``twin_id``."""
    install()
    token = _TWIN.set(twin_id)
    try:
        yield
    finally:
        _TWIN.reset(token)


_NUMBER = re.compile(r"[-+]?\d[\d.]*(?:e[-+]?\d+)?")


class _Collector(logging.Filter):
    """Holds back INFO and WARNING records; one per level and message shape (numbers aside)
    with its count. Errors pass at once, and so does DEBUG (asked for, every line)."""

    def __init__(self) -> None:
        super().__init__()
        self.first: dict[tuple[str, int, str], logging.LogRecord] = {}
        self.count: dict[tuple[str, int, str], int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno not in (logging.INFO, logging.WARNING):
            return True
        key = (record.name, record.levelno, _NUMBER.sub("#", record.getMessage()))
        self.first.setdefault(key, record)
        self.count[key] = self.count.get(key, 0) + 1
        return False


@contextmanager
def collapsed(logger_names: Sequence[str], during: str) -> Iterator[None]:
    """Info and warnings of ``logger_names`` are held back and logged at the end, once per
    level and message shape (numbers aside): the first of each, with ``(and N more like it
    during <during>)`` when it repeated (a model's fit message per fold is noise)."""
    collector = _Collector()
    loggers = [logging.getLogger(n) for n in logger_names]
    for lg in loggers:
        lg.addFilter(collector)
    try:
        yield
    finally:
        for lg in loggers:
            lg.removeFilter(collector)
        for key, record in collector.first.items():
            n = collector.count[key]
            if n > 1:
                record.msg = f"{record.getMessage()} (and {n - 1} more like it during {during})"
                record.args = ()
            logging.getLogger(record.name).handle(record)
