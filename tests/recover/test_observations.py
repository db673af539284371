"""Tests of polarshape.recover.observations: flattening, the pyramid, crop and paste-back."""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from polarshape.recover.observations import (
    RecoveryInputs, crop_inputs, downsample_inputs, flatten_observations, paste_crop,
)


def _inputs(h: int = 8, w: int = 10, k: int = 3) -> RecoveryInputs:
    gen = torch.Generator().manual_seed(0)
    stokes = torch.rand(k, 3, h, w, generator=gen, dtype=torch.float64)
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[2:6, 3:9] = True
    lights = torch.nn.functional.normalize(torch.randn(k, h, w, 3, generator=gen, dtype=torch.float64) +
                                           torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64), dim=-1)
    view = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(h, w, 3)
    return RecoveryInputs(stokes, mask.expand(k, h, w).clone(), torch.zeros(k, h, w, dtype=torch.bool), mask, lights,
                          torch.rand(k, h, w, generator=gen, dtype=torch.float64), view, 1e-3, True)


def test_flatten_is_pixel_first_and_row_major() -> None:
    inp = _inputs()
    obs = flatten_observations(inp, inp.mask)
    p = int(inp.mask.sum())
    assert obs.stokes.shape == (p, 3, 3) and obs.lights.shape == (p, 3, 3) and obs.irradiance.shape == (p, 3)
    rows, cols = torch.nonzero(inp.mask, as_tuple=True)
    i = 5  # the sixth mask pixel in row-major order
    assert torch.equal(obs.stokes[i], inp.stokes[:, :, rows[i], cols[i]])
    assert torch.equal(obs.lights[i], inp.lights[:, rows[i], cols[i]])
    sub = obs.select(torch.tensor([i]))
    assert torch.equal(sub.irradiance[0], inp.irradiance[:, rows[i], cols[i]]) and sub.num_pixels == 1


def test_downsample_averages_and_keeps_unit_directions() -> None:
    inp = _inputs()
    half = downsample_inputs(inp)
    assert half.shape == (4, 5) and half.noise_std == inp.noise_std / 2
    torch.testing.assert_close(half.stokes[1, 0, 1, 2], inp.stokes[1, 0, 2:4, 4:6].mean())
    torch.testing.assert_close(half.lights.norm(dim=-1), torch.ones(3, 4, 5, dtype=torch.float64))
    # a half-resolution pixel is in the mask only when its four children are
    assert torch.equal(half.mask, inp.mask.reshape(4, 2, 5, 2).all(3).all(1))


def test_crop_and_paste_back_round_trip() -> None:
    inp = _inputs()
    crop = crop_inputs(inp)
    assert crop.shape == (4, 6) and crop.offset == (2, 3) and bool(crop.mask.all())
    normals = torch.nn.functional.normalize(torch.rand(4, 6, 3, dtype=torch.float64), dim=-1)
    full = paste_crop(normals, crop, inp, channels_last=True)
    assert full.shape == (8, 10, 3) and torch.equal(full[2:6, 3:9], normals)
    assert bool(torch.isnan(full[~inp.mask]).all())
    rendered = paste_crop(crop.stokes, crop, inp, 0.0)
    assert torch.equal(rendered[..., 2:6, 3:9], crop.stokes) and float(rendered[..., 0, 0].abs().max()) == 0.0
    flags = paste_crop(crop.mask, crop, inp, False)
    assert flags.dtype == torch.bool and torch.equal(flags, inp.mask)
    assert math.isnan(float(paste_crop(crop.stokes[0, 0], crop, inp)[0, 0]))


def test_zero_stride_lights_stay_views_through_crop_and_pyramid() -> None:
    """Directional lights as expand() views (what preprocessing returns): the pyramid keeps them views
    (no (K, H, W, 3) array) and agrees with the materialised inputs."""
    inp = _inputs()
    k, (h, w) = inp.num_lights, inp.shape
    direction = torch.nn.functional.normalize(torch.tensor([[0.3, 0.1, -1.0], [-0.2, 0.4, -1.0], [0.0, -0.5, -1.0]],
                                                           dtype=torch.float64), dim=-1)
    views = replace(inp, lights=direction[:, None, None].expand(k, h, w, 3),
                    irradiance=torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64)[:, None, None].expand(k, h, w))
    dense = replace(views, lights=views.lights.contiguous(), irradiance=views.irradiance.contiguous())
    half, half_dense = downsample_inputs(crop_inputs(views)), downsample_inputs(crop_inputs(dense))
    assert half.lights.stride()[1:3] == (0, 0) and half.irradiance.stride()[1:] == (0, 0)
    torch.testing.assert_close(half.lights, half_dense.lights, rtol=0, atol=1e-12)
    torch.testing.assert_close(half.irradiance, half_dense.irradiance, rtol=0, atol=1e-12)
    obs, obs_dense = flatten_observations(views, views.mask), flatten_observations(dense, dense.mask)
    assert torch.equal(obs.lights, obs_dense.lights) and torch.equal(obs.irradiance, obs_dense.irradiance)
