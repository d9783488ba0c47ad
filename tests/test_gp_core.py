"""Kernels, the stable factorization and live conditioning against GPy itself."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import pseudotwin  # noqa: F401  (sets BLAS threads before numpy is used)
from pseudotwin.errors import NumericalError
from pseudotwin.gp.kernels import KERNELS, LcmParams, Term, stationary
from pseudotwin.gp.posterior import IncrementalPosterior
from pseudotwin.gp.stable import scaled_cholesky
from pseudotwin.gp.train import FitData, fit_lcm, gpy_model, gpy_stationary

GPY_DIAG_JITTER = 1e-8


def random_params(rng: np.random.Generator, kernel: str, P: int, Q: int) -> LcmParams:
    terms = tuple(
        Term(
            lengthscale=float(rng.uniform(0.3, 4.0)),
            W=rng.normal(size=(P, 1)),
            kappa=rng.uniform(0.01, 0.3, size=P),
            variance=float(rng.uniform(0.5, 2.0)),
            power=float(rng.uniform(0.3, 3.0)),
        )
        for _ in range(Q)
    )
    return LcmParams(kernel, terms, rng.uniform(0.005, 0.05, size=P))


@pytest.mark.parametrize("kernel", KERNELS)
def test_stationary_kernels_equal_gpy(kernel: str) -> None:
    rng = np.random.default_rng(3)
    t = rng.uniform(0, 12, size=30)
    k = gpy_stationary(kernel, lengthscale=1.7, power=0.8)
    k.variance = 1.3
    ours = stationary(kernel, np.abs(t[:, None] - t[None, :]) / 1.7, 1.3, 0.8)
    np.testing.assert_allclose(ours, k.K(t[:, None]), rtol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    kernel=st.sampled_from(KERNELS),
    P=st.integers(1, 4),
    Q=st.integers(1, 3),
)
def test_lcm_covariance_is_positive_semidefinite(seed: int, kernel: str, P: int, Q: int) -> None:
    rng = np.random.default_rng(seed)
    params = random_params(rng, kernel, P, Q)
    n = 40
    t = rng.uniform(0, 24, size=n)
    o = rng.integers(0, P, size=n)
    K = params.K(t, o, t, o)
    np.testing.assert_allclose(K, K.T, atol=1e-12)
    assert np.linalg.eigvalsh(K).min() > -1e-9 * np.abs(K).max()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 60), spread=st.floats(0.0, 8.0))
def test_scaled_cholesky_identities(seed: int, n: int, spread: float) -> None:
    """log|K| and K⁻¹y through D agree with dense linear algebra, for badly scaled K."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    scale = np.exp(rng.uniform(-spread, spread, size=n))
    K = (A @ A.T + n * np.eye(n)) * np.outer(scale, scale)
    f = scaled_cholesky(K)
    assert f.jitter == 0.0
    np.testing.assert_allclose(f.L @ f.L.T * np.outer(f.d, f.d), K, rtol=1e-9, atol=0)
    sign, logdet = np.linalg.slogdet(K)
    assert sign > 0
    assert f.logdet() == pytest.approx(logdet, rel=1e-9, abs=1e-9)
    y = rng.normal(size=n)
    np.testing.assert_allclose(K @ f.solve(y), y, rtol=1e-7, atol=1e-7 * np.abs(y).max())
    np.testing.assert_allclose(f.inverse() @ K, np.eye(n), atol=1e-6)


def test_jitter_escalates_only_when_needed_and_is_reported() -> None:
    v = np.array([1.0, 2.0, 3.0])
    K = np.outer(v, v) * 1e6  # rank one: singular, and badly scaled
    f = scaled_cholesky(K)
    assert f.jitter > 0
    assert f.jitter <= 1e-2
    # the regularized factor is a factor of the scaled matrix plus exactly that jitter
    S = K / np.outer(f.d, f.d)
    np.testing.assert_allclose(f.L @ f.L.T, S + f.jitter * np.eye(3), atol=1e-12)


def test_hopeless_matrix_raises_numerical_error() -> None:
    with pytest.raises(NumericalError):
        scaled_cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]) * -1)
    with pytest.raises(NumericalError):
        scaled_cholesky(np.array([[1.0, np.nan], [np.nan, 1.0]]))


