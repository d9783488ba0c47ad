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
from typing import TYPE_CHECKING, Any

from pseudotwin import __version__
from pseudotwin.core.files import write_replacing
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import OfTwin, Quantity, TwinSpec
from pseudotwin.errors import ArtifactError, ConfigError
from pseudotwin.live.calibration import SigmaCalibration
from pseudotwin.live.envelope import Envelope
from pseudotwin.live.failover import Failover
from pseudotwin.models.base import TwinModel
from pseudotwin.models.registry import MODELS

if TYPE_CHECKING:
    from pseudotwin.config.model import TwinConfig
    from pseudotwin.core.thinning import Thinning

FORMAT = "pseudotwin-artifact"
# 2: σ calibration, validation, the ref model, VARMA re-levelling; version 1 still loads.
# 3: the training envelope (live/envelope.py); older versions load without one.
# 4: reference failover (live/failover.py); older versions load without any.
# 5: covariates (twin.covariates, the triv-cov model); older versions have none.
# 6: the envelope's judged criteria (envelope.kept, .judged, rule.widen; analysis/criteria.py);
#    older envelopes load with every criterion acting and σ × 2, as they were trained.
# 7: the envelope's pairs of references (criterion ``disagreement``); older envelopes have
#    none, so nothing about how their references relate can make them uncertain.
# 8: single-reference failovers (``failover_alone``, twins with three references or more);
#    older versions have none: two silent references make them stale.
VERSION = 8


@dataclass(frozen=True)
class Artifact(OfTwin):
    """A trained twin.

    models: kind → fitted model; primary: the kind published as the twin's ``estimate``.
    training: period, days used and sensors, as written by ``train``.
    calibration: kind → the σ of its estimates, from the training days (older artifacts
    have none: their models' own spread is published).
    validation: the candidates' leave-one-day-out scores and why the primary won.
    envelope: the references' training ranges behind quality ``uncertain`` and which of its
    criteria act (format < 3: none, never uncertain; 3–5: every criterion acts, σ × 2).
    failover: lost reference → the validated candidate that answers without it (older
    artifacts and single-reference twins have none: a silent reference makes them stale).
    failover_alone: kept reference → the validated candidate that reads it alone, for two or
    more silent references (twins with three references or more; live/failover.py).
    """

    spec: TwinSpec
    models: dict[str, TwinModel]
    primary: str
    training: dict[str, Any] = field(default_factory=dict)
    created: str = ""
    calibration: dict[str, SigmaCalibration] = field(default_factory=dict)
    validation: dict[str, Any] = field(default_factory=dict)
    envelope: Envelope | None = None
    failover: dict[str, Failover] = field(default_factory=dict)
    failover_alone: dict[str, Failover] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.primary not in self.models:
            raise ArtifactError(f"primary model {self.primary!r} is not in the artifact")
        for m in self.models.values():
            m.share(self.models)
        if self.failover_alone and len(self.spec.references) < 3:
            # with two, the failover on one alone is the failover without the other
            raise ArtifactError("failovers on one reference alone need three references or "
                                f"more; the twin has {len(self.spec.references)}")
        lost = [f.lost for f in self.failovers]
        if len(set(lost)) != len(lost):  # the live twin runs one estimator per lost set
            raise ArtifactError("two failovers do without the same references")

    @property
    def failovers(self) -> tuple[Failover, ...]:
        """Every failover: those without one reference, then those on one alone."""
        return (*self.failover.values(), *self.failover_alone.values())

    @property
    def withheld(self) -> dict[str, str]:
        """Models trained but not published live: kind → why (from validation)."""
        return dict(self.validation.get("withheld", {}))

    @property
    def training_end(self) -> dt.date | None:
        """The last local day the models were trained on (None: not recorded)."""
        end = self.training.get("end")
        return dt.date.fromisoformat(end) if end else None

    @property
    def published(self) -> list[str]:
        """The models the daemon runs and publishes: the primary and the baselines that
        validation did not withhold."""
        return [k for k in self.models if k == self.primary or k not in self.withheld]

    def to_dict(self) -> dict[str, Any]:
        """The artifact as JSON data (NaN/inf as null, so it round-trips through from_dict)."""
        return _finite({
            "format": FORMAT,
            "version": VERSION,
            "created": self.created or dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "pseudotwin": __version__,
            "twin": {**self.spec.to_dict(), "primary": self.primary},
            "hours": self.hours.to_dict(),
            "training": self.training,
            "models": {kind: m.to_dict() for kind, m in self.models.items()},
            "calibration": {kind: c.to_dict() for kind, c in self.calibration.items()},
            "validation": self.validation,
            **({"envelope": self.envelope.to_dict()} if self.envelope else {}),
            **({"failover": {r: f.to_dict() for r, f in self.failover.items()}}
               if self.failover else {}),
            **({"failover_alone": {r: f.to_dict() for r, f in self.failover_alone.items()}}
               if self.failover_alone else {}),
        })

    def save(self, path: str | Path) -> Path:
        text = json.dumps(self.to_dict(), indent=1, ensure_ascii=False)
        # whole or not at all: a daemon never loads half an artifact
        return write_replacing(Path(path),
                               lambda tmp: tmp.write_text(text + "\n", encoding="utf-8"))

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
        _check_finite(d, where)
        try:
            twin = d["twin"]
            spec = TwinSpec(
                tuple(twin["references"]), str(twin["target"]), Quantity.parse(twin["quantity"]),
                OperatingHours.from_dict(d["hours"]), tuple(twin.get("covariates", ())),
            )
            models: dict[str, TwinModel] = {}
            for kind, md in d["models"].items():
                if kind not in MODELS:
                    raise ArtifactError(f"{where}: unknown model kind {kind!r}")
                models[kind] = MODELS[kind].from_dict(md, spec)
            calibration = {
                str(kind): SigmaCalibration.from_dict(c)
                for kind, c in d.get("calibration", {}).items() if kind in models
            }
            envelope = (Envelope.from_dict(d["envelope"], spec.hours)
                        if d.get("envelope") is not None else None)
            failover = {str(r): Failover.from_dict((str(r),), f, spec)
                        for r, f in (d.get("failover") or {}).items()}
            alone = {str(r): _alone(str(r), f, spec)
                     for r, f in (d.get("failover_alone") or {}).items()}
            for key in ("training", "validation"):
                if not isinstance(d.get(key, {}), dict):
                    raise TypeError(f"{key} is not an object")
            return cls(spec, models, str(twin["primary"]), d.get("training", {}),
                       d.get("created", ""), calibration, d.get("validation", {}), envelope,
                       failover, alone)
        except ArtifactError as exc:
            # a model's own check does not know the file: name it
            if str(exc).startswith(f"{where}:"):
                raise
            raise ArtifactError(f"{where}: {exc}") from None
        except ConfigError as exc:
            raise ArtifactError(f"{where}: {exc}") from None
        except (KeyError, TypeError, ValueError, IndexError, AttributeError,
                ArithmeticError) as exc:  # a value of the wrong JSON type, or out of range
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


