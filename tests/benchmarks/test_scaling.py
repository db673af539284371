"""benchmarks/scaling.py: the fit of time against pixels × lights that its tables print."""

from __future__ import annotations

import math

import pytest


@pytest.fixture(scope="module")
def scaling(benchmark_module):  # noqa: ANN001, ANN201 (a script module)
    return benchmark_module("scaling")


def test_linear_fit_of_a_fixed_cost_plus_a_linear_term(scaling) -> None:  # noqa: ANN001
    x = [1e4, 4e4, 1.6e5, 6.4e5]
    a, c, r2, exponent = scaling.linear_fit(x, [0.5 + 1e-5 * v for v in x])
    assert a == pytest.approx(0.5) and c == pytest.approx(1e-5) and r2 == pytest.approx(1.0)
    assert 0.5 < exponent < 1.0  # the fixed cost still bends the upper half a little


def test_the_exponent_spans_two_sizes_when_the_larger_cases_share_one(scaling) -> None:  # noqa: ANN001
    # the largest cases at one size (the 1024² and full-frame captures hold the same sphere, 93 % of the frame's
    # height: the same pixels × lights): the upper half of the points held that one x only and the exponent read nan
    x = [1e4, 1.6e5, 1.6e5, 1.6e5]
    _, _, _, exponent = scaling.linear_fit(x, [3e-5 * v for v in x])
    assert exponent == pytest.approx(1.0)
    _, _, _, one_size = scaling.linear_fit([1e4, 1e4], [1.0, 1.1])
    assert math.isnan(one_size)