@pytest.mark.parametrize("kernel", ["rq", "matern52"])
@pytest.mark.parametrize("Q,P", [(1, 2), (2, 3), (3, 3)])  # ICM and LCM
def test_incremental_posterior_equals_gpy_prediction(kernel: str, Q: int, P: int) -> None:
    rng = np.random.default_rng(Q * 10 + P)
    params = random_params(rng, kernel, P, Q)
    n = 120
    t = np.sort(rng.uniform(7.5, 19.0, size=n))
    o = rng.integers(0, P - 1, size=n)  # references only: the target is never observed live
    y = np.sin(t) + 0.1 * rng.normal(size=n)
    post = IncrementalPosterior(params, capacity=8)  # forces re-allocations on the way
    for i in rng.permutation(n):  # arrival order must not matter
        post.add(t[i], o[i], y[i])
    # GPy's exact inference always adds 1e-8 to the diagonal of K + noise: give GPy 1e-8 less
    # noise so both sides condition on the very same matrix.
    gpy_params = LcmParams(kernel, params.terms, params.noise - GPY_DIAG_JITTER)
    model = gpy_model(gpy_params, t, o, y, fix_variance=False)
    ts = np.linspace(8.0, 19.0, 23)
    target = P - 1
    mu, var = model.predict(
        np.column_stack([ts, np.full(len(ts), target)]),
        Y_metadata={"output_index": np.full((len(ts), 1), target)},
    )
    mine = np.array([post.predict(x, target, include_noise=False) for x in ts])
    mu_f, var_f = model.predict_noiseless(
        np.column_stack([ts, np.full(len(ts), target)]),
        Y_metadata={"output_index": np.full((len(ts), 1), target)},
    )
    np.testing.assert_allclose(mine[:, 0], mu_f[:, 0], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(mine[:, 1], var_f[:, 0], rtol=1e-6)
    # with the target's sensor noise (the pseudo-measurement's own std)
    noisy = np.array([post.predict(x, target)[1] for x in ts])
    np.testing.assert_allclose(noisy, var[:, 0] + GPY_DIAG_JITTER, rtol=1e-6)
    assert np.allclose(mu, mu_f)


def test_the_packed_factor_keeps_at_most_a_quarter_of_spare_room() -> None:
    """Grown with the rows, the factor's quadratic size held up to 56 % of spare room by the
    evening: it grows by a quarter of its size, and the estimates stay those of one block."""
    rng = np.random.default_rng(5)
    params = random_params(rng, "rq", 2, 1)
    t = np.linspace(7.5, 19.0, 300)
    y = np.sin(t) + 0.1 * rng.normal(size=len(t))
    grown, block = IncrementalPosterior(params), IncrementalPosterior(params, capacity=400)
    for i, (ti, yi) in enumerate(zip(t, y, strict=True)):
        grown.add(ti, 0, yi)
        grown.predict(ti, 1)  # its row now, as the live twin does at every reading
        block.add(ti, 0, yi)
        needed = (i + 1) * (i + 2) // 2
        assert needed <= len(grown._P) <= max(1.25 * needed, 32 * 33 // 2)  # noqa: SLF001
    for x in (8.0, 12.5, 18.9):
        np.testing.assert_allclose(grown.predict(x, 1), block.predict(x, 1), rtol=1e-12)


@pytest.mark.parametrize("one_by_one", [True, False], ids=["row", "block"])
def test_failed_extension_falls_back_to_regularized_refactorization(one_by_one: bool) -> None:
    rng = np.random.default_rng(0)
    params = random_params(rng, "rq", 2, 1)
    params = LcmParams("rq", params.terms, np.array([1e-14, 1e-14]))  # noise-free: duplicates
    post = IncrementalPosterior(params)
    for _ in range(3):
        post.add(9.0, 0, 0.5)  # the same point three times: exactly singular
        if one_by_one:
            post.flush()
    post.flush()  # lazy: the pending points are conditioned on here
    assert post.refactorizations >= 1
    assert post.jitter > 0
    mean, var = post.predict(9.0, 1)
    assert np.isfinite(mean) and np.isfinite(var)


@pytest.mark.parametrize("every", [2, 15, 200])
def test_predictions_do_not_depend_on_when_predictions_were_asked(every: int) -> None:
    """Lazy conditioning: a posterior asked after every observation and one asked after
    every ``every``-th give the same predictions, to the last bit (what a baseline
    published on the grid or at every reading relies on), revisions and new residuals of
    all observations included."""
    rng = np.random.default_rng(every)
    params = random_params(rng, "rq", 3, 2)
    n = 200
    t = np.sort(rng.uniform(7.5, 19.0, size=n))
    o = rng.integers(0, 2, size=n)
    r = np.sin(t) + 0.1 * rng.normal(size=n)
    often, seldom = IncrementalPosterior(params, capacity=8), IncrementalPosterior(params, 8)
    for i in range(n):
        for post in (often, seldom):
            post.add(t[i], o[i], r[i] + 1.0)
            post.revise(i, r[i])
        often.predict(t[i], 2)
        if i % every == every - 1 or i == n - 1:
            for x in (t[i], 12.0):
                for out in (0, 2):
                    assert seldom.predict(x, out) == often.predict(x, out)
    new = rng.normal(size=n + 1)
    for post in (often, seldom):
        post.add(19.5, 0, 0.3)
        post.set_residuals(new)
    assert seldom.predict(15.0, 2) == often.predict(15.0, 2)
    assert seldom.refactorizations == often.refactorizations == 0


def test_a_failed_block_leaves_the_posterior_without_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rng = np.random.default_rng(0)
    params = random_params(rng, "rq", 2, 1)
    params = LcmParams("rq", params.terms, np.array([1e-14, 1e-14]))  # noise-free: duplicates
    post = IncrementalPosterior(params)
    post.add(8.0, 0, 0.1)
    before = post.predict(10.0, 1)

    def failing(self: IncrementalPosterior) -> None:  # fault injection: no regularization helps
        raise NumericalError("injected")

    monkeypatch.setattr(IncrementalPosterior, "_refactorize", failing)
    for _ in range(3):
        post.add(9.0, 0, 0.5)  # exactly singular as a block
    with pytest.raises(NumericalError, match="injected"):
        post.flush()
    assert post.n == 1
    assert post.predict(10.0, 1) == before


def test_set_residuals_equals_rebuilding() -> None:
    rng = np.random.default_rng(5)
    params = random_params(rng, "matern52", 2, 1)
    t = rng.uniform(8, 18, size=30)
    a = IncrementalPosterior(params)
    for x in t:
        a.add(x, 0, 1.0)
    r = rng.normal(size=30)
    a.set_residuals(r)
    b = IncrementalPosterior(params)
    for x, v in zip(t, r, strict=True):
        b.add(x, 0, v)
    assert a.predict(12.0, 1) == pytest.approx(b.predict(12.0, 1), rel=1e-10)


def test_block_likelihood_is_sum_of_independent_days_and_gradients_are_exact() -> None:
    rng = np.random.default_rng(1)
    params = random_params(rng, "rq", 3, 2)
    S, days = 15, 3
    t = np.tile(np.repeat(np.arange(S) * 0.5 + 8, 3), days)
    o = np.tile(np.tile(np.arange(3), S), days)
    y = np.sin(t) + 0.2 * rng.normal(size=len(t))
    blocks = tuple(slice(i * 3 * S, (i + 1) * 3 * S) for i in range(days))
    blocked = gpy_model(params, t, o, y, blocks=blocks)
    per_day = sum(
        gpy_model(params, t[b], o[b], y[b], fix_variance=True).objective_function()
        for b in blocks
    )
    # GPy's own inference adds 1e-8 to the diagonal; ours adds nothing to a well-posed K.
    assert blocked.objective_function() == pytest.approx(per_day, rel=1e-6)
    assert blocked.checkgrad()


def test_fit_recovers_a_known_correlation_and_records_diagnostics() -> None:
    """Two outputs drawn from a known ICM: the fit finds a strong positive coupling."""
    rng = np.random.default_rng(11)
    true = LcmParams("matern52", (Term(1.5, np.array([[1.0], [0.9]]), np.array([0.05, 0.05])),),
                     np.array([0.01, 0.01]))
    S, days = 30, 4
    th = np.arange(S) * 0.4 + 7.5
    t = np.tile(np.repeat(th, 2), days)
    o = np.tile(np.tile(np.arange(2), S), days)
    y = np.concatenate([
        rng.multivariate_normal(np.zeros(2 * S), true.K(t[: 2 * S], o[: 2 * S], t[: 2 * S],
                                                        o[: 2 * S]) + 0.01 * np.eye(2 * S))
        for _ in range(days)
    ])
    blocks = tuple(slice(i * 2 * S, (i + 1) * 2 * S) for i in range(days))
    params, report, _ = fit_lcm(FitData(t, o, y, blocks, 2), "matern52", restarts=2)
    B = params.terms[0].B
    corr = B[0, 1] / np.sqrt(B[0, 0] * B[1, 1])
    assert corr > 0.8
    assert 0.5 < params.terms[0].lengthscale < 5
    assert np.isfinite(report.nlml) and report.condition_max >= 1.0
    assert report.starts and all("nlml" in s for s in report.starts)
