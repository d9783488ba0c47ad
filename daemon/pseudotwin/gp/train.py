"""Training of multi-output GPs with GPy as the engine and the stable algorithm inside.

GPy supplies the kernels, their gradients and the parameter transforms; the inference step
is ours (:class:`BlockStableInference`): the training days are independent realizations of
one daily process (the twin only ever conditions on *today*), so the likelihood is a sum over
day blocks, each factorized with two-sided scaling and escalating jitter (DESIGN.md §4).

What differs from GPy's ``optimize_restarts`` (measured in scripts/compare_gpy_restarts.py):
1. starts come from the data: each term's W from an eigen-direction of the outputs' second
   moment, lengthscales spread from fast to slow, generous κ and noise to start from;
2. smart stopping: restarts end as soon as two of them agree on the optimum, and the best is
   then polished with tight tolerances.
(Fixing the kernel variances — B carries the scale — was tried: the same optima, but L-BFGS
needs ~3× the iterations in that geometry, so they stay free as in GPy.)
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable
from typing import Any

import GPy
import numpy as np
from GPy.inference.latent_function_inference import ExactGaussianInference
from GPy.inference.latent_function_inference.posterior import PosteriorExact
from scipy.optimize import minimize

from pseudotwin.errors import FitError, NumericalError
from pseudotwin.gp.fitdata import FitData, FitReport
from pseudotwin.gp.kernels import LcmParams, Term, kernel_spec
from pseudotwin.gp.stable import COND_WARN, scaled_cholesky

log = logging.getLogger(__name__)
LOG_2PI = float(np.log(2 * np.pi))


class BlockStableInference(ExactGaussianInference):
    """Exact inference over independent day blocks with the stable factorization.

    Only the diagonal blocks of K are ever formed; ``grad_dict["dL_dK_blocks"]`` carries the
    per-block gradients for :class:`BlockGP`.
    """

    def __init__(self, blocks: tuple[slice, ...], artificial_noise: float = 0.0) -> None:
        super().__init__()
        self.blocks = blocks
        self.artificial_noise = artificial_noise
        self.last_jitter = 0.0

    def inference(
        self, kern, X, likelihood, Y, mean_function=None, Y_metadata=None, K=None,
        variance=None, Z_tilde=None,
    ):
        if variance is None:
            variance = likelihood.gaussian_variance(Y_metadata)
        y = Y[:, 0]
        N = len(y)
        noise = np.broadcast_to(np.asarray(variance, float), (N,)) + self.artificial_noise
        alpha = np.zeros(N)
        dK_diag = np.zeros(N)
        Wi = np.zeros((N, N))
        dks = []
        logdet = quad = 0.0
        jit = 0.0
        for b in self.blocks:
            Kb = kern.K(X[b])
            Kb[np.diag_indices_from(Kb)] += noise[b]
            f = scaled_cholesky(Kb)
            a = f.solve(y[b])
            Ki = f.inverse()
            logdet += f.logdet()
            quad += float(y[b] @ a)
            alpha[b] = a
            Wi[b, b] = Ki
            dk = 0.5 * (np.outer(a, a) - Ki)
            dks.append(dk)
            dK_diag[b] = np.diag(dk)
            jit = max(jit, f.jitter)
        self.last_jitter = jit
        log_marginal = -0.5 * (N * LOG_2PI + logdet + quad)
        dL_dthetaL = likelihood.exact_inference_gradients(dK_diag, Y_metadata)
        post = PosteriorExact(woodbury_inv=Wi, woodbury_vector=alpha[:, None], K=Wi)
        grads = {"dL_dK_blocks": dks, "dL_dthetaL": dL_dthetaL, "dL_dm": alpha}
        return post, log_marginal, grads


class BlockGP(GPy.core.GP):
    """A GPy GP whose likelihood is a sum over independent blocks (training days)."""

    def parameters_changed(self) -> None:
        inf = self.inference_method
        self.posterior, self._log_marginal_likelihood, self.grad_dict = inf.inference(
            self.kern, self.X, self.likelihood, self.Y_normalized, self.mean_function,
            self.Y_metadata,
        )
        self.likelihood.update_gradients(self.grad_dict["dL_dthetaL"])
        total = np.zeros(self.kern.size)
        for b, dk in zip(inf.blocks, self.grad_dict["dL_dK_blocks"], strict=True):
            self.kern.update_gradients_full(dk, self.X[b])
            total += self.kern.gradient
        self.kern.gradient = total


# -- GPy model construction --------------------------------------------------------------
def gpy_stationary(kernel: str, lengthscale: float = 1.0, power: float = 1.0) -> GPy.kern.Kern:
    """The GPy twin of :func:`~pseudotwin.gp.kernels.stationary` (from the kernel registry)."""
    return kernel_spec(kernel).gpy(lengthscale, power)


def gpy_model(
    params: LcmParams,
    t: np.ndarray,
    o: np.ndarray,
    y: np.ndarray,
    blocks: tuple[slice, ...] | None = None,
    fix_variance: bool = True,
    artificial_noise: float = 0.0,
) -> GPy.core.GP:
    """A GPy model with the given hyper-parameters.

    blocks=None gives GPy's own exact inference (one block; used to check our posterior),
    otherwise our block-stable inference (training).
    """
    P = params.n_outputs
    parts = []
    for i, term in enumerate(params.terms):
        k = gpy_stationary(params.kernel, term.lengthscale, term.power)
        k.variance = term.variance
        if fix_variance:
            k.variance.fix()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c = GPy.kern.Coregionalize(
                1, P, rank=term.W.shape[1], W=term.W.copy(), kappa=term.kappa.copy(),
                active_dims=[1], name="B",
            )
        parts.append(k.prod(c, name=f"term{i}"))
    kern = parts[0]
    for p in parts[1:]:
        kern = kern + p
    lik = GPy.likelihoods.MixedNoise(
        [
            GPy.likelihoods.Gaussian(variance=float(v), name=f"noise{i}")
            for i, v in enumerate(params.noise)
        ]
    )
    X = np.column_stack([np.asarray(t, float), np.asarray(o, float)])
    Y = np.asarray(y, float)[:, None]
    meta = {"output_index": np.asarray(o, int)[:, None]}
    if blocks is None:
        return GPy.core.GP(X, Y, kern, lik, Y_metadata=meta)
    inf = BlockStableInference(blocks, artificial_noise)
    return BlockGP(X, Y, kern, lik, inference_method=inf, Y_metadata=meta)


def params_from_gpy(model: GPy.core.GP, kernel: str) -> LcmParams:
    """Read hyper-parameters back from a GPy model built by :func:`gpy_model`."""
    kern = model.kern
    prods = kern.parts if isinstance(kern, GPy.kern.Add) else [kern]
    spec = kernel_spec(kernel)
    terms = []
    for prod in prods:
        st, co = prod.parts
        power = float(st.power.values[0]) if spec.has_power else 1.0
        terms.append(
            Term(
                lengthscale=float(st.lengthscale.values[0]),
                W=np.array(co.W.values, float),
                kappa=np.array(co.kappa.values, float),
                variance=float(st.variance.values[0]),
                power=power,
            )
        )
    noise = np.array([float(lk.variance.values[0]) for lk in model.likelihood.likelihoods_list])
    return LcmParams(kernel, tuple(terms), noise)


# -- objective --------------------------------------------------------------------------
def _objective(model: GPy.core.GP) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
    def f(x: np.ndarray) -> tuple[float, np.ndarray]:
        try:
            val, grad = model._objective_grads(x)
        except (NumericalError, np.linalg.LinAlgError, ValueError, FloatingPointError):
            return 1e25, np.zeros_like(x)
        if not np.isfinite(val) or not np.all(np.isfinite(grad)):
            return 1e25, np.zeros_like(x)
        return float(val), np.asarray(grad, float)

    return f


# L-BFGS-B stopping as GPy's own optimizer (scipy's factr 1e7, pgtol 1e-5).
FTOL = 1e7 * np.finfo(float).eps
GTOL = 1e-5


def optimize(model: GPy.core.GP, max_iter: int = 400, ftol: float = FTOL) -> dict[str, Any]:
    """L-BFGS-B on the NLML in GPy's transformed parameter space; model left at the optimum."""
    x0 = model.optimizer_array.copy()
    res = minimize(
        _objective(model), x0, jac=True, method="L-BFGS-B",
        options={"maxiter": max_iter, "ftol": ftol, "gtol": GTOL, "maxcor": 20},
    )
    model.optimizer_array = res.x
    return {"nlml": float(model.objective_function()), "iterations": int(res.nit),
            "evaluations": int(res.nfev), "converged": bool(res.success),
            "message": str(res.message)}


