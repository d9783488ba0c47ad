"""Merged GP points (gp/points.py) and the posterior's moving points (gp/posterior.py)."""

from __future__ import annotations

import numpy as np
import pytest

import pseudotwin  # noqa: F401  (sets BLAS threads before numpy is used)
from pseudotwin.gp.kernels import LcmParams, Term
from pseudotwin.gp.points import PointBuckets
from pseudotwin.gp.posterior import IncrementalPosterior

FIVE_MIN = 5 / 60


def params() -> LcmParams:
    return LcmParams("rq", (Term(2.0, np.array([[1.0], [0.8], [0.9]]),
                                 np.array([0.05, 0.05, 0.1]), 1.0, 1.5),),
                     np.array([0.01, 0.01, 0.02]))


def test_one_minute_points_merge_into_five_minute_means() -> None:
    b = PointBuckets(FIVE_MIN)
    got = [b.offer(0, 8 + i / 60, float(i), next_index=i) for i in range(12)]
    new = [i for i, g in enumerate(got) if g[0] is None]
    assert new == [0, 5, 10]  # one GP point per five minutes
    index, hours, value = got[4]  # the fifth minute joins the first point
    assert index == 0
    assert hours == pytest.approx(8 + 2 / 60) and value == pytest.approx(2.0)  # the means
    # another output keeps its own buckets
    assert b.offer(1, 8 + 1 / 60, 7.0, next_index=12) == (None, 8 + 1 / 60, 7.0)
    # a revised window point of the newest bucket moves its point's value
    assert b.revise(0, 8 + 11 / 60, 21.0)[1:] == pytest.approx((8 + 10.5 / 60, 15.5))
    with pytest.raises(KeyError):
        b.revise(0, 8 + 1 / 60, 0.0)  # an older bucket's member: never revised by the window
    # out of order into an older bucket: its sums move
    index, hours, value = b.offer(0, 8 + 4.5 / 60, 100.0, next_index=13)
    assert index == 0 and value == pytest.approx((0 + 1 + 2 + 3 + 4 + 100) / 6)
    # out of order before every bucket: a new point, which a later one may join
    assert b.offer(0, 7.9, 50.0, next_index=14) == (None, 7.9, 50.0)
    assert b.offer(0, 7.91, 52.0, next_index=15) == (14, pytest.approx(7.905), 51.0)
    with pytest.raises(KeyError):
        b.revise(0, 7.9, 0.0)  # never the newest bucket
    assert b.revise(0, 8 + 11 / 60, 23.0)[0] == 10  # the newest is still the newest
    with pytest.raises(ValueError, match="positive"):
        PointBuckets(0.0)


@pytest.mark.parametrize("predict_every", [1, 7])
def test_moving_points_equal_conditioning_on_the_final_points(predict_every: int) -> None:
    """Points moved by each reading that joins them (predicted in between or not) give the
    posterior of their final times and values."""
    rng = np.random.default_rng(predict_every)
    n = 300
    t = 7.5 + np.arange(n) / 60 + rng.uniform(0, 0.005, size=n)
    o = rng.integers(0, 2, size=n)
    y = np.sin(t) + 0.05 * rng.normal(size=n)
    buckets = PointBuckets(FIVE_MIN)
    moving = IncrementalPosterior(params(), capacity=8)
    for i in range(n):
        j, h, v = buckets.offer(int(o[i]), t[i], y[i], moving.n)
        if j is None:
            moving.add(h, int(o[i]), v)
        else:
            moving.move(j, h, v)
        if i % predict_every == 0:
            moving.predict(t[i], 2)
    final = IncrementalPosterior(params())
    for i in range(moving.n):
        final.add(moving.t[i], moving.o[i], moving.r[i])
    assert moving.n < n / 2  # merged: two outputs, five minutes
    for x in (8.0, 11.3, t[-1]):
        np.testing.assert_allclose(moving.predict(x, 2), final.predict(x, 2), rtol=1e-8)
