"""The model artifact: everything needed to run a twin, in one versioned JSON file.

Human-readable on purpose (an engineer can see B matrices, lengthscales, the TRIV offset
profile and the fit diagnostics with ``less``); arrays are JSON lists.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pseudotwin import __version__
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.errors import ArtifactError
from pseudotwin.models.corrgp import CorrGpLcm, CorrGpTriv
from pseudotwin.models.triv import TrivModel
from pseudotwin.models.varma import VarmaModel

FORMAT = "pseudotwin-artifact"
VERSION = 1
MODEL_CLASSES: dict[str, Any] = {
    "corrgp-triv": CorrGpTriv,
    "corrgp-lcm": CorrGpLcm,
    "triv": TrivModel,
    "varma": VarmaModel,
}
UNITS = {"temperature": "°C", "co2": "ppm"}


@dataclass(frozen=True)
class Artifact:
    """A trained twin.

    models: kind → fitted model; primary: the kind published as the twin's ``estimate``.
    training: period, days used and sensors, as written by ``train``.
    """

    references: tuple[str, ...]
    target: str
    quantity: str
    hours: OperatingHours
    models: dict[str, Any]
    primary: str
    training: dict[str, Any] = field(default_factory=dict)
    created: str = ""

    def __post_init__(self) -> None:
        if self.quantity not in UNITS:
            raise ArtifactError(f"unknown quantity {self.quantity!r} (temperature or co2)")
        if self.primary not in self.models:
            raise ArtifactError(f"primary model {self.primary!r} is not in the artifact")
        if self.target in self.references:
            raise ArtifactError("the target cannot also be a reference")

    @property
    def unit(self) -> str:
        return UNITS[self.quantity]

    @property
    def sensors(self) -> tuple[str, ...]:
        return (*self.references, self.target)

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "created": self.created or dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "pseudotwin": __version__,
            "twin": {
                "references": list(self.references),
                "target": self.target,
                "quantity": self.quantity,
                "unit": self.unit,
                "primary": self.primary,
            },
            "hours": self.hours.to_dict(),
            "training": self.training,
            "models": {kind: m.to_dict() for kind, m in self.models.items()},
        }

    def save(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps(_finite(self.to_dict()), indent=1, ensure_ascii=False)
        tmp = p.with_suffix(p.suffix + ".tmp")
        tmp.write_text(text + "\n", encoding="utf-8")
        tmp.replace(p)  # atomic: a daemon never loads half an artifact
        return p

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "artifact") -> Artifact:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ArtifactError(f"{where}: not a pseudotwin model artifact")
        version = d.get("version")
        if not isinstance(version, int):
            raise ArtifactError(f"{where}: artifact has no format version")
        if version > VERSION:
            raise ArtifactError(
                f"{where}: artifact format version {version} is newer than this pseudotwin "
                f"{__version__} supports (≤ {VERSION}); upgrade pseudotwin or retrain"
            )
        try:
            twin = d["twin"]
            hours = OperatingHours.from_dict(d["hours"])
            refs = tuple(twin["references"])
            target = str(twin["target"])
            models = {}
            for kind, md in d["models"].items():
                if kind not in MODEL_CLASSES:
                    raise ArtifactError(f"{where}: unknown model kind {kind!r}")
                models[kind] = MODEL_CLASSES[kind].from_dict(md, hours, refs, target)
            return cls(
                refs, target, str(twin["quantity"]), hours, models, str(twin["primary"]),
                d.get("training", {}), d.get("created", ""),
            )
        except ArtifactError:
            raise
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ArtifactError(f"{where}: artifact is incomplete or corrupt ({exc!r})") from None

    @classmethod
    def load(cls, path: str | Path) -> Artifact:
        p = Path(path)
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ArtifactError(f"{p}: no such artifact file") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ArtifactError(f"{p}: cannot read artifact ({exc})") from None
        return cls.from_dict(d, str(p))


def artifact_hash(path: str | Path) -> str:
    """sha256 of the artifact file, recorded next to every estimate it produced."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _finite(obj: Any) -> Any:
    """JSON has no NaN/inf: store them as null so the file stays standard JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj
