"""Albedo textures: mappings and patterns."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from polarshape.scene.textures import AlbedoTexture, load_grey_image, make_texture

F64 = torch.float64


def test_spherical_uv_faces_the_camera_at_u_half_and_runs_top_to_bottom():
    tex = AlbedoTexture("checker", "spherical", (0.0, 0.0, 1.0))
    pts = torch.tensor([[0.0, 0.0, 0.5], [0.0, -0.5, 1.0], [0.0, 0.5, 1.0], [0.5, 0.0, 1.0]], dtype=F64)
    uv = tex.uv(pts)
    assert uv[0].tolist() == pytest.approx([0.5, 0.5])
    assert uv[1, 1].item() == pytest.approx(0.0) and uv[2, 1].item() == pytest.approx(1.0)
    assert uv[3, 0].item() == pytest.approx(0.75)  # +x is a quarter turn from the camera-facing point


def test_checker_and_stripes_alternate():
    tex = AlbedoTexture("checker", "planar", (0.0, 0.0, 0.0), cells=2.0, low=0.2, high=0.9, size_m=1.0)
    # planar: u = 0.5 + x, cells 2 -> cell boundaries at x = 0
    pts = torch.tensor([[-0.25, -0.25, 3.0], [0.25, -0.25, 3.0], [0.25, 0.25, 3.0]], dtype=F64)
    assert tex(pts).tolist() == pytest.approx([0.2, 0.9, 0.2])  # cells (0,0), (1,0), (1,1)
    stripes = AlbedoTexture("stripes", "planar", (0.0, 0.0, 0.0), cells=2.0, low=0.2, high=0.9, size_m=1.0)
    assert stripes(pts).tolist() == pytest.approx([0.2, 0.9, 0.9])


def test_image_texture_samples_bilinearly(tmp_path):
    img = np.zeros((2, 2), np.uint8)
    img[0, 1] = 255
    path = tmp_path / "tex.png"
    cv2.imwrite(str(path), img)
    tex = make_texture("image", "planar", (0.0, 0.0, 0.0), low=0.0, high=1.0, size_m=1.0, path=path)
    # pixel centres at u = 0.25, 0.75; the centre of the image averages the four pixels
    pts = torch.tensor([[0.25, -0.25, 0.0], [-0.25, -0.25, 0.0], [0.0, 0.0, 0.0]], dtype=F64)
    assert tex(pts).tolist() == pytest.approx([1.0, 0.0, 0.25])


def test_colour_image_becomes_grey(tmp_path):
    img = np.zeros((4, 4, 3), np.uint16)
    img[..., 2] = 65535  # pure red (BGR)
    path = tmp_path / "red.png"
    cv2.imwrite(str(path), img)
    assert load_grey_image(path) == pytest.approx(np.full((4, 4), 0.299))


def test_bad_textures_are_refused(tmp_path):
    with pytest.raises(ValueError, match="path"):
        make_texture("image", "planar", (0, 0, 0))
    with pytest.raises(ValueError, match="nothing.png"):
        make_texture("image", "planar", (0, 0, 0), path=tmp_path / "nothing.png")
    with pytest.raises(ValueError, match="mapping"):
        AlbedoTexture("checker", "cylindrical", (0, 0, 0))  # type: ignore[arg-type]
    assert math.isfinite(AlbedoTexture("stripes", "spherical", (0, 0, 0))(torch.zeros(1, 3, dtype=F64)).item())
