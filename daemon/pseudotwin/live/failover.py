"""Reference failover: what answers for the primary when a reference it needs is silent.

With several references, a reference that goes stale (silent longer than ``stale_after``) or
has never reported would make the primary's estimate ``stale``. ``train`` therefore keeps, per
reference the primary reads, the best validated candidate trained on the *other* references
(:mod:`pseudotwin.analysis.failover`), with its own calibrated σ; and, with three references
or more, per reference the best validated candidate trained on that reference *alone*, which
answers when two or more are silent. The live twin publishes the best validated of those whose
references are all fresh, with quality ``fallback``, and names the lost references; ``stale``
remains only when no failover can answer from fresh references.

In the artifact: ``"failover": {lost_ref: {"kind", "model", "calibration", "nrmse_pct",
"reason"}}`` (format version 4) and ``"failover_alone": {kept_ref: {...}}`` (version 8);
older artifacts have none of either and behave as before.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import ArtifactError
from pseudotwin.live.calibration import SigmaCalibration
from pseudotwin.models.base import TwinModel
from pseudotwin.models.registry import MODELS

#: ``lost`` written down when nothing is lost (estimates.csv, the history store).
NONE_LOST = "[]"


def lost_json(lost: Sequence[str]) -> str:
    """The silent references as the payload's JSON list, as estimates.csv and the history
    store write them (sensor ids may hold any printable character, a comma or a space too)."""
    return json.dumps(list(lost), ensure_ascii=False) if lost else NONE_LOST


@dataclass(frozen=True)
class Failover:
    """A candidate that answers when the references ``lost`` are silent.

    lost: the references it does without (one, or all but the one it reads); kind: its model
    kind; model: fitted on the other references (``model.references_`` holds none of
    ``lost``); calibration: its σ from the same leave-one-day-out validation as every
    model's (None: not validated, its own spread is published); nrmse_pct: its held-out daily
    NRMSE on the training days [%], which ranks failovers when several could answer.
    """

    lost: tuple[str, ...]
    kind: str
    model: TwinModel
    calibration: SigmaCalibration | None
    nrmse_pct: float
    reason: str = ""

    def __post_init__(self) -> None:
        if isinstance(self.lost, str):  # a str is a tuple of characters: say so here
            raise TypeError("Failover.lost is a tuple of references, not one str")
        if not self.lost:
            raise ArtifactError("a failover must do without at least one reference")
        if read := [r for r in self.lost if r in self.model.references_]:
            raise ArtifactError(f"the failover for {self.name} reads {', '.join(read)} itself")

    @property
    def name(self) -> str:
        """The lost references, as logs and errors name the failover."""
        return ", ".join(self.lost)

    @property
    def label(self) -> str:
        """What it answers for, as ``train`` prints it: "without A1" or "on A3 alone"."""
        return label(self.lost, self.model.references_)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind, "model": self.model.to_dict(),
            **({"calibration": self.calibration.to_dict()} if self.calibration else {}),
            "nrmse_pct": self.nrmse_pct, "reason": self.reason,
        }

    @classmethod
    def from_dict(cls, lost: tuple[str, ...], d: Mapping[str, Any], spec: TwinSpec
                  ) -> Failover:
        """Raises ArtifactError, or ValueError/KeyError when ``d`` does not fit ``spec``."""
        name = ", ".join(lost)
        if strange := [r for r in lost if r not in spec.references]:
            raise ArtifactError(f"failover for {', '.join(map(repr, strange))}, which is not "
                                "one of the references")
        kind = str(d["kind"])
        if kind not in MODELS:
            raise ArtifactError(f"failover for {name}: unknown model kind {kind!r}")
        calib = d.get("calibration")
        model = MODELS[kind].from_dict(d["model"], spec)
        foreign = set(model.references_) - set(spec.references)
        if foreign:
            raise ArtifactError(f"failover for {name} reads {', '.join(sorted(foreign))}, "
                                "which the twin does not")
        return cls(lost, kind, model,
                   SigmaCalibration.from_dict(calib) if calib is not None else None,
                   float(d["nrmse_pct"]), str(d.get("reason", "")))


def label(lost: Sequence[str], reads: Sequence[str]) -> str:
    """A failover doing without ``lost`` and reading ``reads``, as ``train`` names it:
    "without A1" (one lost) or "on A3 alone" (all but one)."""
    return f"without {lost[0]}" if len(lost) == 1 else f"on {', '.join(reads)} alone"


def picked(failovers: Iterable[Failover], silent: Collection[str]) -> Failover | None:
    """The failover the live twin answers with while ``silent`` are silent and every other
    reference reports (None: the estimate is stale)."""
    return next(iter(ranked(failovers, lambda s: s not in silent)), None)


def ranked(failovers: Iterable[Failover], fresh: Callable[[str], bool]) -> list[Failover]:
    """The failovers that could answer now (every reference they read is ``fresh``), best
    validated first (lowest held-out NRMSE; on a tie, the one doing without fewer); empty
    when none can."""
    able = [f for f in failovers if all(fresh(s) for s in f.model.references_)]
    return sorted(able, key=lambda f: (f.nrmse_pct, len(f.lost), f.lost))
