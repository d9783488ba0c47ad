"""What a GP fit takes and reports, without the training engine.

Kept apart from :mod:`pseudotwin.gp.train` so that loading an artifact (the daemon, backfill)
never imports GPy and its plotting stack: ~50 MB and a second of start-up that the live path
does not use.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pseudotwin.errors import FitError

__all__ = ["FitData", "FitReport"]


@dataclass(frozen=True)
class FitData:
    """Training points of a multi-output GP, grouped in independent day blocks.

    t: [N] time of day [h]; o: [N] output index; y: [N] normalized values;
    blocks: one slice per day into the (day-sorted) arrays.
    """

    t: np.ndarray
    o: np.ndarray
    y: np.ndarray
    blocks: tuple[slice, ...]
    n_outputs: int

    def __post_init__(self) -> None:
        if not (len(self.t) == len(self.o) == len(self.y)):
            raise ValueError("t, o, y must have one entry per point")
        if len(self.t) == 0:
            raise FitError("no training points")


@dataclass
class FitReport:
    """Diagnostics of one fit, stored in the artifact."""

    nlml: float = float("inf")
    starts: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    jitter_max: float = 0.0
    condition_max: float = 0.0
    n_points: int = 0
    n_params: int = 0
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "nlml": self.nlml,
            "starts": self.starts,
            "seconds": round(self.seconds, 3),
            "jitter_max": self.jitter_max,
            "condition_max": self.condition_max,
            "n_points": self.n_points,
            "n_params": self.n_params,
            "warnings": self.warnings,
        }