# -- data-driven initialization -----------------------------------------------------------
def _second_moment(data: FitData) -> np.ndarray:
    """E[y yᵀ] over time points where all outputs are observed: [P, P] (zero-mean GP → no
    centering)."""
    P = data.n_outputs
    rows = []
    for b in data.blocks:
        t, o, y = data.t[b], data.o[b], data.y[b]
        for tt in np.unique(t):
            m = t == tt
            if m.sum() == P and set(o[m]) == set(range(P)):
                v = np.zeros(P)
                v[o[m]] = y[m]
                rows.append(v)
    if len(rows) < 3:
        M = np.diag([np.mean(data.y[data.o == p] ** 2) for p in range(P)])
    else:
        A = np.array(rows)
        M = A.T @ A / len(A)
    return M + 1e-6 * np.eye(P)


def _rank_w(M: np.ndarray, rank: int, frac: float) -> tuple[np.ndarray, np.ndarray]:
    """W [P, rank] from the leading eigenpairs of frac·M, κ from what is left of the diagonal."""
    vals, vecs = np.linalg.eigh(M)
    order = np.argsort(vals)[::-1][:rank]
    W = vecs[:, order] * np.sqrt(np.clip(vals[order], 1e-6, None) * frac)
    kappa = np.clip(np.diag(M) * frac - np.sum(W**2, axis=1), 0.02 * np.diag(M) * frac, None)
    return W, kappa + 1e-4


