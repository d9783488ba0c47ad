"""What a twin pseudo-measures: one value object shared by config, training, artifact and
evaluation, so "does this artifact fit this twin?" is a comparison."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from pseudotwin.core.horizon import OperatingHours
from pseudotwin.errors import ConfigError


class Quantity(StrEnum):
    """The physical quantity of a twin; it selects the default kernel and the unit."""

    TEMPERATURE = "temperature"
    CO2 = "co2"

    @property
    def unit(self) -> str:
        return _UNITS[self]

    @classmethod
    def parse(cls, text: object) -> Quantity:
        try:
            return cls(str(text))
        except ValueError:
            choices = ", ".join(q.value for q in cls)
            raise ConfigError(f"unknown quantity {text!r} (one of {choices})") from None


_UNITS = {Quantity.TEMPERATURE: "°C", Quantity.CO2: "ppm"}


@dataclass(frozen=True)
class TwinSpec:
    """One pseudo-measurement stream's identity.

    references: the permanent sensors fed live, in model order; target: the desk sensor
    (measured only while commissioning); quantity: temperature [°C] or co2 [ppm]; hours:
    operating hours, slot grid and time zone; covariates: other permanent sensors fed live
    (any quantity, e.g. CO2 or illuminance for a temperature twin) that only the models made
    for them read (``triv-cov``); validation decides whether they help.
    """

    references: tuple[str, ...]
    target: str
    quantity: Quantity
    hours: OperatingHours
    covariates: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "references", tuple(self.references))
        object.__setattr__(self, "covariates", tuple(self.covariates))
        object.__setattr__(self, "quantity", Quantity.parse(self.quantity))
        if not self.references:
            raise ConfigError("a twin needs at least one reference sensor")
        if len(set(self.references)) != len(self.references):
            raise ConfigError(f"references listed twice: {', '.join(self.references)}")
        if self.target in self.references:
            raise ConfigError(f"target {self.target!r} is also listed as a reference")
        if len(set(self.covariates)) != len(self.covariates):
            raise ConfigError(f"covariates listed twice: {', '.join(self.covariates)}")
        both = [c for c in self.covariates if c in self.references or c == self.target]
        if both:
            raise ConfigError(f"covariate(s) {', '.join(both)} also listed as reference or "
                              "target")

    @property
    def sensors(self) -> tuple[str, ...]:
        """References then target: the outputs of the multi-output models."""
        return (*self.references, self.target)

    @property
    def inputs(self) -> tuple[str, ...]:
        """References then covariates: every sensor the twin reads live."""
        return (*self.references, *self.covariates)

    @property
    def unit(self) -> str:
        return self.quantity.unit

    def differences(self, other: TwinSpec, theirs: str = "the other's") -> list[str]:
        """What differs between this spec and ``other`` (say, a config and an artifact:
        ``theirs="the artifact's"``), one readable line each; empty when they describe the
        same twin. The order of the references does not matter."""
        out = []
        if set(self.references) != set(other.references):
            out.append(f"references {', '.join(sorted(self.references))} differ from "
                       f"{theirs} {', '.join(sorted(other.references))}")
        if set(self.covariates) != set(other.covariates):
            out.append(f"covariates {', '.join(sorted(self.covariates)) or '(none)'} differ "
                       f"from {theirs} {', '.join(sorted(other.covariates)) or '(none)'}")
        if self.target != other.target:
            out.append(f"target {self.target!r} differs from {theirs} {other.target!r}")
        if self.quantity != other.quantity:
            out.append(f"quantity {self.quantity.value!r} differs from {theirs} "
                       f"{other.quantity.value!r}")
        if self.hours != other.hours:
            out.append(f"operating hours / slot grid / time zone ({self.hours.describe()}) "
                       f"differ from {theirs} ({other.hours.describe()})")
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "references": list(self.references),
            "target": self.target,
            "quantity": self.quantity.value,
            "unit": self.unit,
            **({"covariates": list(self.covariates)} if self.covariates else {}),
        }


class OfTwin:
    """Read access to a ``spec: TwinSpec`` attribute's parts, for the value objects that
    belong to one twin (its training set, its artifact)."""

    spec: TwinSpec

    @property
    def references(self) -> tuple[str, ...]:
        return self.spec.references

    @property
    def target(self) -> str:
        return self.spec.target

    @property
    def quantity(self) -> Quantity:
        return self.spec.quantity

    @property
    def hours(self) -> OperatingHours:
        return self.spec.hours

    @property
    def unit(self) -> str:
        return self.spec.unit

    @property
    def sensors(self) -> tuple[str, ...]:
        return self.spec.sensors

    @property
    def covariates(self) -> tuple[str, ...]:
        return self.spec.covariates

    @property
    def inputs(self) -> tuple[str, ...]:
        return self.spec.inputs
