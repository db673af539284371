"""Tests of polarshape.metrics: the angle between normals, error statistics, aligned depth error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarshape.metrics import angular_error_deg, angular_error_stats, depth_rmse_aligned


def test_angular_error_and_stats() -> None:
    a = np.zeros((2, 3, 3))
    a[..., 2] = -1.0
    b = a.copy()
    t = np.radians(10.0)
    b[0, 0] = [np.sin(t), 0.0, -np.cos(t)]
    b[0, 1] = [0.0, 0.0, 1.0]  # opposite: 180°
    b[1, 2] = np.nan  # missing
    err = angular_error_deg(a, b)
    assert err[0, 0] == pytest.approx(10.0) and err[0, 1] == pytest.approx(180.0) and err[1, 1] == 0.0
    assert np.isnan(err[1, 2])
    mask = np.ones((2, 3), bool)
    mask[0, 1] = False
    err = angular_error_deg(a, b, mask)
    stats = angular_error_stats(err, reference_pixels=int(mask.sum()))
    assert stats["pixels"] == 4 and stats["mean_deg"] == pytest.approx(2.5) and stats["median_deg"] == 0.0
    assert stats["coverage"] == pytest.approx(0.8) and stats["within_5deg"] == pytest.approx(0.75)
    assert angular_error_stats(np.full((2, 2), np.nan)) == {"pixels": 0}
    with pytest.raises(ValueError, match="vectors must both be"):
        angular_error_deg(a, b[..., :2])


def test_depth_rmse_is_invariant_to_scale_and_offset() -> None:
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.4, 0.5, (20, 20))
    estimate = 3.0 * truth - 7.0
    estimate[0, 0] = np.nan
    exact = depth_rmse_aligned(estimate, truth)
    assert exact["rmse"] < 1e-12 and exact["scale"] == pytest.approx(1 / 3) and exact["pixels"] == 399
    noisy = estimate + rng.normal(0.0, 0.03, truth.shape)  # σ 0.01 after scaling by 1/3
    assert depth_rmse_aligned(noisy, truth)["rmse"] == pytest.approx(0.01, rel=0.15)
    assert depth_rmse_aligned(noisy, truth, np.zeros((20, 20), bool)) == {"pixels": 0}


def test_angular_error_takes_tensors_and_returns_tensors() -> None:
    """One formula for tensors and arrays: the same degrees, NaN for a zero vector, tensor in → tensor out."""
    a = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float32)
    b = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float32)
    err = angular_error_deg(a, b)
    assert isinstance(err, torch.Tensor) and err.dtype == torch.float64
    assert float(err[0]) == 0.0 and float(err[1]) == pytest.approx(90.0) and bool(torch.isnan(err[2]))
    np.testing.assert_array_equal(angular_error_deg(a.numpy(), b.numpy()), err.numpy())
    with pytest.raises(ValueError, match="vectors must both be"):
        angular_error_deg(a, b[:, :2])
