"""Tests of polarshape.recover.edges (albedo steps from every light) and its use in preprocessing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.imaging.pixels import counts_to_float, float_to_counts
from polarshape.imaging.stokes import dolp
from polarshape.io.capture import Capture, parse_capture_spec
from polarshape.recover.edges import find_albedo_edges
from polarshape.recover.preprocess import preprocess_capture, superpixel_stokes

K, H, W = 4, 8, 12


def _shading(k: int, h: int, w: int) -> torch.Tensor:
    """(K, h, w) smooth shading, a gentle ramp in a different direction under every light."""
    y, x = torch.meshgrid(torch.linspace(0, 1, h, dtype=torch.float64), torch.linspace(0, 1, w, dtype=torch.float64),
                          indexing="ij")
    angles = torch.arange(k, dtype=torch.float64) * (2 * math.pi / k)
    return 0.3 * (1 + 0.15 * (torch.cos(angles)[:, None, None] * x + torch.sin(angles)[:, None, None] * y))


def test_a_step_between_blocks_marks_both_sides_adjacent_and_none_on_it() -> None:
    albedo = torch.ones(H, W, dtype=torch.float64)
    albedo[:, W // 2:] = 3.0  # the step on a block boundary
    s0 = _shading(K, H, W) * albedo
    edges = find_albedo_edges(s0, torch.ones_like(s0, dtype=torch.bool))
    cols = edges.adjacent.all(0)
    assert cols.nonzero().flatten().tolist() == [W // 2 - 1, W // 2]
    assert not edges.adjacent[:, : W // 2 - 1].any() and not edges.adjacent[:, W // 2 + 1:].any()
    assert not edges.on_edge.any()


def test_a_mixed_block_is_on_the_edge_and_its_neighbours_adjacent() -> None:
    albedo = torch.ones(H, W, dtype=torch.float64)
    albedo[:, W // 2 + 1:] = 4.0
    albedo[:, W // 2] = 2.5  # half the sites of this column of blocks see each albedo
    s0 = _shading(K, H, W) * albedo
    edges = find_albedo_edges(s0, torch.ones_like(s0, dtype=torch.bool))
    assert edges.on_edge.all(0).nonzero().flatten().tolist() == [W // 2]
    assert edges.on_edge.sum() == H
    assert edges.adjacent.all(0).nonzero().flatten().tolist() == [W // 2 - 1, W // 2, W // 2 + 1]


def test_shading_alone_is_no_edge() -> None:
    """A steep ramp the same way under every light (a limb) and a highlight under one light."""
    x = torch.linspace(0, 1, W, dtype=torch.float64)
    s0 = _shading(K, H, W) * torch.exp(3.0 * x)  # ×1.3 from block to block under every light
    s0[1, 3:5, 4:6] *= 4.0  # a highlight under light 1 only
    edges = find_albedo_edges(s0, torch.ones_like(s0, dtype=torch.bool))
    assert not edges.adjacent.any() and not edges.on_edge.any()


def test_a_step_seen_by_dim_lights_alone_is_no_edge() -> None:
    """Near two lights' terminator (a plain sphere's rim under 12 lights) their s0 is small and its log steep: with
    noise, a ramp there reads as a step flat on both sides under those two lights, while the ten bright lights
    see no change — an albedo step would scale them all."""
    k = 12
    s0 = _shading(k, H, W)  # ≈ 0.3: the bright lights
    drop = torch.ones(W, dtype=torch.float64)
    drop[W // 2:] = 0.7  # ×1.43 across one block boundary, flat on both sides
    s0[:2] = 0.03 * drop  # the two lights near their terminator
    edges = find_albedo_edges(s0, torch.ones_like(s0, dtype=torch.bool))
    assert not edges.adjacent.any() and not edges.on_edge.any()


def test_a_step_dimmed_by_a_highlight_under_one_light_is_still_an_edge() -> None:
    """A strong surface reflection under one light (unchanged by the albedo) shrinks the step it sees."""
    albedo = torch.ones(H, W, dtype=torch.float64)
    albedo[:, W // 2:] = 3.0
    s0 = _shading(K, H, W) * albedo
    s0[0] += 1.0  # under light 0 the step is ×1.4 instead of ×3, and that light carries most of the radiance
    edges = find_albedo_edges(s0, torch.ones_like(s0, dtype=torch.bool))
    assert edges.adjacent.all(0).nonzero().flatten().tolist() == [W // 2 - 1, W // 2]


def test_a_step_seen_under_one_light_only_is_no_edge() -> None:
    albedo = torch.ones(H, W, dtype=torch.float64)
    albedo[:, W // 2:] = 3.0
    s0 = _shading(K, H, W) * albedo
    usable = torch.zeros_like(s0, dtype=torch.bool)
    usable[0] = True
    edges = find_albedo_edges(s0, usable)
    assert not edges.adjacent.any()


def test_bad_arguments() -> None:
    s0 = _shading(K, H, W)
    usable = torch.ones_like(s0, dtype=torch.bool)
    with pytest.raises(ValueError, match="min_ratio"):
        find_albedo_edges(s0, usable, min_ratio=1.0)
    with pytest.raises(ValueError, match="min_lights"):
        find_albedo_edges(s0, usable, min_lights=1)
    with pytest.raises(ValueError, match="usable"):
        find_albedo_edges(s0, usable[:, 1:])
    with pytest.raises(ValueError, match="min_weight"):
        find_albedo_edges(s0, usable, min_weight=0.0)


def _textured_capture() -> tuple[Capture, int]:
    """An unpolarised surface (I_θ = ½ s0 at every site) with an albedo step ×4 through the middle of a
    column of blocks, under four directional lights; returns the capture and that column."""
    h2, w2 = 2 * H, 2 * W
    raw_albedo = torch.ones(h2, w2, dtype=torch.float64)
    column = W // 2
    raw_albedo[:, 2 * column + 1:] = 4.0  # the step between the two sites of block column ``column``
    shading = torch.nn.functional.interpolate(_shading(K, H, W)[None], size=(h2, w2), mode="bilinear",
                                              align_corners=True)[0]
    mosaic = 0.5 * 0.4 * shading * raw_albedo  # (K, 2H, 2W) I_θ = ½ s0
    lights = [{"direction": [math.sin(0.5) * math.cos(a), math.sin(0.5) * math.sin(a), -math.cos(0.5)],
               "frame": f"frames/{i:03d}.png"} for i, a in enumerate(np.linspace(0, 2 * math.pi, K, endpoint=False))]
    spec = parse_capture_spec({"format": "polarshape-capture/1", "camera": {"projection": "orthographic", "bit_depth": 12},
                               "lights": lights})
    frames = np.stack([float_to_counts(mosaic[i], 12) for i in range(K)])
    return Capture(spec=spec, frames=frames, mask=None), column


def test_preprocessing_takes_no_false_polarisation_from_an_albedo_step() -> None:
    capture, column = _textured_capture()
    plain = preprocess_capture(capture, albedo_edges=False, mixed_sigma=None, polarisation_check=False)
    edged = preprocess_capture(capture, mixed_sigma=None, polarisation_check=False)
    inner = (slice(None), slice(1, -1), slice(1, -1))  # away from the image border
    p_plain = dolp(plain.stokes)[inner]  # (K, H − 2, W − 2)
    p_edged = dolp(edged.stokes)[inner]
    assert float(p_plain.max()) > 0.2  # the bilinear estimate mixes the other side in (and the mixed column)
    assert plain.albedo_edges is None
    marked = edged.albedo_edges
    assert marked is not None and marked.all(0).nonzero().flatten().tolist() == [column]
    assert not edged.valid[:, :, column].any()
    assert float(p_edged[edged.valid[inner]].max()) < 0.01  # every kept observation: the true DoLP 0


def test_blocks_next_to_a_step_take_their_own_four_sites_estimate() -> None:
    """Only the blocks next to the step are read again (polarshape.recover.preprocess reads just those): their
    Stokes vectors are the super-pixel estimate of the whole frame there, rounded once to float32."""
    capture, _ = _textured_capture()
    plain = preprocess_capture(capture, albedo_edges=False, mixed_sigma=None, polarisation_check=False)
    edged = preprocess_capture(capture, mixed_sigma=None, polarisation_check=False)
    mosaic = counts_to_float(capture.frames, 12, dtype=torch.float64)  # (K, 2H, 2W)
    own = superpixel_stokes(mosaic, capture.layout, demosaic="superpixel").to(torch.float32)  # (K, 3, H, W)
    swapped = (edged.stokes != plain.stokes).any(1)  # (K, H, W)
    assert int(swapped.any(0).sum()) >= 2 * H  # both columns next to the step
    assert torch.equal(edged.stokes, torch.where(swapped.unsqueeze(1), own, plain.stokes))
