"""Camera models: one ray per raw-mosaic pixel, OpenCV frame."""

from __future__ import annotations

import pytest
import torch

from polarshape.cameras import OrthographicCamera, PerspectiveCamera


def test_orthographic_rays_are_parallel_and_centred():
    cam = OrthographicCamera(8, 6, 0.5)
    o, d = cam.rays()
    assert o.shape == d.shape == (6, 8, 3)
    assert torch.all(d == torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert torch.allclose(o[0, 1] - o[0, 0], torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64))
    assert torch.allclose(o[1, 0] - o[0, 0], torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64))  # y down
    assert torch.allclose(o.mean(dim=(0, 1)), torch.zeros(3, dtype=torch.float64))
    shifted = OrthographicCamera(8, 6, 0.5, cx=0.0, cy=0.0)
    assert torch.all(shifted.rays()[0][0, 0] == 0)
    v = cam.view_directions(torch.randn(4, 3))
    assert torch.all(v == torch.tensor([0.0, 0.0, -1.0]))


def test_perspective_rays_reproject_to_their_pixels():
    cam = PerspectiveCamera(10, 8, fx=20.0, fy=25.0, cx=4.0, cy=3.0)
    o, d = cam.rays()
    assert torch.all(o == 0)
    assert torch.allclose(d.norm(dim=-1), torch.ones(8, 10, dtype=torch.float64))
    assert torch.allclose(d[3, 4], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    u = 20.0 * d[..., 0] / d[..., 2] + 4.0
    v = 25.0 * d[..., 1] / d[..., 2] + 3.0
    assert torch.allclose(u, torch.arange(10, dtype=torch.float64).expand(8, 10))
    assert torch.allclose(v, torch.arange(8, dtype=torch.float64)[:, None].expand(8, 10))
    p = 2.0 * d
    assert torch.allclose(cam.view_directions(p), -d)


def test_dtype_and_device_follow_the_request():
    o, d = PerspectiveCamera(4, 4, 10, 10, 1.5, 1.5).rays(dtype=torch.float32)
    assert o.dtype == d.dtype == torch.float32


@pytest.mark.parametrize("make", [lambda: OrthographicCamera(7, 8, 1.0), lambda: PerspectiveCamera(8, 5, 1, 1, 0, 0)])
def test_odd_sizes_are_refused(make):
    with pytest.raises(ValueError, match="even"):
        make()


def test_bad_scale_is_refused():
    with pytest.raises(ValueError, match="pixel_size_m"):
        OrthographicCamera(8, 8, 0.0)
    with pytest.raises(ValueError, match="fx"):
        PerspectiveCamera(8, 8, -1.0, 1.0, 0, 0)
