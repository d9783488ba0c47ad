"""Long-lived objects out of the cyclic garbage collector's way.

A process that loads its modules and twins once and then allocates many short-lived objects
(a reading, an estimate, a row) triggers collections that traverse every object alive, the
imported numpy/scipy/pandas and the twins included. ``gc.freeze`` moves what is alive now
into a permanent generation that no collection traverses: the daemon's full collections over
a thousand twins stopped every thread for ~0.7 s, and a backfill in one process spent ~20 %
of its CPU in them (30 days of one twin: 6.0 s → 4.8–5.2 s). The backfill's worker processes
measured no gain (their work is the same, their heap smaller), so they do not freeze.
"""

from __future__ import annotations

import gc


def freeze_long_lived() -> None:
    """Collect once, then exempt every object alive now from later collections. For the
    processes pseudotwin's commands own (daemon, recorder, backfill), after loading."""
    gc.collect()
    gc.freeze()
