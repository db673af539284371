"""Tests of polarshape.checks: shape and dtype checks at the boundary."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from polarshape.checks import check_dtype_floating, check_shape, check_tensor, format_shape
from polarshape.errors import PolarshapeError, ShapeError


@pytest.mark.parametrize(
    ("shape", "spec"),
    [
        ((3,), ["*", "3"]),
        ((4, 5, 3), ["*", "3"]),
        ((), ["*"]),
        ((2, 3, 4, 4), ["*", "3", "H", "W"]),
        ((3, 4, 4), ["*", "3", "H", "W"]),
        ((5, 3), ["K", "3"]),
        ((4, 4), ["H", "H"]),
        ((2, 6, 8), ["*", "2H", "2W"]),
        ((3, 6), ["H", "2H"]),
        ((0, 3), ["N", "3"]),
    ],
)
@pytest.mark.parametrize("kind", ["torch", "numpy"])
def test_matching_shapes_pass(shape: tuple[int, ...], spec: list[str], kind: str) -> None:
    x = torch.zeros(shape) if kind == "torch" else np.zeros(shape)
    check_shape(x, spec, "x")


@pytest.mark.parametrize(
    ("shape", "spec", "message"),
    [
        ((4, 2), ["*", "3"], "normals must have shape (*, 3); got (4, 2)"),
        ((), ["*", "3"], "normals must have shape (*, 3); got ()"),
        ((5,), ["4"], "normals must have shape (4,); got (5,)"),
        ((2, 5, 3), ["K", "3"], "normals must have shape (K, 3); got (2, 5, 3)"),
        ((3,), ["K", "3"], "normals must have shape (K, 3); got (3,)"),
        ((3, 4), ["H", "H"], "normals must have shape (H, H); got (3, 4) (H is 3 and 4)"),
        ((4, 5), ["*", "2H", "2W"], "normals must have shape (*, 2H, 2W); got (4, 5) (2W: 5 is not a multiple of 2)"),
        ((4, 4), ["H", "2H"], "normals must have shape (H, 2H); got (4, 4) (H is 4 and 2)"),
    ],
)
def test_wrong_shapes_name_argument_expected_and_received(shape: tuple[int, ...], spec: list[str], message: str) -> None:
    with pytest.raises(ShapeError, match=re.escape(message) + "$"):
        check_shape(torch.zeros(shape), spec, "normals")


def test_detail_follows_the_expected_shape() -> None:
    with pytest.raises(ShapeError, match=re.escape("stokes must have shape (*, 3, H, W) (s0, s1, s2); got (4, 2, 2)")):
        check_shape(torch.zeros(4, 2, 2), ["*", "3", "H", "W"], "stokes", "(s0, s1, s2)")


def test_shape_error_is_a_value_error_and_a_polarshape_error() -> None:
    with pytest.raises(ValueError):
        check_shape(np.zeros((2, 2)), ["3"], "x")
    with pytest.raises(PolarshapeError):
        check_shape(np.zeros((2, 2)), ["3"], "x")


def test_not_an_array_is_a_type_error() -> None:
    with pytest.raises(TypeError, match="points must be a torch.Tensor or numpy array; got list"):
        check_shape([[0.0, 0.0, 1.0]], ["*", "3"], "points")


@pytest.mark.parametrize("spec", [["3", "*"], ["H", ""], ["0H"]])
def test_malformed_spec_is_a_programming_error(spec: list[str]) -> None:
    with pytest.raises(ValueError, match="malformed shape") as info:
        check_shape(torch.zeros(3), spec, "x")
    assert not isinstance(info.value, ShapeError)


def test_check_tensor_and_floating_dtype() -> None:
    t = torch.zeros(2)
    assert check_tensor(t, "x") is t and check_dtype_floating(t, "x") is t
    assert check_dtype_floating(t.double(), "x").dtype == torch.float64
    with pytest.raises(TypeError, match=r"x must be a torch.Tensor; got ndarray \(convert with torch.as_tensor\)"):
        check_tensor(np.zeros(2), "x")
    with pytest.raises(TypeError, match=r"x must be a floating-point tensor; got dtype torch.int32 \(convert with .float\(\)\)"):
        check_dtype_floating(torch.zeros(2, dtype=torch.int32), "x")
    with pytest.raises(TypeError, match=r"\(use counts_to_float\)"):
        check_dtype_floating(torch.zeros(2, dtype=torch.uint8), "mosaic", "use counts_to_float")


def test_format_shape_prints_like_a_tuple() -> None:
    assert format_shape(torch.Size([4, 2])) == "(4, 2)"
    assert format_shape(["K"]) == "(K,)"
    assert format_shape(()) == "()"
