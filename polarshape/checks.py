"""Argument checks at the boundary of public functions (kornia's ``KORNIA_CHECK_SHAPE`` is the model).

A shape is written as a list of dimension names, e.g. ``["*", "3", "H", "W"]``:

* ``"*"`` (first entry only): any number of leading dimensions, none included;
* a digit string such as ``"3"``: that size exactly;
* a name (``"K"``, ``"H"``): any size, but every use of the same name must have the same size;
* a name after a factor (``"2H"``): a multiple of the factor, ``H`` being the quotient (so
  ``["*", "2H", "2W"]`` is an image of even height and width, and ``["H", "2H"]`` says the second
  size is twice the first).

A wrong shape raises :class:`~polarshape.errors.ShapeError` (a ``ValueError``) naming the argument,
the expected shape and the shape received; a wrong type or dtype raises ``TypeError``.

Example:
    >>> check_shape(torch.zeros(4, 2), ["*", "3"], "normals")
    Traceback (most recent call last):
    ...
    polarshape.errors.ShapeError: normals must have shape (*, 3); got (4, 2)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from polarshape.errors import ConfigError, DeviceError, ShapeError

__all__ = [
    "check_dtype_floating",
    "check_finite",
    "check_shape",
    "check_tensor",
    "format_shape",
    "resolve_device",
    "to_numpy",
]


def format_shape(dims: Sequence[object]) -> str:
    """``(4, 2)``, ``(K,)``, ``(*, 3, H, W)``: a shape as Python prints a tuple."""
    items = [str(d) for d in dims]
    return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"


def check_tensor(x: object, name: str) -> Tensor:
    """Return ``x`` if it is a ``torch.Tensor``, else raise a ``TypeError`` naming ``name``."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor; got {type(x).__name__} (convert with torch.as_tensor)")
    return x


def check_dtype_floating(x: object, name: str, fix: str = "convert with .float()") -> Tensor:
    """Return ``x`` if it is a floating-point ``torch.Tensor``, else raise a ``TypeError``.

    Args:
        x: the argument.
        name: its name in the message.
        fix: how to convert, appended to the message in parentheses.
    """
    x = check_tensor(x, name)
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor; got dtype {x.dtype} ({fix})")
    return x


def _shape_of(x: object, name: str) -> tuple[int, ...]:
    shape = getattr(x, "shape", None)
    if shape is None:
        raise TypeError(f"{name} must be a torch.Tensor or numpy array; got {type(x).__name__}")
    return tuple(int(d) for d in shape)


def _parse_dim(dim: str) -> tuple[int, str]:
    """``"3"`` -> (3, ""), ``"H"`` -> (1, "H"), ``"2H"`` -> (2, "H")."""
    digits = len(dim) - len(dim.lstrip("0123456789"))
    factor = int(dim[:digits]) if digits else 1
    return factor, dim[digits:]


def _malformed(dim: str) -> bool:
    """An empty name, a "*" after the first entry, or a zero factor ("0H")."""
    factor, symbol = _parse_dim(dim)
    return not dim or "*" in dim or (factor == 0 and bool(symbol))


