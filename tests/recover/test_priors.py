"""Tests of polarshape.recover.priors: the MAP smoothness prior and filling pixels without data."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from polarshape.metrics import angular_error_deg
from polarshape.recover.priors import fill_unsupported, map_smoothing


def _sphere_cap(h: int, w: int) -> Tensor:
    """(h, w, 3) unit normals of a sphere cap facing the camera (n_z < 0), ≈ 3° apart."""
    y, x = torch.meshgrid(torch.linspace(-0.35, 0.35, h, dtype=torch.float64),
                          torch.linspace(-0.35, 0.35, w, dtype=torch.float64), indexing="ij")
    return torch.stack([x, y, -(1 - x * x - y * y).sqrt()], -1)


def testmap_smoothing_lowers_noise_and_keeps_strong_data() -> None:
    """map_smoothing on a noisy tilted plane: lower error, exact where the data are strong, a no-op at 0."""
    gen = torch.Generator().manual_seed(0)
    h = w = 24
    truth = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64), dim=0).expand(h, w, 3)
    noisy = torch.nn.functional.normalize(truth + 0.02 * torch.randn(h, w, 3, generator=gen, dtype=torch.float64), dim=-1)
    pixels = torch.ones(h, w, dtype=torch.bool)
    pixels[:3, :3] = False
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye - noisy.unsqueeze(-1) * noisy.unsqueeze(-2)  # tangent-plane information, 1 / (0.02 rad)²
    info = proj / 0.02**2
    info[10, 10] *= 1e6  # one pixel with (almost) exact data
    noisy[10, 10] = truth[10, 10]
    info[~pixels] = 0
    same, lam0 = map_smoothing(noisy.clone(), info, pixels, 0.0)
    assert lam0 == 0 and torch.equal(same, noisy)
    smooth, lam = map_smoothing(torch.where(pixels[..., None], noisy, torch.nan), info, pixels, 1.0)
    assert lam == pytest.approx(1 / 0.02**2, rel=1e-6)
    err0 = angular_error_deg(noisy[pixels], truth[pixels]).mean()
    err1 = angular_error_deg(smooth[pixels], truth[pixels]).mean()
    assert err1 < 0.6 * err0
    assert float(angular_error_deg(smooth[10, 10], truth[10, 10])) < 0.01
    assert bool(torch.isnan(smooth[~pixels]).all()) and torch.allclose(smooth[pixels].norm(dim=-1), torch.ones(1, dtype=torch.float64))


def testfill_unsupported_takes_neighbours_and_marks_unreachable_pixels() -> None:
    h = w = 16
    truth = _sphere_cap(h, w)
    pixels = torch.ones(h, w, dtype=torch.bool)
    pixels[:, 13] = False  # columns 14-15 form a separate component
    supported = torch.ones(h, w, dtype=torch.bool)
    supported[5:9, 5:9] = False  # a hole inside the object
    supported[:, 14:] = False  # a component with no supported pixel at all
    garbage = truth.clone()
    garbage[~supported] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # back-facing nonsense
    k_b = torch.full((h, w), 0.5, dtype=torch.float64)
    k_b[~supported] = 7.0
    normals, albedo, filled = fill_unsupported(garbage, k_b, pixels, supported)
    # every pixel without data is marked, also those no neighbour could fill: none passes for measured
    assert torch.equal(filled, pixels & ~supported)
    reached = filled & (torch.arange(w) < 13)
    assert float(angular_error_deg(normals[reached], truth[reached]).max()) < 8.0  # ≤ two grid steps
    torch.testing.assert_close(normals[reached].norm(dim=-1), torch.ones(int(reached.sum()), dtype=torch.float64))
    torch.testing.assert_close(albedo[reached], torch.full((int(reached.sum()),), 0.5, dtype=torch.float64))
    assert torch.equal(normals[supported], garbage[supported])
    assert torch.equal(normals[:, 14:], garbage[:, 14:])  # unreachable: unchanged