#: What the daemon and check-config say of an artifact without σ calibration.
UNVALIDATED = ("its artifact was trained without validation (fewer than three training days, "
               "or an old artifact): σ is each model's own spread, not calibrated on days "
               "it did not see, and the primary was not chosen by held-out scores")


def _alone(kept: str, d: Any, spec: TwinSpec) -> Failover:
    """The failover reading ``kept`` alone: it does without every other reference (and
    refuses to load when it reads one)."""
    if kept not in spec.references:
        raise ArtifactError(f"failover on {kept!r} alone, which is not one of the references")
    return Failover.from_dict(tuple(r for r in spec.references if r != kept), d, spec)


def check_artifact(
    twin: TwinConfig, art: Artifact | None = None, hours: OperatingHours | None = None,
    thinning: Thinning | None = None,
) -> list[str]:
    """Problems between a twin's configuration and its artifact (empty when they fit):
    what ``check-config``, ``run`` and ``backfill`` refuse. Without ``hours`` the artifact's
    are taken, and a config without a target takes the artifact's; ``thinning``, the
    sensors' window policy, is compared with the one training learnt from (artifacts that
    record it)."""
    art = art or Artifact.load(twin.artifact)
    problems = [_with_remedy(p) for p in
                twin.spec(hours or art.hours, art.target).differences(art.spec, "the artifact's")]
    learnt = art.training.get("min_interval_seconds", {})
    if thinning is None:
        return problems
    for sensor, seconds in learnt.items():
        live = thinning.interval(sensor).total_seconds()
        if not math.isclose(live, seconds):
            problems.append(
                f"min_interval_seconds of {sensor} is {live:g}, but the twin learnt from one "
                f"point per {seconds:g} s (its σ was measured on that window): set "
                f"min_interval_seconds = {seconds:.15g} on that sensor, or retrain for this "
                f"window (train --config, which takes the sensors' own)")
    return problems


def _with_remedy(problem: str) -> str:
    """A difference between a twin's configuration and its artifact, with what to do: the
    bare difference left a user who renamed a sensor or corrected the time zone stuck."""
    retrain = "retrain the twin for this configuration (train --config, which takes its "
    if problem.startswith(("references", "covariates")):
        return (f"{problem}: a sensor's id names its history and the artifact's inputs, so "
                "keep the id the twin was trained with if only the sensor's name or topic "
                f"changed (the topic may change), else {retrain}sensors)")
    if problem.startswith("operating hours"):
        return f"{problem}: {retrain}time zone and hours; days recorded so far are reused)"
    return f"{problem}: {retrain}sensors and hours) or point artifact at the right file"


def artifact_hash(path: str | Path) -> str:
    """sha256 of the artifact file, recorded next to every estimate it produced."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _check_finite(obj: Any, where: str, path: str = "$") -> None:
    """ArtifactError naming the JSON path of the first number that is not finite (the JSON
    parser turns ``Infinity``/``NaN`` into floats; saved artifacts write them as null)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        raise ArtifactError(f"{where}: {path} is {obj}, not a finite number "
                            "(corrupt artifact; retrain the twin)")
    if isinstance(obj, dict):
        for k, v in obj.items():
            _check_finite(v, where, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _check_finite(v, where, f"{path}[{i}]")


def _finite(obj: Any) -> Any:
    """JSON has no NaN/inf: store them as null so the file stays standard JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj
