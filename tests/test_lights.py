"""Lights: direction, irradiance, shadow-ray length."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.lights import DirectionalLight, PointLight, light_from_dict, light_to_dict


def test_directional_light_is_normalised_and_uniform():
    light = DirectionalLight((0.0, 3.0, -4.0), 2.0)
    assert light.direction == pytest.approx((0.0, 0.6, -0.8))
    points = torch.randn(5, 7, 3, dtype=torch.float64)
    l, e, dist = light.illuminate(points)
    assert l.shape == (5, 7, 3) and e.shape == dist.shape == (5, 7)
    assert torch.allclose(l, torch.tensor([0.0, 0.6, -0.8], dtype=torch.float64).expand(5, 7, 3))
    assert torch.all(e == 2.0) and torch.all(torch.isinf(dist))


def test_point_light_falls_off_with_inverse_square():
    light = PointLight((0.0, 0.0, 0.0), 3.0)
    points = torch.tensor([[0.0, 0.0, 1.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.5]], dtype=torch.float64)
    l, e, dist = light.illuminate(points)
    assert torch.allclose(e, torch.tensor([3.0, 0.75, 12.0], dtype=torch.float64))
    assert torch.allclose(dist, torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64))
    assert torch.allclose(l[1], torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))


def test_light_dict_round_trip_and_errors():
    for light in (DirectionalLight((0.0, 0.0, -1.0), 0.5), PointLight((0.1, 0.2, 0.3), 2.0)):
        assert light_from_dict(light_to_dict(light)) == light
    with pytest.raises(ValueError, match="exactly one"):
        light_from_dict({"direction": [0, 0, -1], "position": [0, 0, 0]})
    with pytest.raises(ValueError, match="exactly one"):
        light_from_dict({"intensity": 1.0})
    with pytest.raises(ValueError, match="non-zero"):
        DirectionalLight((0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="intensity"):
        PointLight((0.0, 0.0, 0.0), -1.0)
    assert math.isclose(sum(c * c for c in light_from_dict({"direction": [1, 1, -1]}).direction), 1.0)
