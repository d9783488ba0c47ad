"""Reference failover: what answers for the primary when a reference it needs is silent.

With several references, a reference that goes stale (silent longer than ``stale_after``) or
has never reported would make the primary's estimate ``stale``. ``train`` therefore keeps, per
reference the primary reads, the best validated candidate trained on the *other* references
(:mod:`pseudotwin.analysis.failover`), with its own calibrated σ. The live twin publishes that
candidate with quality ``fallback`` and names the lost reference; ``stale`` remains only when
no failover can answer from fresh references.

In the artifact (format version 4): ``"failover": {lost_ref: {"kind", "model", "calibration",
"nrmse_pct", "reason"}}``; older artifacts have none and behave as before.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from pseudotwin.core.spec import TwinSpec
from pseudotwin.errors import ArtifactError
from pseudotwin.live.calibration import SigmaCalibration
from pseudotwin.models.base import TwinModel
from pseudotwin.models.registry import MODELS


@dataclass(frozen=True)
class Failover:
    """The candidate that answers when ``lost`` is silent.

    kind: its model kind; model: fitted on the other references (``model.references_`` never
    holds ``lost``); calibration: its σ from the same leave-one-day-out validation as every
    model's (None: not validated, its own spread is published); nrmse_pct: its held-out daily
    NRMSE on the training days [%], which ranks failovers when several could answer.
    """

    lost: str
    kind: str
    model: TwinModel
    calibration: SigmaCalibration | None
    nrmse_pct: float
    reason: str = ""

    def __post_init__(self) -> None:
        if self.lost in self.model.references_:
            raise ArtifactError(f"the failover for {self.lost} reads {self.lost} itself")

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind, "model": self.model.to_dict(),
            **({"calibration": self.calibration.to_dict()} if self.calibration else {}),
            "nrmse_pct": self.nrmse_pct, "reason": self.reason,
        }

    @classmethod
    def from_dict(cls, lost: str, d: Mapping[str, Any], spec: TwinSpec) -> Failover:
        """Raises ArtifactError, or ValueError/KeyError when ``d`` does not fit ``spec``."""
        if lost not in spec.references:
            raise ArtifactError(f"failover for {lost!r}, which is not one of the references")
        kind = str(d["kind"])
        if kind not in MODELS:
            raise ArtifactError(f"failover for {lost}: unknown model kind {kind!r}")
        calib = d.get("calibration")
        model = MODELS[kind].from_dict(d["model"], spec)
        foreign = set(model.references_) - set(spec.references)
        if foreign:
            raise ArtifactError(f"failover for {lost} reads {', '.join(sorted(foreign))}, "
                                "which the twin does not")
        return cls(lost, kind, model,
                   SigmaCalibration.from_dict(calib) if calib is not None else None,
                   float(d["nrmse_pct"]), str(d.get("reason", "")))


def ranked(failovers: Mapping[str, Failover], fresh: Callable[[str], bool]) -> list[Failover]:
    """The failovers that could answer now (every reference they read is ``fresh``), best
    validated first (lowest held-out NRMSE); empty when none can."""
    able = [f for f in failovers.values() if all(fresh(s) for s in f.model.references_)]
    return sorted(able, key=lambda f: (f.nrmse_pct, f.lost))