def _mismatch(got: tuple[int, ...], dims: Sequence[str], leading: bool) -> str | None:
    """None if ``got`` fits ``dims`` (the trailing dimensions when ``leading``), else the reason
    to append to the message ("" when the expected shape says it all)."""
    if len(got) < len(dims) or (not leading and len(got) != len(dims)):
        return ""
    bound: dict[str, int] = {}
    for dim, size in zip(dims, got[len(got) - len(dims):]):
        factor, symbol = _parse_dim(dim)
        if not symbol:
            if size != factor:
                return ""
            continue
        if size % factor:
            return f" ({dim}: {size} is not a multiple of {factor})"
        if bound.setdefault(symbol, size // factor) != size // factor:
            return f" ({symbol} is {bound[symbol]} and {size // factor})"
    return None


def check_shape(x: object, shape: Sequence[str], name: str, detail: str = "") -> None:
    """Raise :class:`ShapeError` unless ``x.shape`` matches the dimension names ``shape``.

    Args:
        x: a tensor or array (anything with a ``.shape``; else ``TypeError``).
        shape: dimension names, e.g. ``["*", "3", "H", "W"]`` (see the module docstring).
        name: the argument's name in the message.
        detail: what the dimensions mean, shown after the expected shape, e.g. ``"(s0, s1, s2)"``.

    Raises:
        ShapeError: ``"<name> must have shape (<shape>) <detail>; got (<x.shape>)"``.
        ValueError: ``shape`` itself is malformed ("*" not first, an empty name, a zero factor).

    Example:
        >>> check_shape(torch.zeros(2, 3, 4, 4), ["*", "3", "H", "W"], "stokes")  # passes
    """
    dims = list(shape)
    leading = bool(dims) and dims[0] == "*"
    if leading:
        dims = dims[1:]
    if any(_malformed(d) for d in dims):
        raise ValueError(f"malformed shape {list(shape)!r}: '*' may only come first; a factor must be >= 1")
    got = _shape_of(x, name)
    reason = _mismatch(got, dims, leading)
    if reason is not None:
        note = f" {detail}" if detail else ""
        raise ShapeError(f"{name} must have shape {format_shape(shape)}{note}; got {format_shape(got)}{reason}")


def to_numpy(x: Any, dtype: Any = None) -> np.ndarray:
    """``x`` (torch tensor on any device, numpy array, or array-like) as a numpy array: the one
    conversion at the boundary. Tensors are detached and copied to the CPU; ``dtype`` (optional)
    casts the result."""
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu").numpy()
    out = np.asarray(x)
    return out if dtype is None else out.astype(dtype, copy=False)


def wait_for_device(device: torch.device | str) -> None:
    """Block until the work queued on ``device`` has finished: CUDA runs asynchronously, so a wall-clock
    time read without it measures the queueing, not the work. Nothing to wait for on the CPU (no-op).
    One call per timed stage, never inside a loop (it is a host sync)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def check_finite(x: Tensor, name: str) -> Tensor:
    """Return ``x`` if every element is finite, else raise a ``ValueError`` naming ``name``.

    One reduction and one host sync per call: check once at a public entry, not in inner loops.
    """
    if not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(
            f"{name} must be finite; got {bad} NaN/Inf value(s) of {x.numel()} (shape {format_shape(x.shape)})"
        )
    return x


def _set_to(field: str, value: str) -> str:
    """How a user sets ``field`` to ``value``: ``--device cpu`` on the command line, ``device: cpu`` in a file."""
    return f"{field} {value}" if field.startswith("-") else f"{field}: {value}"


def resolve_device(device: str | torch.device, field: str = "device") -> torch.device:
    """The torch device named by ``device``, checked before any work starts (the one place that does).

    ``auto`` is ``cuda`` when torch sees a GPU, else ``cpu``; ``cpu``, ``cuda``, ``cuda:N`` and ``mps``
    are taken as they are once torch can use them.

    Args:
        device: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"`` or a ``torch.device``.
        field: where the value came from, named in the messages (``"device"``, ``"--device"``).

    Raises:
        ConfigError: not a device name (``"gpu"``) — invalid input (exit status 2).
        DeviceError: a device this machine or this torch build cannot use (``cuda`` with a CPU-only
            torch, no GPU, ``cuda:3`` with two GPUs) — cannot run (exit status 3).

    Example:
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    if isinstance(device, str) and device.strip().lower() == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device.strip() if isinstance(device, str) else device)
    except (RuntimeError, TypeError, ValueError):
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(
            f"{field} {str(device)!r} is not a device polarshape can use; use cpu, cuda, cuda:N, mps or auto"
        )
    fix = f"use {_set_to(field, 'cpu')} (or auto)"
    if dev.type == "cuda":
        if torch.version.cuda is None and not torch.cuda.is_available():
            raise DeviceError(f"{field} {str(device)!r} requested but torch has no CUDA (torch {torch.__version__}): {fix}")
        if not torch.cuda.is_available():
            raise DeviceError(
                f"{field} {str(device)!r} requested but torch {torch.__version__} (CUDA {torch.version.cuda}) sees no "
                f"GPU (check the driver and CUDA_VISIBLE_DEVICES): {fix}"
            )
        count = torch.cuda.device_count()
        if dev.index is not None and dev.index >= count:
            raise DeviceError(
                f"{field} {str(device)!r} requested but torch sees {count} GPU(s) (cuda:0 to cuda:{count - 1}): "
                f"use {_set_to(field, 'cuda:0')}, cpu or auto"
            )
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise DeviceError(f"{field} {str(device)!r} requested but torch {torch.__version__} has no MPS device here: {fix}")
    return dev
