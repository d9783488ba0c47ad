"""The one registry of twin models: kind → class. A new model is one class and one entry."""

from __future__ import annotations

from pseudotwin.errors import DataError
from pseudotwin.models.base import TwinModel
from pseudotwin.models.blend import BlendModel
from pseudotwin.models.corrgp import CorrGpLcm, CorrGpMulti, CorrGpTriv
from pseudotwin.models.covariate import TrivCovModel
from pseudotwin.models.ref import RefModel
from pseudotwin.models.triv import TrivModel, TrivShrunkModel, TrivSmoothModel, TrivWeekModel
from pseudotwin.models.varma import VarmaModel

# From the simplest: validation prefers the earlier of two models that score alike.
MODELS: dict[str, type[TwinModel]] = {
    cls.kind: cls for cls in (RefModel, TrivModel, TrivShrunkModel, TrivSmoothModel,
                              TrivWeekModel, TrivCovModel, CorrGpTriv, CorrGpMulti, CorrGpLcm,
                              BlendModel, VarmaModel)
}
ALL_MODELS: tuple[str, ...] = tuple(MODELS)


def model_class(kind: str) -> type[TwinModel]:
    """The class of model ``kind``; DataError naming the choices when there is none."""
    try:
        return MODELS[kind]
    except KeyError:
        raise DataError(f"unknown model {kind!r}; choose from {', '.join(MODELS)}") from None


def build(kind: str, options: dict[str, object] | None = None) -> TwinModel:
    """An unfitted model of ``kind`` with the settings in ``options`` it accepts."""
    cls = model_class(kind)
    given = options or {}
    return cls(**{k: v for k, v in given.items() if k in cls.options})
