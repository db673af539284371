"""Shared helpers for the forward-model tests: random geometries in the camera frame."""

from __future__ import annotations

import numpy as np
import torch


def orthonormal_basis(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents (x, y) of the unit vectors z (..., 3)."""
    helper = torch.where(z[..., :1].abs() < 0.9, torch.tensor([1.0, 0, 0], dtype=z.dtype), torch.tensor([0, 1.0, 0], dtype=z.dtype))
    x = torch.nn.functional.normalize(torch.linalg.cross(helper.expand_as(z), z, dim=-1), dim=-1)
    return x, torch.linalg.cross(z, x, dim=-1)


def around(axis: torch.Tensor, theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Unit vectors at polar angle theta, azimuth phi about ``axis`` (..., 3)."""
    x, y = orthonormal_basis(axis)
    st, ct = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    return st * (torch.cos(phi)[..., None] * x + torch.sin(phi)[..., None] * y) + ct * axis


def random_geometry(rng: np.random.Generator, n: int, *, max_deg: float = 89.9, perspective: bool = True, dtype=torch.float64):
    """(N, L, V), each (n, 3): views near the optical axis (perspective rays up to ~20° off-axis),
    normals facing V up to ``max_deg``, lights in front of N up to ``max_deg`` (uniform in cos)."""
    off = 0.35 if perspective else 0.0
    v = torch.tensor(rng.normal(size=(n, 3)) * [off, off, 0] + [0, 0, -1.0], dtype=dtype)
    v = torch.nn.functional.normalize(v, dim=-1)
    cmin = np.cos(np.radians(max_deg))
    th_n = torch.tensor(np.arccos(rng.uniform(cmin, 1.0, n)), dtype=dtype)
    th_l = torch.tensor(np.arccos(rng.uniform(cmin, 1.0, n)), dtype=dtype)
    n_ = around(v, th_n, torch.tensor(rng.uniform(0, 2 * np.pi, n), dtype=dtype))
    l_ = around(n_, th_l, torch.tensor(rng.uniform(0, 2 * np.pi, n), dtype=dtype))
    return n_, l_, v


def angle_diff_mod_pi(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a − b| modulo π, in [0, π/2]."""
    d = torch.remainder(a - b, torch.pi)
    return torch.minimum(d, torch.pi - d)
