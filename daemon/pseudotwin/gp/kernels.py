"""Stationary kernels over time of day and the multi-output LCM covariance.

Conventions are GPy's (variance σ², lengthscale ℓ [h], power α) so that hyper-parameters
move between GPy (training) and numpy (live conditioning) unchanged:

- ``rq``:       σ² (1 + r²/2)^(-α)               with r = |t - t'| / ℓ
- ``matern52``: σ² (1 + √5 r + 5/3 r²) e^(-√5 r)
- ``matern32``: σ² (1 + √3 r) e^(-√3 r)
- ``rbf``:      σ² e^(-r²/2)

The LCM covariance of outputs i, j is  k((t,i),(t',j)) = Σ_k B_k[i,j] k_k(t,t'),
B_k = W_k W_kᵀ + diag(κ_k).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

_SQRT3 = np.sqrt(3.0)
_SQRT5 = np.sqrt(5.0)

#: numpy kernel of the scaled distance r = |Δt|/ℓ: (r, variance, power) → k (r's shape).
KernelFn = Callable[[np.ndarray, float, float], np.ndarray]
#: GPy factory: (lengthscale, power) → a 1-D GPy kernel of variance 1 (GPy is imported lazily:
#: the live daemon never needs it).
GpyFactory = Callable[[float, float], Any]


def _rq(r: np.ndarray, variance: float, power: float) -> np.ndarray:
    return variance * np.exp(-power * np.log1p(0.5 * r * r))


def _matern52(r: np.ndarray, variance: float, power: float) -> np.ndarray:
    return variance * (1.0 + _SQRT5 * r + (5.0 / 3.0) * r * r) * np.exp(-_SQRT5 * r)


def _matern32(r: np.ndarray, variance: float, power: float) -> np.ndarray:
    return variance * (1.0 + _SQRT3 * r) * np.exp(-_SQRT3 * r)


def _rbf(r: np.ndarray, variance: float, power: float) -> np.ndarray:
    return variance * np.exp(-0.5 * r * r)


def _gpy(cls_name: str, with_power: bool) -> GpyFactory:
    def make(lengthscale: float = 1.0, power: float = 1.0) -> Any:
        import GPy  # training only

        cls = getattr(GPy.kern, cls_name)
        extra = {"power": power} if with_power else {}
        return cls(1, variance=1.0, lengthscale=lengthscale, **extra)

    return make


@dataclass(frozen=True)
class KernelSpec:
    """One stationary kernel, the same in numpy (live) and GPy (training).

    params: its hyper-parameters under GPy's names (``power`` only where the kernel has one;
    kernels without it keep power 1.0, unused).
    """

    name: str
    value: KernelFn
    gpy: GpyFactory
    params: tuple[str, ...]

    @property
    def has_power(self) -> bool:
        return "power" in self.params


_BASE = ("variance", "lengthscale")
#: The one kernel registry: name → numpy function, GPy factory, parameter names. The CLI's
#: ``--kernel`` choices, the Corr-GP models, training and live conditioning all read it.
KERNEL_REGISTRY: dict[str, KernelSpec] = {
    spec.name: spec
    for spec in (
        KernelSpec("rq", _rq, _gpy("RatQuad", True), (*_BASE, "power")),
        KernelSpec("matern52", _matern52, _gpy("Matern52", False), _BASE),
        KernelSpec("matern32", _matern32, _gpy("Matern32", False), _BASE),
        KernelSpec("rbf", _rbf, _gpy("RBF", False), _BASE),
    )
}
KERNELS = tuple(KERNEL_REGISTRY)
DEFAULT_KERNEL = {"temperature": "rq", "co2": "matern52"}


def kernel_spec(name: str) -> KernelSpec:
    """The registry entry of ``name`` (ValueError naming the choices if there is none)."""
    try:
        return KERNEL_REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown kernel {name!r}; choose one of {', '.join(KERNELS)}"
        ) from None


def stationary(name: str, r: np.ndarray, variance: float, power: float) -> np.ndarray:
    """Kernel value for scaled distance r = |Δt|/ℓ (any shape)."""
    return kernel_spec(name).value(r, variance, power)


@dataclass(frozen=True)
class Term:
    """One LCM term B ⊗ k(t, t').

    lengthscale [h]; power only used by ``rq``; W: [P, R]; kappa: [P].
    """

    lengthscale: float
    W: np.ndarray
    kappa: np.ndarray
    variance: float = 1.0
    power: float = 1.0

    @property
    def B(self) -> np.ndarray:
        """Coregionalization matrix: [P, P]."""
        return self.W @ self.W.T + np.diag(self.kappa)


@dataclass(frozen=True)
class LcmParams:
    """Hyper-parameters of a multi-output GP (ICM when it has one term).

    kernel: kernel name shared by all terms; noise: Gaussian noise variance per output [P]
    (normalized units).
    """

    kernel: str
    terms: tuple[Term, ...]
    noise: np.ndarray
    _B: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {self.kernel!r}; choose one of {', '.join(KERNELS)}")
        if not self.terms:
            raise ValueError("an LCM needs at least one term")
        P = len(self.noise)
        for t in self.terms:
            if t.W.shape[0] != P or t.kappa.shape != (P,):
                raise ValueError("W / kappa shapes do not match the number of outputs")
            if not (t.lengthscale > 0 and t.variance > 0 and t.power > 0):
                raise ValueError("kernel hyper-parameters must be positive")
        object.__setattr__(self, "_B", np.stack([t.B for t in self.terms]))

    @property
    def n_outputs(self) -> int:
        return len(self.noise)

    def K(
        self, t1: np.ndarray, o1: np.ndarray, t2: np.ndarray, o2: np.ndarray
    ) -> np.ndarray:
        """Cross-covariance of latent outputs: t1, o1: [N]; t2, o2: [M] → [N, M]."""
        d = np.abs(np.asarray(t1, float)[:, None] - np.asarray(t2, float)[None, :])
        out = np.zeros_like(d)
        o1 = np.asarray(o1, int)
        o2 = np.asarray(o2, int)
        for k, term in enumerate(self.terms):
            kt = stationary(self.kernel, d / term.lengthscale, term.variance, term.power)
            out += self._B[k][o1[:, None], o2[None, :]] * kt
        return out

    def k_vec(self, t: float, o: int, ts: np.ndarray, os_: np.ndarray) -> np.ndarray:
        """Covariance of one latent point with many: [M]. The hot path of live updates."""
        d = np.abs(ts - t)
        out = np.zeros(len(ts))
        for k, term in enumerate(self.terms):
            out += self._B[k][o, os_] * stationary(
                self.kernel, d / term.lengthscale, term.variance, term.power
            )
        return out

    def prior_var(self, o: int) -> float:
        """Latent prior variance of output o at any time."""
        return float(sum(self._B[k][o, o] * t.variance for k, t in enumerate(self.terms)))

    # -- serialization ----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "kernel": self.kernel,
            "noise": self.noise.tolist(),
            "terms": [
                {
                    "variance": t.variance,
                    "lengthscale": t.lengthscale,
                    "power": t.power,
                    "W": t.W.tolist(),
                    "kappa": t.kappa.tolist(),
                    "B": t.B.tolist(),
                }
                for t in self.terms
            ],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LcmParams:
        terms = tuple(
            Term(
                lengthscale=float(t["lengthscale"]),
                W=np.asarray(t["W"], float).reshape(len(d["noise"]), -1),
                kappa=np.asarray(t["kappa"], float),
                variance=float(t["variance"]),
                power=float(t["power"]),
            )
            for t in d["terms"]
        )
        return cls(str(d["kernel"]), terms, np.asarray(d["noise"], float))
