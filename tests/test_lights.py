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


def test_coincident_lights_are_found_by_angle_and_distance():
    from polarshape.lights import Lights

    tilt = math.radians(0.1)
    lights = Lights((
        DirectionalLight((0.0, 0.0, -1.0)),
        DirectionalLight((0.3, 0.0, -1.0)),
        DirectionalLight((math.sin(tilt), 0.0, -math.cos(tilt))),  # 0.1° from light 0
        PointLight((0.1, 0.0, 0.2)),
        PointLight((0.1, 0.0005, 0.2)),  # 0.5 mm from light 3
        PointLight((0.0, 0.0, 0.2)),
    ))
    pairs = lights.coincident(max_angle_deg=0.5, max_distance_m=1e-3)
    assert [(i, j) for i, j, _ in pairs] == [(0, 2), (3, 4)]
    assert pairs[0][2] == pytest.approx(0.1) and pairs[1][2] == pytest.approx(5e-4)
    assert lights.coincident(max_angle_deg=0.05, max_distance_m=1e-4) == []


def test_lights_behind_a_surface_depth():
    from polarshape.lights import Lights

    lights = Lights((
        DirectionalLight((0.0, 0.0, -1.0)),
        DirectionalLight((1.0, 0.0, 0.0)),  # grazing: allowed
        DirectionalLight((0.0, 0.6, 0.8)),  # pointing away from the camera
        PointLight((0.0, 0.0, 0.3)),
        PointLight((0.0, 0.0, 0.5)),  # at the surface depth
        PointLight((0.1, 0.0, 0.7)),  # beyond it
    ))
    assert lights.behind(0.5) == [2, 4, 5]
    assert lights.behind(math.inf) == [2]