def _count_params(model: GPy.core.GP) -> int:
    return int(model.optimizer_array.size)


def _diagnose(params: LcmParams, data: FitData, report: FitReport) -> None:
    cond = 0.0
    jit = 0.0
    for b in data.blocks:
        K = params.K(data.t[b], data.o[b], data.t[b], data.o[b])
        K[np.diag_indices_from(K)] += params.noise[data.o[b]]
        f = scaled_cholesky(K)
        cond = max(cond, f.condition_number())
        jit = max(jit, f.jitter)
    report.condition_max = cond
    report.jitter_max = jit
    if cond > COND_WARN:
        msg = f"condition number {cond:.2e} of a training block approaches 1e6"
        report.warnings.append(msg)
        log.warning(msg)
    if jit > 0:
        msg = f"training blocks needed jitter {jit:.1e} (scaled units)"
        report.warnings.append(msg)
        log.warning(msg)


def _spread(n_terms: int) -> list[float]:
    """Starting lengthscales [h] spread geometrically over 0.5 … 8 h (slow and fast terms)."""
    if n_terms == 1:
        return [1.0]
    return list(np.geomspace(0.5, 8.0, n_terms))


def _broad_terms(M: np.ndarray, n_terms: int, rank: int, variant: int,
                 rng: np.random.Generator) -> list[Term]:
    """Starting points that leave the optimizer room: large κ, RQ power 2, B from the data.

    variant 0: term k gets the k-th eigen-direction of the outputs' second moment;
    variant 1: every term starts from the leading direction, split evenly;
    variant ≥2: a random perturbation of variant 0.
    """
    P = M.shape[0]
    vals, vecs = np.linalg.eigh(M)
    order = np.argsort(vals)[::-1]
    kappa = 0.5 * np.diag(M) / n_terms
    terms = []
    for k, ls in enumerate(_spread(n_terms)):
        if variant == 1:
            W, _ = _rank_w(M, rank, 1.0 / n_terms)
            W = W * (1.0 + 0.1 * k)
        else:
            cols = [order[(k + j) % P] for j in range(rank)]
            W = vecs[:, cols] * np.sqrt(np.clip(vals[cols], 1e-3, None))
            if variant >= 2:
                W = W + 0.3 * rng.standard_normal(W.shape) * np.sqrt(np.mean(np.diag(M)))
                ls = ls * float(np.exp(rng.normal(0.0, 0.5)))
        # The slowest term starts close to a constant within the day (small RQ power): the
        # day-to-day level differences between outputs, which training days always show.
        slow = k == n_terms - 1 and n_terms > 1 and variant % 2 == 0
        terms.append(Term(float(ls), W, kappa.copy(), power=0.1 if slow else 2.0))
    return terms


def fit_lcm(
    data: FitData,
    kernel: str,
    n_terms: int = 1,
    rank: int = 1,
    restarts: int = 3,
    artificial_noise: float = 0.0,
    max_iter: int = 1000,
    seed: int = 0,
    agree_tol: float = 0.05,
) -> tuple[LcmParams, FitReport, GPy.core.GP]:
    """Fit an LCM with ``n_terms`` terms (an ICM for 1) by data-initialized L-BFGS-B restarts.

    At most ``restarts`` starts, ending early once the two best agree within ``agree_tol``
    nats; the best is then polished with tight tolerances. Returns the hyper-parameters, the
    fit report and the GPy model at the optimum.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    report = FitReport(n_points=len(data.y))
    M = _second_moment(data)
    # Start noisy: from a small-noise start the optimizer tends to run into degenerate
    # optima (RQ power → 0, a noise variance → 0) and stall there.
    noise0 = 0.1 * np.diag(M)

    def build(terms: list[Term], noise: np.ndarray) -> GPy.core.GP:
        return gpy_model(
            LcmParams(kernel, tuple(terms), noise), data.t, data.o, data.y,
            blocks=data.blocks, artificial_noise=artificial_noise, fix_variance=False,
        )

    results: list[tuple[float, GPy.core.GP]] = []
    for i in range(max(1, restarts)):
        m = build(_broad_terms(M, n_terms, rank, i, rng), noise0.copy())
        info = optimize(m, max_iter=max_iter)
        report.starts.append({"start": i, **info})
        results.append((info["nlml"], m))
        if _agree(results, agree_tol):
            break
    best_nlml, model = min(results, key=lambda r: r[0])
    if not np.isfinite(best_nlml):
        raise FitError("no optimizer start reached a finite likelihood")
    polish = optimize(model, max_iter=300, ftol=1e-12)
    report.starts.append({"start": "polish", **polish})
    report.nlml = min(best_nlml, polish["nlml"])
    report.n_params = _count_params(model)
    params = params_from_gpy(model, kernel)
    _diagnose(params, data, report)
    report.seconds = time.perf_counter() - t0
    return params, report, model


def _agree(results: list[tuple[float, Any]], tol: float) -> bool:
    vals = sorted(r[0] for r in results)
    return len(vals) >= 2 and abs(vals[1] - vals[0]) <= tol
