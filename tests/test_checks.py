"""Tests of polarshape.checks: shape, dtype and finiteness checks at the boundary, and the device check."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from polarshape.checks import (
    check_dtype_floating, check_finite, check_shape, check_tensor, format_shape, resolve_device, wait_for_device,
)
from polarshape.cli.errors import exit_status
from polarshape.errors import ConfigError, DeviceError, PolarshapeError, ShapeError


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


# --- resolve_device --------------------------------------------------------------------------


def test_resolve_device_takes_cpu_and_auto() -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")


def test_wait_for_device_syncs_a_gpu_only(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[object] = []
    monkeypatch.setattr(torch.cuda, "synchronize", lambda device=None: calls.append(device))
    wait_for_device("cpu")
    wait_for_device(torch.device("cpu"))
    assert calls == []  # nothing queued on the CPU
    wait_for_device("cuda:1")
    assert calls == [torch.device("cuda:1")]  # that GPU, not the current one


@pytest.mark.parametrize("name", ["gpu", "cuda:x", "", "meta"])
def test_an_unknown_device_is_invalid_input_naming_the_field(name: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(f"--device {name!r} is not a device")) as info:
        resolve_device(name, "--device")
    assert exit_status(info.value) == 2


def test_cuda_without_cuda_cannot_run_and_names_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    """A CPU-only torch (as here, or made so): DeviceError, exit status 3, the fix in the message."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.version, "cuda", None)
    with pytest.raises(DeviceError, match=re.escape(f"device 'cuda' requested but torch has no CUDA (torch {torch.__version__}): "
                                                    "use device: cpu (or auto)")) as info:
        resolve_device("cuda")
    assert exit_status(info.value) == 3 and isinstance(info.value, RuntimeError)
    with pytest.raises(DeviceError, match=re.escape("use --device cpu (or auto)")):
        resolve_device("cuda:0", "--device")
    assert resolve_device("auto") == torch.device("cpu")
    monkeypatch.setattr(torch.version, "cuda", "12.4")  # a CUDA build on a machine without a GPU
    with pytest.raises(DeviceError, match="sees no GPU .check the driver and CUDA_VISIBLE_DEVICES"):
        resolve_device("cuda")


def test_a_gpu_index_past_the_last_gpu_cannot_run(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(DeviceError, match=re.escape("torch sees 2 GPU(s) (cuda:0 to cuda:1)")):
        resolve_device("cuda:2")


# --- check_finite ----------------------------------------------------------------------------


def test_check_finite_names_the_argument() -> None:
    x = torch.tensor([[0.0, 0.0, 1.0], [float("nan"), 0.0, float("inf")]])
    assert check_finite(x[:1], "normal") is not None
    with pytest.raises(ValueError, match=re.escape("normal must be finite; got 2 NaN/Inf value(s) of 6 (shape (2, 3))")):
        check_finite(x, "normal")
